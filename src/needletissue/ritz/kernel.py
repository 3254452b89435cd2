"""Compiled (Numba) Newton solver of the Ritz stationarity equations, one sample per loop pass.

Energy of one sample (paper Eqs. 9-12, coefficients c in mm, s = z / l):

    Pi(c) = EI / (2 l^3) |c|^2 + sum_layers int k (y / 2 + y^2 / 4) dz - F v(z3),
    y = v^2 (1 + v'^2)  (cos term: x = v / cos(theta) = v sqrt(1 + v'^2))  or  y = v^2.

The spring integrals use Gauss-Legendre rules that are exact for the polynomial integrand (see
basis.quadrature_points); gradient and Hessian are analytic. Newton from rest with a Cholesky
solve, a diagonal shift when the Hessian is not positive definite, and an Armijo backtracking
line search on Pi. Pure NumPy on scalars would cost ~1 us per operation; compiled, one p = 3 solve
takes a few microseconds, which is what a control loop and a million-sample Monte Carlo need.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Columns of the per-sample scalar output.
ORDER, ITER, STATUS, TIP, TIP_DVDZ, LOAD, VMAX, ZMAX, U_BEND, U_SPRING, WORK, ERR, NCOLS = range(13)
OK, MAX_ITER, LINE_SEARCH, NOT_FINITE = 0, 1, 2, 3

_MAXIT = 200
_RTOL = 1e-9  # last Newton step, relative to |c|
_ATOL = 1e-13  # mm


@njit(cache=True)
def _basis_at(x, n, A, Ad, P, phi, dphi):
    """phi_i and dphi_i/ds at x = 2 s - 1 for i < n (Legendre recurrence, stable for any order)."""
    P[0] = 1.0
    P[1] = x
    for m in range(1, n + 1):
        P[m + 1] = ((2 * m + 1) * x * P[m] - m * P[m - 1]) / (m + 1)
    for i in range(n):
        sv = 0.0
        sd = 0.0
        for m in range(i + 3):
            sv += A[i, m] * P[m]
            sd += Ad[i, m] * P[m]
        phi[i] = sv
        dphi[i] = sd


@njit(cache=True)
def _points(p, l, T, K, cos_term, A, Ad, GX, GW, P, phi, dphi, W):
    """Fill Gauss points of all layers: phi (Q, n), dphi (Q, n) as dv/dz per unit c, W (Q) = k * weight."""
    n = p - 1
    nq = 4 * p - 1 if cos_term else 2 * p + 1
    q = 0
    za = 0.0
    for j in range(T.shape[0]):
        zb = za + T[j]
        half = 0.5 * (zb - za)
        for g in range(nq):
            z = za + half * (GX[nq, g] + 1.0)
            _basis_at(2.0 * z / l - 1.0, n, A, Ad, P, phi[q], dphi[q])
            for i in range(n):
                dphi[q, i] /= l
            W[q] = K[j] * half * GW[nq, g]
            q += 1
        za = zb
    return q


@njit(cache=True)
def _energy(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, grad, g, H):
    """Total potential energy; with grad, also its gradient g and Hessian H (lower triangle filled)."""
    eb = 0.0
    for i in range(n):
        eb += c[i] * c[i]
    eb *= 0.5 * kb
    wk = 0.0
    for i in range(n):
        wk += c[i] * phi3[i]
    wk *= F
    if grad:
        for i in range(n):
            g[i] = kb * c[i] - F * phi3[i]
            for j in range(i + 1):
                H[i, j] = kb if i == j else 0.0
    es = 0.0
    for q in range(Q):
        v = 0.0
        d = 0.0
        for i in range(n):
            v += c[i] * phi[q, i]
            d += c[i] * dphi[q, i]
        if cos_term:
            f = 1.0 + d * d
            y = v * v * f
        else:
            y = v * v
        w = W[q]
        es += w * (0.5 * y + 0.25 * y * y)
        if grad:
            ey = 0.5 * w * (1.0 + y)
            eyy = 0.5 * w
            if cos_term:
                yv = 2.0 * v * f
                yp = 2.0 * v * v * d
                ev = ey * yv
                ep = ey * yp
                evv = eyy * yv * yv + ey * 2.0 * f
                evp = eyy * yv * yp + ey * 4.0 * v * d
                epp = eyy * yp * yp + ey * 2.0 * v * v
                for i in range(n):
                    a = phi[q, i]
                    b = dphi[q, i]
                    g[i] += ev * a + ep * b
                    for j in range(i + 1):
                        H[i, j] += (evv * a * phi[q, j] + evp * (a * dphi[q, j] + b * phi[q, j])
                                    + epp * b * dphi[q, j])
            else:
                ev = ey * 2.0 * v
                evv = eyy * 4.0 * v * v + ey * 2.0
                for i in range(n):
                    a = phi[q, i]
                    g[i] += ev * a
                    for j in range(i + 1):
                        H[i, j] += evv * a * phi[q, j]
    return eb + es - wk, eb, es, wk


# Orders 3 and 4 (n = 2, 3 coefficients: the default order and its error estimate) unrolled by hand,
# on a transposed copy S of the basis values (S[i] = phi_i, S[n + i] = dphi_i at the Gauss points),
# so that the loop over points runs 4 points per AVX instruction. That needs two fast-math flags:
# 'reassoc' (sums over points in another order) and 'contract' (fused multiply-add); both only
# change round-off (tests/ritz/test_ritz_fast.py: same results as _energy to 1e-12). No 'nnan' or
# 'ninf': the Newton loop relies on inf/nan to report a non-finite energy.
_FM = {"reassoc", "contract"}


@njit(cache=True, fastmath=_FM)
def _energy2(c, Q, S, W, cos_term, kb, F, phi3, grad, g, H):
    c0 = c[0]
    c1 = c[1]
    eb = 0.5 * kb * (c0 * c0 + c1 * c1)
    wk = F * (c0 * phi3[0] + c1 * phi3[1])
    es = 0.0
    if not grad:
        for q in range(Q):
            v = c0 * S[0, q] + c1 * S[1, q]
            y = v * v
            if cos_term:
                d = c0 * S[2, q] + c1 * S[3, q]
                y *= 1.0 + d * d
            es += W[q] * (0.5 * y + 0.25 * y * y)
        return eb + es - wk, eb, es, wk
    g0 = kb * c0 - F * phi3[0]
    g1 = kb * c1 - F * phi3[1]
    h00 = kb
    h10 = 0.0
    h11 = kb
    if cos_term:
        for q in range(Q):
            a0 = S[0, q]
            a1 = S[1, q]
            b0 = S[2, q]
            b1 = S[3, q]
            w = W[q]
            v = c0 * a0 + c1 * a1
            d = c0 * b0 + c1 * b1
            f = 1.0 + d * d
            y = v * v * f
            es += w * (0.5 * y + 0.25 * y * y)
            ey = 0.5 * w * (1.0 + y)
            eyy = 0.5 * w
            yv = 2.0 * v * f
            yp = 2.0 * v * v * d
            ev = ey * yv
            ep = ey * yp
            evv = eyy * yv * yv + ey * 2.0 * f
            evp = eyy * yv * yp + ey * 4.0 * v * d
            epp = eyy * yp * yp + ey * 2.0 * v * v
            g0 += ev * a0 + ep * b0
            g1 += ev * a1 + ep * b1
            h00 += evv * a0 * a0 + 2.0 * evp * a0 * b0 + epp * b0 * b0
            h10 += evv * a1 * a0 + evp * (a1 * b0 + b1 * a0) + epp * b1 * b0
            h11 += evv * a1 * a1 + 2.0 * evp * a1 * b1 + epp * b1 * b1
    else:
        for q in range(Q):
            a0 = S[0, q]
            a1 = S[1, q]
            w = W[q]
            v = c0 * a0 + c1 * a1
            y = v * v
            es += w * (0.5 * y + 0.25 * y * y)
            ey = 0.5 * w * (1.0 + y)
            ev = ey * 2.0 * v
            evv = 2.0 * w * v * v + ey * 2.0
            g0 += ev * a0
            g1 += ev * a1
            h00 += evv * a0 * a0
            h10 += evv * a1 * a0
            h11 += evv * a1 * a1
    g[0] = g0
    g[1] = g1
    H[0, 0] = h00
    H[1, 0] = h10
    H[1, 1] = h11
    return eb + es - wk, eb, es, wk


@njit(cache=True, fastmath=_FM, inline="always")
def _spring_point_cos(w, v, d, a0, a1, a2, b0, b1, b2):
    """One Gauss point (weight w) of the spring energy w (y/2 + y^2/4), y = v^2 (1 + d^2), with v = a . c and
    d = b . c for three coefficients c: (energy, gradient (3), Hessian (6: 00 10 11 20 21 22)) in c."""
    f = 1.0 + d * d
    y = v * v * f
    ey = 0.5 * w * (1.0 + y)
    eyy = 0.5 * w
    yv = 2.0 * v * f
    yp = 2.0 * v * v * d
    ev = ey * yv
    ep = ey * yp
    evv = eyy * yv * yv + ey * 2.0 * f
    evp = eyy * yv * yp + ey * 4.0 * v * d
    epp = eyy * yp * yp + ey * 2.0 * v * v
    # H = sum [a b] [[evv, evp], [evp, epp]] [a b]^T, through u = evv a + evp b, t = evp a + epp b
    u0 = evv * a0 + evp * b0
    u1 = evv * a1 + evp * b1
    u2 = evv * a2 + evp * b2
    t0 = evp * a0 + epp * b0
    t1 = evp * a1 + epp * b1
    t2 = evp * a2 + epp * b2
    return (w * (0.5 * y + 0.25 * y * y), ev * a0 + ep * b0, ev * a1 + ep * b1, ev * a2 + ep * b2,
            u0 * a0 + t0 * b0, u1 * a0 + t1 * b0, u1 * a1 + t1 * b1, u2 * a0 + t2 * b0, u2 * a1 + t2 * b1,
            u2 * a2 + t2 * b2)


@njit(cache=True, fastmath=_FM, inline="always")
def _spring_point(w, v, a0, a1, a2):
    """_spring_point_cos without the cos term (y = v^2, v = a . c)."""
    y = v * v
    ev = w * (1.0 + y) * v
    evv = 2.0 * w * v * v + w * (1.0 + y)
    return (w * (0.5 * y + 0.25 * y * y), ev * a0, ev * a1, ev * a2, evv * a0 * a0, evv * a1 * a0, evv * a1 * a1,
            evv * a2 * a0, evv * a2 * a1, evv * a2 * a2)


@njit(cache=True, fastmath=_FM)
def _energy3(c, Q, S, W, cos_term, kb, F, phi3, grad, g, H):
    c0 = c[0]
    c1 = c[1]
    c2 = c[2]
    eb = 0.5 * kb * (c0 * c0 + c1 * c1 + c2 * c2)
    wk = F * (c0 * phi3[0] + c1 * phi3[1] + c2 * phi3[2])
    es = 0.0
    if not grad:
        for q in range(Q):
            v = c0 * S[0, q] + c1 * S[1, q] + c2 * S[2, q]
            y = v * v
            if cos_term:
                d = c0 * S[3, q] + c1 * S[4, q] + c2 * S[5, q]
                y *= 1.0 + d * d
            es += W[q] * (0.5 * y + 0.25 * y * y)
        return eb + es - wk, eb, es, wk
    g0 = kb * c0 - F * phi3[0]
    g1 = kb * c1 - F * phi3[1]
    g2 = kb * c2 - F * phi3[2]
    h00 = kb
    h10 = 0.0
    h11 = kb
    h20 = 0.0
    h21 = 0.0
    h22 = kb
    if cos_term:
        for q in range(Q):
            a0 = S[0, q]
            a1 = S[1, q]
            a2 = S[2, q]
            b0 = S[3, q]
            b1 = S[4, q]
            b2 = S[5, q]
            r = _spring_point_cos(W[q], c0 * a0 + c1 * a1 + c2 * a2, c0 * b0 + c1 * b1 + c2 * b2, a0, a1, a2,
                                  b0, b1, b2)
            es += r[0]
            g0 += r[1]
            g1 += r[2]
            g2 += r[3]
            h00 += r[4]
            h10 += r[5]
            h11 += r[6]
            h20 += r[7]
            h21 += r[8]
            h22 += r[9]
    else:
        for q in range(Q):
            a0 = S[0, q]
            a1 = S[1, q]
            a2 = S[2, q]
            r = _spring_point(W[q], c0 * a0 + c1 * a1 + c2 * a2, a0, a1, a2)
            es += r[0]
            g0 += r[1]
            g1 += r[2]
            g2 += r[3]
            h00 += r[4]
            h10 += r[5]
            h11 += r[6]
            h20 += r[7]
            h21 += r[8]
            h22 += r[9]
    g[0] = g0
    g[1] = g1
    g[2] = g2
    H[0, 0] = h00
    H[1, 0] = h10
    H[1, 1] = h11
    H[2, 0] = h20
    H[2, 1] = h21
    H[2, 2] = h22
    return eb + es - wk, eb, es, wk


@njit(cache=True)
def _transpose(Q, n, phi, dphi, S):
    """S[i, q] = phi[q, i], S[n + i, q] = dphi[q, i] (the layout of _energy2/3)."""
    for i in range(n):
        for q in range(Q):
            S[i, q] = phi[q, i]
            S[n + i, q] = dphi[q, i]


@njit(cache=True)
def _energy_any(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, grad, g, H, fast, S):
    """_energy, through the unrolled n = 2, 3 versions when fast (the reference path otherwise)."""
    if fast and n == 2:
        return _energy2(c, Q, S, W, cos_term, kb, F, phi3, grad, g, H)
    if fast and n == 3:
        return _energy3(c, Q, S, W, cos_term, kb, F, phi3, grad, g, H)
    return _energy(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, grad, g, H)


@njit(cache=True)
def _cholesky_solve(H, g, n, shift, Lw, d):
    """d = -(H + shift I)^-1 g from the lower triangle of H; False if not positive definite."""
    for i in range(n):
        for j in range(i + 1):
            s = H[i, j] + (shift if i == j else 0.0)
            for m in range(j):
                s -= Lw[i, m] * Lw[j, m]
            if i == j:
                if not s > 0.0:
                    return False
                Lw[i, i] = np.sqrt(s)
            else:
                Lw[i, j] = s / Lw[j, j]
    for i in range(n):
        s = -g[i]
        for m in range(i):
            s -= Lw[i, m] * d[m]
        d[i] = s / Lw[i, i]
    for i in range(n - 1, -1, -1):
        s = d[i]
        for m in range(i + 1, n):
            s -= Lw[m, i] * d[m]
        d[i] = s / Lw[i, i]
    return True


@njit(cache=True)
def _newton(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, wk, fast):
    """Minimise Pi over order-p trial functions starting from c (in place). Returns (iterations, status).

    Converged when a full, positive-definite Newton step is below 1e-9 |c| (+1e-13 mm): Newton's
    quadratic rate leaves an error of order the square of that step.
    """
    P, phi, dphi, W, phi3, dphi3, g, H, g2, H2, Lw, d, ct, S = wk
    n = p - 1
    Q = _points(p, l, T, K, cos_term, A, Ad, GX, GW, P, phi, dphi, W)
    if fast and n <= 3:
        _transpose(Q, n, phi, dphi, S)
    _basis_at(2.0 * z3 / l - 1.0, n, A, Ad, P, phi3, dphi3)
    pi, eb, es, w = _energy_any(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, True, g, H, fast, S)
    for it in range(_MAXIT):
        if not np.isfinite(pi):
            return it, NOT_FINITE
        shift = 0.0
        pd = _cholesky_solve(H, g, n, 0.0, Lw, d)
        if not pd:
            shift = 1e-8 * kb
            while not _cholesky_solve(H, g, n, shift, Lw, d):
                shift *= 10.0
        dn = 0.0
        cn = 0.0
        slope = 0.0
        for i in range(n):
            dn = max(dn, abs(d[i]))
            cn = max(cn, abs(c[i] + d[i]))
            slope += g[i] * d[i]
        # Full step, evaluated with gradient and Hessian (accepted almost always: reused next pass).
        for i in range(n):
            ct[i] = c[i] + d[i]
        pt, ebt, est, wt = _energy_any(ct, n, Q, phi, dphi, W, cos_term, kb, F, phi3, True, g2, H2, fast, S)
        scale = abs(eb) + abs(es) + abs(w) + 1e-300
        # Armijo on Pi; below the round-off of Pi (quadratic regime) the full step is taken.
        if pt <= pi + 1e-4 * slope or -slope <= 1e-13 * scale:
            for i in range(n):
                c[i] = ct[i]
            g, g2 = g2, g
            H, H2 = H2, H
            pi, eb, es, w = pt, ebt, est, wt
            # converged: a tiny Newton step, or a Newton decrement below the round-off of Pi
            if pd and (dn <= _RTOL * cn + _ATOL or -slope <= 1e-15 * scale):
                return it + 1, OK
            continue
        t = 0.5
        while True:
            for i in range(n):
                ct[i] = c[i] + t * d[i]
            pt = _energy_any(ct, n, Q, phi, dphi, W, cos_term, kb, F, phi3, False, g2, H2, fast, S)[0]
            if pt <= pi + 1e-4 * t * slope:
                break
            t *= 0.5
            if t < 1e-14:
                return it, LINE_SEARCH
        for i in range(n):
            c[i] = ct[i]
        pi, eb, es, w = _energy_any(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, True, g, H, fast, S)
    return _MAXIT, MAX_ITER


@njit(cache=True)
def _workspace(pmax, nl):
    n = pmax - 1
    qmax = max(nl, 1) * (4 * pmax - 1)
    return (np.empty(pmax + 2), np.empty((qmax, n)), np.empty((qmax, n)), np.empty(qmax),
            np.empty(n), np.empty(n), np.empty(n), np.empty((n, n)), np.empty(n), np.empty((n, n)),
            np.empty((n, n)), np.empty(n), np.empty(n), np.empty((2 * n, qmax)))


@njit(cache=True)
def _post(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, grid, gphi, wk, out, react, fast):
    """Deflections, slope, maximum, energies and per-layer spring reactions of a solved sample."""
    P, phi, dphi, W, phi3, dphi3, g, H, g2, H2, Lw, d, ct, S = wk
    n = p - 1
    Q = _points(p, l, T, K, cos_term, A, Ad, GX, GW, P, phi, dphi, W)
    # load point
    _basis_at(2.0 * z3 / l - 1.0, n, A, Ad, P, phi3, dphi3)
    pi, eb, es, wk_ = _energy(c, n, Q, phi, dphi, W, cos_term, kb, F, phi3, False, g, H)
    v3 = 0.0
    for i in range(n):
        v3 += c[i] * phi3[i]
    out[LOAD] = v3
    out[U_BEND] = eb
    out[U_SPRING] = es
    out[WORK] = wk_
    # tip
    _basis_at(1.0, n, A, Ad, P, phi3, dphi3)
    vt = 0.0
    st = 0.0
    for i in range(n):
        vt += c[i] * phi3[i]
        st += c[i] * dphi3[i]
    out[TIP] = vt
    out[TIP_DVDZ] = st / l
    # maximum |v| on the grid, refined by Newton on dv/ds = 0 inside the bracketing cells
    ng = grid.shape[0]
    kbest = 0
    vbest = 0.0
    for k in range(ng):
        v = 0.0
        for i in range(n):
            v += c[i] * gphi[k, i]
        if abs(v) > abs(vbest):
            vbest = v
            kbest = k
    sbest = grid[kbest]
    if 0 < kbest < ng - 1:
        lo = grid[kbest - 1]
        hi = grid[kbest + 1]
        s = sbest
        for _ in range(30):
            x = 2.0 * s - 1.0
            _basis_at(x, n, A, Ad, P, phi3, dphi3)
            dv = 0.0
            d2v = 0.0
            for i in range(n):
                dv += c[i] * dphi3[i]
                d2v += c[i] * np.sqrt(2.0 * i + 1.0) * P[i]
            if d2v == 0.0:
                break
            step = dv / d2v
            s = min(max(s - step, lo), hi)
            if abs(step) < 1e-15:
                break
        _basis_at(2.0 * s - 1.0, n, A, Ad, P, phi3, dphi3)
        v = 0.0
        for i in range(n):
            v += c[i] * phi3[i]
        if abs(v) > abs(vbest):
            vbest = v
            sbest = s
    out[VMAX] = vbest
    out[ZMAX] = sbest * l
    # spring reaction of each layer: int k (x + x^3) dz, x = v / cos(theta) (Eq. 8)
    nq = 4 * p - 1 if cos_term else 2 * p + 1
    for j in range(T.shape[0]):
        r = 0.0
        for q in range(j * nq, (j + 1) * nq):
            v = 0.0
            dd = 0.0
            for i in range(n):
                v += c[i] * phi[q, i]
                dd += c[i] * dphi[q, i]
            x = v * np.sqrt(1.0 + dd * dd) if cos_term else v
            r += W[q] * (x + x * x * x)
        react[j] = r


@njit(cache=True)
def _newton_any(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, wk, fast):
    """_newton; on the fast path, orders 3 and 4 as literals (the compiler then specialises the loops
    over coefficients and Gauss points: ~1.7x on the whole order-3 solve)."""
    if fast and p == 3:
        return _newton(3, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, wk, True)
    if fast and p == 4:
        return _newton(4, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, wk, True)
    return _newton(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, wk, fast)


@njit(cache=True)
def _post_any(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, grid, gphi, wk, out, react, fast):
    if fast and p == 3:
        return _post(3, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, grid, gphi, wk, out, react, True)
    return _post(p, c, F, kb, l, z3, T, K, cos_term, A, Ad, GX, GW, grid, gphi, wk, out, react, fast)


# ---- Order 3 in closed form (issue 18) ----
# At p = 3 the trial function is v = s^2 (a + b s), a = c0/2 - sqrt(3) c1/2, b = c1/sqrt(3)
# (basis.py: phi0 = s^2/2, phi1 = sqrt(3) (s^3/3 - s^2/2)), and v' = s (2a + 3b s) / l. With
# u = a + b s, w = 2a + 3b s the spring energy density 0.5 y + 0.25 y^2, y = v^2 (1 + v'^2), is
#     0.5 s^4 u^2 + 0.5 s^6 (uw)^2 / l^2 + 0.25 [s^8 u^4 + 2 s^10 u^2 (uw)^2 / l^2 + s^12 (uw)^4 / l^4],
# and each term a^(d-i) b^i of these forms carries exactly s^(e+i). Integrated over the layers, the
# spring energy is therefore a sum of binary forms in (a, b) of degrees 2, 4, 6, 8 whose 24 coefficients
# are integers times single moments mu_m = l sum_j k_j int_layer s^m ds (m = 4..20; to 22 for the
# order-4 step): exact, like the Gauss rule, and independent of c and F. They are computed once per
# model (once per batch when only the force varies); a Newton iteration then costs ~200 flops instead
# of a sum over 22 Gauss points.
_R3 = np.sqrt(3.0)


def _mul(p, q):
    """Product of two polynomials in (b, c) (a is the homogeneous complement): coefficient [j, k] of
    a^(d-j-k) b^j c^k, terms of c beyond c^2 dropped (the order-4 step needs them up to second order)."""
    r = np.zeros((p.shape[0] + q.shape[0] - 1, 3))
    for (j, k), x in np.ndenumerate(p):
        for (jj, kk), y in np.ndenumerate(q):
            if k + kk <= 2:
                r[j + jj, k + kk] += x * y
    return r


# u = a + b s + c s^2 and w = 2a + 3b s + 4c s^2 (c: the order-4 coefficient, zero at order 3); every
# term a^i b^j c^k of u^2, u^4, (uw)^2, u^2 (uw)^2, (uw)^4 carries s^(j + 2k)
_U = np.array([[1.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
_UW = _mul(_U, np.array([[2.0, 4.0, 0.0], [3.0, 0.0, 0.0]]))
_U2 = _mul(_U, _U)
_U4 = _mul(_U2, _U2)
_UW2 = _mul(_UW, _UW)
_U2UW2 = _mul(_U2, _UW2)
_UW4 = _mul(_UW2, _UW2)
# Layout of the per-model table: the value forms (degrees 2, 4, 6, 8: 3 + 5 + 7 + 9 coefficients),
# the Hessian forms (degrees 0, 2, 4, 6, triples aa, ab, bb: 3 (1 + 3 + 5 + 7)), the order-4 forms at
# c = 0 (the same degrees, triples ac, bc, cc), phi0(s3), phi1(s3), phi2(s3) (order 4), then the
# constants of the forms' length scale r (below; _scale).
# The gradient and the value follow from the Hessian forms by Euler's identity for a form P of
# degree d: a P_a + b P_b = d P (and the same for P_a, P_b of degree d - 1, and P_c at c = 0).
# Scale: the forms are in s = z / h with h = r l. At s = z / l (cubic_table) r = 1; the per-row
# tables (cubic_table_rows) keep h = the tissue's thickness, so that they are sums k_j G_j of columns
# computed once per thickness set, with no power of l per coefficient. The form in (a, b, c) of
# s = z / l is the form of s = z / h at (r^2 a, r^3 b, r^4 c) (v = a s^2 + b s^3 + c s^4): its
# derivatives scale by r^2, r^3, r^4 per a, b, c.
_NV, _NH = 24, 48
_PHI3 = _NV + 2 * _NH
_SC = _PHI3 + 3
_NTAB = _SC + 18  # r^0..r^8 end at _SC + 17
_NMU = 132  # cubic_table's scratch
_INV = 1.0 / np.arange(1.0, 25.0)  # _INV[n - 1] = 1 / n (multiplications, not divisions, per moment)
# Beyond these the closed form hands the sample to the Gauss path, which then reports exactly what it
# always did (overflow to inf/nan happens at other magnitudes in the two forms); both are far outside
# any physical needle (|v| / l <= 0.25).
_C_BIG = 1e30  # mm
_E_BIG = 1e150  # N mm
FALLBACK = -1


@njit(cache=True, inline="always")
def _value_forms(k, mu, l, il2, out, o):
    """The coefficients of c^k (times a^i b^j, by j) of the spring energy's forms of degrees 2, 4, 6, 8
    from the moments mu (a term b^j c^k of a form with s^e carries s^(e + j + 2k)), to out[o:]."""
    il4 = il2 * il2
    e = 2 * k
    for i in range(3 - k):
        out[o + i] = 0.5 * _U2[i, k] * mu[4 + e + i] * l
    o += 3 - k
    for i in range(5 - k):
        out[o + i] = (0.5 * il2 * _UW2[i, k] * mu[6 + e + i] + 0.25 * _U4[i, k] * mu[8 + e + i]) * l
    o += 5 - k
    for i in range(7 - k):
        out[o + i] = 0.5 * il2 * _U2UW2[i, k] * mu[10 + e + i] * l
    o += 7 - k
    for i in range(9 - k):
        out[o + i] = 0.25 * il4 * _UW4[i, k] * mu[12 + e + i] * l


@njit(cache=True)
def cubic_table(l, T, K, z3, cos_term, tab, mu):
    """Fill tab (_NTAB) with the order-3 energy forms of one model (geometry and k; not F), and the
    order-4 forms at c = 0 of the error estimate's Newton step, in s = z / l (r = 1). mu: scratch of
    _NMU floats (offsets, not slices: a slice costs two reference-count updates)."""
    _moments(1.0 / l, T, K, mu)
    _all_forms(mu, l, (1.0 if cos_term else 0.0) / (l * l), mu, 72)
    _expand(mu, 72, tab)
    _phi3(l, z3, tab)
    _scale(1.0, tab)


@njit(cache=True)
def thickness_table(T, cos_term, G, ZQ, mu, GX):
    """Columns of the per-row tables of one thickness set: G[j] = the forms (tab[:_PHI3]) of a unit k
    in layer j alone, in s = z / h, h = the total thickness (returned; 0 without layers); and _post's
    Gauss points (_tissue_points). mu: scratch of _NMU floats."""
    nl = T.shape[0]
    h = 0.0
    for j in range(nl):
        h += T[j]
    e = np.zeros(nl)
    for j in range(nl):
        e[j] = 1.0
        _moments(1.0 / h, T, e, mu)
        e[j] = 0.0
        _all_forms(mu, h, (1.0 if cos_term else 0.0) / (h * h), mu, 72)
        _expand(mu, 72, G[j])
    _tissue_points(T, cos_term, ZQ, GX)
    return h


@njit(cache=True)
def cubic_table_rows(l, K, g, z3, h, tab, G):
    """cubic_table of row g of K from thickness_table's columns G (total thickness h): the forms
    sum_j k_j G_j in s = z / h, r = h / l. The same energy as cubic_table's to round-off (~1e-15 relative), not bit for
    bit: every coefficient is rounded once in its own k-combination."""
    for i in range(_PHI3):
        tab[i] = 0.0
    for j in range(K.shape[1]):  # may be 0 layers (no tissue)
        kj = K[g, j]
        for i in range(_PHI3):
            tab[i] += kj * G[j, i]
    _phi3(l, z3, tab)
    _scale(h / l, tab)


@njit(cache=True, inline="always")
def _scale(r, tab):
    """tab[_SC:]: the chain rule from the table's scaled (a, b) = (r^2 a, r^3 b) to c (_powers,
    _to_c; at r = 1 exactly the constants of da/dc = (1/2, -sqrt(3)/2), db/dc = (0, 1/sqrt(3)), so a
    force-only batch's table gives the same bits as before the scale), then r^0..r^8 (_step4c)."""
    r2 = r * r
    r4 = r2 * r2
    tab[_SC] = 0.5 * r2
    tab[_SC + 1] = 0.5 * _R3 * r2
    tab[_SC + 2] = (1.0 / _R3) * (r2 * r)
    tab[_SC + 3] = 0.25 * r4
    tab[_SC + 4] = (1.0 / _R3) * (r4 * r)
    tab[_SC + 5] = 0.5 * _R3 * r4
    tab[_SC + 6] = 0.75 * r4
    tab[_SC + 7] = r4 * r
    tab[_SC + 8] = (1.0 / 3.0) * (r4 * r2)
    tab[_SC + 9] = 1.0
    for i in range(1, 9):
        tab[_SC + 9 + i] = tab[_SC + 8 + i] * r


@njit(cache=True, inline="always")
def _reaction_points(l, K, g, cos_term, ZQ, GW, PQ):
    """PQ: s of _post's Gauss points (from _tissue_points' ZQ), then k * weight * dz/dxi (_post's W,
    the same operations), layer by layer, for the model of row g of K."""
    nq = 11 if cos_term else 7
    nl = K.shape[1]
    il = 1.0 / l
    q = 0
    for j in range(nl):
        w = K[g, j] * ZQ[j, 11]
        for i in range(nq):
            PQ[q] = ZQ[j, i] * il
            PQ[q + nl * nq] = w * GW[nq, i]
            q += 1


@njit(cache=True)
def _tissue_points(T, cos_term, ZQ, GX):
    """ZQ[j, g] = z of _post's Gauss point g in layer j, ZQ[j, 11] the layer's half-thickness."""
    nq = 11 if cos_term else 7
    za = 0.0
    for j in range(T.shape[0]):
        zb = za + T[j]
        half = 0.5 * (zb - za)
        for g in range(nq):
            ZQ[j, g] = za + half * (GX[nq, g] + 1.0)
        ZQ[j, 11] = half
        za = zb


@njit(cache=True, inline="always")
def _all_forms(mu, l, il2, V, o):
    """V (at V[o:]) from the moments mu[:24]."""
    _value_forms(0, mu, l, il2, V, o)
    _value_forms(1, mu, l, il2, V, o + 24)
    _value_forms(2, mu, l, il2, V, o + 44)


@njit(cache=True, inline="always")
def _expand(V, o, tab):
    """tab[:_PHI3] from V (at V[o:]): the Hessian forms and, at c = 0, the c-derivatives (d2/da2 of
    a^(d-i) b^i is (d-i)(d-i-1) a^(d-2-i) b^i, and so on; loops per degree: an index list was slower)."""
    for i in range(_NV):
        tab[i] = V[o + i]
    kh = _NV
    kc = _NV + _NH
    off = o
    o1 = o + 24
    o2 = o + 44
    for d in range(2, 10, 2):
        for j in range(d - 1):
            tab[kh] = (d - j) * (d - j - 1) * V[off + j]
            tab[kh + 1] = (d - j - 1) * (j + 1) * V[off + j + 1]
            tab[kh + 2] = (j + 2) * (j + 1) * V[off + j + 2]
            kh += 3
        for j in range(d - 1):
            tab[kc] = (d - 1 - j) * V[o1 + j]
            tab[kc + 1] = (j + 1) * V[o1 + j + 1]
            tab[kc + 2] = 2.0 * V[o2 + j]
            kc += 3
        off += d + 1
        o1 += d
        o2 += d - 1


@njit(cache=True, inline="always")
def _moments(il, T, K, mu):
    """mu[m] = sum_j k_j int_layer s^m ds, s = z il (mu[24:72]: scratch)."""
    # per layer [sa, sb]: mu[24 + n] = sb^n - sa^n, mu[48 + n] = sa^n
    for m in range(24):
        mu[m] = 0.0
    sa = 0.0
    for j in range(T.shape[0]):
        h = T[j] * il
        sb = sa + h
        # D_(m+k) = sb^k D_m + sa^m D_k: sums of positive terms (no cancellation in thin layers),
        # and with k = 4 four independent chains instead of one of length 22
        mu[25] = h
        mu[48] = 1.0
        mu[49] = sa
        for n in range(2, 5):
            mu[24 + n] = sb * mu[23 + n] + mu[47 + n] * h
            mu[48 + n] = mu[47 + n] * sa
        sb2 = sb * sb
        sb4 = sb2 * sb2
        d4 = mu[28]
        p4 = mu[52]
        for n in range(5, 24):
            mu[24 + n] = sb4 * mu[20 + n] + mu[44 + n] * d4
            mu[48 + n] = mu[44 + n] * p4
        kj = K[j]
        for n in range(5, 24):
            mu[n - 1] += kj * mu[24 + n] * _INV[n - 1]
        sa = sb


@njit(cache=True, inline="always")
def _phi3(l, z3, tab):
    s3 = z3 / l
    tab[_PHI3] = 0.5 * s3 * s3
    tab[_PHI3 + 1] = _R3 * (s3 * s3 * s3 / 3.0 - 0.5 * s3 * s3)
    tab[_PHI3 + 2] = s3 * s3 * (_M4[2, 0] + s3 * (_M4[2, 1] + s3 * _M4[2, 2]))


@njit(cache=True)
def _energy3c(c0, c1, tab, kb, F, grad, pw):
    """Order-3 energy from the table: (Pi, U_bend, U_spring, work, g0, g1, H00, H10, H11) in c."""
    a, b = _powers(c0, c1, tab, pw)
    eb = 0.5 * kb * (c0 * c0 + c1 * c1)
    wk = F * (c0 * tab[_PHI3] + c1 * tab[_PHI3 + 1])
    es = 0.0
    if not grad:
        # the value forms, one partial sum per degree (independent chains of additions)
        off = 0
        for d in range(2, 10, 2):
            e = 0.0
            for i in range(d + 1):
                e += tab[off + i] * (pw[d - i] * pw[9 + i])
            es += e
            off += d + 1
        return eb + es - wk, eb, es, wk, 0.0, 0.0, 0.0, 0.0, 0.0
    ga, gb, es, haa, hab, hbb = _forms(a, b, tab, pw, False)[:6]
    g0, g1, h00, h10, h11 = _to_c(kb, F, c0, c1, tab, ga, gb, haa, hab, hbb)
    return eb + es - wk, eb, es, wk, g0, g1, h00, h10, h11


@njit(cache=True, inline="always")
def _powers(c0, c1, tab, pw):
    """(a, b) of the order-3 coefficients c in the table's scale (r^2 a, r^3 b), and pw[k] = a^k,
    pw[9 + k] = b^k (k <= 8)."""
    a = tab[_SC] * c0 - tab[_SC + 1] * c1
    b = c1 * tab[_SC + 2]
    pw[0] = 1.0
    pw[9] = 1.0
    for k in range(1, 9):
        pw[k] = pw[k - 1] * a
        pw[9 + k] = pw[8 + k] * b
    return a, b


@njit(cache=True, inline="always")
def _forms(a, b, tab, pw, quartic):
    """The Hessian forms (degrees 0, 2, 4, 6; triples aa, ab, bb from tab[_NV]) at (a, b), and by Euler
    the gradient and the value of the spring energy: (P_a, P_b, U_spring, H_aa, H_ab, H_bb); with
    quartic also the order-4 forms at c = 0 (triples ac, bc, cc from tab[_NV + _NH], same monomials):
    P_c, H_ac, H_bc, H_cc (else zeros). (a, b) and the derivatives in the table's scale (_powers)."""
    p1 = p2 = val = h11 = h12 = h22 = 0.0
    pc = hac = hbc = hcc = 0.0
    k = _NV
    for m in range(0, 8, 2):
        s11 = 0.0
        s12 = 0.0
        s22 = 0.0
        sac = 0.0
        sbc = 0.0
        scc = 0.0
        for j in range(m + 1):
            t = pw[m - j] * pw[9 + j]
            s11 += tab[k] * t
            s12 += tab[k + 1] * t
            s22 += tab[k + 2] * t
            if quartic:
                sac += tab[k + _NH] * t
                sbc += tab[k + _NH + 1] * t
                scc += tab[k + _NH + 2] * t
            k += 3
        q1 = (a * s11 + b * s12) * _INV[m]  # 1 / (d - 1)
        q2 = (a * s12 + b * s22) * _INV[m]
        val += (a * q1 + b * q2) * _INV[m + 1]  # 1 / d
        p1 += q1
        p2 += q2
        h11 += s11
        h12 += s12
        h22 += s22
        if quartic:
            pc += (a * sac + b * sbc) * _INV[m]  # P_c has degree d - 1
            hac += sac
            hbc += sbc
            hcc += scc
    return p1, p2, val, h11, h12, h22, pc, hac, hbc, hcc


@njit(cache=True)
def _step4c(c0, c1, F, kb, tab, pw):
    """The error estimate's order-4 step: one Newton step from the order-3 answer (c0, c1, 0), its
    gradient and Hessian from the closed-form forms at c = 0 (exact like order 3's; no Gauss points).
    (positive definite, d0, d1, d2) in the order-4 basis coefficients."""
    a, b = _powers(c0, c1, tab, pw)
    ga, gb, es, haa, hab, hbb, gc, hac, hbc, hcc = _forms(a, b, tab, pw, True)
    o = _SC + 9  # r^0: the derivatives back in s = z / l, for _to_x4
    r = _to_x4(kb, F, c0, c1, 0.0, tab[_PHI3], tab[_PHI3 + 1], tab[_PHI3 + 2], ga * tab[o + 2],
               gb * tab[o + 3], gc * tab[o + 4], haa * tab[o + 4], hab * tab[o + 5], hbb * tab[o + 6],
               hac * tab[o + 6], hbc * tab[o + 7], hcc * tab[o + 8])
    return _chol3(r[3], r[4], r[5], r[6], r[7], r[8], r[0], r[1], r[2], 0.0)


@njit(cache=True)
def _to_c(kb, F, c0, c1, tab, ga, gb, haa, hab, hbb):
    """Gradient and Hessian in c from those of the spring energy in the table's (a, b), with bending
    and load: da/dc = (1/2, -sqrt(3)/2) r^2, db/dc = (0, 1/sqrt(3)) r^3 (_scale)."""
    o = _SC
    g0 = kb * c0 - F * tab[_PHI3] + tab[o] * ga
    g1 = kb * c1 - F * tab[_PHI3 + 1] - tab[o + 1] * ga + gb * tab[o + 2]
    h00 = kb + tab[o + 3] * haa
    h10 = 0.5 * (hab * tab[o + 4] - tab[o + 5] * haa)
    h11 = kb + tab[o + 6] * haa - tab[o + 7] * hab + hbb * tab[o + 8]
    return g0, g1, h00, h10, h11


@njit(cache=True)
def _chol2(h00, h10, h11, g0, g1, shift):
    """d = -(H + shift I)^-1 g for n = 2 as L D L^T (two divisions, no square roots); the
    positive-definiteness test is _cholesky_solve's (both pivots > 0). (positive definite, d0, d1)."""
    s0 = h00 + shift
    if not s0 > 0.0:
        return False, 0.0, 0.0
    r0 = 1.0 / s0
    l10 = h10 * r0
    s1 = h11 + shift - l10 * h10
    if not s1 > 0.0:
        return False, 0.0, 0.0
    d1 = (l10 * g0 - g1) / s1
    d0 = -g0 * r0 - l10 * d1
    return True, d0, d1


@njit(cache=True)
def _safe(c0, c1, es, pi):
    return abs(c0) <= _C_BIG and abs(c1) <= _C_BIG and es <= _E_BIG and np.isfinite(pi)


@njit(cache=True)
def _newton3c(c, F, kb, tab, pw):
    """_newton at p = 3 from rest on the closed-form energy: the same steps, line search and tests.
    Returns (iterations, status, U_bend, U_spring, work at c), status FALLBACK when c or the energy
    leaves the range where both forms are finite (the caller then runs the Gauss path from rest)."""
    c0 = 0.0
    c1 = 0.0
    # at rest: Pi = 0, g = -F phi(s3), H = bending + linear springs (the degree-0 Hessian form)
    pi = eb = es = w = 0.0
    kh = _NV
    g0, g1, h00, h10, h11 = _to_c(kb, F, c0, c1, tab, 0.0, 0.0, tab[kh], tab[kh + 1], tab[kh + 2])
    for it in range(_MAXIT):
        shift = 0.0
        pd, d0, d1 = _chol2(h00, h10, h11, g0, g1, 0.0)
        if not pd:
            shift = 1e-8 * kb
            while True:
                ok, d0, d1 = _chol2(h00, h10, h11, g0, g1, shift)
                if ok:
                    break
                shift *= 10.0
        t0 = c0 + d0
        t1 = c1 + d1
        dn = max(abs(d0), abs(d1))
        cn = max(abs(t0), abs(t1))
        slope = g0 * d0 + g1 * d1
        scale = abs(eb) + abs(es) + abs(w) + 1e-300
        last = pd and (dn <= _RTOL * cn + _ATOL or -slope <= 1e-15 * scale)
        # gradient and Hessian at the trial point only if another iteration will use them
        pt, ebt, est, wt, q0, q1, k00, k10, k11 = _energy3c(t0, t1, tab, kb, F, not last, pw)
        if not _safe(t0, t1, est, pt):
            c[0] = c0
            c[1] = c1
            return 0, FALLBACK, 0.0, 0.0, 0.0
        if pt <= pi + 1e-4 * slope or -slope <= 1e-13 * scale:
            c0 = t0
            c1 = t1
            if last:
                c[0] = c0
                c[1] = c1
                return it + 1, OK, ebt, est, wt
            pi, eb, es, w, g0, g1, h00, h10, h11 = pt, ebt, est, wt, q0, q1, k00, k10, k11
            continue
        t = 0.5
        while True:
            t0 = c0 + t * d0
            t1 = c1 + t * d1
            r = _energy3c(t0, t1, tab, kb, F, False, pw)
            if not _safe(t0, t1, r[2], r[0]):
                return 0, FALLBACK, 0.0, 0.0, 0.0
            if r[0] <= pi + 1e-4 * t * slope:
                break
            t *= 0.5
            if t < 1e-14:
                c[0] = c0
                c[1] = c1
                return it, LINE_SEARCH, eb, es, w
        c0 = t0
        c1 = t1
        pi, eb, es, w, g0, g1, h00, h10, h11 = _energy3c(c0, c1, tab, kb, F, True, pw)
        if not _safe(c0, c1, es, pi):
            return 0, FALLBACK, 0.0, 0.0, 0.0
    c[0] = c0
    c[1] = c1
    return _MAXIT, MAX_ITER, eb, es, w


@njit(cache=True)
def _post3c(c, l, nl, cos_term, tab, eb, es, wk, out, react, m, fq, PQ):
    """_post at p = 3 in closed form, given the energies at c. The layer reactions use _post's Gauss
    rule (PQ from _reaction_points): their integrand carries sqrt(1 + v'^2), which no rule integrates
    exactly."""
    c0 = c[0]
    c1 = c[1]
    a = 0.5 * c0 - 0.5 * _R3 * c1
    b = c1 * (1.0 / _R3)
    out[LOAD] = c0 * tab[_PHI3] + c1 * tab[_PHI3 + 1]
    out[U_BEND] = eb
    out[U_SPRING] = es
    out[WORK] = wk
    out[TIP] = a + b
    out[TIP_DVDZ] = c0 / l  # dv/ds(1) = 2a + 3b = c0
    # maximum |v| as _post finds it on the 65-point grid s = k/64: v' = s (2a + 3b s) vanishes only at
    # s = 0 and s* = -2a/(3b), so the grid maximum is at the grid points around s* or at s = 1; an
    # interior grid maximum is refined to s* (where _post's Newton on dv/ds = 0 converges)
    # (selects, not branches: which candidate wins varies from row to row)
    ss = -2.0 * a / (3.0 * b) if b != 0.0 else -1.0
    kbest = 0
    vbest = 0.0
    lo = int(ss * 64.0) if 0.0 < ss < 1.0 else 64
    # the candidates lo, lo + 1, 64 in _post's order (it keeps the first strict maximum; a repeated
    # 64 never wins again)
    for k in (lo, min(lo + 1, 64), 64):
        s = k / 64.0
        v = s * s * (a + b * s)
        better = abs(v) > abs(vbest)
        vbest = v if better else vbest
        kbest = k if better else kbest
    sbest = kbest / 64.0
    v = ss * ss * (a + b * ss)
    better = (0 < kbest) & (kbest < 64) & (abs(v) > abs(vbest))
    vbest = v if better else vbest
    sbest = ss if better else sbest
    out[VMAX] = vbest
    out[ZMAX] = sbest * l
    nq = 11 if cos_term else 7
    il = 1.0 / l
    a2 = 2.0 * a * il  # dv/dz = s (a2 + b3 s)
    b3 = 3.0 * b * il
    # the points of all layers first (independent: one vectorised loop, square roots included), then
    # each layer's sum in order (one loop per layer of 11 points: 98 -> 66 ns per _post3c, load 7.7)
    nt = nl * nq
    for q in range(nt):
        s = PQ[q]
        v = s * s * (a + b * s)
        if cos_term:
            dd = s * (a2 + b3 * s)
            x = v * np.sqrt(1.0 + dd * dd)
        else:
            x = v
        fq[q] = PQ[nt + q] * (x + x * x * x)
    for j in range(nl):
        r = 0.0
        for q in range(j * nq, (j + 1) * nq):
            r += fq[q]
        react[m, j] = r


# ---- Order 4 for the order-3 error estimate (issue 18) ----
# The estimate solves order 4 from the order-3 answer. On the Gauss path that solve cost ~80 % of a
# solve with its estimate, mostly the Legendre basis at the 30 points (_points, per sample) and the
# array-based Newton. Here the basis is in monomial form, v = s^2 (a + b s + c s^2), evaluated at each
# point (the points are cheap to place: quartic_points), and the Newton state is in scalars. Same
# Gauss rule, same iteration: results equal the Gauss path's to round-off. (Order 4 as closed-form
# moments like order 3 was tried: the forms of degree 8 in (a, b, c) lose up to 8 digits to
# cancellation when stiff tissue makes a + b s + c s^2 small over the layers, and were slower.)
_R5 = np.sqrt(5.0)
# (a, b, c) = x @ _M4 for basis coefficients x (basis.monomial_matrix(4)[:, 2:])
_M4 = np.array([[0.5, 0.0, 0.0], [-0.5 * _R3, 1.0 / _R3, 0.0], [0.5 * _R5, -_R5, 0.5 * _R5]])


@njit(cache=True)
def quartic_points(l, T, K, z3, cos_term, tab, GX, GW):
    """tab (3 + 2 Q): phi_0..2(s3), then the Gauss points of the order-4 rule: s, then k * weight * dz/dxi."""
    il = 1.0 / l
    s3 = z3 * il
    s32 = s3 * s3
    for i in range(3):
        tab[i] = s32 * (_M4[i, 0] + s3 * (_M4[i, 1] + s3 * _M4[i, 2]))
    nq = 15 if cos_term else 9
    nl = T.shape[0]
    q = 3
    za = 0.0
    for j in range(nl):
        zb = za + T[j]
        half = 0.5 * (zb - za)
        for g in range(nq):
            tab[q] = (za + half * (GX[nq, g] + 1.0)) * il
            tab[q + nl * nq] = K[j] * half * GW[nq, g]
            q += 1
        za = zb
    return nl * nq


@njit(cache=True, fastmath=_FM)
def _energy4g(x0, x1, x2, tab, n, il, cos_term, kb, F, grad):
    """Order-4 energy on the Gauss points of quartic_points (basis in monomial form: phi = s^2 (1, s, s^2)
    in (a, b, c)): (Pi, U_bend, U_spring, work, g (3), H (6: 00 10 11 20 21 22)) in x."""
    a = x0 * _M4[0, 0] + x1 * _M4[1, 0] + x2 * _M4[2, 0]
    b = x1 * _M4[1, 1] + x2 * _M4[2, 1]
    c = x2 * _M4[2, 2]
    eb = 0.5 * kb * (x0 * x0 + x1 * x1 + x2 * x2)
    wk = F * (x0 * tab[0] + x1 * tab[1] + x2 * tab[2])
    es = 0.0
    o = 3
    if not grad:
        for q in range(n):
            s = tab[o + q]
            v = s * s * (a + s * (b + s * c))
            y = v * v
            if cos_term:
                d = s * (2.0 * a + s * (3.0 * b + s * 4.0 * c)) * il
                y *= 1.0 + d * d
            es += tab[o + n + q] * (0.5 * y + 0.25 * y * y)
        return eb + es - wk, eb, es, wk, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    ga = gb = gc = 0.0
    haa = hab = hac = hbb = hbc = hcc = 0.0
    if cos_term:
        for q in range(n):
            s = tab[o + q]
            a0 = s * s  # dv/d(a, b, c) and d(dv/dz)/d(a, b, c)
            a1 = a0 * s
            a2 = a1 * s
            b0 = 2.0 * s * il
            b1 = 3.0 * a0 * il
            b2 = 4.0 * a1 * il
            r = _spring_point_cos(tab[o + n + q], a * a0 + b * a1 + c * a2, a * b0 + b * b1 + c * b2, a0, a1, a2,
                                  b0, b1, b2)
            es += r[0]
            ga += r[1]
            gb += r[2]
            gc += r[3]
            haa += r[4]
            hab += r[5]
            hbb += r[6]
            hac += r[7]
            hbc += r[8]
            hcc += r[9]
    else:
        for q in range(n):
            s = tab[o + q]
            a0 = s * s
            a1 = a0 * s
            a2 = a1 * s
            r = _spring_point(tab[o + n + q], a * a0 + b * a1 + c * a2, a0, a1, a2)
            es += r[0]
            ga += r[1]
            gb += r[2]
            gc += r[3]
            haa += r[4]
            hab += r[5]
            hbb += r[6]
            hac += r[7]
            hbc += r[8]
            hcc += r[9]
    g0, g1, g2, h00, h10, h11, h20, h21, h22 = _to_x4(kb, F, x0, x1, x2, tab[0], tab[1], tab[2], ga, gb,
                                                      gc, haa, hab, hbb, hac, hbc, hcc)
    return eb + es - wk, eb, es, wk, g0, g1, g2, h00, h10, h11, h20, h21, h22


@njit(cache=True, fastmath=_FM)
def _to_x4(kb, F, x0, x1, x2, p0, p1, p2, ga, gb, gc, haa, hab, hbb, hac, hbc, hcc):
    """Order-4 gradient and Hessian in the basis coefficients x from those of the spring energy in
    (a, b, c) = x _M4 (g_x = M g, H_x = M H M^T), with bending and the load at phi(s3) = (p0, p1, p2):
    (g0, g1, g2, h00, h10, h11, h20, h21, h22)."""
    g0 = kb * x0 - F * p0 + _M4[0, 0] * ga
    g1 = kb * x1 - F * p1 + _M4[1, 0] * ga + _M4[1, 1] * gb
    g2 = kb * x2 - F * p2 + _M4[2, 0] * ga + _M4[2, 1] * gb + _M4[2, 2] * gc
    u00 = _M4[0, 0] * haa
    u10 = _M4[1, 0] * haa + _M4[1, 1] * hab
    u11 = _M4[1, 0] * hab + _M4[1, 1] * hbb
    u20 = _M4[2, 0] * haa + _M4[2, 1] * hab + _M4[2, 2] * hac
    u21 = _M4[2, 0] * hab + _M4[2, 1] * hbb + _M4[2, 2] * hbc
    u22 = _M4[2, 0] * hac + _M4[2, 1] * hbc + _M4[2, 2] * hcc
    h00 = kb + u00 * _M4[0, 0]
    h10 = u10 * _M4[0, 0]
    h11 = kb + u10 * _M4[1, 0] + u11 * _M4[1, 1]
    h20 = u20 * _M4[0, 0]
    h21 = u20 * _M4[1, 0] + u21 * _M4[1, 1]
    h22 = kb + u20 * _M4[2, 0] + u21 * _M4[2, 1] + u22 * _M4[2, 2]
    return g0, g1, g2, h00, h10, h11, h20, h21, h22


@njit(cache=True)
def _chol3(h00, h10, h11, h20, h21, h22, g0, g1, g2, shift):
    """d = -(H + shift I)^-1 g for n = 3 as L D L^T in scalars: three divisions, no square roots (a
    chain of 12 divisions and roots cost ~60 ns per step); the positive-definiteness test is
    _cholesky_solve's (all pivots > 0). (positive definite, d0, d1, d2)."""
    s0 = h00 + shift
    if not s0 > 0.0:
        return False, 0.0, 0.0, 0.0
    r0 = 1.0 / s0
    l10 = h10 * r0
    l20 = h20 * r0
    s1 = h11 + shift - l10 * h10
    if not s1 > 0.0:
        return False, 0.0, 0.0, 0.0
    r1 = 1.0 / s1
    e21 = h21 - l20 * h10  # l21 * s1
    l21 = e21 * r1
    s2 = h22 + shift - l20 * h20 - l21 * e21
    if not s2 > 0.0:
        return False, 0.0, 0.0, 0.0
    y1 = l10 * g0 - g1
    y2 = l20 * g0 - l21 * y1 - g2
    d2 = y2 / s2
    d1 = y1 * r1 - l21 * d2
    d0 = -g0 * r0 - l10 * d1 - l20 * d2
    return True, d0, d1, d2


@njit(cache=True)
def _newton4(c, F, kb, tab, n, il, cos_term):
    """_newton at p = 4 from c (in place) on _energy4g: the same steps, line search and tests.
    Returns (iterations, status); FALLBACK (c untouched) when c or the energy leaves the range where
    both forms are finite (the caller then runs the Gauss path from the same start)."""
    c0 = c[0]
    c1 = c[1]
    c2 = c[2]
    r = _energy4g(c0, c1, c2, tab, n, il, cos_term, kb, F, True)
    pi, eb, es, w, g0, g1, g2, h00, h10, h11, h20, h21, h22 = r
    if not (_safe(c0, c1, es, pi) and abs(c2) <= _C_BIG):
        return 0, FALLBACK
    for it in range(_MAXIT):
        shift = 0.0
        pd, d0, d1, d2 = _chol3(h00, h10, h11, h20, h21, h22, g0, g1, g2, 0.0)
        if not pd:
            shift = 1e-8 * kb
            while True:
                ok, d0, d1, d2 = _chol3(h00, h10, h11, h20, h21, h22, g0, g1, g2, shift)
                if ok:
                    break
                shift *= 10.0
        t0 = c0 + d0
        t1 = c1 + d1
        t2 = c2 + d2
        dn = max(abs(d0), abs(d1), abs(d2))
        cn = max(abs(t0), abs(t1), abs(t2))
        slope = g0 * d0 + g1 * d1 + g2 * d2
        scale = abs(eb) + abs(es) + abs(w) + 1e-300
        last = pd and (dn <= _RTOL * cn + _ATOL or -slope <= 1e-15 * scale)
        if last and -slope <= 1e-13 * scale:  # the test below accepts it whatever Pi is there
            c[0] = t0
            c[1] = t1
            c[2] = t2
            return it + 1, OK
        r = _energy4g(t0, t1, t2, tab, n, il, cos_term, kb, F, not last)
        if not (_safe(t0, t1, r[2], r[0]) and abs(t2) <= _C_BIG):
            return 0, FALLBACK
        if r[0] <= pi + 1e-4 * slope or -slope <= 1e-13 * scale:
            c0 = t0
            c1 = t1
            c2 = t2
            if last:
                c[0] = c0
                c[1] = c1
                c[2] = c2
                return it + 1, OK
            pi, eb, es, w, g0, g1, g2, h00, h10, h11, h20, h21, h22 = r
            continue
        t = 0.5
        while True:
            t0 = c0 + t * d0
            t1 = c1 + t * d1
            t2 = c2 + t * d2
            r = _energy4g(t0, t1, t2, tab, n, il, cos_term, kb, F, False)
            if not (_safe(t0, t1, r[2], r[0]) and abs(t2) <= _C_BIG):
                return 0, FALLBACK
            if r[0] <= pi + 1e-4 * t * slope:
                break
            t *= 0.5
            if t < 1e-14:
                c[0] = c0
                c[1] = c1
                c[2] = c2
                return it, LINE_SEARCH
        c0 = t0
        c1 = t1
        c2 = t2
        r = _energy4g(c0, c1, c2, tab, n, il, cos_term, kb, F, True)
        pi, eb, es, w, g0, g1, g2, h00, h10, h11, h20, h21, h22 = r
        if not (_safe(c0, c1, es, pi) and abs(c2) <= _C_BIG):
            return 0, FALLBACK
    c[0] = c0
    c[1] = c1
    c[2] = c2
    return _MAXIT, MAX_ITER



@njit(cache=True)
def _sup4(x0, x1, x2, grid):
    """max over the grid s = k/64 of |v| for order-4 basis coefficients x, in monomial form. Between the
    critical points of v = s^2 (a + b s + c s^2) (s = 0 and the roots of 2a + 3b s + 4c s^2) |v| is
    monotone, or falls to zero and rises: the grid maximum is at s = 1 or next to an interior critical
    point, so only those points are evaluated (the 65-point scan cost ~100 ns). Selects instead of
    branches (which case applies varies from row to row: a mispredicted branch costs more than the
    few flops of the unused case): 46 -> 27 ns on random coefficients."""
    a = x0 * _M4[0, 0] + x1 * _M4[1, 0] + x2 * _M4[2, 0]
    b = x1 * _M4[1, 1] + x2 * _M4[2, 1]
    c = x2 * _M4[2, 2]
    n = grid.shape[0] - 1
    s = grid[n]  # 1, evaluated as at the other points (the same round-off as a scan)
    e = abs(s * s * (a + s * (b + s * c)))
    # the roots (-1: none); the unused expressions may be inf or NaN
    disc = 9.0 * b * b - 32.0 * a * c
    quad = (c != 0.0) & (disc >= 0.0)
    q = -0.5 * (3.0 * b + np.copysign(np.sqrt(disc if quad else 0.0), b))
    r1 = q / (4.0 * c) if quad else (-2.0 * a / (3.0 * b) if (c == 0.0) & (b != 0.0) else -1.0)
    r2 = 2.0 * a / q if quad & (q != 0.0) else -1.0
    return max(e, max(_grid_pair(r1, a, b, c, grid, n), _grid_pair(r2, a, b, c, grid, n)))


@njit(cache=True, inline="always")
def _grid_pair(r, a, b, c, grid, n):
    """max |v| at the grid points k/n and (k + 1)/n around s = r, or at s = 1 (already in the max)
    when r is not in (0, 1)."""
    k = int((r if 0.0 < r < 1.0 else 1.0) * n)
    s = grid[k]
    t = grid[min(k + 1, n)]
    return max(abs(s * s * (a + s * (b + s * c))), abs(t * t * (a + t * (b + t * c))))


def _solve_range(start, stop, F, KB, L, Z3, T, K, cos_term, order, auto, pmax, tol,
                 A, Ad, GX, GW, grid, gphi, C, S, R, fast, closed, estimate, mono4, step):
    """Samples start..stop-1. The model arrays KB, L, Z3, T, K have one row per sample, or a single
    row that every sample shares (a batch that varies the force only). closed: order 3 through the
    closed-form energy (cubic_table); estimate: also solve order p + 1 for error_estimate (else NaN);
    mono4: with closed, the order-4 solve of the order-3 estimate through _newton4 (else Gauss path);
    step: with mono4 and not auto, that solve replaced by one Newton step (_step4c)."""
    nl = T.shape[1]
    wk = _workspace(pmax + 1, nl)
    c = np.zeros(pmax)
    c2 = np.zeros(pmax)
    tab = np.empty(_NTAB)
    mu = np.empty(_NMU)
    pw = np.empty(18)
    fq = np.empty(max(nl, 1) * 11)  # _post3c's reaction integrands
    out = np.full(NCOLS, np.nan)  # one sample's scalars (NaN where a failed sample has none)
    shared = L.shape[0] == 1
    cubic = closed and order == 3
    tab4 = np.empty(3 + 2 * max(nl, 1) * 15)
    n4 = 0
    # one closed-form order-4 Newton step for the order-3 estimate (not in auto: order 5 starts from
    # the converged order 4); where its Hessian is not positive definite, the full order-4 solve
    step4 = cubic and mono4 and step and not auto
    G = np.empty((nl, _PHI3))  # thickness_table of the thicknesses Tc (total h)
    ZQ = np.empty((nl, 12))  # _post's Gauss points of Tc, or of the row's thicknesses
    Tc = np.full(nl, np.nan)
    h = 0.0
    PQ = np.empty(2 * nl * 11)
    if cubic and shared:
        cubic_table(L[0], T[0], K[0], Z3[0], cos_term, tab, mu)
        _tissue_points(T[0], cos_term, ZQ, GX)
        _reaction_points(L[0], K, 0, cos_term, ZQ, GW, PQ)
    for m in range(start, stop):
        g = 0 if shared else m
        for i in range(pmax):
            c[i] = 0.0
        p = order
        gauss = True
        if cubic:
            if not shared:
                same = True
                for j in range(nl):
                    same = same and T[g, j] == Tc[j]
                if not same:  # columns for a run of equal thicknesses, else this row's own table
                    nxt = g + 1 < T.shape[0]
                    for j in range(nl):
                        nxt = nxt and T[g + 1, j] == T[g, j]
                    if nxt:
                        h = thickness_table(T[g], cos_term, G, ZQ, mu, GX)
                        Tc[:] = T[g]
                        same = True
                    else:
                        cubic_table(L[g], T[g], K[g], Z3[g], cos_term, tab, mu)
                        _tissue_points(T[g], cos_term, ZQ, GX)
                        Tc[:] = np.nan
                if same:
                    cubic_table_rows(L[g], K, g, Z3[g], h, tab, G)
                _reaction_points(L[g], K, g, cos_term, ZQ, GW, PQ)
            it, st, eb, es, wk_ = _newton3c(c, F[m], KB[g], tab, pw)
            gauss = st == FALLBACK
            if gauss:
                c[0] = 0.0
                c[1] = 0.0
        if gauss:
            it, st = _newton_any(p, c, F[m], KB[g], L[g], Z3[g], T[g], K[g], cos_term, A, Ad, GX, GW,
                                 wk, fast)
        est = np.inf if estimate else np.nan
        prev = np.inf  # change from order p - 1 to p
        while estimate and st == OK:
            # error estimate: sup-norm change of v on the grid when the order is raised by one
            for i in range(pmax):
                c2[i] = c[i]
            c2[p - 1] = 0.0
            if step4 and not gauss and p == 3:  # one order-4 Newton step in closed form
                pd, d0, d1, d2 = _step4c(c[0], c[1], F[m], KB[g], tab, pw)
                est = _sup4(d0, d1, d2, grid)
                if pd and np.isfinite(est):
                    break
            st2 = FALLBACK
            if cubic and mono4 and p == 3:  # order 4 in monomial form, scalar state
                if not shared or n4 == 0:
                    n4 = quartic_points(L[g], T[g], K[g], Z3[g], cos_term, tab4, GX, GW)
                it2, st2 = _newton4(c2, F[m], KB[g], tab4, n4, 1.0 / L[g], cos_term)
            if st2 == FALLBACK:
                it2, st2 = _newton_any(p + 1, c2, F[m], KB[g], L[g], Z3[g], T[g], K[g], cos_term,
                                       A, Ad, GX, GW, wk, fast)
            if st2 != OK:
                st = st2
                break
            if cubic and mono4 and p == 3:
                est = _sup4(c2[0] - c[0], c2[1] - c[1], c2[2], grid)
            else:
                est = 0.0
                for k in range(grid.shape[0]):
                    dv = c2[p - 1] * gphi[k, p - 1]
                    for i in range(p - 1):
                        dv += (c2[i] - c[i]) * gphi[k, i]
                    est = max(est, abs(dv))
            if not auto:
                break
            # auto: stop when the changes to AND from order p are both below tol (one small change
            # alone can be a parity accident of the basis), or at the highest order
            if (est <= tol and prev <= tol) or p >= pmax:
                if prev < np.inf:
                    est = max(est, prev)
                break
            prev = est
            for i in range(pmax):
                c[i] = c2[i]
            p += 1
            it = it2
        out[ORDER] = p
        out[ITER] = it
        out[STATUS] = st
        out[ERR] = est
        for i in range(pmax - 1):
            C[m, i] = c[i] if i < p - 1 else 0.0
        if st == OK:
            if p == 3 and not gauss:
                _post3c(c, L[g], nl, cos_term, tab, eb, es, wk_, out, R, m, fq, PQ)
            else:
                _post_any(p, c, F[m], KB[g], L[g], Z3[g], T[g], K[g], cos_term, A, Ad, GX, GW, grid,
                          gphi, wk, out, R[m], fast)
        else:
            for i in range(TIP, ERR):
                out[i] = np.nan
        # S is (NCOLS, N): every output column contiguous, ready to be handed out without a copy
        for i in range(NCOLS):
            S[i, m] = out[i]


def _solve_all(F, KB, L, Z3, T, K, cos_term, order, auto, pmax, tol, A, Ad, GX, GW, grid, gphi,
               C, S, R, chunks, fast, closed, estimate, mono4, step):
    N = F.shape[0]
    size = (N + chunks - 1) // chunks
    for b in prange(chunks):
        start = b * size
        stop = min(N, start + size)
        if start < stop:
            _solve_range(start, stop, F, KB, L, Z3, T, K, cos_term, order, auto, pmax, tol,
                         A, Ad, GX, GW, grid, gphi, C, S, R, fast, closed, estimate, mono4, step)


_solve_range = njit(cache=True)(_solve_range)
solve_serial = njit(cache=True)(_solve_all)
solve_parallel = njit(cache=True, parallel=True)(_solve_all)
