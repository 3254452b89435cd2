"""Verification of the frictional contact item (ipctk barrier + lagged smoothed friction).

Expected values come from statics (Coulomb: tangential force = mu N while sliding; equilibrium: the
contact transmits the applied load) and from the barrier's construction (interpenetration < dhat).
"""

import felupe as fem
import numpy as np
import pytest

from needletissue.errors import ConvergenceError, InputError
from needletissue.fem.contact import ContactSettings, resolve_interfaces
from needletissue.fem.contact.mesh import split_interfaces
from needletissue.models.contact_verify import build_model, pressed_blocks, solve_steps, stacked_boxes

DHAT = 0.1  # the default (ContactSettings.dhat)
EPS_V = 1e-3
MU = 0.3
LAG = "step"


def _block_on_plane(h, mu, lag="iteration"):
    """10 mm block (G = 1 MPa) on a 30 x 30 x 5 mm stiffer plate (G = 10 MPa), interface at z = 0."""
    mesh = stacked_boxes({"plate": ((0, 0, -5), (30, 30, 0)), "block": ((10, 10, 0), (20, 20, 10))}, h)
    mats = {"plate": fem.NeoHooke(mu=10.0, bulk=50.0), "block": fem.NeoHooke(mu=1.0, bulk=5.0)}
    settings = ContactSettings(dhat=DHAT, youngs_modulus=3.0, eps_v=EPS_V, lag=lag)
    return build_model(mesh, mats, {"plate-block": mu}, settings)


def _top_nodes_and_weights(model, z):
    X = model.field.region.mesh.points
    top = np.flatnonzero(np.isclose(X[:, 2], z) & (X[:, 0] >= 10 - 1e-9) & (X[:, 0] <= 20 + 1e-9)
                         & (X[:, 1] >= 10 - 1e-9) & (X[:, 1] <= 20 + 1e-9))
    return X, top


PRESS = 0.5  # mm, prescribed downward displacement of the block's top (about 15 N)


def _slide(h, shear, mode, lag=LAG):
    """Press the block's rigid top down by PRESS (a body held only by contact needs a displacement-
    controlled normal: at zero gap the barrier is not yet active), then shear it (mode "disp":
    prescribed ux in mm; mode "force": a total tangential force in N). Returns (model, solution,
    top nodes, normal force N)."""
    m = _block_on_plane(h, MU, lag)
    X, top = _top_nodes_and_weights(m, 10.0)
    u = m.field[0]
    on_top = np.isin(np.arange(len(X)), top)
    bnd = {
        "bottom": fem.Boundary(u, mask=np.isclose(X[:, 2], -5)),
        "top_yz": fem.Boundary(u, mask=on_top, skip=(1, 0, 0)),
    }
    if mode == "disp":
        bnd["top_x"] = fem.Boundary(u, mask=on_top, skip=(0, 1, 1))
    load = fem.PointLoad(m.field, top)
    m.solids.append(load)
    n = len(top)

    def apply(t):
        # first half of the ramp: press; second half: shear at full press
        bnd["top_yz"].update(np.array([0.0, -PRESS * min(1.0, 2 * t)]))
        s = shear * max(0.0, 2 * t - 1)
        values = np.zeros((n, 3))
        if mode == "force":
            values[:, 0] = s / n
        else:
            bnd["top_x"].update(s)
        load.update(values)

    sol = solve_steps(m, bnd, apply, [0.5, 0.75, 1.0], initial_step=0.25, min_step=1 / 64)
    r = sol.steps[-1].reaction.reshape(-1, 3)
    normal = r[top, 2].sum()  # reaction on the prescribed top (pressing down: > 0 on the body)
    return m, sol, top, abs(normal)


def test_contact_solve_repeats_bit_for_bit():
    """The same frictional solve twice in one process gives the same bits: ipctk's threaded sums made the
    reaction differ at 1e-15 from run to run, and once the Newton path with it (a suite run's cut-back)."""
    a = _slide(2.5, 1.5, "disp")
    b = _slide(2.5, 1.5, "disp")
    assert a[3] == b[3]
    assert np.array_equal(a[1].steps[-1].reaction, b[1].steps[-1].reaction)


def _slip_x(model, displacement):
    itf = model.contact.surface.interfaces[0]
    return (displacement[itf.nodes_b] - displacement[itf.nodes_a])[:, 0]


def _slip(model, displacement):
    itf = model.contact.surface.interfaces[0]
    jump = displacement[itf.nodes_b] - displacement[itf.nodes_a]
    return np.abs(jump[:, 0])


def test_block_slides_at_mu_n_when_pushed_beyond_it():
    """Displacement-controlled shear of 1.5 mm (> elastic shear of the block): tangential reaction
    = mu N (Coulomb, within 3 %), the block slides (interface slip >> eps_v)."""
    m, sol, top, N = _slide(2.5, 1.5, "disp")
    assert N > 5.0
    r = sol.steps[-1].reaction.reshape(-1, 3)
    tangential = r[top, 0].sum()  # internal force at the prescribed dofs = applied shear
    assert tangential / N == pytest.approx(MU, rel=0.03)
    assert _slip(m, sol.steps[-1].displacement).min() > 100 * EPS_V


def test_block_sticks_below_mu_n_and_fails_to_find_equilibrium_above():
    """Force-controlled shear: 0.5 mu N is carried with slip of the order of eps_v (stick);
    1.5 mu N has no static equilibrium: the solver cuts back and raises ConvergenceError."""
    _, _, _, N = _slide(2.5, 0.0, "force")  # the normal force of the press alone
    m, sol, _, n_sheared = _slide(2.5, 0.5 * MU * N, "force")
    assert n_sheared == pytest.approx(N, rel=0.05)
    # slip added by the shear (the press alone slides the rim outward: Poisson expansion); the
    # rim may micro-slip (Cattaneo-Mindlin), the bulk of the interface sticks
    added = _slip_x(m, sol.steps[-1].displacement) - _slip_x(m, sol.steps[0].displacement)
    assert np.median(np.abs(added)) < 5 * EPS_V
    with pytest.raises(ConvergenceError, match="load factor"):
        _slide(2.5, 1.5 * MU * N, "force")


def _pressed(h, friction, push=1.0):
    """Two blocks (G = 10 and 1 MPa) pressed by a prescribed top displacement; x = 0 and y = 0 are
    symmetry planes, the bottom slides on z = -5."""
    m, sol = pressed_blocks(h, friction, ContactSettings(dhat=DHAT, youngs_modulus=3.0, eps_v=EPS_V), push)
    X = m.field.region.mesh.points
    r = sol.steps[-1].reaction.reshape(-1, 3)
    top, bottom = np.isclose(X[:, 2], 10), np.isclose(X[:, 2], -5)
    return m, sol, r[top, 2].sum(), r[bottom, 2].sum()


def test_pressed_blocks_transmit_the_normal_force_without_interpenetration():
    m, sol, r_top, r_bottom = _pressed(2.5, {"lower-upper": MU})
    # the whole load crosses the contact: equal and opposite reactions, and the contact forces on
    # the upper block's collision vertices add up to the applied load
    assert r_top < -10.0
    assert r_bottom == pytest.approx(-r_top, rel=1e-6)
    f = m.contact.contact_forces()
    upper = m.contact.surface.side_b > 0
    assert f[upper, 2].sum() == pytest.approx(-r_top, rel=1e-3)
    # interpenetration (physical gap < 0) stays below dhat; the barrier never let it pass through
    # (node pairs off the rim: at the rim the softer block bulges over the edge of the lower one)
    itf = m.contact.surface.interfaces[0]
    inner = np.all(m.mesh.points[itf.nodes_a, :2] < 10 - 1e-6, axis=1)
    opening = m.contact.gap_opening(sol.steps[-1].displacement)["lower-upper"][inner]
    assert opening.min() > -DHAT
    assert opening.min() < 0  # the contact is loaded, so it is compressed into the barrier zone
    assert sol.steps[-1].contact["max_interpenetration_mm"] < DHAT
    # frictional contact is softer than a bonded interface (Poisson expansion is less restrained),
    # stiffer than frictionless contact
    _, _, r_bonded, _ = _pressed(2.5, None)
    _, _, r_free, _ = _pressed(2.5, {"lower-upper": 0.0})
    assert abs(r_free) < abs(r_top) < abs(r_bonded)


def test_pressed_blocks_mesh_refinement():
    """Halving the element size (5 -> 2.5 mm) changes the transmitted force by < 2 % (the area-weighted barrier is
    a pressure law, so no mesh-dependent penalty)."""
    _, _, r_coarse, _ = _pressed(5.0, {"lower-upper": MU})
    _, _, r_fine, _ = _pressed(2.5, {"lower-upper": MU})
    assert r_fine == pytest.approx(r_coarse, rel=0.02)


def test_split_duplicates_only_the_interface_nodes():
    mesh = stacked_boxes({"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (10, 10, 10))}, 2.5)
    split, (itf,) = split_interfaces(mesh, ["lower-upper"])
    n_interface = 5 * 5  # grid nodes on the 10 x 10 mm interface with h = 2.5
    assert len(split.points) == len(mesh.points) + n_interface
    assert np.allclose(split.points[itf.nodes_a], split.points[itf.nodes_b])
    lower = set(np.unique(split.cells[split.regions["lower"]]))
    upper = set(np.unique(split.cells[split.regions["upper"]]))
    assert not lower & upper  # the bodies no longer share a node


def test_bad_input_names_the_field():
    mesh = stacked_boxes({"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (10, 10, 10))}, 5.0)
    with pytest.raises(InputError, match="interfaces"):
        resolve_interfaces(mesh, "paper", {"lower-upper": -0.1})
    with pytest.raises(InputError, match="does not exist"):
        resolve_interfaces(mesh, "paper", {"needle-muscle": 0.3})
    with pytest.raises(InputError, match="bonded"):
        resolve_interfaces(mesh, "glued")
    with pytest.raises(InputError, match="no region"):
        split_interfaces(mesh, ["lower-bone"])
    with pytest.raises(InputError, match="dhat"):
        ContactSettings(dhat=0)
    assert resolve_interfaces(mesh, "bonded") == {}
    assert resolve_interfaces(mesh, "paper") == {}  # no needle, muscle or bone in this mesh
    assert resolve_interfaces(mesh, "bonded", {"upper-lower": 0.5}) == {"upper-lower": 0.5}


def test_friction_option_parsing():
    from needletissue.fem.contact import parse_friction

    assert parse_friction(["needle-muscle=0.3", "bone-needle = 0.9"]) == {"needle-muscle": 0.3, "bone-needle": 0.9}
    for bad in (["needle-muscle"], ["needle-muscle=abc"], ["needle-muscle=-1"], ["=0.3"]):
        with pytest.raises(InputError, match="friction"):
            parse_friction(bad)


def test_split_quadratic_mesh_keeps_midside_nodes_with_their_side():
    box = stacked_boxes({"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (10, 10, 10))}, 2.5)
    mesh = box.to_quadratic()
    split, (itf,) = split_interfaces(mesh, ["lower-upper"])
    on_plane = np.flatnonzero(np.isclose(mesh.points[:, 2], 0.0))  # corner and midside nodes at z = 0
    assert len(split.points) == len(mesh.points) + len(on_plane)
    assert itf.faces_a.shape[1] == 6
    lower = set(np.unique(split.cells[split.regions["lower"]]))
    upper = set(np.unique(split.cells[split.regions["upper"]]))
    assert not lower & upper
    # every side-b face node is a copy at the same place as its side-a twin
    assert np.allclose(split.points[itf.nodes_b], mesh.points[itf.nodes_a])


def test_material_groups_name_anatomical_regions():
    from needletissue.fem.contact.mesh import group_regions, material_groups

    mats = {"gluteus_medius": "muscle", "iliopsoas": "muscle", "hip_cortical": "cortical_bone",
            "hip_cancellous": "cancellous_bone", "needle_1": "needle", "adipose": "adipose"}
    groups = material_groups(mats)
    assert set(groups["muscle"]) == {"gluteus_medius", "iliopsoas"}
    assert set(groups["bone"]) == {"hip_cortical", "hip_cancellous"}
    assert groups["cortical_bone"] == ("hip_cortical",)
    box = stacked_boxes({"hip_cortical": ((0, 0, -5), (10, 10, 0)), "iliopsoas": ((0, 0, 0), (10, 10, 10))}, 5.0)
    assert group_regions(box, "bone") == ()  # by name: no region called bone
    assert group_regions(box, "bone", groups) == ("hip_cortical",)
    assert resolve_interfaces(box, "paper", groups=groups) == {"muscle-bone": 0.3}
    split, (itf,) = split_interfaces(box, ["muscle-bone"], groups)
    assert itf.regions_a == ("iliopsoas",) and itf.regions_b == ("hip_cortical",)


def test_split_keeps_the_ring_bonded_to_a_third_region_tied():
    """Where side a (lower) also touches a region it stays bonded to (side, bonded to lower and to
    upper), the shared line is not split: upper stays tied to lower there, and the collision
    surface keeps the two sides separate components (no side-b triangle on a shared node)."""
    from needletissue.fem.contact import ContactSurface

    boxes = {"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (5, 10, 10)), "side": ((5, 0, 0), (10, 10, 10))}
    mesh = stacked_boxes(boxes, 2.5)
    split, (itf,) = split_interfaces(mesh, ["lower-upper"])
    ring = np.flatnonzero(np.isclose(mesh.points[:, 0], 5) & np.isclose(mesh.points[:, 2], 0))
    assert len(ring) == 5
    assert not np.isin(ring, itf.nodes_a).any()
    upper = np.unique(split.cells[split.regions["upper"]])
    assert np.isin(ring, upper).all()  # upper keeps the original ring nodes, shared with lower
    # every other interface node is duplicated
    assert len(split.points) == len(mesh.points) + 3 * 5 - 5
    surface = ContactSurface.build(split.points, [itf], {"lower-upper": 0.3}, gap=0.09)
    a = surface.faces[np.isin(surface.faces, np.flatnonzero(surface.side_a)).all(axis=1)]
    b = surface.faces[~np.isin(surface.faces, np.flatnonzero(surface.side_a)).any(axis=1)]
    assert len(a) + len(b) == len(surface.faces)
    assert not np.isin(surface.vertices[b], ring).any()


def test_split_rim_region_keeps_the_tissue_rim_in_one_piece():
    """rim=("side",): the line where lower (side a), upper (side b) and side (bonded to both) meet is
    split too; its copies belong to upper and side, so upper slides on lower right up to the line
    while staying bonded to side, and side stays bonded to lower everywhere else."""
    from needletissue.fem.contact import ContactSurface

    boxes = {"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (5, 10, 10)), "side": ((5, 0, 0), (10, 10, 10))}
    mesh = stacked_boxes(boxes, 2.5)
    split, (itf,) = split_interfaces(mesh, ["lower-upper"], rim=("side",))
    ring = np.flatnonzero(np.isclose(mesh.points[:, 0], 5) & np.isclose(mesh.points[:, 2], 0))
    assert np.isin(ring, itf.nodes_a).all()
    assert len(split.points) == len(mesh.points) + 3 * 5  # every interface node has a copy
    nodes = {r: set(np.unique(split.cells[split.regions[r]])) for r in boxes}
    assert not nodes["lower"] & nodes["upper"]
    copies = set(itf.nodes_b[np.isin(itf.nodes_a, ring)])
    assert copies <= nodes["upper"] & nodes["side"]
    # side keeps its bond to lower on the plane x > 5 (grid nodes 7.5 and 10 across, 5 along y)
    assert len(nodes["lower"] & nodes["side"]) == 2 * 5
    # lower's faces bonded to side along the line (one row, x 5..7.5) are collision faces of side a:
    # upper's rim slides onto lower's surface, not off its boundary edge
    assert len(itf.skirt_a) == 2 * 4 and np.isin(itf.skirt_a, ring).any(axis=1).all()
    assert np.all(split.points[itf.skirt_a][..., 0] >= 5) and np.allclose(split.points[itf.skirt_a][..., 2], 0)
    surface = ContactSurface.build(split.points, [itf], {"lower-upper": 0.3}, gap=0.09)
    assert len(surface.faces) == 2 * len(itf.faces_a) + len(itf.skirt_a)  # no side-b triangle dropped


@pytest.mark.parametrize("quadratic", [False, True])
def test_split_where_three_contact_interfaces_meet_keeps_every_face_in_contact(quadratic):
    """A pin (needle) through muscle into bone: needle-muscle, muscle-bone and bone-needle meet on a
    line. Split in that order, every face of each interface of the conforming mesh is a contact face
    (none left neither bonded nor in contact along the line), the three bodies share no node, and each
    pair is two nodes at one place."""
    from needletissue.fem.contact.mesh import interface_faces

    boxes = {"needle": ((5, 0, -2.5), (10, 10, 10)), "muscle": ((0, 0, 0), (5, 10, 10)),
             "cortical_bone": ((0, 0, -5), (5, 10, 0)), "cancellous_bone": ((5, 0, -5), (10, 10, -2.5))}
    mesh = stacked_boxes(boxes, 2.5)
    if quadratic:
        mesh = mesh.to_quadratic()
    names = ["needle-muscle", "muscle-bone", "bone-needle"]
    split, itfs = split_interfaces(mesh, names)
    bone = ("cortical_bone", "cancellous_bone")
    sides = {"needle-muscle": (("needle",), ("muscle",)), "muscle-bone": (("muscle",), bone),
             "bone-needle": (bone, ("needle",))}
    for itf in itfs:
        conforming, _ = interface_faces(mesh, *sides[itf.name])
        assert len(itf.faces_a) == len(itf.faces_b) == len(conforming), itf.name
        assert np.allclose(split.points[itf.nodes_a], split.points[itf.nodes_b])
        assert not np.isin(itf.nodes_a, itf.nodes_b).any()
    nodes = {k: set(np.unique(split.cells[np.concatenate([split.regions[r] for r in v])].ravel()))
             for k, v in {"needle": ("needle",), "muscle": ("muscle",), "bone": bone}.items()}
    assert not nodes["needle"] & nodes["muscle"] and not nodes["muscle"] & nodes["bone"]
    assert not nodes["bone"] & nodes["needle"]
    # the line x = 5, z = 0 (5 corner nodes) has one node per body: two copies added
    line = np.isclose(mesh.points[:, 0], 5) & np.isclose(mesh.points[:, 2], 0)
    at_line = np.isclose(split.points[:, 0], 5) & np.isclose(split.points[:, 2], 0)
    assert at_line.sum() == 3 * line.sum()


def test_implicit_friction_tangent_matches_finite_differences():
    """lag="iteration": the Jacobian includes the derivatives of the normal forces and tangent bases
    (ipctk force_jacobian by the lagged displacements), so it is the derivative of the residual:
    central differences agree to 1e-6 (barrier active, block sliding)."""
    m = _block_on_plane(2.5, MU, lag="iteration")
    c = m.contact
    X = m.field.region.mesh.points
    rng = np.random.default_rng(0)
    block = np.zeros(len(X), bool)
    block[np.unique(m.mesh.cells[m.mesh.regions["block"]])] = True
    u = np.zeros_like(X)
    u[block] = [0.0, 0.0, -0.03]  # 0.03 mm into the barrier (gap 0.09 of dhat 0.1)
    u[block, 0] += 0.002 + 0.01 * rng.random(block.sum())  # slip > eps_v: sliding
    u[block, 1] += 0.003 * rng.random(block.sum())  # off the axes (ipctk's tangent basis branches there)
    m.field[0].values[:] = u
    c.assemble.vector(m.field)
    K = c.assemble.matrix(m.field)
    assert c.results.info["active_contacts"] > 100
    du = np.zeros_like(u)
    du[block] = rng.standard_normal((block.sum(), 3))
    eps = 1e-7
    r = []
    for s in (1, -1):
        m.field[0].values[:] = u + s * eps * du
        r.append(c.assemble.vector(m.field).toarray().ravel())
    fd = (r[0] - r[1]) / (2 * eps)
    assert np.linalg.norm(K @ du.ravel() - fd) < 1e-6 * np.linalg.norm(fd)
    assert abs(K - K.T).max() > 1e-3 * abs(K).max()  # friction makes it non-symmetric


def _edge_pair(theta, slide=0.01, crossing=True):
    """Edge a on the x axis, edge b 0.095 mm (0.95 dhat) above it in y and turned by theta about y,
    crossing a's line at x = 0.7 (closest points inside both edges; crossing=False: b turned about
    its first end, the closest points at that end: ipctk's edge-vertex type), b sliding along x by
    `slide`. Rest: parallel (ipctk's mollifier threshold eps_x = 1e-3 |a|^2 |b|^2 = 1e-3 mm^4)."""
    import ipctk

    def pts(t):
        z0, z1 = (-0.5 * t, 0.5 * t) if crossing else (0.0, t)
        return np.asfortranarray([[0, 0, 0], [1, 0, 0], [0.2, 0.095, z0], [1.2, 0.095, z1]], float)

    rest = pts(0.0)
    cmesh = ipctk.CollisionMesh(rest, np.array([[0, 1], [2, 3]], np.int32), np.zeros((0, 3), np.int32))
    V = pts(theta)
    collisions = ipctk.NormalCollisions()
    collisions.use_area_weighting = True
    collisions.build(cmesh, V, DHAT)
    slip = np.asfortranarray(np.zeros_like(V))
    slip[2:, 0] = slide
    return cmesh, rest, V, collisions, slip


def _edge_pair_friction(theta, crossing=True):
    import ipctk
    from needletissue.fem.contact.item import tangential_collisions

    cmesh, rest, V, collisions, slip = _edge_pair(theta, crossing=crossing)
    barrier = ipctk.BarrierPotential(DHAT, 1.0, True)
    friction = ipctk.FrictionPotential(EPS_V)
    tangential, added = tangential_collisions(cmesh, V, collisions, barrier, np.full(4, MU))
    f = friction.force(tangential, cmesh, rest, np.asfortranarray(V - rest), slip, barrier)
    if not crossing:
        return f, None, None, added
    (c,) = collisions.ee_collisions  # one edge-edge pair, closest points inside both edges
    x = c.dof(V, cmesh.edges, cmesh.faces)
    # the same pair, unmollified, for reference
    full = ipctk.EdgeEdgeTangentialCollision(c, x, barrier)
    full.mu_s = full.mu_k = full.mu_s_effective_lagged = full.mu_k_effective_lagged = MU
    f1 = friction.force(full, c.dof(rest, cmesh.edges, cmesh.faces), x - c.dof(rest, cmesh.edges, cmesh.faces),
                        c.dof(slip, cmesh.edges, cmesh.faces), barrier)
    return f, f1, c.mollifier(x), added


def test_edge_edge_friction_scales_with_the_barriers_mollifier_and_is_continuous():
    """A nearly parallel edge-edge pair inside dhat: its barrier is scaled by ipctk's mollifier m
    (0 parallel .. 1 at sin^2 = eps_x); its friction must be m times the unmollified one, so it grows
    continuously through the threshold. ipctk 1.6.1's TangentialCollisions.build leaves the pairs
    with m < 1 out: friction 0 below the threshold, the full Coulomb force just above (a jump of
    the whole pair's friction: the residual floor of the default needle mesh)."""
    import ipctk

    threshold = np.sqrt(1e-3)  # theta with |a x b|^2 = theta^2 = eps_x (from the rest lengths, 1 mm)
    for theta in (1e-3, 0.01, 0.02, 0.03):
        f, f1, m, added = _edge_pair_friction(theta)
        assert 0 < m < 1 and len(added) == 1
        assert np.linalg.norm(f1) > 1e-4  # sliding (slip 10 eps_v): mu N per unit area-weight
        np.testing.assert_allclose(f, m * f1, rtol=1e-10, atol=1e-16)
    below, f1_below, m_below, _ = _edge_pair_friction(threshold * (1 - 1e-7))
    above, f1_above, m_above, added = _edge_pair_friction(threshold * (1 + 1e-7))
    assert m_above == 1 and not added and m_below > 1 - 1e-6
    np.testing.assert_allclose(above, f1_above, rtol=1e-12)  # ipctk's own pair above the threshold
    assert np.linalg.norm(below - above) < 1e-5 * np.linalg.norm(above)
    # closest points at an edge end: above the threshold ipctk's set has the edge-vertex pair
    below, _, _, added = _edge_pair_friction(threshold * (1 - 1e-7), crossing=False)
    above, _, _, none = _edge_pair_friction(threshold * (1 + 1e-7), crossing=False)
    assert len(added) == 1 and isinstance(added[0][0], ipctk.EdgeVertexTangentialCollision) and not none
    assert np.linalg.norm(above) > 1e-4
    assert np.linalg.norm(below - above) < 1e-5 * np.linalg.norm(above)


def test_edge_edge_friction_tangent_includes_the_mollifiers_derivative():
    """lag="iteration": d(friction force)/d(positions) of a mollified pair = ipctk's force_jacobian
    (velocities + lagged displacements, which differentiate N, not m) + F / m (x) grad m: central
    differences of the force agree to 1e-6."""
    import ipctk
    from needletissue.fem.contact.item import mollifier_force_jacobian, tangential_collisions

    theta = 0.02
    cmesh, rest, V, collisions, slip = _edge_pair(theta)
    barrier = ipctk.BarrierPotential(DHAT, 1.0, True)
    friction = ipctk.FrictionPotential(EPS_V)
    mu = np.full(4, MU)

    def force(dV):
        Vp = np.asfortranarray(V + dV)
        col = ipctk.NormalCollisions()
        col.use_area_weighting = True
        col.build(cmesh, Vp, DHAT)
        t, _ = tangential_collisions(cmesh, Vp, col, barrier, mu)
        return friction.force(t, cmesh, rest, np.asfortranarray(Vp - rest), np.asfortranarray(slip + dV), barrier)

    t, added = tangential_collisions(cmesh, V, collisions, barrier, mu)
    W = ipctk.FrictionPotential.DiffWRT
    args = (t, cmesh, rest, np.asfortranarray(V - rest), slip, barrier)
    J = friction.force_jacobian(*args, W.VELOCITIES) + friction.force_jacobian(*args, W.LAGGED_DISPLACEMENTS)
    Jm = mollifier_force_jacobian(friction, added, cmesh, rest, V, slip, barrier)
    rng = np.random.default_rng(1)
    d = rng.standard_normal(V.shape)
    eps = 1e-7
    fd = (force(eps * d) - force(-eps * d)) / (2 * eps)
    assert np.linalg.norm(J @ d.ravel() - fd) > 1e-3 * np.linalg.norm(fd)  # ipctk's alone misses m's part
    assert np.linalg.norm((J + Jm) @ d.ravel() - fd) < 1e-6 * np.linalg.norm(fd)


def test_nearly_parallel_filter_keeps_every_mollified_edge_pair():
    """The vectorised pre-test of tangential_collisions keeps exactly the edge-edge collisions whose
    mollifier ipctk computes below 1, at rest and deformed."""
    import ipctk

    from needletissue.fem.contact import item

    rng = np.random.default_rng(0)
    V = rng.normal(size=(400, 3))
    E = rng.integers(0, 400, size=(300, 2))
    E = E[E[:, 0] != E[:, 1]]
    # nearly parallel copies of some edges, 0.01 mm away
    V = np.vstack([V, V[:200] + 1e-3 * rng.normal(size=(200, 3)) + [0.0, 0.0, 0.01]])
    E = np.vstack([E, E[E.max(1) < 200] + 400]).astype(np.int32)
    cmesh = ipctk.CollisionMesh(V, E, np.zeros((0, 3), np.int32))
    for X in (V, V + 2e-3 * rng.normal(size=V.shape)):
        collisions = ipctk.NormalCollisions()
        collisions.build(cmesh, X, 0.05)
        ee = collisions.ee_collisions
        kept = {(c.edge0_id, c.edge1_id) for c in item._nearly_parallel(ee, X, cmesh.edges)[0]}
        mollified = {(c.edge0_id, c.edge1_id) for c in ee if c.mollifier(c.dof(X, cmesh.edges, cmesh.faces)) < 1}
        assert len(ee) > 500 and len(mollified) > 10
        assert kept == mollified


def _give_up_at(residuals):
    """The iteration (1-based) at which the contact line search gives up on an increment with these
    relative residuals, or None."""
    from types import SimpleNamespace

    from felupe.tools._newton import NewtonConvergenceError

    from needletissue.fem.contact.item import StallLinesearch

    search = StallLinesearch([])
    search.fnorms, search.history = [], []
    for k, r in enumerate(residuals, 1):
        try:
            search.after_iteration(None, SimpleNamespace(fnorm=r, success=r < 1e-8))
        except NewtonConvergenceError as exc:
            assert "plateau" in str(exc)
            return k
    return None


def test_contact_newton_gives_up_on_a_plateau_and_not_on_slow_progress():
    """Residual histories logged by benchmarks/contact_newton_log.py (docs/contact.md, "Giving up on a
    plateau"): the coarse needle model's failed 200 -> 300 N increment (stuck at ~21) and its failed 200 ->
    250 N one (a floor at 6.6e-6) each ran maxiter = 25 iterations before their cut-back; the default
    mesh's 12.3 N increment falls by a few per cent per iteration and converges in 16."""
    stuck = [859.2, 382.3, 134.9, 23.25, 21.18, 21.13, 21.09, 21.08, 21.02, 20.96, 20.94, 20.86, 20.75, 491200.0]
    floor = [486.1, 0.002963, 0.03929, 7.98e-06, 2.141e-05, 6.22e-05, 7.14e-06, 6.59e-06, 6.635e-06, 0.0003689,
             7.824e-06, 6.595e-06, 6.705e-06, 0.0001793]
    slow = [398.9, 355.1, 349.5, 307.0, 286.5, 288.2, 278.0, 266.8, 259.2, 225.3, 189.7, 60.59, 18.85, 7.21,
            0.9326, 8.554e-10]
    assert _give_up_at(stuck) == 10  # instead of 25
    assert _give_up_at(floor) == 13
    assert _give_up_at(slow) is None
    assert _give_up_at([1.0 * 0.97 ** k for k in range(40)]) is None  # 3 % per iteration is progress
    assert _give_up_at([1.0 * 0.995 ** k for k in range(40)]) == 6  # 0.5 % is not


def test_collision_free_fraction_stops_short_of_the_other_surface():
    """CollisionFreeStep.step_fraction (Newton's steps and fem.solve's predictor in contact runs): a step that
    would push the block through the plate is shortened to `fraction` of the largest collision-free part of it,
    which the CCD then admits while the whole step it does not; a step away from the plate is taken whole."""
    import ipctk

    from needletissue.fem.contact.item import CollisionFreeStep

    m = _block_on_plane(5.0, MU)
    item = m.contact
    X = m.field.region.mesh.points
    u = np.zeros_like(X)
    du = np.zeros_like(X)
    block = np.flatnonzero(X[:, 2] > 1e-9)
    block = np.union1d(block, item.surface.vertices[item.surface.side_b > 0])  # and its split interface copies
    du[block, 2] = -0.3  # three dhat down: through the plate

    step = CollisionFreeStep([item])
    f = step.step_fraction(u, du)
    assert 0 < f < step.fraction
    v = item.surface.vertices  # `fraction` of the collision-free part: a margin below what CCD allows
    assert f == pytest.approx(step.fraction * item.step_bound(u[v], du[v]))
    V0, through, short = (item.positions((u + s * du)[v]) for s in (0.0, 1.0, f))
    assert not ipctk.is_step_collision_free(item.cmesh, V0, through, narrow_phase_ccd=item.ccd)
    assert ipctk.is_step_collision_free(item.cmesh, V0, short, narrow_phase_ccd=item.ccd)
    # the block's face moved down by f * 0.3 mm, less than the virtual gap it started with
    assert f * 0.3 < item.settings.gap
    assert step.step_fraction(u, -du) == 1.0
