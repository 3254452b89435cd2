"""Frictional contact between deformable FElupe bodies via the IPC Toolkit (``ipctk``).

``FrictionalContact`` is a FElupe item (attributes ``field``, ``assemble``, ``results``): it is
assembled beside the SolidBodies by ``felupe.newtonraphson``/``Job`` and by
``needletissue.fem.solve(..., items=[contact])``. Its vector and matrix are the gradient and Hessian
of the IPC barrier potential (normal contact) plus the smoothed, lagged friction dissipative potential,
mapped from the collision-surface vertices to the global displacement dofs.

Modelling choices (details and the reasons in docs/contact.md):

* Interfaces come from a conforming mesh split by ``needletissue.fem.contact.mesh.split_interfaces``; the two sides
  start coincident. The barrier needs a positive distance, so side b's collision vertices are shifted
  by ``gap = 0.9 dhat`` outward of side a, from every side-a face at their node
  (``virtual_gap_offsets``): zero physical gap is (almost) the barrier's activation distance, and the
  physical interpenetration is bounded by ``gap < dhat`` (the barrier diverges before it).
* Area-weighted ("convergent") barrier: ``stiffness`` is a contact stiffness per area (MPa/mm), so the
  contact pressure does not depend on the mesh size.
* Friction (Li et al. 2020, IPC): slip is the displacement since the last converged step; the normal
  forces and tangent bases are those of the current state (``lag="iteration"``, the default: the
  Jacobian includes their derivatives, ipctk's ``force_jacobian`` by the lagged displacements, so
  Newton stays quadratic and friction acts from the first increment), or those of the last converged
  step (``lag="step"``: symmetric Jacobian, but one step behind and the first increment frictionless).
  Slip below ``eps_v`` (mm) is the smoothed static regime.
* Every evaluation checks, by continuous collision detection from the last converged state, that the
  surfaces did not pass through each other; if they did, the residual is NaN, so a line search halves
  the step and a plain Newton iteration fails and the load step is cut back.
"""

from __future__ import annotations

from dataclasses import dataclass, field as dc_field
from functools import lru_cache

import ipctk
import numpy as np
from felupe import LinesearchPlugin, Plugin
from felupe.plugins import LinesearchTrial
from felupe.mechanics import Assemble, Results
from scipy.sparse import coo_matrix, csr_matrix

from needletissue.errors import InputError, check_number
from needletissue.fem.contact.mesh import SplitInterface, triangles, vertex_normals, virtual_gap_offsets

# ipctk on one thread: its threaded sums (TBB) differ in the last bits from run to run, and a contact Newton
# path near a barrier follows them (the pressed-block test reached 0.852 of its load in one run of the suite and
# converged in the others; the same model repeated in one process gave a reaction differing at 1e-15 each time,
# bit for bit equal on one thread). Its share of a contact solve is a few percent (docs/contact.md).
ipctk.set_num_threads(1)

PAPER_INTERFACES = {"needle-muscle": 0.3, "muscle-bone": 0.3, "bone-needle": 0.9}
"""Friction coefficients of the paper (section 2.3): every other interface is bonded."""


@dataclass(frozen=True)
class ContactSettings:
    """Numerical parameters of the contact (units mm, MPa).

    dhat: barrier activation distance = largest admitted interpenetration, mm.
    stiffness: barrier stiffness per area, MPa/mm (None: ``default_stiffness(youngs_modulus, dhat)``).
    youngs_modulus: modulus of the softer body, MPa, used only for the default stiffness.
    eps_v: slip below which friction is smoothed (static regime), mm per load step.
    lag: "iteration" (friction from the current normal forces/tangent bases, consistent tangent:
      friction from the first increment) or "step" (those of the last converged step: the first
      increment is frictionless).
    gap_fraction: the coincident sides start gap_fraction * dhat apart for the barrier: < 1 keeps
      the barrier slightly active at rest (a tiny prestress, but a positive contact stiffness, so a
      body held only by contact is not singular at the first iteration).
    pressure_fraction: the default stiffness carries pressure_fraction * youngs_modulus at d = dhat/2.
    """

    dhat: float = 1e-1
    stiffness: float | None = None
    youngs_modulus: float = 1.0
    eps_v: float = 1e-3
    lag: str = "iteration"
    gap_fraction: float = 0.9
    pressure_fraction: float = 0.1

    def __post_init__(self):
        check_number("contact.dhat", self.dhat, gt=0)
        check_number("contact.youngs_modulus", self.youngs_modulus, gt=0)
        check_number("contact.eps_v", self.eps_v, gt=0)
        if self.stiffness is not None:
            check_number("contact.stiffness", self.stiffness, gt=0)
        check_number("contact.gap_fraction", self.gap_fraction, gt=0, le=1)
        check_number("contact.pressure_fraction", self.pressure_fraction, gt=0)
        if self.lag not in ("iteration", "step"):
            raise InputError("contact.lag", f"must be 'iteration' or 'step', got {self.lag!r}")

    @property
    def gap(self) -> float:
        """Virtual initial gap of the split interfaces (mm)."""
        return self.gap_fraction * self.dhat

    @property
    def kappa(self) -> float:
        if self.stiffness is not None:
            return float(self.stiffness)
        return default_stiffness(self.youngs_modulus, self.dhat, self.pressure_fraction)


def default_stiffness(youngs_modulus: float, dhat: float, fraction: float = 0.1) -> float:
    """Barrier stiffness (MPa/mm) at which a flat contact carries a pressure of `fraction` E at d = dhat/2.

    Higher pressures push d further towards 0 but never through it. The pressure per unit stiffness
    of ipctk's area-weighted barrier is measured on a flat patch (``unit_pressure``), not assumed.
    """
    return fraction * youngs_modulus / unit_pressure(dhat, 0.5 * dhat)


@lru_cache(maxsize=64)
def unit_pressure(dhat: float, distance: float) -> float:
    """Contact pressure (MPa) of the barrier with stiffness 1 between two parallel, coincidently
    meshed flat 8 x 8 patches at the given distance (interior vertices only, to avoid edge effects)."""
    n, L = 9, 8.0
    g = np.linspace(0, L, n)
    X, Y = np.meshgrid(g, g, indexing="ij")
    xy = np.c_[X.ravel(), Y.ravel()]
    ids = np.arange(n * n).reshape(n, n)
    q = np.c_[ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()]
    tri = np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    V = np.vstack([np.c_[xy, np.zeros(n * n)], np.c_[xy, np.full(n * n, distance)]])
    F = np.vstack([tri, tri[:, ::-1] + n * n]).astype(np.int32)
    mesh = ipctk.CollisionMesh(np.asfortranarray(V), np.asfortranarray(ipctk.edges(F), dtype=np.int32), np.asfortranarray(F))
    mesh.can_collide = ipctk.make_connected_components_filter(np.asfortranarray(F))
    c = _collisions()
    c.build(mesh, np.asfortranarray(V), dhat)
    g = ipctk.BarrierPotential(dhat, 1.0, True).gradient(c, mesh, np.asfortranarray(V)).reshape(-1, 3)
    interior = (ids[2:-2, 2:-2].ravel()) + n * n  # top-patch vertices away from the rim
    h = L / (n - 1)
    return float(-g[interior, 2].mean() / h**2)


def _collisions():
    c = ipctk.NormalCollisions()
    c.use_area_weighting = True
    # the standard IPC collision set: with IMPROVED_MAX_APPROX Newton stalled, its residual jumping
    # between 1e-8 and 1e-3 at every load (anatomical model, first increment); IPC converges quadratically
    c.collision_set_type = ipctk.NormalCollisions.IPC
    return c


def resolve_interfaces(mesh, mode: str = "paper", overrides: dict[str, float] | None = None,
                       groups: dict[str, tuple[str, ...]] | None = None) -> dict[str, float]:
    """Interfaces to model as frictional contact -> friction coefficient.

    mode "bonded": none (unless overridden); "paper": those of PAPER_INTERFACES present in the mesh
    (groups with regions that share faces). overrides {"needle-muscle": 0.3, ...} add or change a pair;
    a pair not present in the mesh or a coefficient < 0 raises InputError. ``groups``: group -> regions
    (``needletissue.fem.contact.mesh.material_groups``) for meshes with anatomical region names.
    """
    from needletissue.fem.contact.mesh import group_regions, interface_faces, parse_interface_name

    if mode not in ("bonded", "paper"):
        raise InputError("interfaces", f"must be 'bonded' or 'paper', got {mode!r}")

    def present(name):
        ga, gb = parse_interface_name(name)
        ra, rb = group_regions(mesh, ga, groups), group_regions(mesh, gb, groups)
        return bool(ra) and bool(rb) and len(interface_faces(mesh, ra, rb)[0]) > 0

    def canonical(name):
        ga, gb = parse_interface_name(name)
        for known in PAPER_INTERFACES:
            if set(parse_interface_name(known)) == {ga, gb}:
                return known
        return name

    chosen = {}
    if mode == "paper":
        chosen = {k: v for k, v in PAPER_INTERFACES.items() if present(k)}
    for name, mu in (overrides or {}).items():
        mu = check_number(f"interfaces.{name}", mu, ge=0)
        key = canonical(name)
        if not present(key):
            raise InputError(
                "interfaces",
                f"interface {name!r} does not exist in the mesh (regions: {sorted(mesh.regions)})",
            )
        chosen[key] = mu
    return chosen


def parse_friction(items: list[str]) -> dict[str, float]:
    """["needle-muscle=0.3", ...] -> {"needle-muscle": 0.3}; InputError names the bad entry."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise InputError("--friction", f"expected PAIR=MU like needle-muscle=0.3, got {item!r}")
        try:
            mu = float(value)
        except ValueError:
            raise InputError("--friction", f"{item!r}: the friction coefficient must be a number") from None
        out[name.strip()] = check_number(f"--friction {name.strip()}", mu, ge=0)
    return out


@dataclass
class ContactSurface:
    """The collision surface of all split interfaces (vertex ids index the full mesh)."""

    vertices: np.ndarray  # (nv,) full node ids
    faces: np.ndarray  # (nf, 3) local vertex ids (linear triangles)
    offset: np.ndarray  # (nv, 3) shift of the collision vertices (side b: dhat * normal of side a)
    side_a: np.ndarray  # (nv,) bit mask: interfaces where the vertex is on side a
    side_b: np.ndarray  # (nv,) bit mask: interfaces where the vertex is on side b
    friction: np.ndarray  # (nv,) friction coefficient per vertex
    interfaces: list[SplitInterface] = dc_field(default_factory=list)

    @classmethod
    def build(cls, points, interfaces: list[SplitInterface], friction: dict[str, float], gap: float):
        if len(interfaces) > 62:
            raise InputError("interfaces", "at most 62 contact interfaces")
        points = np.asarray(points, dtype=float)
        tri_a = [triangles(i.faces_a) for i in interfaces]
        # side b's triangles at a node it shares with side a (not split: bonded there) would join the
        # two bodies into one collision component; their other vertices stay in the neighbours
        tri_b = [triangles(i.faces_b) for i in interfaces]
        keep = [~np.isin(tb, ta).any(axis=1) for ta, tb in zip(tri_a, tri_b)]
        tri_b = [tb[k] for tb, k in zip(tri_b, keep)]
        skirt = [triangles(i.skirt_a) for i in interfaces]  # collision only: no pairs, no offset
        vertices = np.unique(np.concatenate([t.ravel() for t in tri_a + tri_b + skirt]))
        local = np.full(len(points), -1)
        local[vertices] = np.arange(len(vertices))
        side_a = np.zeros(len(vertices), dtype=np.int64)
        side_b = np.zeros(len(vertices), dtype=np.int64)
        mu = np.zeros(len(vertices))
        count = np.zeros(len(vertices))
        offset = np.zeros((len(vertices), 3))
        for k, (itf, ta, tb, sk) in enumerate(zip(interfaces, tri_a, tri_b, skirt)):
            side_a[local[ta.ravel()]] |= 1 << k
            side_b[local[tb.ravel()]] |= 1 << k
            m = check_number(f"interfaces.{itf.name}", friction[itf.name], ge=0)
            for t in (np.vstack([ta, sk]), tb):
                ids = np.unique(local[t.ravel()])
                mu[ids] += m
                count[ids] += 1
            # side b's copies go gap from every side-a face at their partner node (virtual_gap_offsets)
            vb = np.unique(tb)
            partner = np.arange(len(points))
            partner[itf.nodes_b] = itf.nodes_a
            offset[local[vb]] += virtual_gap_offsets(points, ta, partner[vb], gap)[0]
        faces = local[np.vstack(tri_a + tri_b + skirt)]
        return cls(vertices, faces, offset, side_a, side_b, mu / np.maximum(count, 1), list(interfaces))


class CollisionFreeStep(Plugin):
    """FElupe plugin (before the line search): shorten the Newton increment to `fraction` of the
    largest step that passes no contact surface through another, instead of halving it and
    assembling the residual at every rejected trial. `.alphas` keeps the fractions taken (< 1)."""

    def __init__(self, items, fraction: float = 0.9):
        self.items = [i for i in items if hasattr(i, "step_bound")]
        self.fraction = fraction
        self.alphas: list[float] = []

    def step_fraction(self, u, du) -> float:
        """The part of the step u -> u + du (displacements of all points, (n, 3), mm) to take: 1, or `fraction` of
        the largest that passes no contact surface through another (fem.solve's predictor takes it too)."""
        if not self.items:
            return 1.0
        alpha = min(i.step_bound(u[i.surface.vertices], du[i.surface.vertices]) for i in self.items)
        return 1.0 if alpha >= 1 else self.fraction * alpha

    def after_linear_solve(self, context, st):
        u = st.x[0].values
        f = self.step_fraction(u, np.asarray(st.dx)[:u.size].reshape(-1, 3))
        if f < 1:
            self.alphas.append(f / self.fraction)
            st.dx = f * st.dx


class StallLinesearch(LinesearchPlugin):
    """FElupe line search for contact runs (after `CollisionFreeStep`): Newton's full step (halved
    only while inadmissible: det F <= 0 or a non-finite residual) until the residual stalls, i.e. the
    last `patience` iterations did not go below `progress` x the best before them (a cycle, docs/contact.md);
    then, until the residual falls to `recover` x its best at the stall or stalls again, the contact items' Hessians
    are projected to PSD (every step a descent direction of the potential) and the step is searched
    on the potential's slope s(a) = r(x + a dx) . dx: a trial is accepted when s(a) <= eta |s(0)| or
    the residual contracts to `contraction` |r(0)|; a rejected one's a moves to the slope's zero
    (linear interpolation, within [0.1, 0.9] of it). Easy increments keep Newton's quadratic
    convergence (no stall, no projection).

    An increment whose best residual of its last `window` iterations is not below `plateau` x its best
    before them has stopped converging (a barrier pair the Newton step keeps running into, or a residual
    floor): it raises NewtonConvergenceError there, so fem.solve cuts the increment back at once instead
    of after its `maxiter` iterations (docs/contact.md, "Giving up on a plateau")."""

    project = True
    progress = 0.5  # a residual counts as progress below this x the best before it
    window = 5
    plateau = 0.95  # None: never give up before maxiter

    def __init__(self, items, patience: int = 2, recover: float = 1e-2, eta: float = 0.5,
                 contraction: float = 0.9, max_trials: int = 10):
        super().__init__(admissible=True, residual=False, max_halvings=max_trials,
                         criteria=[lambda trial: trial.finite])
        self.items = [i for i in items if hasattr(i, "project")]
        self.patience, self.recover = patience, recover
        self.eta, self.contraction = eta, contraction
        self.fnorms: list[float] = []
        self.level = None  # best residual at the stall; None: full Newton steps
        self.stalls = 0

    def _damp(self, level):
        self.level = level
        for i in self.items:
            i.project = level is not None and self.project

    def before_newton(self, context, st):
        super().before_newton(context, st)
        self.fnorms = []
        self.history = []  # every residual of this increment
        self._damp(None)

    def after_iteration(self, context, st):
        self.fnorms.append(float(st.fnorm))
        h, w = self.history, self.window
        h.append(float(st.fnorm) if np.isfinite(st.fnorm) else np.inf)
        if (self.plateau is not None and not st.success and len(h) > w
                and not min(h[-w:]) < self.plateau * min(h[:-w])):
            from felupe.tools._newton import NewtonConvergenceError

            raise NewtonConvergenceError(
                f"contact Newton on a plateau: best |r| {min(h[-w:]):.3g} in the last {w} iterations against "
                f"{min(h[:-w]):.3g} before them")
        fn, k = self.fnorms, self.patience
        if len(fn) > k and min(fn[-k:]) >= self.progress * min(fn[:-k]):  # stalled: switch full <-> damped
            self.stalls += 1
            self.fnorms = [fn[-1]]
            self._damp(min(fn) if self.level is None else None)
        elif self.level is not None and fn[-1] < self.recover * self.level:
            self.fnorms = [fn[-1]]
            self._damp(None)

    def after_linear_solve(self, context, st):
        if self.level is None:
            return super().after_linear_solve(context, st)
        from felupe.tools._newton import NewtonConvergenceError, _restore, _snapshot

        x, dx = st.x, st.dx
        dof1 = slice(None) if context.dof1 is None else context.dof1
        s0 = float(np.dot(st.fun[dof1], dx[dof1]))
        r0 = float(np.linalg.norm(st.fun[dof1]))
        descent = s0 < 0
        snapshot = _snapshot(x)
        alpha = 1.0
        for k in range(self.max_halvings + 1):
            _restore(x, snapshot)
            trial = LinesearchTrial(context, st, context.update(x, alpha * dx), alpha, alpha * dx, k)
            if self.check_admissible(trial) and trial.finite:
                s = float(np.dot(trial.fun[dof1], dx[dof1]))
                if (not descent or s <= self.eta * abs(s0)
                        or np.linalg.norm(trial.fun[dof1]) <= self.contraction * r0):
                    st.x, st.fun, st.dx, st.alpha, st.updated = trial.x, trial.fun, trial.dx, alpha, True
                    self.alphas[-1].append(alpha)
                    return
                alpha *= float(np.clip(-s0 / (s - s0), 0.1, 0.9))  # the slope's zero, s linear in a
            else:
                alpha *= 0.5
        _restore(x, snapshot)
        for item in context.items or []:
            item.field.link(x)
        raise NewtonConvergenceError(f"contact line search: no admissible step in {self.max_halvings + 1} trials")


class _ContactResults(Results):
    """FElupe calls update_statevars() after a converged Newton solve: accept the displacements as
    the new slip reference and, for lag="step", refresh the lagged normal forces/tangent bases."""

    def __init__(self, item):
        super().__init__()
        self._item = item

    def update_statevars(self):
        # keep the slip reference and lag of the step just converged: its forces (contact_forces)
        self._item._accepted = (self.statevars.copy(), self._item._lagged)
        super().update_statevars()
        self._item._base = None
        if self._item.settings.lag == "step":
            self._item.update_lag()


_T = ipctk.EdgeEdgeDistanceType
# an edge-edge distance type -> the friction pair ipctk's collision set makes of it: its kind and the
# positions of its two ids in (ea, eb, a0, a1, b0, b1)
_EDGE_PAIR_KINDS = {
    _T.EA_EB: ("ee", 0, 1),
    _T.EA_EB0: ("ev", 0, 4), _T.EA_EB1: ("ev", 0, 5), _T.EA0_EB: ("ev", 1, 2), _T.EA1_EB: ("ev", 1, 3),
    _T.EA0_EB0: ("vv", 2, 4), _T.EA0_EB1: ("vv", 2, 5), _T.EA1_EB0: ("vv", 3, 4), _T.EA1_EB1: ("vv", 3, 5),
}


def tangential_collisions(cmesh, V, collisions, barrier, mu, reuse: dict | None = None):
    """ipctk's friction pairs of `collisions` at the vertices V, plus those of the nearly parallel
    edge-edge collisions that ipctk's build leaves out (mollifier m < 1), with their weight times m
    like their barrier's: such a pair's friction then grows with its barrier instead of jumping from
    0 to its full value where m reaches 1 (docs/contact.md, "Edge-edge friction with the mollifier").
    Each is the pair ipctk's collision set makes of the edges above the threshold, by its distance
    type: edge-edge, edge-vertex or vertex-vertex (the line-line closest point of nearly parallel
    edges lies far outside them). mu: per collision vertex, blended as ipctk does (interpolated at
    the closest point, the two sides averaged). Returns the TangentialCollisions and, per added pair,
    (tangential collision, m, the edge pair's vertex ids, eps_x).

    `reuse`: a dict kept by the caller between calls. With a uniform mu the added pairs' objects are
    taken from it and given their new weight: ipctk's friction force and its Jacobians recompute the
    normal force, tangent basis and closest point from the lagged positions they are given, so only a
    pair's vertices, weight and mu matter there. Building the objects was ~40 us per pair, 6-22 ms per
    evaluation on the coarse needle model (docs/contact.md, "Giving up on a plateau")."""
    tangential = ipctk.TangentialCollisions()
    tangential.build(cmesh, V, collisions, barrier, mu, mu)
    E, F = cmesh.edges, cmesh.faces
    uniform = reuse is not None and mu.size > 0 and bool(np.all(mu == mu[0]))
    kept = {}
    added, lists = [], {"ee": [], "ev": [], "vv": []}
    near, ids = _nearly_parallel(collisions.ee_collisions, V, E)
    quads = np.column_stack([E[ids[:, 0]], E[ids[:, 1]]])  # a0, a1, b0, b1 per pair
    X = V[quads].reshape(-1, 12)  # = c.dof(V, E, F) per pair
    rows = np.column_stack([ids, quads]).tolist()  # ea, eb, a0, a1, b0, b1 as Python ints
    for c, x, q, row in zip(near, X, quads, rows):
        m = c.mollifier(x)
        if m >= 1.0:  # ipctk's build has it
            continue
        kind, p0, p1 = _EDGE_PAIR_KINDS[c.dtype]
        ea, eb, a0, a1, b0, b1 = row
        pair = (row[p0], row[p1])
        key = (ea, eb, kind, pair)  # one object per edge pair: two edge pairs may give the same vertex pair
        t = reuse.get(key) if uniform else None
        if t is None:
            if kind == "ee":
                t = ipctk.EdgeEdgeTangentialCollision(c, x, barrier)
                mus = [mu[i] + (mu[j] - mu[i]) * t.closest_point[k] for k, (i, j) in enumerate(((a0, a1), (b0, b1)))]
            elif kind == "ev":
                n = ipctk.EdgeVertexNormalCollision(*pair)
                t = ipctk.EdgeVertexTangentialCollision(n, n.dof(V, E, F), barrier)
                i, j = E[pair[0]]
                mus = [mu[i] + (mu[j] - mu[i]) * t.closest_point[0], mu[pair[1]]]
            else:
                n = ipctk.VertexVertexNormalCollision(*pair)
                t = ipctk.VertexVertexTangentialCollision(n, n.dof(V, E, F), barrier)
                mus = [mu[pair[0]], mu[pair[1]]]
            t.mu_s = t.mu_k = t.mu_s_effective_lagged = t.mu_k_effective_lagged = 0.5 * (mus[0] + mus[1])
        t.weight = c.weight * m
        kept[key] = t
        lists[kind].append(t)
        # numbers only: a reference into `collisions` dangles (segfault) once it is rebuilt
        added.append((t, m, q, float(c.eps_x)))
    if uniform:
        reuse.clear()
        reuse.update(kept)
    if not added:
        return tangential, added
    # into a new set (which copies the pairs): the lists read from `tangential` refer into its vectors
    # (assigning them back to it segfaulted)
    out = ipctk.TangentialCollisions()
    out.vv_collisions = list(tangential.vv_collisions) + lists["vv"]
    out.ev_collisions = list(tangential.ev_collisions) + lists["ev"]
    out.ee_collisions = list(tangential.ee_collisions) + lists["ee"]
    out.fv_collisions = list(tangential.fv_collisions)
    return out, added


def _nearly_parallel(ee, V, E):
    """The edge-edge collisions that may have a mollifier m < 1 at V: |ea x eb|^2 below their eps_x
    (ipctk's test), by NumPy for all of them at once, with a margin for round-off; the caller applies
    ipctk's own test to these. Returns them and their (edge0, edge1) ids. Calling ipctk per collision
    for the test cost ~60 ms per evaluation on the coarse anatomical model (~3,000 edge-edge
    collisions, a few mollified)."""
    if not ee:
        return [], np.zeros((0, 2), int)
    ids = np.array([(c.edge0_id, c.edge1_id) for c in ee])
    eps = np.array([c.eps_x for c in ee])
    a, b = E[ids[:, 0]], E[ids[:, 1]]
    cross = np.cross(V[a[:, 1]] - V[a[:, 0]], V[b[:, 1]] - V[b[:, 0]])
    keep = np.flatnonzero(np.einsum("ij,ij->i", cross, cross) < eps * (1 + 1e-6))
    return [ee[i] for i in keep], ids[keep]


def mollifier_force_jacobian(friction, added, cmesh, rest, V, slip, barrier):
    """The part of d(friction force)/d(positions) that ipctk's force_jacobian(LAGGED_DISPLACEMENTS)
    misses for the pairs of tangential_collisions (lag="iteration"): it differentiates the normal
    force, not the weight's mollifier; F = m F1, so F1 (x) grad m = F / m (x) grad m."""
    E, F = cmesh.edges, cmesh.faces
    n = rest.size
    rows, cols, vals = [], [], []
    for t, m, ids, eps_x in added:
        if m <= 0.0:  # exactly parallel: grad m = 0
            continue
        grad_m = ipctk.edge_edge_mollifier_gradient(*V[ids], eps_x)
        x0 = t.dof(rest, E, F)
        f = friction.force(t, x0, t.dof(V, E, F) - x0, t.dof(slip, E, F), barrier)
        rows_ = (3 * np.asarray(t.vertex_ids(E, F))[:t.num_vertices(), None] + np.arange(3)).ravel()
        cols_ = (3 * ids[:, None] + np.arange(3)).ravel()
        rows.append(np.repeat(rows_, 12))
        cols.append(np.tile(cols_, len(rows_)))
        vals.append(np.outer(f / m, grad_m).ravel())
    if not vals:
        return csr_matrix((n, n))
    return csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


class FrictionalContact:
    """FElupe item: IPC barrier contact + lagged smoothed friction on split interfaces.

    field: the global FieldContainer (its first field is the displacement on all mesh points).
    surface: ContactSurface of the split interfaces; settings: ContactSettings.
    ``results.statevars`` holds the displacements of the collision vertices at the last converged
    step (the reference of the slip); ``results.info`` the contact state of the last evaluation.
    """

    def __init__(self, field, surface: ContactSurface, settings: ContactSettings = ContactSettings()):
        self.field = field
        self.surface = surface
        self.settings = settings
        self.npoints = field[0].values.shape[0]
        points = np.asarray(field.region.mesh.points, dtype=float)
        self.rest = np.asfortranarray(points[surface.vertices] + surface.offset)
        edges = ipctk.edges(np.asfortranarray(surface.faces, dtype=np.int32))
        self.cmesh = ipctk.CollisionMesh(
            self.rest, np.asfortranarray(edges, dtype=np.int32), np.asfortranarray(surface.faces, dtype=np.int32)
        )
        # bodies are separate connected components of the collision surface after the split:
        # only cross-component pairs collide (no self-contact of a body's own surface)
        self.cmesh.can_collide = ipctk.make_connected_components_filter(
            np.asfortranarray(surface.faces, dtype=np.int32)
        )
        self.barrier = ipctk.BarrierPotential(settings.dhat, settings.kappa, True)
        self.friction = ipctk.FrictionPotential(settings.eps_v)
        # Tight-Inclusion CCD stalls on coincident parallel faces (the split interfaces); the
        # additive CCD is conservative and fast there
        self.ccd = ipctk.AdditiveCCD()
        self.mu = np.asarray(surface.friction, dtype=float)
        self.collisions = _collisions()
        self.tangential = ipctk.TangentialCollisions()
        nv = len(surface.vertices)
        self.dofs = (3 * surface.vertices[:, None] + np.arange(3)).ravel()
        self.results = _ContactResults(self)
        self.results.statevars = np.zeros((nv, 3))
        self.results.info = {}
        self._lagged = None  # (vertices, collisions) of the last converged step for lag="step"
        self._accepted = None  # (slip reference, lag) with which the last converged step was solved
        self._base = None  # displacements of the last tangent (the Newton iterate); None: the converged ones
        self._state = None
        self._mollified = []  # mollified edge-edge friction pairs of the last _tangential
        self._pairs = {}  # their objects, reused by the next (tangential_collisions)
        self.project = False  # PSD-projected Hessians (StallLinesearch sets it while Newton stalls)
        self.assemble = Assemble(vector=self._vector, matrix=self._matrix)

    # -- helpers -------------------------------------------------------------------------------
    def _u(self):
        return np.asarray(self.field[0].values)[self.surface.vertices]

    def positions(self, u=None) -> np.ndarray:
        """Collision-vertex positions for the collision-vertex displacements u."""
        if u is None:
            u = self._u()
        return np.asfortranarray(self.rest + u)

    def admissible(self) -> bool:
        """False if the surfaces passed through each other since the last converged state (CCD)."""
        return bool(self._evaluate()["admissible"])

    def checkpoint(self):
        return {"statevars": self.results.statevars.copy(), "lagged": self._lagged, "accepted": self._accepted}

    def restore(self, checkpoint):
        self.results.statevars = checkpoint["statevars"].copy()
        self._base = None
        self._lagged = checkpoint["lagged"]
        self._accepted = checkpoint.get("accepted")

    def _global_vector(self, g):
        shape = (self._ndof_total(), 1)
        return csr_matrix((g, (self.dofs, np.zeros_like(self.dofs))), shape=shape)

    def _ndof_total(self):
        return 3 * self.npoints

    # -- assembly --------------------------------------------------------------------------------
    def _evaluate(self):
        u = self._u()
        u_prev = self.results.statevars
        V = self.positions(u)
        # CCD from the Newton iterate the trial is a step of: a path through the converged state
        # could cross a surface the iterates went round
        V0 = self.positions(u_prev if self._base is None else self._base)
        admissible = bool(np.all(np.isfinite(V))) and ipctk.is_step_collision_free(
            self.cmesh, V0, V, narrow_phase_ccd=self.ccd
        )
        state = {"u": u, "V": V, "admissible": admissible}
        if admissible:
            self.collisions.build(self.cmesh, V, self.settings.dhat)
            reuse = self._pairs if self.settings.lag == "iteration" else None
            self.tangential, self._mollified = self._tangential(V, self.collisions, self._lagged, reuse)
            state["slip"] = np.asfortranarray(u - u_prev)
        self._state = state
        self.results._statevars = u.copy()
        return state

    def _tangential(self, V, collisions, lagged, reuse=None):
        """Friction pairs: from the current collisions (lag="iteration") or the lagged (vertices,
        collisions) of a converged state (lag="step"; None: none yet, frictionless), and the
        mollified edge-edge pairs among them (tangential_collisions)."""
        tangential = ipctk.TangentialCollisions()
        lag = (V, collisions) if self.settings.lag == "iteration" else lagged
        mollified = []
        if lag is not None and np.any(self.mu > 0) and len(lag[1]) > 0:
            tangential, mollified = tangential_collisions(self.cmesh, lag[0], lag[1], self.barrier, self.mu, reuse)
        return tangential, mollified

    def _gradient(self, V, collisions, tangential, slip):
        """Gradient of barrier + friction potential on the collision-vertex dofs."""
        g = self.barrier.gradient(collisions, self.cmesh, V)
        if len(tangential) > 0:
            if self.settings.lag == "iteration":  # normal forces and bases of the current state
                g = g - self.friction.force(tangential, self.cmesh, self.rest,
                                            np.asfortranarray(V - self.rest), slip, self.barrier)
            else:
                g = g + self.friction.gradient(tangential, self.cmesh, slip)
        return g

    def _vector(self, field=None, parallel=False):
        if field is not None:
            self.field = field
        s = self._evaluate()
        if not s["admissible"]:
            g = np.full(len(self.dofs), np.nan)
        else:
            g = self._gradient(s["V"], self.collisions, self.tangential, s["slip"])
            self.results.info = self.contact_state(s["V"])
        self.results.force = self._global_vector(g)
        return self.results.force

    def _matrix(self, field=None, parallel=False):
        if field is not None:
            self.field = field
        s = self._state
        if s is None or not np.array_equal(s["u"], self._u()):
            s = self._evaluate()
        n = self._ndof_total()
        if not s["admissible"]:
            return csr_matrix((n, n))
        self._base = s["u"].copy()
        # exact Hessians: a PSD projection (CLAMP) made Newton converge linearly (measured); only
        # while Newton stalls (StallLinesearch)
        psd = ipctk.PSDProjectionMethod.CLAMP if self.project else ipctk.PSDProjectionMethod.NONE
        H = self.barrier.hessian(self.collisions, self.cmesh, s["V"], psd)
        if len(self.tangential) > 0 and self.settings.lag == "iteration":
            # consistent: the friction force's derivative by the slip and by the state its normal
            # forces, tangent bases and closest points are taken at (non-symmetric)
            args = (self.tangential, self.cmesh, self.rest, np.asfortranarray(s["V"] - self.rest), s["slip"], self.barrier)
            W = ipctk.FrictionPotential.DiffWRT
            H = H - self.friction.force_jacobian(*args, W.VELOCITIES) - self.friction.force_jacobian(*args, W.LAGGED_DISPLACEMENTS)
            H = H - mollifier_force_jacobian(self.friction, self._mollified, self.cmesh, self.rest, s["V"], s["slip"], self.barrier)
        elif len(self.tangential) > 0:
            H = H + self.friction.hessian(self.tangential, self.cmesh, s["slip"], psd)
        H = coo_matrix(H)
        K = csr_matrix((H.data, (self.dofs[H.row], self.dofs[H.col])), shape=(n, n))
        self.results.stiffness = K
        return K

    def update_lag(self):
        """For lag="step": take the normal forces and tangent bases of the current state."""
        V = self.positions()
        c = _collisions()
        c.build(self.cmesh, V, self.settings.dhat)
        self._lagged = (V, c)

    def step_bound(self, u, du) -> float:
        """Largest fraction of the step u -> u + du (collision-vertex displacements, mm) that passes no
        surface through another (ipctk's collision-free step size, additive CCD)."""
        return float(ipctk.compute_collision_free_stepsize(
            self.cmesh, self.positions(u), self.positions(u + du), narrow_phase_ccd=self.ccd))

    # -- output ----------------------------------------------------------------------------------
    def contact_state(self, V=None) -> dict:
        """Number of active contacts, smallest distance and largest interpenetration (mm)."""
        if V is None:
            V = self.positions()
        c = self.collisions
        # ipctk returns the squared distance
        dmin = np.sqrt(c.compute_minimum_distance(self.cmesh, V)) if len(c) else float(self.settings.dhat)
        return {
            "active_contacts": len(c),
            "min_distance_mm": float(dmin),
            "max_interpenetration_mm": float(max(0.0, self.settings.gap - dmin)),
        }

    def contact_forces(self) -> np.ndarray:
        """Nodal contact + friction forces on the collision vertices (nv, 3), N, at the current state,
        with the friction of the step that converged to it (its slip and lagged normal forces)."""
        u = self._u()
        V = self.positions(u)
        reference, lag = self._accepted if self._accepted is not None else (self.results.statevars, self._lagged)
        collisions = _collisions()
        collisions.build(self.cmesh, V, self.settings.dhat)
        tangential, _ = self._tangential(V, collisions, lag)
        return -self._gradient(V, collisions, tangential, np.asfortranarray(u - reference)).reshape(-1, 3)

    def gap_opening(self, displacement: np.ndarray) -> dict[str, np.ndarray]:
        """Normal opening (mm, > 0 = separated) of each originally coincident node pair per interface."""
        points = np.asarray(self.field.region.mesh.points, dtype=float)
        out = {}
        for itf in self.surface.interfaces:
            normal = vertex_normals(points, itf.faces_a)[0][itf.nodes_a]
            jump = displacement[itf.nodes_b] - displacement[itf.nodes_a]
            out[itf.name] = np.einsum("ij,ij->i", jump, normal)
        return out
