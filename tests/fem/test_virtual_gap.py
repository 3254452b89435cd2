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


def test_min_norm_point_is_exact_where_it_is_known_and_never_longer_than_slsqp():
    """The shortest offset that clears every face plane by the gap: gap n for one face, gap (e1 + e2) and
    gap (1, 1, 1) at a staircase's edge and corner, none between opposite faces (a pinch point); for
    random corners it satisfies every constraint, its multipliers are >= 0 (KKT), and SciPy's SLSQP
    (what it replaced) finds nothing shorter."""
    from scipy.optimize import minimize

    from needletissue.fem.contact.mesh import _min_norm_points

    g = 0.095
    e = np.eye(3)
    x = _min_norm_points(np.array([e[:1], [e[2]]]), g)
    np.testing.assert_allclose(x, [[g, 0, 0], [0, 0, g]], atol=1e-15)
    np.testing.assert_allclose(_min_norm_points(np.array([e[:2]]), g), [[g, g, 0]], atol=1e-15)
    np.testing.assert_allclose(_min_norm_points(np.array([e]), g), [[g, g, g]], atol=1e-15)
    assert np.all(np.isinf(_min_norm_points(np.array([[e[0], -e[0]]]), g)))
    rng = np.random.default_rng(7)
    for k in (2, 3, 4, 6):
        N = rng.normal(size=(40, k, 3)) * 0.6 + [0, 0, 1]  # normals around +z: a feasible corner
        N /= np.linalg.norm(N, axis=2, keepdims=True)
        X = _min_norm_points(N, g)
        for n, x in zip(N, X):
            assert (n @ x).min() >= g * (1 - 1e-9)
            active = np.abs(n @ x - g) <= 1e-9 * g
            lam = np.linalg.lstsq(n[active].T, 2 * x, rcond=None)[0]  # grad |x|^2 = N_active^T lam
            np.testing.assert_allclose(n[active].T @ lam, 2 * x, atol=1e-9 * g)
            assert lam.min() >= -1e-9
            r = minimize(lambda y: y @ y, n.mean(axis=0) * 2 * g, jac=lambda y: 2 * y, method="SLSQP",
                         constraints=[{"type": "ineq", "fun": lambda y: n @ y - g, "jac": lambda y: n}])
            if r.success and (n @ r.x).min() >= g * (1 - 1e-9):
                assert x @ x <= r.x @ r.x * (1 + 1e-12)
