"""The split sides' virtual gap (fem.contact.mesh.virtual_gap_offsets): every side-b copy starts the gap
away from every side-a face at its node, also at the right-angled edges of a voxel staircase, and pinch
points that no offset separates stay tied."""

import ipctk
import numpy as np
import pytest

from needletissue.fem.contact import ContactSurface
from needletissue.fem.contact.item import _collisions
from needletissue.fem.contact.mesh import split_interfaces, triangles
from needletissue.models.contact_verify import stacked_boxes

GAP = 0.09  # 0.9 dhat with dhat = 0.1 mm (ContactSettings' defaults)


def _rest_distances(points, surface):
    """Barrier distances (mm) of all collision pairs within dhat = GAP / 0.9 in the rest state."""
    V = np.asfortranarray(points[surface.vertices] + surface.offset)
    F = np.asfortranarray(surface.faces, dtype=np.int32)
    mesh = ipctk.CollisionMesh(V, np.asfortranarray(ipctk.edges(F), dtype=np.int32), F)
    mesh.can_collide = ipctk.make_connected_components_filter(F)
    c = _collisions()
    c.build(mesh, V, GAP / 0.9)
    return np.array([np.sqrt(c[i].compute_distance(c[i].dof(V, mesh.edges, mesh.faces))) for i in range(len(c))])


def _vertex_normal_offsets(points, itf, surface):
    """The rule before: side a's area-weighted vertex normal x gap (reference, to show what changed)."""
    ta = triangles(itf.faces_a)
    n = np.zeros((len(points), 3))
    fn = np.cross(points[ta[:, 1]] - points[ta[:, 0]], points[ta[:, 2]] - points[ta[:, 0]])
    for j in range(3):
        np.add.at(n, ta[:, j], fn)
    partner = np.arange(len(points))
    partner[itf.nodes_b] = itf.nodes_a
    b = ~np.isin(surface.vertices, np.unique(ta))
    out = np.zeros_like(surface.offset)
    nb = n[partner[surface.vertices[b]]]
    out[b] = GAP * nb / np.linalg.norm(nb, axis=1, keepdims=True)
    return out


def test_flat_interface_keeps_the_normal_offset():
    mesh = stacked_boxes({"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (10, 10, 10))}, 2.5)
    split, (itf,) = split_interfaces(mesh, ["lower-upper"])
    s = ContactSurface.build(split.points, [itf], {"lower-upper": 0.3}, gap=GAP)
    b = np.isin(s.vertices, itf.nodes_b)
    assert b.sum() == 25
    np.testing.assert_allclose(s.offset[b], np.tile([0, 0, GAP], (25, 1)), atol=1e-12)
    assert np.all(s.offset[~b] == 0)
    assert _rest_distances(split.points, s).min() == pytest.approx(GAP, rel=1e-9)


def test_staircase_edges_start_the_gap_apart():
    """Side a an L-shaped step (a convex and a concave right-angled edge), side b over it: every side-b copy
    lies >= gap from the plane of each side-a face at its node, the closest rest pair is >= 0.9 gap apart,
    while side a's vertex normal left the convex edge gap/sqrt(2) from the faces beside it."""
    boxes = {"lower_base": ((0, 0, -5), (10, 10, 0)), "lower_step": ((0, 0, 0), (5, 10, 5)),
             "upper_low": ((5, 0, 0), (10, 10, 5)), "upper_top": ((0, 0, 5), (10, 10, 10))}
    mesh = stacked_boxes(boxes, 2.5)
    split, (itf,) = split_interfaces(mesh, ["lower-upper"])
    assert len(itf.nodes_a) == 5 * (3 + 1 + 3)  # z = 0 (x >= 5), x = 5 (0 < z < 5), z = 5 (x <= 5): none tied
    s = ContactSurface.build(split.points, [itf], {"lower-upper": 0.3}, gap=GAP)
    ta = triangles(itf.faces_a)
    fn = np.cross(split.points[ta[:, 1]] - split.points[ta[:, 0]], split.points[ta[:, 2]] - split.points[ta[:, 0]])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    pos = dict(zip(itf.nodes_b.tolist(), itf.nodes_a.tolist()))
    for k, v in enumerate(s.vertices):
        if v in pos:
            faces = (ta == pos[v]).any(axis=1)
            assert (fn[faces] @ s.offset[k]).min() >= GAP * (1 - 1e-3)
    d = _rest_distances(split.points, s)
    assert d.min() >= 0.9 * GAP
    old = ContactSurface(s.vertices, s.faces, _vertex_normal_offsets(split.points, itf, s), s.side_a, s.side_b,
                         s.friction, s.interfaces)
    assert _rest_distances(split.points, old).min() == pytest.approx(GAP / np.sqrt(2), rel=0.02)
    # the convex edge (x = 5, z = 5) moves along the diagonal by sqrt(2) gap
    edge = np.isclose(split.points[s.vertices, 0], 5) & np.isclose(split.points[s.vertices, 2], 5)
    edge &= np.isin(s.vertices, itf.nodes_b)
    np.testing.assert_allclose(s.offset[edge], np.tile([GAP, 0, GAP], (edge.sum(), 1)), atol=1e-6 * GAP)


def test_pinch_points_stay_tied():
    """A 2 x 2 x 2 checkerboard of 5 mm cubes: the cubes of a side touch each other only along the central
    lines, where side a's faces point in opposite directions (no offset separates a copy from both): those
    nodes stay tied, every other interface node is split, and the rest pairs start >= 0.9 gap apart."""
    boxes = {f"{'a' if (i + j + k) % 2 == 0 else 'b'}_{i}{j}{k}": ((5 * i, 5 * j, 5 * k), (5 * i + 5, 5 * j + 5, 5 * k + 5))
             for i in range(2) for j in range(2) for k in range(2)}
    mesh = stacked_boxes(boxes, 2.5)
    split, (itf,) = split_interfaces(mesh, ["a-b"])
    on_two_mid_planes = (np.isclose(mesh.points, 5).sum(axis=1) >= 2)
    pinch = np.flatnonzero(on_two_mid_planes)
    assert len(pinch) == 13  # three central lines of 5 nodes sharing the centre
    assert not np.isin(pinch, itf.nodes_a).any()
    interface = np.flatnonzero(np.isclose(mesh.points, 5).any(axis=1))
    assert set(itf.nodes_a.tolist()) == set(interface.tolist()) - set(pinch.tolist())
    s = ContactSurface.build(split.points, [itf], {"a-b": 0.3}, gap=GAP)
    assert _rest_distances(split.points, s).min() >= 0.9 * GAP
