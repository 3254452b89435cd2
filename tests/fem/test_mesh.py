"""TaggedMesh: gmsh physical groups in and out, quadratic conversion, quality checks."""

import numpy as np
import pytest

from needletissue.errors import InputError
from needletissue.fem import TaggedMesh


@pytest.fixture(scope="module")
def gmsh_two_layers(tmp_path_factory):
    """A 10 x 10 x 8 mm box: muscle below z = 5, adipose above; surfaces 'bottom' and 'top'."""
    import gmsh

    path = tmp_path_factory.mktemp("msh") / "layers.msh"
    gmsh.initialize(["-nt", "1"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("layers")
        occ = gmsh.model.occ
        a = occ.addBox(0, 0, 0, 10, 10, 5)
        b = occ.addBox(0, 0, 5, 10, 10, 3)
        occ.fragment([(3, a)], [(3, b)])
        occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [a], name="muscle")
        gmsh.model.addPhysicalGroup(3, [b], name="adipose")
        def faces_at(z):
            return [t for d, t in gmsh.model.getEntities(2)
                    if abs(gmsh.model.occ.getCenterOfMass(2, t)[2] - z) < 1e-9]
        gmsh.model.addPhysicalGroup(2, faces_at(0.0), name="bottom")
        gmsh.model.addPhysicalGroup(2, faces_at(8.0), name="top")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 2.5)
        gmsh.model.mesh.generate(3)
        live = TaggedMesh.from_gmsh()
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return path, live


def test_read_msh_physical_groups(gmsh_two_layers):
    path, live = gmsh_two_layers
    m = TaggedMesh.read(path).check(regions=["muscle", "adipose"], surfaces=["top", "bottom"])
    # region volumes are the boxes' volumes (planar faces: exact up to round-off)
    vol = m.volumes()
    assert vol[m.regions["muscle"]].sum() == pytest.approx(500.0, rel=1e-12)
    assert vol[m.regions["adipose"]].sum() == pytest.approx(300.0, rel=1e-12)
    assert m.surface_area("top") == pytest.approx(100.0, rel=1e-12)
    assert np.allclose(m.points[m.surface_nodes("bottom"), 2], 0.0)
    # the live gmsh model gives the same mesh
    assert live.stats()["cells_by_region"] == m.stats()["cells_by_region"]
    assert len(live.points) == len(m.points)
    s = m.stats()
    assert s["tetrahedra"] == len(m.cells) and 0 < s["min_quality"] <= 1


def test_to_quadratic_midpoints_and_surfaces(gmsh_two_layers):
    m = TaggedMesh.read(gmsh_two_layers[0])
    q = m.to_quadratic()
    assert q.cells.shape[1] == 10 and q.order == 2
    edges = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
    mid = q.points[q.cells[:, 4:]]
    ends = 0.5 * (q.points[q.cells[:, edges[:, 0]]] + q.points[q.cells[:, edges[:, 1]]])
    np.testing.assert_allclose(mid, ends, atol=1e-12)
    tri = q.surfaces["top"]
    assert tri.shape[1] == 6
    tedges = np.array([[0, 1], [1, 2], [2, 0]])
    np.testing.assert_allclose(q.points[tri[:, 3:]],
                               0.5 * (q.points[tri[:, tedges[:, 0]]] + q.points[tri[:, tedges[:, 1]]]), atol=1e-12)
    # consistent nodal loads of a uniform traction sum to the area
    nodes, w = q.nodal_area_weights("top")
    assert w.sum() == pytest.approx(100.0, rel=1e-12)
    # the meshio round trip keeps the tetra10 node order
    import meshio

    m2 = TaggedMesh.read(meshio.Mesh(q.points, [("tetra10", q.cells)]))
    assert np.array_equal(m2.cells, q.cells) and list(m2.regions) == ["solid"]


def test_check_rejects_inverted_and_missing():
    m = TaggedMesh.box((1, 1, 1), (2, 2, 2))
    m.check()
    bad = TaggedMesh(m.points, m.cells.copy(), m.regions, m.surfaces)
    bad.cells[0, [0, 1]] = bad.cells[0, [1, 0]]
    with pytest.raises(InputError, match="inverted"):
        bad.check()
    with pytest.raises(InputError, match="missing surface 'gripper'"):
        m.check(surfaces=["gripper"])
    with pytest.raises(InputError, match="missing region 'needle_1'"):
        m.check(regions=["needle_1"])
    with pytest.raises(InputError, match="file not found"):
        TaggedMesh.read("/nonexistent/mesh.msh")


def test_gmsh_tetra10_node_order(tmp_path):
    """gmsh order-2 meshes (curved) read from the live model and from .msh agree, in VTK order:
    every midside node lies near its own edge's centre (a swapped 8/9 would put it an edge away)."""
    import gmsh

    gmsh.initialize(["-nt", "1"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        v = gmsh.model.occ.addCylinder(0, 0, 0, 10, 0, 0, 2)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [v], name="needle")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 1.5)
        gmsh.model.mesh.generate(3)
        gmsh.model.mesh.setOrder(2)
        live = TaggedMesh.from_gmsh()
        gmsh.write(str(tmp_path / "c.msh"))
    finally:
        gmsh.finalize()
    m = TaggedMesh.read(tmp_path / "c.msh")
    assert np.array_equal(live.cells, m.cells) and np.allclose(live.points, m.points)
    e = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
    p = m.points
    offset = np.linalg.norm(p[m.cells[:, 4:]] - 0.5 * (p[m.cells[:, e[:, 0]]] + p[m.cells[:, e[:, 1]]]), axis=-1)
    edge = np.linalg.norm(p[m.cells[:, e[:, 0]]] - p[m.cells[:, e[:, 1]]], axis=-1)
    assert (offset / edge).max() < 0.15  # curved boundary edges bow a little, never a whole edge
    assert (offset > 1e-6).any()  # and some are curved (on the cylinder)
