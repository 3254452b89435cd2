"""Compiled (Numba) core: the Cosserat-rod equations of each needle, shooting, and the clamp's Newton.

Each needle is a geometrically exact (Reissner/Simo) rod, parametrised by its reference coordinate z
(z = 0 the bone surface). State along z: position r (3), rotation R (3x3, columns = the section's
director triad; R = I unloaded, e3 along the needle), internal force n and moment m (3 each, global
frame; what the part above z exerts on the part below):

    r' = R (e3 + Gamma),  Gamma = C_G^-1 R^T n,   C_G = diag(kGA, kGA, EA)     (shear, extension)
    R' = R [kappa]x,      kappa = C_K^-1 R^T m,   C_K = diag(EI, EI, GJ)       (bending, torsion)
    n' = -f(r, z),        m' = -r' x n

with the distributed support f per unit reference length: bone (linear foundation, lateral k_h and
axial k_z on u = r - X, torsional k_t on the twist, rocking k_r on the tilt: the cortex plate's bending), tissue (the paper's F = k (x + x^3) on the lateral displacement x = |u_xy|),
nothing above the skin. RK4 with fixed steps inside each segment (segment ends on the layer
interfaces, where f jumps).

Boundary values: at the tip in the bone n = k_tip u_z e3, m = 0 (end bearing), unknown r, R;
with a rigid root (z = 0): r = X, R = I, unknown n, m. At the clamp end z_c: r = P0 + c + Q (X - P0),
R = Q with the clamp pose (c, Q = exp(phi)) (elastic clamp: plus the clamp bar's deflection at the pin,
residual()). Unknowns: 6 per needle (shooting) + 6 of the clamp; the
residuals: 6 per needle (end mismatch) + 6 clamp equilibrium with the applied wrench (dead load) at
P0 + c. Newton with a forward-difference Jacobian (one integration per needle unknown), load
stepping with cut-back. The batch (batch_anchor) runs lanes of quasi-Newton solves in lock-step from an
anchor's predictor, one vectorised integration per pin and pass (integrate_lanes, elastic section only).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# constants vector P
EI, GJ, EA, KGA, SHEAR, KTIP, LS, FS, MS, Z0, ZC, RIGID, NPL, ELASTIC, CLO = range(15)
NP = 15
# With an elastic-plastic section, P[NP:] holds the moment-curvature table of the section: NPL points
# curvature kappa_i (1/mm), then moment M_i (N mm), then dkappa/dM at the nodes (cubic Hermite kappa(M), C1),
# monotonic loading (deformation theory).
# With an elastic clamp (P[ELASTIC] = 1), P[P[CLO]:] holds its compliance (6n x 6n, row-major; after the plastic
# table): the displacement and rotation of pin k's attachment, in the clamp's co-rotated axes and relative to
# its reference section (the load point's), per unit force and moment that pin j exerts on the clamp there
# (frame.model.clamp_compliance).
OK, MAX_ITER, NOT_FINITE, CUTBACK = 0, 1, 2, 3
_FD = 1e-7
# Newton's own forward-difference step (scaled unknowns). 1e-7 was too coarse where the shooting residual is
# strongly curved: a bone-rooted pin through a plastic hinge amplifies a tip perturbation so much that 1e-5
# already overflows the integration; the Jacobian's truncation error then made Newton converge only linearly
# (contraction ~0.5, ~25 iterations at any load step), and the cut-back halved the step for nothing (23,787
# load steps, issue #14). With 1e-9 it converges quadratically there (tests/frame/test_frame_physics.py);
# the rounding error of the scaled residual (~1e-16) stays far below.
_FD_NEWTON = 1e-9
_MAXIT = 25
MAX_STEPS = 200   # load steps in one solve_path: beyond this it reports CUTBACK instead of creeping on
LANES = 32        # the batch's solves integrated in lock-step (one vectorised integration per pin and pass)
LANES_Q = 18 * LANES


@njit(cache=True)
def expm(w, R):
    """Rotation matrix of the rotation vector w (Rodrigues), into R (3x3)."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if t2 < 1e-16:
        a = 1.0 - t2 / 6.0
        b = 0.5 - t2 / 24.0
    else:
        t = np.sqrt(t2)
        a = np.sin(t) / t
        b = (1.0 - np.cos(t)) / t2
    x, y, z = w[0], w[1], w[2]
    R[0, 0] = 1.0 - b * (y * y + z * z)
    R[1, 1] = 1.0 - b * (x * x + z * z)
    R[2, 2] = 1.0 - b * (x * x + y * y)
    R[0, 1] = -a * z + b * x * y
    R[1, 0] = a * z + b * x * y
    R[0, 2] = a * y + b * x * z
    R[2, 0] = -a * y + b * x * z
    R[1, 2] = -a * x + b * y * z
    R[2, 1] = a * x + b * y * z


@njit(cache=True, fastmath=True, inline="always")
def _rhs(z, s, x0, y0, kind, kh, kz, kt, kr, P, ds, iKGA, iEA, iEI, iGJ, shear, npl):
    # R row-major in s[3:12]: R[i, j] = s[3 + 3 i + j]; iKGA ... the section's compliances (shear = 0: rigid
    # in shear and extension); npl > 0: the elastic-plastic moment-curvature table in P
    n0, n1, n2 = s[12], s[13], s[14]
    m0, m1, m2 = s[15], s[16], s[17]
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = s[3], s[4], s[5], s[6], s[7], s[8], s[9], s[10], s[11]
    nl0 = R00 * n0 + R10 * n1 + R20 * n2
    nl1 = R01 * n0 + R11 * n1 + R21 * n2
    nl2 = R02 * n0 + R12 * n1 + R22 * n2
    ml0 = R00 * m0 + R10 * m1 + R20 * m2
    ml1 = R01 * m0 + R11 * m1 + R21 * m2
    ml2 = R02 * m0 + R12 * m1 + R22 * m2
    g0 = shear * nl0 * iKGA
    g1 = shear * nl1 * iKGA
    g2 = 1.0 + shear * nl2 * iEA
    t0 = R00 * g0 + R01 * g1 + R02 * g2
    t1 = R10 * g0 + R11 * g1 + R12 * g2
    t2 = R20 * g0 + R21 * g1 + R22 * g2
    ds[0] = t0
    ds[1] = t1
    ds[2] = t2
    k0 = ml0 * iEI
    k1 = ml1 * iEI
    k2 = ml2 * iGJ
    if npl > 0:
        mb = np.sqrt(ml0 * ml0 + ml1 * ml1)
        base = NP + npl
        if mb > P[base + 1]:  # beyond the first table segment (elastic up to first yield)
            lo = 1
            hi = npl - 1
            if mb >= P[base + hi]:
                j = hi - 1
            else:
                while hi - lo > 1:
                    mid = (lo + hi) // 2
                    if P[base + mid] <= mb:
                        lo = mid
                    else:
                        hi = mid
                j = lo
            # cubic Hermite in M with the section's exact slopes dkappa/dM at the nodes: kappa(M) is C1, so
            # Newton converges quadratically (linear interpolation kinks at every node: Newton stalled)
            sl = base + npl
            hM = P[base + j + 1] - P[base + j]
            q = (mb - P[base + j]) / hM
            if q <= 1.0:
                q2 = q * q
                q3 = q2 * q
                kap = ((2.0 * q3 - 3.0 * q2 + 1.0) * P[NP + j] + (q3 - 2.0 * q2 + q) * hM * P[sl + j]
                       + (-2.0 * q3 + 3.0 * q2) * P[NP + j + 1] + (q3 - q2) * hM * P[sl + j + 1])
            else:  # beyond the table: along its last tangent
                kap = P[NP + j + 1] + (mb - P[base + j + 1]) * P[sl + j + 1]
            f = kap / mb
            k0 = ml0 * f
            k1 = ml1 * f
    # R' = R [k]x ; [k]x = [[0,-k2,k1],[k2,0,-k0],[-k1,k0,0]]
    ds[3] = R01 * k2 - R02 * k1
    ds[4] = -R00 * k2 + R02 * k0
    ds[5] = R00 * k1 - R01 * k0
    ds[6] = R11 * k2 - R12 * k1
    ds[7] = -R10 * k2 + R12 * k0
    ds[8] = R10 * k1 - R11 * k0
    ds[9] = R21 * k2 - R22 * k1
    ds[10] = -R20 * k2 + R22 * k0
    ds[11] = R20 * k1 - R21 * k0
    ux = s[0] - x0
    uy = s[1] - y0
    uz = s[2] - z
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    if kind == 0:
        f0 = -kh * ux
        f1 = -kh * uy
        f2 = -kz * uz
    elif kind == 1:
        w = kh * (1.0 + ux * ux + uy * uy)
        f0 = -w * ux
        f1 = -w * uy
    ds[12] = -f0
    ds[13] = -f1
    ds[14] = -f2
    # m' = -r' x n - l, l = -(kr psi_x, kr psi_y, kt psi_z) the bone's rocking and torsional restraint
    # (psi = vee(R - R^T)/2, the small-rotation vector: the cortex turns by ~0.05 rad at most)
    ds[15] = -(t1 * n2 - t2 * n1)
    ds[16] = -(t2 * n0 - t0 * n2)
    ds[17] = -(t0 * n1 - t1 * n0)
    if kind == 0:
        ds[17] += kt * 0.5 * (R10 - R01)
        ds[15] += kr * 0.5 * (R21 - R12)
        ds[16] += kr * 0.5 * (R02 - R20)


@njit(cache=True)
def _start(a, x0, y0, P, s, Rw):
    """Initial state at the root from the 6 (scaled) shooting unknowns a."""
    for i in range(18):
        s[i] = 0.0
    if P[RIGID] > 0.0:
        s[0] = x0
        s[1] = y0
        s[2] = P[Z0]
        s[3] = 1.0
        s[7] = 1.0
        s[11] = 1.0
        for i in range(3):
            s[12 + i] = a[i] * P[FS]
            s[15 + i] = a[3 + i] * P[MS]
    else:
        s[0] = x0 + a[0] * P[LS]
        s[1] = y0 + a[1] * P[LS]
        s[2] = P[Z0] + a[2] * P[LS]
        expm(a[3:6], Rw)
        for i in range(3):
            for j in range(3):
                s[3 + 3 * i + j] = Rw[i, j]
        s[14] = P[KTIP] * a[2] * P[LS]


@njit(cache=True, fastmath=True)
def integrate(a, x0, y0, SZ, SK, SKH, SKZ, SKT, SN, P, end, store, do_store):
    """Integrate one needle from its root to the clamp; end state into `end` (18; if it has a 19th entry,
    the largest |u| over the step boundaries goes there: the key numbers without a second integration);
    with do_store the state at every step boundary into store (nodes, 18)."""
    s = np.empty(18)
    k1 = np.empty(18)
    k2 = np.empty(18)
    k3 = np.empty(18)
    k4 = np.empty(18)
    t = np.empty(18)
    Rw = np.empty((3, 3))
    _start(a, x0, y0, P, s, Rw)
    iKGA = 1.0 / P[KGA]
    iEA = 1.0 / P[EA]
    iEI = 1.0 / P[EI]
    iGJ = 1.0 / P[GJ]
    shear = 1.0 if P[SHEAR] > 0.0 else 0.0
    npl = int(P[NPL])
    node = 0
    if do_store:
        store[0, :] = s
    best = (s[0] - x0) ** 2 + (s[1] - y0) ** 2 + (s[2] - SZ[0]) ** 2
    for g in range(SK.shape[0]):
        za = SZ[g]
        nst = SN[g]
        h = (SZ[g + 1] - za) / nst
        kind = SK[g]
        kh = SKH[g]
        kz = SKZ[g]
        kt = SKT[g, 0]   # torsion about the axis
        kr = SKT[g, 1]   # rocking (tilt about x and y)
        for st in range(nst):
            z = za + st * h
            _rhs(z, s, x0, y0, kind, kh, kz, kt, kr, P, k1, iKGA, iEA, iEI, iGJ, shear, npl)
            for i in range(18):
                t[i] = s[i] + 0.5 * h * k1[i]
            _rhs(z + 0.5 * h, t, x0, y0, kind, kh, kz, kt, kr, P, k2, iKGA, iEA, iEI, iGJ, shear, npl)
            for i in range(18):
                t[i] = s[i] + 0.5 * h * k2[i]
            _rhs(z + 0.5 * h, t, x0, y0, kind, kh, kz, kt, kr, P, k3, iKGA, iEA, iEI, iGJ, shear, npl)
            for i in range(18):
                t[i] = s[i] + h * k3[i]
            _rhs(z + h, t, x0, y0, kind, kh, kz, kt, kr, P, k4, iKGA, iEA, iEI, iGJ, shear, npl)
            for i in range(18):
                s[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            node += 1
            if do_store:
                store[node, :] = s
            d = (s[0] - x0) ** 2 + (s[1] - y0) ** 2 + (s[2] - z - h) ** 2
            if d > best:
                best = d
    for i in range(18):
        end[i] = s[i]
    if end.shape[0] > 18:
        end[18] = np.sqrt(best)


@njit(cache=True)
def _clamp_deflection(E, Q, P, D):
    """Elastic clamp: the deflection D[k] = (displacement, rotation) of pin k's attachment relative to the clamp's
    reference section, in the clamp's axes, under the end wrenches of all pins: the wrench pin j exerts on the
    clamp is (-n_j, -m_j) (global), Q^T (-n_j, -m_j) in the clamp's axes; D = C w (small strain)."""
    nn = E.shape[0]
    N6 = 6 * nn
    off = int(P[CLO])
    w = np.empty(N6)
    for j in range(nn):
        for a in range(3):
            vf = 0.0
            vm = 0.0
            for b in range(3):
                vf -= Q[b, a] * E[j, 12 + b]
                vm -= Q[b, a] * E[j, 15 + b]
            w[6 * j + a] = vf
            w[6 * j + 3 + a] = vm
    for r in range(N6):
        v = 0.0
        base = off + r * N6
        for c in range(N6):
            v += P[base + c] * w[c]
        D[r // 6, r % 6] = v


@njit(cache=True)
def residual(E, yc, NX, P0, W, lam, P, res):
    """Scaled residuals: per needle end position and rotation mismatch, then the clamp's equilibrium.

    Rigid clamp: pin k's end must be at P0 + c + Q (X_k - P0) with the rotation Q. Elastic clamp: at its
    attachment's deflected pose, P0 + c + Q (X_k - P0 + du_k) and Q exp(dtheta_k), (du_k, dtheta_k) the clamp's
    compliance times the pins' end wrenches in the clamp's axes (_clamp_deflection)."""
    _residual(E, yc, NX, P0, W, lam, P, res, np.empty((3, 3)), np.empty((NX.shape[0], 6)))


@njit(cache=True)
def _residual(E, yc, NX, P0, W, lam, P, res, Q, D):
    """residual() with its work arrays Q (3, 3) and D (needles, 6) passed in: the batch's lanes call it every pass,
    and two allocations were about half of its ~0.3 us."""
    nn = NX.shape[0]
    expm(yc[3:6], Q)
    elastic = P[ELASTIC] > 0.0
    if elastic:
        _clamp_deflection(E, Q, P, D)
    c0 = yc[0] * P[LS]
    c1 = yc[1] * P[LS]
    c2 = yc[2] * P[LS]
    p0 = P0[0] + c0
    p1 = P0[1] + c1
    p2 = P0[2] + c2
    F0 = lam * W[0]
    F1 = lam * W[1]
    F2 = lam * W[2]
    M0 = lam * W[3]
    M1 = lam * W[4]
    M2 = lam * W[5]
    for k in range(nn):
        X0 = NX[k, 0] - P0[0]
        X1 = NX[k, 1] - P0[1]
        X2 = P[ZC] - P0[2]
        for i in range(3):
            target = P0[i] + yc[i] * P[LS] + Q[i, 0] * X0 + Q[i, 1] * X1 + Q[i, 2] * X2
            if elastic:
                target += Q[i, 0] * D[k, 0] + Q[i, 1] * D[k, 1] + Q[i, 2] * D[k, 2]
            res[6 * k + i] = (E[k, i] - target) / P[LS]
        # 0.5 vee(A - A^T), A = Q^T R, R[i, j] = E[k, 3 + 3 i + j]: the six off-diagonal entries (no array: the
        # batch calls this ~3 times per solve)
        A01 = Q[0, 0] * E[k, 4] + Q[1, 0] * E[k, 7] + Q[2, 0] * E[k, 10]
        A02 = Q[0, 0] * E[k, 5] + Q[1, 0] * E[k, 8] + Q[2, 0] * E[k, 11]
        A10 = Q[0, 1] * E[k, 3] + Q[1, 1] * E[k, 6] + Q[2, 1] * E[k, 9]
        A12 = Q[0, 1] * E[k, 5] + Q[1, 1] * E[k, 8] + Q[2, 1] * E[k, 11]
        A20 = Q[0, 2] * E[k, 3] + Q[1, 2] * E[k, 6] + Q[2, 2] * E[k, 9]
        A21 = Q[0, 2] * E[k, 4] + Q[1, 2] * E[k, 7] + Q[2, 2] * E[k, 10]
        res[6 * k + 3] = 0.5 * (A21 - A12)
        res[6 * k + 4] = 0.5 * (A02 - A20)
        res[6 * k + 5] = 0.5 * (A10 - A01)
        if elastic:  # the attachment's section turned by dtheta_k (small) relative to the reference
            res[6 * k + 3] -= D[k, 3]
            res[6 * k + 4] -= D[k, 4]
            res[6 * k + 5] -= D[k, 5]
        n0, n1, n2 = E[k, 12], E[k, 13], E[k, 14]
        r0 = E[k, 0] - p0
        r1 = E[k, 1] - p1
        r2 = E[k, 2] - p2
        F0 -= n0
        F1 -= n1
        F2 -= n2
        M0 -= E[k, 15] + r1 * n2 - r2 * n1
        M1 -= E[k, 16] + r2 * n0 - r0 * n2
        M2 -= E[k, 17] + r0 * n1 - r1 * n0
    b = 6 * nn
    res[b] = F0 / P[FS]
    res[b + 1] = F1 / P[FS]
    res[b + 2] = F2 / P[FS]
    res[b + 3] = M0 / P[MS]
    res[b + 4] = M1 / P[MS]
    res[b + 5] = M2 / P[MS]


@njit(cache=True)
def _norm(v):
    x = 0.0
    for i in range(v.shape[0]):
        a = abs(v[i])
        if not a < np.inf:  # NaN or inf: max() would drop a NaN
            return np.inf
        x = max(x, a)
    return x


@njit(cache=True)
def newton(y, lam, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol, maxit):
    """Newton on all unknowns y (in place) at load factor lam. Returns (iterations, status)."""
    nn = NX.shape[0]
    N = 6 * nn + 6
    E = np.empty((nn, 18))
    dummy = np.empty((1, 18))
    res = np.empty(N)
    J = np.empty((N, N))
    for k in range(nn):
        integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
    residual(E, y[6 * nn:], NX, P0, W, lam, P, res)
    for it in range(maxit):
        rn = _norm(res)
        if not np.isfinite(rn):
            return it, NOT_FINITE
        if rn <= tol:
            return it, OK
        _fd_columns(y, E, res, lam, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, _FD_NEWTON, J)
        for i in range(N):
            for j in range(N):
                if not np.isfinite(J[i, j]):
                    return it, NOT_FINITE
        dy = np.linalg.solve(J, -res)
        if not np.isfinite(_norm(dy)):
            return it, NOT_FINITE
        for i in range(N):
            y[i] += dy[i]
        for k in range(nn):
            integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
        residual(E, y[6 * nn:], NX, P0, W, lam, P, res)
        if not (_norm(res) < 1e3 * max(rn, 1e-3)):
            return it + 1, NOT_FINITE  # diverging: let the caller cut the load step
    if _norm(res) <= tol:
        return maxit, OK
    return maxit, MAX_ITER


@njit(cache=True)
def solve_path(y, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol, max_cuts):
    """Load stepping from y (a converged state at load factor 0, or a guess at 1) to lam = 1.

    Tries the whole load first; halves the increment on failure (cut-back) at most max_cuts times in a
    row, doubles it after a step that converged in <= 6 iterations; at most MAX_STEPS steps (then CUTBACK:
    a path that needs more is not converging in any useful sense). Returns (total Newton iterations, status,
    steps)."""
    N = y.shape[0]
    yprev = y.copy()
    lam = 0.0
    dl = 1.0
    total = 0
    steps = 0
    cuts = 0
    while lam < 1.0:
        target = min(1.0, lam + dl)
        it, st = newton(y, target, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol, _MAXIT)
        total += it
        if st == OK:
            lam = target
            steps += 1
            for i in range(N):
                yprev[i] = y[i]
            cuts = 0
            if it <= 6:
                dl *= 2.0
            if steps >= MAX_STEPS and lam < 1.0:
                return total, CUTBACK, steps
        else:
            for i in range(N):
                y[i] = yprev[i]
            dl *= 0.5
            cuts += 1
            if cuts > max_cuts:
                return total, CUTBACK, steps
    return total, OK, steps


@njit(cache=True)
def states(y, NX, SZ, SK, SKH, SKZ, SKT, SN, P, store):
    """Node states of every needle at the solution y: store (needles, nodes, 18)."""
    end = np.empty(18)
    for k in range(NX.shape[0]):
        integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, end, store[k], True)


@njit(cache=True)
def jacobian(y, lam, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, J):
    """Forward-difference Jacobian (step _FD) of the residual at y into J: Broyden's tangent at rest."""
    nn = NX.shape[0]
    N = 6 * nn + 6
    E = np.empty((nn, 18))
    dummy = np.empty((1, 18))
    res = np.empty(N)
    for k in range(nn):
        integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
    residual(E, y[6 * nn:], NX, P0, W, lam, P, res)
    _fd_columns(y, E, res, lam, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, _FD, J)


@njit(cache=True)
def _fd_columns(y, E, res, lam, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, h, J):
    """Forward differences of step h around y (end states E, residual res) into J: needle columns need
    one integration each, clamp columns only the algebra."""
    nn = NX.shape[0]
    N = 6 * nn + 6
    E2 = np.empty((nn, 18))
    dummy = np.empty((1, 18))
    r2 = np.empty(N)
    a = np.empty(6)
    for k in range(nn):
        for j in range(6):
            for i in range(6):
                a[i] = y[6 * k + i]
            a[j] += h
            for q in range(nn):
                for i in range(18):
                    E2[q, i] = E[q, i]
            integrate(a, NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E2[k], dummy, False)
            residual(E2, y[6 * nn:], NX, P0, W, lam, P, r2)
            for i in range(N):
                J[i, 6 * k + j] = (r2[i] - res[i]) / h
    yc = y[6 * nn:].copy()
    for j in range(6):
        yc[j] += h
        residual(E, yc, NX, P0, W, lam, P, r2)
        yc[j] -= h
        for i in range(N):
            J[i, 6 * nn + j] = (r2[i] - res[i]) / h


@njit(cache=True)
def broyden(y, H, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol, maxit, E, have_E=False):
    """Quasi-Newton at the full load from y (in place) with the inverse tangent H (in place, updated by
    Broyden's 'good' rank-one formula): one integration per needle and iteration. For the control loop:
    H from the unloaded state (a model constant) or from the last solve. E (needles, 19): the end states
    (and max |u|) at the last y; have_E: E already holds them at the start y (a warm start from the last
    answer: the wrench enters the residual only additively, so the needles need no new integration).
    Returns (iterations, status)."""
    nn = NX.shape[0]
    N = 6 * nn + 6
    dummy = np.empty((1, 18))
    res = np.empty(N)
    rnew = np.empty(N)
    s = np.empty(N)
    dr = np.empty(N)
    Hd = np.empty(N)
    sH = np.empty(N)
    if not have_E:
        for k in range(nn):
            integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
    residual(E, y[6 * nn:], NX, P0, W, 1.0, P, res)
    rn = _norm(res)
    for it in range(maxit):
        if not np.isfinite(rn):
            return it, NOT_FINITE
        if rn <= tol:
            return it, OK
        for i in range(N):
            v = 0.0
            for j in range(N):
                v -= H[i, j] * res[j]
            s[i] = v
        for i in range(N):
            y[i] += s[i]
        for k in range(nn):
            integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
        residual(E, y[6 * nn:], NX, P0, W, 1.0, P, rnew)
        rn2 = _norm(rnew)
        if not (rn2 < 10.0 * rn + 1e-300):
            return it + 1, NOT_FINITE
        for i in range(N):
            dr[i] = rnew[i] - res[i]
        # H += (s - H dr) s^T H / (s^T H dr)
        den = 0.0
        for i in range(N):
            v = 0.0
            for j in range(N):
                v += H[i, j] * dr[j]
            Hd[i] = v
        for j in range(N):
            v = 0.0
            for i in range(N):
                v += s[i] * H[i, j]
            sH[j] = v
        for i in range(N):
            den += s[i] * Hd[i]
        if den != 0.0:
            for i in range(N):
                c = (s[i] - Hd[i]) / den
                for j in range(N):
                    H[i, j] += c * sH[j]
        for i in range(N):
            res[i] = rnew[i]
        rn = rn2
    if rn <= tol:
        return maxit, OK
    return maxit, MAX_ITER


@njit(cache=True)
def finish(y, E, NX, P0, P, C, zc_top, out):
    """Clamp-centre displacement (3), clamp rotation vector (3) and the max needle deflection into out (7)
    from the end states E (needles, 19) at y: the control loop's answer without post-processing."""
    nn = NX.shape[0]
    Q = np.empty((3, 3))
    expm(y[6 * nn + 3: 6 * nn + 6], Q)
    c = np.empty(3)
    for i in range(3):
        c[i] = y[6 * nn + i] * P[LS]
    for i in range(3):
        v = c[i]
        for j in range(3):
            v += (Q[i, j] - (1.0 if i == j else 0.0)) * (C[j] - P0[j])
        out[i] = v
        out[3 + i] = y[6 * nn + 3 + i]
    best = 0.0
    for k in range(nn):
        best = max(best, E[k, 18])
        X0 = NX[k, 0] - P0[0]
        X1 = NX[k, 1] - P0[1]
        X2 = zc_top - P0[2]
        d = 0.0
        for i in range(3):
            v = c[i] + (Q[i, 0] - (1.0 if i == 0 else 0.0)) * X0 + (Q[i, 1] - (1.0 if i == 1 else 0.0)) * X1 \
                + (Q[i, 2] - (1.0 if i == 2 else 0.0)) * X2
            d += v * v
        best = max(best, np.sqrt(d))
    out[6] = best


@njit(cache=True)
def key_numbers(y, NX, P0, SZ, SK, SKH, SKZ, SKT, SN, P, C, zc_top, out):
    """finish() at y, integrating the needles first."""
    nn = NX.shape[0]
    E = np.empty((nn, 19))
    dummy = np.empty((1, 18))
    for k in range(nn):
        integrate(y[6 * k: 6 * k + 6], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, E[k], dummy, False)
    finish(y, E, NX, P0, P, C, zc_top, out)


@njit(cache=True)
def batch(F, M, y0, H0, NX, P0, SZ, SK, SKH, SKZ, SKT, SN, P, C, zc_top, tol, out, status):
    """N wrenches (rows of F, M) with one model: Broyden from the unloaded state and tangent for each,
    Newton with load stepping when that fails. out (N, 7) as key_numbers; status (N, 2): iterations, code."""
    W = np.empty(6)
    E = np.empty((NX.shape[0], 19))
    for m in range(F.shape[0]):
        for i in range(3):
            W[i] = F[m, i]
            W[3 + i] = M[m, i]
        y = y0.copy()
        H = H0.copy()
        it, st = broyden(y, H, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol[m], 40, E)
        if st == OK:
            finish(y, E, NX, P0, P, C, zc_top, out[m])
        else:
            y = y0.copy()
            it2, st, steps = solve_path(y, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol[m], 12)
            it += it2
            if st == OK:
                key_numbers(y, NX, P0, SZ, SK, SKH, SKZ, SKT, SN, P, C, zc_top, out[m])
        status[m, 0] = it
        status[m, 1] = st


@njit(cache=True)
def pose_solve(y, H, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, C, zc_top, tol, out, E, have_E):
    """Broyden from (y, H) then the key numbers, in one call (one dispatch from Python: the control loop).
    E, have_E as in broyden. Returns (iterations, status); on status != OK the caller falls back to Newton
    with load stepping."""
    it, st = broyden(y, H, NX, P0, W, SZ, SK, SKH, SKZ, SKT, SN, P, tol, 40, E, have_E)
    if st == OK:
        finish(y, E, NX, P0, P, C, zc_top, out)
    return it, st


@njit(cache=True, fastmath=True, inline="always")
def _rhs_lanes(z, X, si, di, x0, y0, cl, ct, kz, kt, kr, iKGA, iEA, iEI, iGJ, shear):
    """_rhs for LANES states, elastic section only: region si of the flat work buffer X (LANES_Q entries, row i of
    the state at i * LANES) in, the derivative into region di. Branch-free (the segment's kind is in the
    coefficients: lateral cl + ct |u|^2, axial kz, torsion kt, rocking kr) so the lane loop vectorises."""
    a = si * LANES_Q
    o = di * LANES_Q
    for l in range(LANES):
        n0 = X[a + 12 * LANES + l]
        n1 = X[a + 13 * LANES + l]
        n2 = X[a + 14 * LANES + l]
        m0 = X[a + 15 * LANES + l]
        m1 = X[a + 16 * LANES + l]
        m2 = X[a + 17 * LANES + l]
        R00, R01, R02 = X[a + 3 * LANES + l], X[a + 4 * LANES + l], X[a + 5 * LANES + l]
        R10, R11, R12 = X[a + 6 * LANES + l], X[a + 7 * LANES + l], X[a + 8 * LANES + l]
        R20, R21, R22 = X[a + 9 * LANES + l], X[a + 10 * LANES + l], X[a + 11 * LANES + l]
        nl0 = R00 * n0 + R10 * n1 + R20 * n2
        nl1 = R01 * n0 + R11 * n1 + R21 * n2
        nl2 = R02 * n0 + R12 * n1 + R22 * n2
        k0 = (R00 * m0 + R10 * m1 + R20 * m2) * iEI
        k1 = (R01 * m0 + R11 * m1 + R21 * m2) * iEI
        k2 = (R02 * m0 + R12 * m1 + R22 * m2) * iGJ
        g0 = shear * nl0 * iKGA
        g1 = shear * nl1 * iKGA
        g2 = 1.0 + shear * nl2 * iEA
        t0 = R00 * g0 + R01 * g1 + R02 * g2
        t1 = R10 * g0 + R11 * g1 + R12 * g2
        t2 = R20 * g0 + R21 * g1 + R22 * g2
        X[o + 0 * LANES + l] = t0
        X[o + 1 * LANES + l] = t1
        X[o + 2 * LANES + l] = t2
        X[o + 3 * LANES + l] = R01 * k2 - R02 * k1
        X[o + 4 * LANES + l] = -R00 * k2 + R02 * k0
        X[o + 5 * LANES + l] = R00 * k1 - R01 * k0
        X[o + 6 * LANES + l] = R11 * k2 - R12 * k1
        X[o + 7 * LANES + l] = -R10 * k2 + R12 * k0
        X[o + 8 * LANES + l] = R10 * k1 - R11 * k0
        X[o + 9 * LANES + l] = R21 * k2 - R22 * k1
        X[o + 10 * LANES + l] = -R20 * k2 + R22 * k0
        X[o + 11 * LANES + l] = R20 * k1 - R21 * k0
        ux = X[a + l] - x0
        uy = X[a + LANES + l] - y0
        w = cl + ct * (ux * ux + uy * uy)
        X[o + 12 * LANES + l] = w * ux
        X[o + 13 * LANES + l] = w * uy
        X[o + 14 * LANES + l] = kz * (X[a + 2 * LANES + l] - z)
        X[o + 15 * LANES + l] = -(t1 * n2 - t2 * n1) + kr * 0.5 * (R21 - R12)
        X[o + 16 * LANES + l] = -(t2 * n0 - t0 * n2) + kr * 0.5 * (R02 - R20)
        X[o + 17 * LANES + l] = -(t0 * n1 - t1 * n0) + kt * 0.5 * (R10 - R01)


@njit(cache=True, fastmath=True)
def integrate_lanes(s, x0, y0, SZ, SK, SKH, SKZ, SKT, SN, P, X, best):
    """integrate() for LANES start states s (18, LANES), in place (end states), elastic section only; best (LANES,):
    the largest |u| over the step boundaries. X: work buffer (6 LANES_Q): the state, the stage's argument and the
    four stages' derivatives as regions of one flat array with offsets fixed at compile time, so that LLVM can
    tell they do not overlap and vectorises the lane loops (with six (18, L) arrays it could not: the right-hand
    side ran scalar, 2.8 x slower per lane integration)."""
    for i in range(18):
        for l in range(LANES):
            X[i * LANES + l] = s[i, l]
    iKGA = 1.0 / P[KGA]
    iEA = 1.0 / P[EA]
    iEI = 1.0 / P[EI]
    iGJ = 1.0 / P[GJ]
    shear = 1.0 if P[SHEAR] > 0.0 else 0.0
    for l in range(LANES):
        best[l] = (X[l] - x0) ** 2 + (X[LANES + l] - y0) ** 2 + (X[2 * LANES + l] - SZ[0]) ** 2
    for g in range(SK.shape[0]):
        za = SZ[g]
        nst = SN[g]
        h = (SZ[g + 1] - za) / nst
        kind = SK[g]
        cl = SKH[g] if kind < 2 else 0.0
        ct = SKH[g] if kind == 1 else 0.0
        kz = SKZ[g] if kind == 0 else 0.0
        kt = SKT[g, 0] if kind == 0 else 0.0
        kr = SKT[g, 1] if kind == 0 else 0.0
        for st in range(nst):
            z = za + st * h
            _rhs_lanes(z, X, 0, 2, x0, y0, cl, ct, kz, kt, kr, iKGA, iEA, iEI, iGJ, shear)
            for j in range(LANES_Q):
                X[LANES_Q + j] = X[j] + 0.5 * h * X[2 * LANES_Q + j]
            _rhs_lanes(z + 0.5 * h, X, 1, 3, x0, y0, cl, ct, kz, kt, kr, iKGA, iEA, iEI, iGJ, shear)
            for j in range(LANES_Q):
                X[LANES_Q + j] = X[j] + 0.5 * h * X[3 * LANES_Q + j]
            _rhs_lanes(z + 0.5 * h, X, 1, 4, x0, y0, cl, ct, kz, kt, kr, iKGA, iEA, iEI, iGJ, shear)
            for j in range(LANES_Q):
                X[LANES_Q + j] = X[j] + h * X[4 * LANES_Q + j]
            _rhs_lanes(z + h, X, 1, 5, x0, y0, cl, ct, kz, kt, kr, iKGA, iEA, iEI, iGJ, shear)
            for j in range(LANES_Q):
                X[j] += h / 6.0 * (X[2 * LANES_Q + j] + 2.0 * X[3 * LANES_Q + j] + 2.0 * X[4 * LANES_Q + j] + X[5 * LANES_Q + j])
            zz = z + h
            for l in range(LANES):
                d = (X[l] - x0) ** 2 + (X[LANES + l] - y0) ** 2 + (X[2 * LANES + l] - zz) ** 2
                if d > best[l]:
                    best[l] = d
    for l in range(LANES):
        best[l] = np.sqrt(best[l])
    for i in range(18):
        for l in range(LANES):
            s[i, l] = X[i * LANES + l]


@njit(cache=True)
def lane_tangents(Ys, W, NX, P0, SZ, SK, SKH, SKZ, SKT, SN, P, h, Hs):
    """Inverse tangents at the points Ys (npt, N) into Hs (npt, N, N): the Jacobians by central differences (step
    h), every pin integration (each point and its +-h perturbations of the pin's 6 unknowns) in lanes. Central, not
    forward: the shooting residual is so curved in the tip unknowns that a forward difference's truncation error
    (~1 % of the inverse tangent at step 1e-7) limits the batch's predictor, not its order. A singular tangent
    raises LinAlgError."""
    npt = Ys.shape[0]
    nn = NX.shape[0]
    N = 6 * nn + 6
    L = LANES
    M = 13 * npt  # per pin and point: the point, then +h and -h along each unknown
    ends = np.empty((nn, M, 18))
    s = np.empty((18, L))
    X = np.empty(6 * LANES_Q)
    best = np.empty(L)
    a = np.empty(6)
    sv = np.empty(18)
    Rw = np.empty((3, 3))
    for k in range(nn):
        for c0 in range(0, M, L):
            for l in range(L):
                q = min(c0 + l, M - 1)  # the last chunk padded with copies
                j = q % 13
                for i in range(6):
                    a[i] = Ys[q // 13, 6 * k + i]
                if j > 0:
                    a[(j - 1) // 2] += h if j % 2 == 1 else -h
                _start(a, NX[k, 0], NX[k, 1], P, sv, Rw)
                for i in range(18):
                    s[i, l] = sv[i]
            integrate_lanes(s, NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, X, best)
            for l in range(min(L, M - c0)):
                for i in range(18):
                    ends[k, c0 + l, i] = s[i, l]
    E = np.empty((nn, 18))
    J = np.empty((N, N))
    rp = np.empty(N)
    rm = np.empty(N)
    yc = np.empty(6)
    for p in range(npt):
        for k in range(nn):
            for i in range(18):
                E[k, i] = ends[k, 13 * p, i]
        for i in range(6):
            yc[i] = Ys[p, 6 * nn + i]
        for k in range(nn):
            for j in range(6):
                for i in range(18):
                    E[k, i] = ends[k, 13 * p + 1 + 2 * j, i]
                residual(E, yc, NX, P0, W, 1.0, P, rp)
                for i in range(18):
                    E[k, i] = ends[k, 13 * p + 2 + 2 * j, i]
                residual(E, yc, NX, P0, W, 1.0, P, rm)
                for i in range(N):
                    J[i, 6 * k + j] = (rp[i] - rm[i]) / (2.0 * h)
            for i in range(18):
                E[k, i] = ends[k, 13 * p, i]
        for j in range(6):
            yc[j] += h
            residual(E, yc, NX, P0, W, 1.0, P, rp)
            yc[j] -= 2.0 * h
            residual(E, yc, NX, P0, W, 1.0, P, rm)
            yc[j] += h
            for i in range(N):
                J[i, 6 * nn + j] = (rp[i] - rm[i]) / (2.0 * h)
        Hs[p] = np.linalg.inv(J)


@njit(cache=True, inline="always")
def _add_term(H, v0, T, c, mean, b6, bw):
    """H += c T and v0 += mean c T[:, b6:b6 + 6] bw: one term of H(W)'s Taylor series and of its path mean's
    product with the residual's change (nonzero in the clamp rows b6.. only)."""
    for i in range(H.shape[0]):
        v = 0.0
        for j in range(H.shape[1]):
            H[i, j] += c * T[i, j]
        for e in range(6):
            v += T[i, b6 + e] * bw[e]
        v0[i] += mean * c * v


@njit(cache=True, fastmath={"reassoc", "contract", "arcp", "nsz"})  # vectorised dot products; NaN/inf checks kept
def batch_anchor(F, M, cell, Wa, ya, Ea, Ha, D, Dk, H2, H2k, NX, P0, SZ, SK, SKH, SKZ, SKT, SN, P, C, zc_top, tol,
                 maxit, out, status):
    """N wrenches, row m near the anchor wrench Wa[c], c = cell[m] (answer ya[c], end states Ea[c], exact inverse
    tangent Ha[c], if Dk[c] >= 0 its derivatives D[Dk[c]] (6, n, n) along the six wrench components and, if
    H2k[c] >= 0, its second derivatives H2[H2k[c]] (21, n, n), the pairs d <= e in row order): H(W) = Ha + sum dw_d
    D_d + sum_(d<=e) c_de dw_d dw_e H2_de / 2 (c_de = 1 on the diagonal, 2 off it). Each starts from its anchor's
    predictor ya - (mean of H(W) along the path) r(ya, W) (the wrench enters the residual linearly: exact to the
    order of H's Taylor series), then Broyden with H(W). LANES solves run in lock-step (one vectorised
    integration per pin and pass); a lane whose solve converged takes the next wrench, of any cell (one call for
    the whole batch: lanes idle only at its end). A solve that fails here gets status MAX_ITER or NOT_FINITE (the
    caller solves it again the robust way); never an unconverged answer."""
    nn = NX.shape[0]
    N = 6 * nn + 6
    n = F.shape[0]
    L = LANES
    Y = np.empty((L, N))
    Hs = np.empty((L, N, N))
    R = np.empty((L, N))
    S = np.empty((L, N))
    RN = np.empty(L)
    IT = np.zeros(L, np.int64)
    MI = np.full(L, -1, np.int64)
    El = np.empty((L, nn, 19))
    st = np.empty((nn, 18, L))
    X = np.empty(6 * LANES_Q)
    best = np.empty(L)
    W = np.empty(6)
    dw = np.empty(6)
    bw = np.empty(6)
    Qw = np.empty((3, 3))
    Dw = np.empty((nn, 6))
    v0 = np.empty(N)
    b6 = 6 * nn
    rnew = np.empty(N)
    dr = np.empty(N)
    Hd = np.empty(N)
    sH = np.empty(N)
    a = np.empty(6)
    Rw = np.empty((3, 3))
    sv = np.empty(18)
    nxt = 0
    active = 0
    while True:
        # load idle lanes: the anchor's predictor
        for l in range(L):
            if MI[l] < 0 and nxt < n:
                m = nxt
                nxt += 1
                MI[l] = m
                IT[l] = 0
                for i in range(3):
                    W[i] = F[m, i]
                    W[3 + i] = M[m, i]
                ca = cell[m]
                H = Hs[l]
                A = Ha[ca]
                for d in range(6):
                    dw[d] = W[d] - Wa[ca, d]
                    bw[d] = dw[d] / (P[FS] if d < 3 else P[MS])  # the residual's change: the clamp rows by bw
                # H(W), and the predictor ya - Hm bw, Hm the mean of H along the path (first-order terms / 2,
                # second-order / 3; components constant over the cell have dw = 0 and cost nothing)
                for i in range(N):
                    for j in range(N):
                        H[i, j] = 0.0
                    v0[i] = 0.0
                _add_term(H, v0, A, 1.0, 1.0, b6, bw)
                dk = Dk[ca]
                if dk >= 0:
                    for d in range(6):
                        if dw[d] != 0.0:
                            _add_term(H, v0, D[dk, d], dw[d], 0.5, b6, bw)
                d2 = H2k[ca]
                if d2 >= 0:
                    q = 0
                    for d in range(6):
                        for e in range(d, 6):
                            c = (0.5 if d == e else 1.0) * dw[d] * dw[e]
                            if c != 0.0:
                                _add_term(H, v0, H2[d2, q], c, 1.0 / 3.0, b6, bw)
                            q += 1
                for i in range(N):
                    Y[l, i] = ya[ca, i] - v0[i]
                active += 1
        if active == 0:
            break
        # one pass: every lane's pins integrated together
        for k in range(nn):
            for l in range(L):
                for i in range(6):
                    a[i] = Y[l, 6 * k + i]
                _start(a, NX[k, 0], NX[k, 1], P, sv, Rw)
                for i in range(18):
                    st[k, i, l] = sv[i]
            integrate_lanes(st[k], NX[k, 0], NX[k, 1], SZ, SK, SKH, SKZ, SKT, SN, P, X, best)
            for l in range(L):
                for i in range(18):
                    El[l, k, i] = st[k, i, l]
                El[l, k, 18] = best[l]
        for l in range(L):
            m = MI[l]
            if m < 0:
                continue
            for i in range(3):
                W[i] = F[m, i]
                W[3 + i] = M[m, i]
            _residual(El[l], Y[l, 6 * nn:], NX, P0, W, 1.0, P, rnew, Qw, Dw)
            rn = _norm(rnew)
            it = IT[l]
            code = -1
            if not np.isfinite(rn) or (it > 0 and not rn < 10.0 * RN[l] + 1e-300):
                code = NOT_FINITE
            elif rn <= tol[m]:
                code = OK
            elif it >= maxit:
                code = MAX_ITER
            if code >= 0:
                if code == OK:
                    finish(Y[l], El[l], NX, P0, P, C, zc_top, out[m])
                status[m, 0] = it
                status[m, 1] = code
                MI[l] = -1
                active -= 1
                continue
            H = Hs[l]
            if it > 0:  # Broyden's good update with the last step S[l] and the residual change
                for i in range(N):
                    dr[i] = rnew[i] - R[l, i]
                den = 0.0
                for i in range(N):
                    v = 0.0
                    for j in range(N):
                        v += H[i, j] * dr[j]
                    Hd[i] = v
                    den += S[l, i] * v
                for j in range(N):
                    sH[j] = 0.0
                for i in range(N):  # s^T H row by row: the inner loop runs along H's rows (vectorises)
                    v = S[l, i]
                    for j in range(N):
                        sH[j] += v * H[i, j]
                if den != 0.0:
                    for i in range(N):
                        c = (S[l, i] - Hd[i]) / den
                        for j in range(N):
                            H[i, j] += c * sH[j]
            for i in range(N):
                v = 0.0
                for j in range(N):
                    v -= H[i, j] * rnew[j]
                S[l, i] = v
                Y[l, i] += v
                R[l, i] = rnew[i]
            RN[l] = rn
            IT[l] = it + 1
