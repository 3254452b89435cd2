"""Solve the needle-frame model: one wrench (control loop), several, or a batch of parameter sets.

Every answer carries `error_estimate_mm` (Richardson: the solve at the model's step and at twice
that step; RK4 converges as h^4, so the error of the fine solve is |fine - coarse| / 15) and the
Newton iterations. A solve that does not converge raises ConvergenceError; an answer outside the
model's validity (a needle deflection larger than the free length) raises InputError naming the force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from needletissue.errors import ConvergenceError, InputError, check_number
from needletissue.frame.model import (
    CANCELLOUS_STRENGTH_MPA, CORTICAL_STRENGTH_MPA, FrameModel, clamp_compliance, shear_factor,
)

TOL = 1e-9        # Newton: scaled residual, relative to the scaled load
# absolute floor: the residual's rounding floor is ~2e-12 scaled (measured), so a tolerance below it made a
# wrench under ~0.5 N fail to converge (pose at 1e-3 N raised); 1e-11 scaled is ~1e-9 mm of clamp motion
TOL_FLOOR = 1e-11
MAX_CUTS = 12
BROYDEN_MAXIT = 40  # then full Newton with load stepping
WARM_REFRESH = 4    # warm starts: refresh the stored tangent when a solve needs more passes
ENDS_CACHE = 8      # pose(): end states kept for warm starts
WARN_DEFLECTION_RATIO = 0.25   # beyond this fraction of the free length the springs are extrapolated


_KERNEL = None


def _kernel():
    """The compiled kernel, imported on first use (Numba compiles or loads its cache then)."""
    global _KERNEL
    if _KERNEL is None:
        from needletissue.frame import kernel

        _KERNEL = kernel
    return _KERNEL


def logm(Q: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of Rodrigues), exact up to pi."""
    c = max(-1.0, min(1.0, (np.trace(Q) - 1.0) / 2.0))
    t = math.acos(c)
    v = np.array([Q[2, 1] - Q[1, 2], Q[0, 2] - Q[2, 0], Q[1, 0] - Q[0, 1]])
    if t < 1e-7:
        return 0.5 * v
    if math.pi - t < 1e-6:  # near pi: axis from the symmetric part
        B = (Q + np.eye(3)) / 2
        axis = np.sqrt(np.maximum(np.diag(B), 0.0))
        k = int(np.argmax(axis))
        axis = B[:, k] / max(axis[k], 1e-300)
        return t * axis / np.linalg.norm(axis)
    return t / (2.0 * math.sin(t)) * v


def expm(w) -> np.ndarray:
    w = np.asarray(w, float)
    t = float(np.linalg.norm(w))
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if t < 1e-8:
        return np.eye(3) + K + K @ K / 2
    return np.eye(3) + math.sin(t) / t * K + (1 - math.cos(t)) / t**2 * K @ K


@dataclass(frozen=True)
class Discretisation:
    """What the compiled kernel needs for one model and one step size."""

    SZ: np.ndarray   # segment ends (segments + 1)
    SK: np.ndarray   # kind: 0 bone, 1 tissue, 2 free
    SKH: np.ndarray  # lateral k, N/mm^2 (factors applied)
    SKZ: np.ndarray  # axial k, N/mm^2
    SKT: np.ndarray  # (segments, 2): torsional and rocking k, N mm/mm per rad
    SN: np.ndarray   # RK4 steps per segment (even)
    P: np.ndarray    # constants (kernel.EI ...)
    NX: np.ndarray   # needle (x, y)
    P0: np.ndarray   # load point
    names: tuple     # segment names
    z: np.ndarray    # reference z of every node
    H0: np.ndarray | None = None  # inverse tangent at rest (set on first use)
    # pose(): the needles' end states (needles, 19) at recent answers, by the answer's bytes, most recent last
    ends: dict = field(default_factory=dict, repr=False, compare=False)


def _attachments(model: FrameModel) -> np.ndarray:
    """Where the pins enter the clamp (their built-in ends), (n, 3) mm."""
    xy = np.asarray(model.needle_xy, float)
    return np.column_stack([xy, np.full(len(xy), model.clamp_bottom_mm)])


def _clamp_tops(model: FrameModel, disc, store, Q) -> np.ndarray | None:
    """Elastic clamp: the deflection (displacement, rotation; clamp axes, relative to its reference section) of
    each pin's top (z = free length, gripped) under the pins' end wrenches, (n, 6); None for the rigid clamp."""
    if model.clamp != "elastic":
        return None
    cache = model.__dict__.setdefault("_clamp_cache", {})
    if "tops" not in cache:
        A = _attachments(model)
        T = A.copy()
        T[:, 2] = model.free_length_mm
        n6 = 6 * len(A)
        cache["tops"] = clamp_compliance(model, np.vstack([A, T]))[n6:, :n6]
    end = store[:, -1, :]
    w = np.concatenate([np.concatenate([Q.T @ -e[12:15], Q.T @ -e[15:18]]) for e in end])
    return (cache["tops"] @ w).reshape(-1, 6)


def discretise(model: FrameModel, coarse: bool = False) -> Discretisation:
    """Segments along a needle and the constants; coarse: half the (even) step counts, for the error
    estimate."""
    k = _kernel()
    m = model
    EI = m.bending_stiffness_Nmm2
    found = m.foundation
    segs = []  # (name, z0, z1, kind, kh, kz, kt, kr)
    a = m.foundation_factor
    if m.root == "bone":
        if m.bone_law == "plate":
            for z0, z1, kh in m.cancellous_profile:
                segs.append(("cancellous", z0, z1, 0, a * kh, m.axial_factor * found["cancellous_axial"],
                             a * found["cancellous_torsion"], 0.0))
        else:
            segs.append(("cancellous", -m.depth_mm, -m.cortex_mm, 0, a * found["cancellous_lateral"],
                         m.axial_factor * found["cancellous_axial"], a * found["cancellous_torsion"], 0.0))
        # plate law: the cortex's axial and rocking springs are its bending (cortex_factor); winkler: the
        # axial shear cylinder (axial_factor) and no rocking spring
        kz_c = (m.cortex_factor if m.bone_law == "plate" else m.axial_factor) * found["cortex_axial"]
        segs.append(("cortex", -m.cortex_mm, 0.0, 0, a * found["cortex_lateral"], kz_c, a * found["cortex_torsion"],
                     m.cortex_factor * found["cortex_rocking"]))
    z = 0.0
    if m.tissue:
        for la in m.layers:
            segs.append((la.name, z, z + la.thickness_mm, 1, m.tissue_factor * la.k_N_per_mm2, 0.0, 0.0, 0.0))
            z += la.thickness_mm
    if m.clamp_bottom_mm > z:
        segs.append(("free", z, m.clamp_bottom_mm, 2, 0.0, 0.0, 0.0, 0.0))
    SZ = np.array([s[1] for s in segs] + [segs[-1][2]], float)
    SN = []
    for name, z0, z1, kind, kh, kz, kt, kr in segs:
        h = m.step_mm
        if kind == 0:  # resolve the foundation's decay lengths: bending, axial, torsion, rocking
            lam = min((4 * EI / kh) ** 0.25, math.sqrt(m.youngs_modulus_MPa * m.area_mm2 / kz),
                      math.sqrt(2 * m.shear_modulus_MPa * m.second_moment_mm4 / kt),
                      math.sqrt(EI / kr) if kr > 0 else math.inf)
            h = min(h, 0.5 * lam)
        n = 2 * max(1, math.ceil((z1 - z0) / (2 * h)))
        SN.append(n // 2 if coarse else n)
    SN = np.array(SN, np.int64)
    kGA = shear_factor(m.poisson) * m.shear_modulus_MPa * m.area_mm2
    L = m.free_length_mm
    nc = 36 * m.needles**2 if m.clamp == "elastic" else 0  # the elastic clamp's compliance, after the table
    if m.plastic:
        from needletissue.frame.model import moment_curvature, section_tangent

        kap, Mk = moment_curvature(m)
        n = kap.size
        P = np.zeros(k.NP + 3 * n + nc)
        P[k.NPL] = n
        P[k.NP: k.NP + n] = kap
        P[k.NP + n: k.NP + 2 * n] = Mk
        P[k.NP + 2 * n: k.NP + 3 * n] = 1.0 / section_tangent(m, kap)  # dkappa/dM at the nodes: a C1 kappa(M)
    else:
        P = np.zeros(k.NP + nc)
    if nc:
        off = P.size - nc
        P[k.ELASTIC] = 1.0
        P[k.CLO] = off
        P[off:] = clamp_compliance(m, _attachments(m)).ravel()
    P[k.EI] = EI
    P[k.GJ] = m.shear_modulus_MPa * 2 * m.second_moment_mm4
    P[k.EA] = m.youngs_modulus_MPa * m.area_mm2
    P[k.KGA] = kGA
    P[k.SHEAR] = 1.0 if m.shear else 0.0
    P[k.KTIP] = m.axial_factor * found["tip_axial_N_per_mm"] if m.root == "bone" else 0.0
    P[k.LS] = L
    P[k.FS] = EI / L**2
    P[k.MS] = EI / L
    P[k.Z0] = SZ[0]
    P[k.ZC] = m.clamp_bottom_mm
    P[k.RIGID] = 1.0 if m.root == "rigid" else 0.0
    zs = [np.array([SZ[0]])]
    for g in range(len(segs)):
        zs.append(np.linspace(SZ[g], SZ[g + 1], SN[g] + 1)[1:])
    return Discretisation(SZ, np.array([s[3] for s in segs], np.int64), np.array([s[4] for s in segs], float),
                          np.array([s[5] for s in segs], float), np.array([s[6:8] for s in segs], float), SN, P, np.array(m.needle_xy, float),
                          np.array(m.load_point_mm, float), tuple(s[0] for s in segs), np.concatenate(zs))


@dataclass(frozen=True)
class NeedleResult:
    """One needle. Displacements mm, rotations rad (rotation vectors), forces N, stresses MPa."""

    position_mm: tuple
    root_slope_rad: float        # tilt of the axis at the bone surface z = 0 from the z axis
    root_rotation_rad: tuple     # rotation vector of the section at z = 0
    tip_rotation_rad: tuple      # rotation vector at the tip in the bone (rigid root: zeros)
    max_deflection_mm: float     # largest |u| over the axis, the part in the clamp included
    max_stress_MPa: float        # largest von Mises stress (axial + bending + torsion) of the section
    z_max_stress_mm: float
    layer_reaction_N: dict       # segment -> force it exerts on the needle (3); "tip": end bearing
    curve_z_mm: np.ndarray       # reference z of the axis points, root .. clamp top
    curve_u_mm: np.ndarray       # (points, 3) displacement of the axis points

    def to_json(self) -> dict:
        return {
            "position_mm": list(self.position_mm),
            "root_slope_rad": self.root_slope_rad,
            "root_rotation_rad": list(self.root_rotation_rad),
            "tip_rotation_rad": list(self.tip_rotation_rad),
            "max_deflection_mm": self.max_deflection_mm,
            "max_stress_MPa": self.max_stress_MPa,
            "z_max_stress_mm": self.z_max_stress_mm,
            "layer_reaction_N": {k: list(v) for k, v in self.layer_reaction_N.items()},
            "curve": {"z_mm": self.curve_z_mm.tolist(), "displacement_mm": self.curve_u_mm.tolist()},
        }


@dataclass(frozen=True)
class FrameResult:
    """One solved wrench."""

    force_N: tuple
    moment_Nmm: tuple
    clamp_displacement_mm: tuple   # of the clamp centre (gripper faces' centre), relative to the bone
    clamp_rotation_rad: tuple      # rotation vector of the clamp relative to the bone
    load_point_displacement_mm: tuple
    max_needle_deflection_mm: float
    needle_yield_utilisation: float   # max von Mises stress / yield strength
    needle_plastic_utilisation: float  # max bending moment / fully plastic moment sigma_y d^3 / 6
    bone_stress_MPa: dict             # cortex, cancellous: largest mean bearing pressure
    bone_utilisation: float           # max over the two of stress / strength
    bone_pose_error_mm: tuple         # where the bone fragment (point at the bone surface under the clamp
    bone_pose_error_rad: tuple        #   centre) is minus where a rigid pin-clamp construct would put it
    needles: tuple
    iterations: int
    load_steps: int
    error_estimate_mm: float
    warnings: tuple = ()
    state: np.ndarray = field(default=None, repr=False)  # Newton unknowns (warm start)

    def to_json(self) -> dict:
        return {
            "force_N": list(self.force_N),
            "moment_Nmm": list(self.moment_Nmm),
            "clamp_displacement_mm": list(self.clamp_displacement_mm),
            "clamp_rotation_rad": list(self.clamp_rotation_rad),
            "load_point_displacement_mm": list(self.load_point_displacement_mm),
            "max_needle_deflection_mm": self.max_needle_deflection_mm,
            "needle_yield_utilisation": self.needle_yield_utilisation,
            "needle_plastic_utilisation": self.needle_plastic_utilisation,
            "bone_stress_MPa": dict(self.bone_stress_MPa),
            "bone_utilisation": self.bone_utilisation,
            "bone_pose_error_mm": list(self.bone_pose_error_mm),
            "bone_pose_error_rad": list(self.bone_pose_error_rad),
            "needles": [n.to_json() for n in self.needles],
            "iterations": self.iterations,
            "load_steps": self.load_steps,
            "error_estimate_mm": self.error_estimate_mm,
            "warnings": list(self.warnings),
        }


def _vec(field_name: str, value, n=3) -> np.ndarray:
    if value is None:
        return np.zeros(n)
    if type(value) is np.ndarray and value.shape == (n,) and value.dtype == np.float64:
        if math.isfinite(sum(value.tolist())):  # the control loop's path: one check (inf - inf is NaN)
            return value.copy()
    try:
        vals = list(value)
    except TypeError:
        raise InputError(field_name, f"expected {n} numbers, got {value!r}") from None
    if len(vals) != n:
        raise InputError(field_name, f"expected {n} numbers, got {value!r}")
    return np.array([check_number(field_name, v) for v in vals], float)


def _tol(disc, W):
    k = _kernel()
    P = disc.P
    w = [abs(x) for x in W.tolist()]
    scale = max(max(w[:3]) / float(P[k.FS]), max(w[3:]) / float(P[k.MS]))
    return max(TOL * scale, TOL_FLOOR)


def _inverse_tangent(disc: Discretisation) -> np.ndarray:
    """Inverse of the tangent at the unloaded state: a constant of the model (the load enters the
    residual additively), the start of every quasi-Newton solve."""
    if disc.H0 is None:
        k = _kernel()
        N = 6 * disc.NX.shape[0] + 6
        J = np.empty((N, N))
        k.jacobian(np.zeros(N), 0.0, disc.NX, disc.P0, np.zeros(6), disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT,
                   disc.SN, disc.P, J)
        try:
            H = np.linalg.inv(J)
        except np.linalg.LinAlgError:
            raise ConvergenceError("frame: singular tangent at rest; the construct is a mechanism") from None
        object.__setattr__(disc, "H0", H)
    return disc.H0


def _run(disc: Discretisation, W: np.ndarray, y0: np.ndarray | None):
    k = _kernel()
    nn = disc.NX.shape[0]
    y = np.zeros(6 * nn + 6) if y0 is None else np.array(y0, float)
    P = disc.P
    tol = _tol(disc, W)
    # quasi-Newton (Broyden) from the unloaded tangent: one integration per pin and iteration
    # A warm start (the control loop) uses the exact inverse tangent at a recent solution instead, and
    # refreshes it (one Jacobian: 6 integrations per pin) when the quasi-Newton needed many passes.
    warm = disc.__dict__.get("H_warm") if y0 is not None else None
    H = (_inverse_tangent(disc) if warm is None else warm).copy()
    yb = y.copy()
    it, st = k.broyden(yb, H, disc.NX, disc.P0, W, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, P,
                       tol, BROYDEN_MAXIT, np.empty((nn, 19)))
    if st == k.OK:
        if y0 is not None and (warm is None or it > WARM_REFRESH):
            J = np.empty((yb.size, yb.size))
            k.jacobian(yb, 1.0, disc.NX, disc.P0, W, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, P, J)
            try:
                object.__setattr__(disc, "H_warm", np.linalg.inv(J))
            except np.linalg.LinAlgError:
                pass
        return yb, it, 1
    args = (disc.NX, disc.P0, W, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, P, tol, MAX_CUTS)
    try:
        it, st, steps = k.solve_path(y, *args)
        if st != k.OK and y0 is not None:  # a warm start that fails: from rest
            y = np.zeros(6 * nn + 6)
            it2, st, steps = k.solve_path(y, *args)
            it += it2
    except np.linalg.LinAlgError as exc:  # a mechanism: some motion nothing resists
        raise ConvergenceError(f"frame Newton: singular tangent ({exc}); the construct is a mechanism "
                               f"under force {W[:3].tolist()} N, moment {W[3:].tolist()} N mm") from None
    if st != k.OK:
        why = (f"{MAX_CUTS} load cut-backs in a row" if steps < k.MAX_STEPS else
               f"{k.MAX_STEPS} load steps without reaching the full load (past a limit load, e.g. a plastic "
               "collapse, or a path Newton cannot follow)")
        raise ConvergenceError(f"frame Newton did not converge for force {W[:3].tolist()} N, moment "
                               f"{W[3:].tolist()} N mm after {it} iterations: {why}")
    return y, it, steps


def _clamp(disc, y):
    k = _kernel()
    nn = disc.NX.shape[0]
    c = y[6 * nn: 6 * nn + 3] * disc.P[k.LS]
    phi = y[6 * nn + 3:].copy()
    return c, phi, expm(phi)


def _key_numbers(model, disc, y):
    """Clamp-centre displacement and the max needle deflection: what the error estimate compares."""
    k = _kernel()
    c, phi, Q = _clamp(disc, y)
    C = np.array(model.clamp_centre_mm)
    uC = c + (Q - np.eye(3)) @ (C - disc.P0)
    store = np.empty((disc.NX.shape[0], disc.z.size, 18))
    k.states(y, disc.NX, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, disc.P, store)
    return uC, store, c, phi, Q


def solve(force=None, moment=None, model: FrameModel | None = None, *, error_estimate: bool = True,
          initial=None) -> FrameResult:
    """The construct under one wrench: force (N, 3) and moment (N mm, 3) at model.load_point_mm.

    initial: the `state` of an earlier result (warm start: the control loop's previous answer).
    error_estimate=False skips the coarse solve (half the cost; error_estimate_mm is then NaN).
    """
    model = FrameModel() if model is None else model
    F = _vec("force_N", force)
    M = _vec("moment_Nmm", moment)
    W = np.concatenate([F, M])
    _check_range(model, F, M)
    fine = _cached_disc(model, False)
    y0 = None if initial is None else np.asarray(initial, float)
    err = float("nan")
    if error_estimate:
        coarse = _cached_disc(model, True)
        yc, itc, _ = _run(coarse, W, y0)
        y, it, steps = _run(fine, W, yc)
        it += itc
    else:
        y, it, steps = _run(fine, W, y0)
    uC, store, c, phi, Q = _key_numbers(model, fine, y)
    res = _post(model, fine, W, y, store, c, phi, Q, uC, it, steps)
    if error_estimate:
        uCc, storec, *_ = _key_numbers(model, coarse, yc)
        dmax = abs(_max_deflection(model, coarse, storec, *_clamp(coarse, yc))[0] - res.max_needle_deflection_mm)
        err = max(float(np.linalg.norm(uC - uCc)), dmax) / 15.0
        res = _replace(res, error_estimate_mm=err)
    return res


# Validity range (stated in docs/frame.md): a pin whose linear deflection estimate exceeds this many
# free lengths would fold over; its answer is not in the model's range and is refused before solving.
MAX_LINEAR_DEFLECTION_RATIO = 3.0


def _range_constants(model: FrameModel):
    """(L, EI, n, P_cr) of _check_range, cached per model (the control loop calls it every time)."""
    cache = model.__dict__.setdefault("_disc_cache", {})
    if "range" not in cache:
        L = model.clamp_bottom_mm + (model.depth_mm if model.root == "bone" else 0.0)
        EI, n = model.bending_stiffness_Nmm2, model.needles
        # compression along the pins beyond their buckling load: the straight answer would be an unstable
        # equilibrium. One pin: a cantilever, pi^2 EI / (4 L^2); several: the clamp guides them, pi^2 EI / L^2
        # (rigid root; the bone's compliance lowers both: a warning below uses the cantilever value).
        cache["range"] = L, EI, n, math.pi**2 * EI / L**2 / (4.0 if n == 1 else 1.0)
    return cache["range"]


def _check_range(model: FrameModel, F, M):
    L, EI, n, P_cr = _range_constants(model)
    est = (math.hypot(F[0], F[1]) * L**3 / (3 * EI) + math.hypot(M[0], M[1]) * L**2 / (2 * EI)) / n
    if -F[2] / n > P_cr:
        raise InputError("force_N", f"outside the model's validity: {-F[2] / n:.4g} N of compression per pin is "
                         f"above its buckling load {P_cr:.4g} N (L = {L:g} mm)")
    if est > MAX_LINEAR_DEFLECTION_RATIO * model.free_length_mm:
        raise InputError("force_N", f"outside the model's validity: force {F.tolist()} N, moment {M.tolist()} N mm "
                         f"would bend the pins by about {est:.3g} mm (linear estimate), more than "
                         f"{MAX_LINEAR_DEFLECTION_RATIO:g} x free length {model.free_length_mm:g} mm")


def _replace(res, **kw):
    from dataclasses import replace

    return replace(res, **kw)


def _cached_disc(model: FrameModel, coarse: bool) -> Discretisation:
    cache = model.__dict__.setdefault("_disc_cache", {})  # frozen dataclass: per-instance cache
    if coarse not in cache:
        cache[coarse] = discretise(model, coarse)
    return cache[coarse]


def _max_deflection(model, disc, store, c, phi, Q):
    """Per needle: largest |u| over the axis nodes and over the part in the clamp (rigid with it; with the elastic
    clamp, with its section at the pin: the end node and the top, deflected with the bar)."""
    out = []
    tops = _clamp_tops(model, disc, store, Q)
    for i in range(disc.NX.shape[0]):
        X = np.column_stack([np.full(disc.z.size, disc.NX[i, 0]), np.full(disc.z.size, disc.NX[i, 1]), disc.z])
        u = store[i, :, :3] - X
        um = float(np.sqrt((u**2).sum(1)).max())
        if tops is None:
            for zc in (model.clamp_bottom_mm, model.free_length_mm):
                Xc = np.array([disc.NX[i, 0], disc.NX[i, 1], zc])
                um = max(um, float(np.linalg.norm(c + (Q - np.eye(3)) @ (Xc - disc.P0))))
        else:  # the end node (z_c) is in u; the top moves with the bar's section there
            Xc = np.array([disc.NX[i, 0], disc.NX[i, 1], model.free_length_mm])
            um = max(um, float(np.linalg.norm(c + (Q - np.eye(3)) @ (Xc - disc.P0) + Q @ tops[i, :3])))
        out.append(um)
    return max(out), out


def _post(model, disc, W, y, store, c, phi, Q, uC, it, steps) -> FrameResult:
    nn = disc.NX.shape[0]
    gmax, per = _max_deflection(model, disc, store, c, phi, Q)
    L = model.free_length_mm
    if not (np.isfinite(gmax) and np.isfinite(store).all()):
        raise ConvergenceError(f"frame: non-finite state after the solve (force {W[:3].tolist()} N, moment "
                               f"{W[3:].tolist()} N mm)")
    if not gmax <= L:
        raise InputError("force_N", f"outside the model's validity: the needle deflects {gmax:.4g} mm, more "
                         f"than its free length {L:g} mm (force {W[:3].tolist()} N, moment {W[3:].tolist()} N mm)")
    r, A, J = model.diameter_mm / 2, model.area_mm2, 2 * model.second_moment_mm4
    I = model.second_moment_mm4
    z = disc.z
    i0 = int(np.argmin(np.abs(z)))  # the bone surface node (a segment end unless root is rigid: z0 = 0)
    bounds = np.concatenate([[0], np.cumsum(disc.SN)])
    tops = _clamp_tops(model, disc, store, Q)
    needles = []
    smax_all = 0.0
    mb_all = 0.0
    ncomp_all = 0.0
    bone = {"cortex": 0.0, "cancellous": 0.0}
    for i in range(nn):
        S = store[i]
        R = S[:, 3:12].reshape(-1, 3, 3)
        nl = np.einsum("kji,kj->ki", R, S[:, 12:15])
        ml = np.einsum("kji,kj->ki", R, S[:, 15:18])
        sig = np.abs(nl[:, 2]) / A + np.hypot(ml[:, 0], ml[:, 1]) * r / I
        tau = np.abs(ml[:, 2]) * r / J
        vm = np.sqrt(sig**2 + 3 * tau**2)
        j = int(np.argmax(vm))
        smax_all = max(smax_all, float(vm[j]))
        mb_all = max(mb_all, float(np.hypot(ml[:, 0], ml[:, 1]).max()))
        ncomp_all = max(ncomp_all, float(-nl[:, 2].min()))
        t0 = R[i0][:, 2]
        slope = math.atan2(math.hypot(t0[0], t0[1]), t0[2])
        X = np.column_stack([np.full(z.size, disc.NX[i, 0]), np.full(z.size, disc.NX[i, 1]), z])
        u = S[:, :3] - X
        react = {}
        for g, name in enumerate(disc.names):
            if name == "free":
                continue
            a, b = bounds[g], bounds[g + 1]
            prev = react.get(name, (0.0, 0.0, 0.0))  # the cancellous bone comes in sub-segments
            react[name] = tuple((np.asarray(prev) + S[a, 12:15] - S[b, 12:15]).tolist())
            if name in bone:
                sl = slice(a, b + 1)
                pr = disc.SKH[g] * np.hypot(u[sl, 0], u[sl, 1]) / model.diameter_mm
                bone[name] = max(bone[name], float(pr.max()))
        if model.root == "bone":
            react["tip"] = tuple((-S[0, 12:15]).tolist())
        # the part in the clamp moves with it (elastic clamp: with the bar's section at the pin)
        zt = np.array([model.clamp_bottom_mm, model.free_length_mm])[1:] if model.clamp_length_mm > 0 else np.empty(0)
        Xt = np.column_stack([np.full(zt.size, disc.NX[i, 0]), np.full(zt.size, disc.NX[i, 1]), zt])
        ut = c + (Xt - disc.P0) @ (Q - np.eye(3)).T
        if tops is not None:
            ut = ut + Q @ tops[i, :3]
        needles.append(NeedleResult(
            position_mm=tuple(disc.NX[i].tolist()), root_slope_rad=slope,
            root_rotation_rad=tuple(logm(R[i0]).tolist()), tip_rotation_rad=tuple(logm(R[0]).tolist()),
            max_deflection_mm=per[i], max_stress_MPa=float(vm[j]), z_max_stress_mm=float(z[j]),
            layer_reaction_N=react, curve_z_mm=np.concatenate([z, zt]), curve_u_mm=np.vstack([u, ut])))
    util = smax_all / model.yield_MPa
    # fully plastic moment of a solid circular section, M_p = sigma_y d^3 / 6 (first yield: sigma_y pi d^3 / 32)
    plastic = mb_all / (model.yield_MPa * model.diameter_mm**3 / 6)
    bone_util = max(bone["cortex"] / CORTICAL_STRENGTH_MPA, bone["cancellous"] / CANCELLOUS_STRENGTH_MPA)
    B = np.array([*model.centre_xy, 0.0])
    e_t = -(c + (Q - np.eye(3)) @ (B - disc.P0))
    warns = []
    if util > 1:
        warns.append(f"needle yields: von Mises {smax_all:.0f} MPa > yield {model.yield_MPa:g} MPa "
                     f"(utilisation {util:.2f}); the elastic pin is not valid here, the pin bends for good")
    Lb = model.clamp_bottom_mm + (model.depth_mm if model.root == "bone" else 0.0)
    P_cant = math.pi**2 * model.bending_stiffness_Nmm2 / (4 * Lb**2)
    if ncomp_all > P_cant:
        warns.append(f"a pin carries {ncomp_all:.0f} N of compression, above the cantilever buckling load "
                     f"{P_cant:.0f} N: the clamp's restraint is what keeps it straight; check the stability")
    if plastic > 1:
        warns.append(f"plastic hinge: bending moment {mb_all:.0f} N mm > the pin's fully plastic moment "
                     f"{model.yield_MPa * model.diameter_mm**3 / 6:.0f} N mm; the pin collapses (bends for good) "
                     "before this load is reached, the elastic deflection is a lower bound")
    if bone_util > 1:
        warns.append(f"bone overloaded: bearing pressure cortex {bone['cortex']:.1f} MPa (strength "
                     f"{CORTICAL_STRENGTH_MPA:g}), cancellous {bone['cancellous']:.2f} MPa (strength "
                     f"{CANCELLOUS_STRENGTH_MPA:g}); the linear bone foundation is not valid here")
    if gmax > WARN_DEFLECTION_RATIO * L:
        warns.append(f"needle deflection {gmax:.3g} mm is more than {WARN_DEFLECTION_RATIO:g} x free length: "
                     "the tissue springs and bone foundation are extrapolated")
    return FrameResult(
        force_N=tuple(W[:3].tolist()), moment_Nmm=tuple(W[3:].tolist()),
        clamp_displacement_mm=tuple(uC.tolist()), clamp_rotation_rad=tuple(phi.tolist()),
        load_point_displacement_mm=tuple(c.tolist()), max_needle_deflection_mm=gmax,
        needle_yield_utilisation=util, needle_plastic_utilisation=plastic, bone_stress_MPa=bone, bone_utilisation=bone_util,
        bone_pose_error_mm=tuple(e_t.tolist()), bone_pose_error_rad=tuple((-phi).tolist()),
        needles=tuple(needles), iterations=int(it), load_steps=int(steps), error_estimate_mm=float("nan"),
        warnings=tuple(warns), state=y)


def solve_wrenches(forces, moments=None, model: FrameModel | None = None) -> list[FrameResult]:
    """One result per wrench (forces (k, 3) N; moments (k, 3) N mm or None), same model."""
    forces = [list(f) for f in forces]
    moments = [None] * len(forces) if moments is None else list(moments)
    if len(moments) != len(forces):
        raise InputError("moment_Nmm", f"need one moment per force ({len(forces)}), got {len(moments)}")
    return [solve(f, m, model) for f, m in zip(forces, moments)]


@dataclass(frozen=True)
class BatchResult:
    """Key numbers of N wrenches, as arrays (the control loop's and the Monte Carlo's answer)."""

    force_N: np.ndarray                  # (N, 3)
    moment_Nmm: np.ndarray               # (N, 3)
    clamp_displacement_mm: np.ndarray    # (N, 3) clamp centre, relative to the bone
    clamp_rotation_rad: np.ndarray       # (N, 3)
    max_needle_deflection_mm: np.ndarray  # (N,)
    iterations: np.ndarray               # (N,)


CELL_MIN = 600      # batch: a cell of fewer than 2 CELL_MIN wrenches is not split (an anchor costs ~100 row solves)
ANCHOR_MIN = 200    # batch: fewest wrenches that get their own anchor (answer, tangent and its derivatives)
CELL_SPREAD = 0.1   # batch: a cell wider than this (scaled wrench, relative to its centre) is split
ANCHOR_FD = 1e-7    # batch anchors: central-difference step of their tangents (scaled unknowns)
ANCHOR_PATH = 1e-2  # batch anchors: points along the answer's path for dH/dW, relative to the scaled wrench


def _anchor(disc: Discretisation, Wa: np.ndarray, vary=np.ones(6, bool), near=None, second=False):
    """(Wa, y, end states, exact inverse tangent, its derivatives (6, n, n) along the wrench components that
    `vary` (the others zero, as all of them if a tangent is singular), with `second` its second derivatives
    (21, n, n: the pairs d <= e in row order), else zeros) at the answer to Wa; the rest state (zero wrench, H0,
    no derivatives) when Wa is zero or its solve fails. near: another anchor to start from (a neighbouring
    cell's: a few quasi-Newton steps instead of ~20 from rest)."""
    k = _kernel()
    nn = disc.NX.shape[0]
    N = 6 * nn + 6
    G = (disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, disc.P)
    rest = disc.__dict__.get("rest")
    if rest is None:
        E0 = np.empty((nn, 19))
        dummy = np.empty((1, 18))
        for q in range(nn):
            k.integrate(np.zeros(6), disc.NX[q, 0], disc.NX[q, 1], *G, E0[q], dummy, False)
        rest = (np.zeros(6), np.zeros(N), E0, _inverse_tangent(disc), np.zeros((6, N, N)), np.zeros((21, N, N)))
        object.__setattr__(disc, "rest", rest)
    if not np.any(Wa):
        return rest
    # polished far below the batch's tolerance (the predictors start from it), but not below the residual's
    # rounding floor: a tighter polish failed for 10-17 of the 256 anchors of 100,000 random wrenches below
    # ~130 N, and those cells started from rest
    tol = max(1e-3 * _tol(disc, Wa), TOL_FLOOR)
    st = k.MAX_ITER
    if near is not None and near[0].any():  # the wrench enters the residual additively: near's end states serve
        ya, Ea = near[1].copy(), near[2].copy()
        st = k.broyden(ya, near[3].copy(), disc.NX, disc.P0, Wa, *G, tol, BROYDEN_MAXIT, Ea, True)[1]
    if st != k.OK:
        ya = np.zeros(N)
        Ea = np.empty((nn, 19))
        if k.broyden(ya, _inverse_tangent(disc).copy(), disc.NX, disc.P0, Wa, *G, tol, BROYDEN_MAXIT, Ea)[1] != k.OK:
            return rest

    def tangents(Ys):  # exact inverse tangents at the points Ys (central differences, in lanes)
        Hs = np.empty((len(Ys), N, N))
        k.lane_tangents(np.ascontiguousarray(Ys), Wa, disc.NX, disc.P0, *G, ANCHOR_FD, Hs)
        return Hs

    try:
        Ha = tangents(ya[None])[0]
    except np.linalg.LinAlgError:
        return rest
    D = np.zeros((6, N, N))
    H2 = np.zeros((21, N, N))
    # In the scaled wrench w (W / the force or moment scale) the wrench enters only the clamp's rows, dr/dw_d = e_c
    # (c = 6 n + d), so the answer's path is y' = -H e_c and y'' = -(dH/dw_d) e_c: tangents at points on it,
    # ANCHOR_PATH of the wrench's scaled size away, give dH/dw (forward differences on the first-order path; with
    # `second`, central ones on the second-order path, and the second derivatives, the mixed ones forward).
    P = disc.P
    size = max(float(np.abs(Wa[:3]).max() / P[k.FS]), float(np.abs(Wa[3:]).max() / P[k.MS]))
    h = ANCHOR_PATH * size
    sc = np.repeat([P[k.FS], P[k.MS]], 3)
    vd = np.flatnonzero(vary)  # a component constant over the cell multiplies its derivatives by zero
    c = 6 * nn + vd
    try:
        D1 = (tangents(ya - h * Ha[:, c].T) - Ha) / h  # (len(vd), N, N), per unit scaled wrench
        if not second:
            D[vd] = D1 / sc[vd, None, None]
            return Wa, ya, Ea, Ha, D, H2
        pairs = [(i, j) for i in range(len(vd)) for j in range(i + 1, len(vd))]
        U = np.vstack([np.eye(len(vd)), -np.eye(len(vd))] + [np.eye(len(vd))[i] + np.eye(len(vd))[j] for i, j in pairs])
        # ya + h (-Ha e_c) u + h^2/2 (-dH/dw e_c)(u, u) for the directions u
        Ys = ya - h * U @ Ha[:, c].T - 0.5 * h * h * np.einsum("pd,pe,dne->pn", U, U, D1[:, :, c])
        Hs = tangents(Ys)
    except np.linalg.LinAlgError:
        return Wa, ya, Ea, Ha, D, H2
    n = len(vd)
    Hp, Hn = Hs[:n], Hs[n:2 * n]
    D[vd] = (Hp - Hn) / (2 * h) / sc[vd, None, None]
    q = {(d, e): i for i, (d, e) in enumerate((d, e) for d in range(6) for e in range(d, 6))}
    for i, d in enumerate(vd):
        H2[q[d, d]] = (Hp[i] - 2 * Ha + Hn[i]) / (h * sc[d]) ** 2
    for p, (i, j) in enumerate(pairs):
        H2[q[vd[i], vd[j]]] = (Hs[2 * n + p] - Hp[i] - Hp[j] + Ha) / (h * h * sc[vd[i]] * sc[vd[j]])
    return Wa, ya, Ea, Ha, D, H2


def _cells(Ws: np.ndarray) -> list:
    """Split the scaled wrenches Ws (N, 6) at the median of their widest component until a cell is narrow
    (CELL_SPREAD of its centre's size) or too small to split: [(rows, wide)], neighbours next to each other; wide:
    the cell stopped for its size, not its spread."""
    WT = np.ascontiguousarray(Ws.T)  # (6, N), reordered in place: reductions and partitions along contiguous rows
    order = np.arange(Ws.shape[0])
    out = []
    todo = [(0, Ws.shape[0])]
    while todo:
        a, b = todo.pop()
        w = WT[:, a:b]
        ext = w.max(1) - w.min(1)
        wide = bool(ext.max() > CELL_SPREAD * max(float(np.abs(w.mean(1)).max()), 1e-3))
        if b - a < 2 * CELL_MIN or not wide:
            out.append((order[a:b], wide))
            continue
        h = (b - a) // 2
        part = np.argpartition(w[int(np.argmax(ext))], h)  # O(n), not a sort: 100,000 rows are split 8 levels deep
        WT[:, a:b] = w[:, part]
        order[a:b] = order[a:b][part]
        todo += [(a + h, b), (a, a + h)]
    return out


def _stack(mats):
    """The nonzero arrays of mats stacked, and each one's index in the stack (-1: zero, not stored)."""
    has = [i for i, a in enumerate(mats) if a.any()]
    idx = np.full(len(mats), -1, np.int64)
    idx[has] = np.arange(len(has))
    return np.array([mats[i] for i in has] or [mats[0]]), idx


def solve_batch(forces, moments=None, model: FrameModel | None = None, *, method: str = "auto") -> BatchResult:
    """Solve N wrenches in one compiled loop (no curves, no error estimate): forces (N, 3) N, moments
    (N, 3) N mm or None. Same validity checks as solve(); a failure raises.

    method "auto": the wrenches are grouped into cells of nearby wrenches; each cell gets an anchor (the exact
    answer and tangent at its mean wrench) and every wrench of the cell starts from the anchor's predictor, in
    lanes of kernel.LANES solves integrated together. "rest": each wrench from the unloaded state, one at a time (the
    earlier method; the elastic-plastic pin always uses it). Both converge every row to the same tolerance."""
    model = FrameModel() if model is None else model
    if method not in ("auto", "rest"):
        raise InputError("method", f"expected 'auto' or 'rest', got {method!r}")
    k = _kernel()
    F = np.atleast_2d(np.asarray(forces, float))
    M = np.zeros_like(F) if moments is None else np.atleast_2d(np.asarray(moments, float))
    for name, a in (("force_N", F), ("moment_Nmm", M)):
        if a.ndim != 2 or a.shape[1] != 3:
            raise InputError(name, f"expected an (N, 3) array, got shape {a.shape}")
        if not np.isfinite(a).all():
            raise InputError(name, f"must be finite, got {a[~np.isfinite(a)][0]} at row "
                             f"{int(np.argwhere(~np.isfinite(a))[0, 0])}")
    if F.shape != M.shape:
        raise InputError("moment_Nmm", f"need one moment per force: {M.shape} vs {F.shape}")
    # _check_range on all rows at once (a Python loop over the rows cost ~3 us each); the first row out of range
    # raises its message
    L, EI, nn, P_cr = _range_constants(model)
    est = (np.hypot(F[:, 0], F[:, 1]) * L**3 / (3 * EI) + np.hypot(M[:, 0], M[:, 1]) * L**2 / (2 * EI)) / nn
    out_of_range = np.flatnonzero((-F[:, 2] / nn > P_cr) | (est > MAX_LINEAR_DEFLECTION_RATIO * model.free_length_mm))
    for m in out_of_range[:1]:
        _check_range(model, F[m], M[m])
    disc = _cached_disc(model, False)
    H0 = _inverse_tangent(disc)
    P = disc.P
    F = np.ascontiguousarray(F)
    M = np.ascontiguousarray(M)
    tol = np.maximum(TOL * np.maximum(np.abs(F).max(1) / P[k.FS], np.abs(M).max(1) / P[k.MS]), TOL_FLOOR)
    N = 6 * disc.NX.shape[0] + 6
    n = F.shape[0]
    out = np.empty((n, 7))
    status = np.zeros((n, 2), np.int64)
    C = np.array(model.clamp_centre_mm)
    G = (disc.NX, disc.P0, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, P, C, model.free_length_mm)
    todo = np.arange(n)
    if method == "auto" and not model.plastic and n:
        Ws = np.hstack([F / P[k.FS], M / P[k.MS]])
        cells = _cells(Ws)
        anchors = []
        for idx, wide in cells:  # neighbouring cells follow each other: each anchor starts from the last
            w = np.hstack([F[idx], M[idx]])
            # second derivatives where the cell is wide (it stopped splitting for its size, not its spread): there
            # they save a quasi-Newton pass per row; on a narrow cell the first-order tangent already converges in one
            anchors.append(_anchor(disc, w.mean(0), w.min(0) < w.max(0), anchors[-1] if anchors else None, wide)
                           if idx.size >= ANCHOR_MIN else _anchor(disc, np.zeros(6)))
        D, Dk = _stack([a[4] for a in anchors])  # anchors with tangent derivatives
        H2, H2k = _stack([a[5] for a in anchors])
        rows = np.concatenate([idx for idx, _ in cells])
        cell = np.repeat(np.arange(len(cells)), [idx.size for idx, _ in cells])
        o = np.empty((n, 7))
        s = np.zeros((n, 2), np.int64)
        k.batch_anchor(F[rows], M[rows], cell, *(np.array([a[i] for a in anchors]) for i in range(4)), D, Dk, H2, H2k,
                       *G[:9], C, model.free_length_mm, tol[rows], BROYDEN_MAXIT, o, s)
        out[rows] = o
        status[rows] = s
        todo = np.flatnonzero(status[:, 1] != k.OK)  # solved again the robust way below
    if todo.size:
        o = np.empty((todo.size, 7))
        s = np.zeros((todo.size, 2), np.int64)
        k.batch(F[todo], M[todo], np.zeros(N), H0, *G[:9], C, model.free_length_mm, tol[todo], o, s)
        out[todo] = o
        s[:, 0] += status[todo, 0]
        status[todo] = s
    bad = np.flatnonzero(status[:, 1] != k.OK)
    if bad.size:
        m = bad[0]
        raise ConvergenceError(f"frame batch: {bad.size} of {F.shape[0]} wrenches did not converge; first row {m}: "
                               f"force {F[m].tolist()} N, moment {M[m].tolist()} N mm")
    over = np.flatnonzero(~(out[:, 6] <= model.free_length_mm))
    if over.size:
        m = over[0]
        raise InputError("force_N", f"outside the model's validity at row {m}: deflection {out[m, 6]:.4g} mm > "
                         f"free length {model.free_length_mm:g} mm")
    return BatchResult(F, M, out[:, :3], out[:, 3:6], out[:, 6], status[:, 0])


def pose(force, moment=None, model: FrameModel | None = None, initial=None):
    """Only the clamp pose and the max deflection, compiled end to end: (clamp_displacement_mm (3),
    clamp_rotation_rad (3), max_needle_deflection_mm, state). For the control loop: one compiled call
    (quasi-Newton and post-processing) unless it has to fall back to Newton with load stepping."""
    model = FrameModel() if model is None else model
    k = _kernel()
    F, M = _vec("force_N", force), _vec("moment_Nmm", moment)
    _check_range(model, F, M)
    disc = _cached_disc(model, False)
    W = np.empty(6)
    W[:3] = F
    W[3:] = M
    C = disc.__dict__.get("C")
    if C is None:
        C = np.array(model.clamp_centre_mm)
        object.__setattr__(disc, "C", C)
    warm = disc.__dict__.get("H_warm") if initial is not None else None
    H = (_inverse_tangent(disc) if warm is None else warm).copy()
    y = np.zeros(6 * disc.NX.shape[0] + 6) if initial is None else np.array(initial, float)
    out = np.empty(7)
    # the needles' end states at recent answers: a warm start from one of them needs no integration
    # before its first step (a few entries, most recently used first: the last answer or a fixed reference)
    ends = disc.ends
    key = y.tobytes() if initial is not None else None
    hit = ends.pop(key, None) if key is not None else None
    E = np.empty((disc.NX.shape[0], 19)) if hit is None else hit.copy()
    if hit is not None:
        ends[key] = hit
    it, st = k.pose_solve(y, H, disc.NX, disc.P0, W, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN,
                          disc.P, C, model.free_length_mm, _tol(disc, W), out, E, hit is not None)
    if st == k.OK:
        ends[y.tobytes()] = E
        while len(ends) > ENDS_CACHE:
            del ends[next(iter(ends))]
    if st != k.OK or (initial is not None and (warm is None or it > WARM_REFRESH)):
        y, it, _ = _run(disc, W, None if initial is None else np.asarray(initial, float))
        k.key_numbers(y, disc.NX, disc.P0, disc.SZ, disc.SK, disc.SKH, disc.SKZ, disc.SKT, disc.SN, disc.P,
                      C, model.free_length_mm, out)
    if not out[6] <= model.free_length_mm:
        raise InputError("force_N", f"outside the model's validity: deflection {out[6]:.4g} mm > free length "
                         f"{model.free_length_mm:g} mm")
    return out[:3], out[3:6], float(out[6]), y
