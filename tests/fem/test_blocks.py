"""The per-region multiblock (.vtm) written beside each result VTU: one block per region, named by the
region, holding exactly that region's cells of the whole-mesh VTU with the same fields; relocatable
(relative piece paths); files and folders following the umask; the .pvd series lists it."""

import os
import shutil

import numpy as np
import pytest

from needletissue.fem import FEModel, PrescribedDisplacement, TaggedMesh, solve
from needletissue.fem.result import write_results

G = np.array([[0.04, 0.02, 0.0], [0.0, -0.03, 0.01], [0.01, 0.0, 0.05]])


@pytest.fixture(scope="module")
def results():
    mesh = TaggedMesh.box((10, 10, 10), (3, 3, 4), layers={"muscle": (0, 5), "adipose": (5, 10)})
    mesh.surfaces["boundary"] = np.concatenate([mesh.surfaces[k] for k in ("xmin", "xmax", "ymin", "ymax",
                                                                            "zmin", "zmax")])
    model = FEModel(mesh, {"muscle": "muscle", "adipose": "adipose"}, order=2)
    return solve(model, [PrescribedDisplacement("boundary", lambda x: x @ G.T)], [0.5, 1.0], progress=False)


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_blocks_are_the_regions_of_the_whole_mesh(tmp_path, results, umask):
    import pyvista as pv

    os.umask(0o027)
    payload = write_results(tmp_path, results, {})
    whole = pv.read(str(tmp_path / payload["vtu"][-1]))
    vtm = tmp_path / "fe_1.vtm"
    blocks = pv.read(str(vtm))
    res = results[-1]
    assert list(blocks.keys()) == sorted(res.region_tags, key=res.region_tags.get) == ["muscle", "adipose"]
    assert sum(b.n_cells for b in blocks) == whole.n_cells
    for name, block in zip(blocks.keys(), blocks):
        ids = np.flatnonzero(np.asarray(whole.cell_data["region"]) == res.region_tags[name])
        assert len(ids) == block.n_cells > 0
        np.testing.assert_array_equal(block.cell_data["mesh_cell_id"], ids)
        for key in ("von_mises_MPa", "cauchy_stress_MPa", "principal_stretches", "region"):
            np.testing.assert_array_equal(block.cell_data[key], whole.cell_data[key][ids])
        nodes = np.asarray(block.point_data["mesh_node_id"])
        np.testing.assert_array_equal(block.points, whole.points[nodes])
        np.testing.assert_array_equal(block.point_data["displacement"], whole.point_data["displacement"][nodes])
        # the same cells: each piece cell's nodes are the whole-mesh cell's nodes
        piece_cells = block.cells.reshape(block.n_cells, -1)[:, 1:]
        whole_cells = whole.cells.reshape(whole.n_cells, -1)[:, 1:]
        np.testing.assert_array_equal(nodes[piece_cells], whole_cells[ids])
        assert any(k.startswith(f"region {res.region_tags[name]} = {name} (material ") for k in block.field_data)
    # files and the pieces' folder follow the umask (0o027: no access for others, no write for the group)
    for f in (vtm, tmp_path / "fe_1.vtu", *sorted((tmp_path / "fe_1").iterdir())):
        assert f.stat().st_mode & 0o777 == 0o640, f
    assert (tmp_path / "fe_1").stat().st_mode & 0o777 == 0o750
    assert not list(tmp_path.rglob(".*")), "temporary files left behind"


def test_blocks_are_relocatable_and_the_series_lists_them(tmp_path, results):
    import pyvista as pv

    write_results(tmp_path / "run", results, {})
    text = (tmp_path / "run" / "fe_1.vtm").read_text(encoding="utf-8")
    assert str(tmp_path) not in text and 'file="fe_1/muscle.vtu"' in text
    moved = tmp_path / "copy"
    shutil.copytree(tmp_path / "run", moved)
    shutil.rmtree(tmp_path / "run")
    assert list(pv.read(str(moved / "fe_1.vtm")).keys()) == ["muscle", "adipose"]
    # the .pvd series (force or load factor as time) reads back as the named blocks at each time
    reader = pv.get_reader(str(moved / "fe.pvd"))
    assert reader.time_values == [0.5, 1.0]
    reader.set_active_time_value(1.0)
    data = reader.read()
    blocks = data[0] if isinstance(data[0], pv.MultiBlock) else data
    assert list(blocks.keys()) == ["muscle", "adipose"]
    m = blocks["muscle"]  # the block at time 1.0 holds the load factor 1.0's field
    np.testing.assert_allclose(m.point_data["displacement"], results[-1].displacement[m.point_data["mesh_node_id"]])
    assert not np.allclose(results[0].displacement, results[-1].displacement)


def test_the_whole_vtu_reads_back_bit_for_bit_in_meshio_and_vtk(tmp_path, results):
    """VTK's writer (zlib level VTU_ZLIB_LEVEL): every array, its dtype, the tetra10 node order and the field
    data come back unchanged through meshio and through VTK's reader (ParaView's)."""
    import meshio
    import pyvista as pv

    res = results[-1]
    path = res.write_vtu(tmp_path / "r.vtu", force_N=12.5, blocks=False)
    m = meshio.read(path)
    assert [c.type for c in m.cells] == ["tetra10"]
    np.testing.assert_array_equal(m.cells[0].data, res.cells)
    np.testing.assert_array_equal(m.points, res.points)
    np.testing.assert_array_equal(m.point_data["displacement"], res.displacement)
    assert set(m.cell_data) == set(res.cell_data)
    for key, values in res.cell_data.items():
        assert m.cell_data[key][0].dtype == np.asarray(values).dtype, key
        np.testing.assert_array_equal(m.cell_data[key][0], values)
    assert m.field_data["force_N"][0] == 12.5 and m.field_data["load_factor"][0] == res.load_factor
    for region, tag in res.region_tags.items():
        name = next(k for k in m.field_data if k.startswith(f"region {tag} = {region}"))
        assert m.field_data[name][0] == tag and m.field_data[name].dtype.kind == "i"
    g = pv.read(path)
    np.testing.assert_array_equal(g.cells_dict[pv.CellType.QUADRATIC_TETRA], res.cells)
    np.testing.assert_array_equal(g.cell_data["green_lagrange_strain"], res.cell_data["green_lagrange_strain"])
    assert b'compressor="vtkZLibDataCompressor"' in path.read_bytes()[:400]
