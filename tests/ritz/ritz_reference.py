"""Independent reference computations for the Ritz tests (no code shared with needletissue.ritz)."""

from __future__ import annotations

import numpy as np
from numpy.polynomial import Polynomial
from scipy.integrate import solve_bvp
from scipy.optimize import root


def cubic_minimiser(F, d, l, E, layers, z3=None, cos=True):
    """Exact stationary point of the paper's cubic trial energy, v = a2 z^2 + a3 z^3.

    Energy integrals by exact polynomial antiderivatives (numpy Polynomial), gradient by complex-step
    differentiation (exact to round-off), stationarity solved by MINPACK (scipy.optimize.root).
    Returns (a2, a3).
    """
    z3 = l if z3 is None else z3
    EI = E * np.pi * d**4 / 64.0

    def energy(b):  # b = (a2 l^2, a3 l^3) in mm: well scaled unknowns
        v = Polynomial([0, 0, b[0] / l**2, b[1] / l**3])
        dv, d2v = v.deriv(), v.deriv(2)
        ub = (d2v * d2v).integ()
        total = 0.5 * EI * (ub(l) - ub(0))
        za = 0.0
        for t, k in layers:
            y = v * v * (1 + dv * dv) if cos else v * v
            e = (0.5 * k * y + 0.25 * k * y * y).integ()
            total = total + e(za + t) - e(za)
            za += t
        return total - F * v(z3)

    def grad(b):
        h = 1e-30
        return np.array([(energy(b + 1j * h * np.eye(2)[j])).imag / h for j in range(2)])

    b0 = np.array([F * l**3 * 3 / (6 * EI), -F * l**3 / (6 * EI)])  # bare cantilever
    sol = root(grad, b0, method="hybr", options={"xtol": 1e-14})
    # MINPACK may stop with "not making good progress" at round-off; judge by the residual instead:
    # |grad| < 1e-9 N with stiffness ~ EI / l^3 > 1 N/mm is a deflection error far below 1e-6 mm.
    assert np.max(abs(grad(sol.x))) < 1e-9 * max(1.0, abs(F)), sol.message
    return sol.x[0] / l**2, sol.x[1] / l**3


def euler_lagrange_bvp(F, d, l, E, layers, z3=None, cos=True, tol=1e-8):
    """Solve the Euler-Lagrange equations of the full (not Ritz) energy with scipy's solve_bvp.

    State (v, theta, M, V): v' = theta, theta' = M / EI, M' = V + e_p, V' = -e_v, e(v, theta) the
    spring energy density; one unit-interval segment per layer / free span so that the jumps of k and
    the point load (V jumps by +F at z3) are exact interface conditions. Returns v(z) callable.
    """
    z3 = l if z3 is None else z3
    EI = E * np.pi * d**4 / 64.0
    cuts = [0.0]
    ks = []
    for t, k in layers:
        cuts.append(cuts[-1] + t)
        ks.append(k)
    if cuts[-1] < l:
        cuts.append(l)
        ks.append(0.0)
    cuts = np.array(cuts)
    if not np.isclose(cuts, z3).any():
        j = np.searchsorted(cuts, z3)
        cuts = np.insert(cuts, j, z3)
        ks.insert(j - 1, ks[j - 1])
    m = len(ks)
    h = np.diff(cuts)
    iload = int(np.argmin(abs(cuts - z3)))  # load acts at cuts[iload]

    def rhs(tau, Y):
        out = np.empty_like(Y)
        for s in range(m):
            v, th, M, V = Y[4 * s: 4 * s + 4]
            k = ks[s]
            if cos:
                y = v * v * (1 + th * th)
                ev = k * (1 + y) * v * (1 + th * th)
                ep = k * (1 + y) * v * v * th
            else:
                ev = k * (1 + v * v) * v
                ep = 0.0 * v
            out[4 * s: 4 * s + 4] = h[s] * np.array([th, M / EI, V + ep, -ev])
        return out

    def bc(Ya, Yb):
        r = [Ya[0], Ya[1]]
        for s in range(m - 1):
            jump = F if s + 1 == iload else 0.0
            r += [Yb[4 * s + 0] - Ya[4 * s + 4], Yb[4 * s + 1] - Ya[4 * s + 5],
                  Yb[4 * s + 2] - Ya[4 * s + 6], Ya[4 * s + 7] - Yb[4 * s + 3] - jump]
        end = -F if iload == m else 0.0
        r += [Yb[4 * m - 2], Yb[4 * m - 1] - end]
        return np.array(r)

    tau = np.linspace(0, 1, 41)
    Y0 = np.zeros((4 * m, tau.size))
    for s in range(m):  # bare cantilever under F at z3 as initial guess
        z = cuts[s] + h[s] * tau
        Y0[4 * s] = F * np.where(z < z3, z**2 * (3 * z3 - z), z3**2 * (3 * z - z3)) / (6 * EI)
        Y0[4 * s + 1] = F * np.where(z < z3, z * (2 * z3 - z), z3**2) / (2 * EI)
        Y0[4 * s + 2] = F * np.maximum(z3 - z, 0.0)
        Y0[4 * s + 3] = np.where(z < z3, -F, 0.0)
    sol = solve_bvp(rhs, bc, tau, Y0, tol=tol, max_nodes=20_000)
    assert sol.success, sol.message

    def v(z):
        z = np.atleast_1d(np.asarray(z, float))
        out = np.empty_like(z)
        for i, zi in enumerate(z):
            s = min(int(np.searchsorted(cuts, zi, side="right")) - 1, m - 1)
            out[i] = sol.sol((zi - cuts[s]) / h[s])[4 * s]
        return out

    return v


PAPER_LAYERS = [(22.0, 0.048), (10.0, 0.023)]
