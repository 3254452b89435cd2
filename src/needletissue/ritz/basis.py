"""Trial functions and quadrature rules of the Ritz model.

The needle deflection on [0, l] is written in the reference coordinate s = z / l in [0, 1] as

    v(z) = sum_i c_i phi_i(s),   phi_i''(s) = sqrt(2 i + 1) P_i(2 s - 1),   phi_i(0) = phi_i'(0) = 0,

i = 0 .. p - 2 (integrated Legendre polynomials). Every phi_i satisfies the clamp conditions
v(0) = v'(0) = 0, the basis is hierarchical (order p + 1 adds one function), the bending energy is
EI / (2 l^3) * sum c_i^2 (diagonal, perfectly conditioned) and the coefficients c_i are in mm.
For p = 3 the span is exactly {z^2, z^3}, the paper's a2 z^2 + a3 z^3 (Eq. 13).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.polynomial import legendre as L

# Highest order a solve may use (the error estimate of order P_MAX needs P_MAX + 1).
P_MAX = 24


@lru_cache(maxsize=None)
def legendre_tables(pmax: int = P_MAX + 1):
    """Legendre-series coefficients (in x = 2 s - 1) of phi_i and dphi_i/ds, i = 0 .. pmax - 2.

    Returns (A, Ad), each of shape (pmax - 1, pmax + 1): phi_i(s) = sum_m A[i, m] P_m(x).
    """
    n = pmax - 1
    A = np.zeros((n, pmax + 1))
    Ad = np.zeros((n, pmax + 1))
    for i in range(n):
        c = np.zeros(i + 1)
        c[i] = np.sqrt(2 * i + 1) / 4.0  # d2/dx2 = (1/4) d2/ds2
        psi = L.legint(c, m=2, lbnd=-1)  # psi(-1) = psi'(-1) = 0
        A[i, : psi.size] = psi
        dpsi = 2.0 * L.legder(psi)  # d/ds = 2 d/dx
        Ad[i, : dpsi.size] = dpsi
    A.setflags(write=False)
    Ad.setflags(write=False)
    return A, Ad


def evaluate(s, order: int, derivative: int = 0) -> np.ndarray:
    """phi_i(s) (derivative 0) or dphi_i/ds (1) or d2phi_i/ds2 (2); shape (*s.shape, order - 1)."""
    A, Ad = legendre_tables()
    n = order - 1
    x = 2.0 * np.asarray(s, dtype=float) - 1.0
    if derivative == 0:
        return np.moveaxis(L.legval(x, A[:n].T, tensor=True), 0, -1)
    if derivative == 1:
        return np.moveaxis(L.legval(x, Ad[:n].T, tensor=True), 0, -1)
    if derivative == 2:
        eye = np.diag(np.sqrt(2.0 * np.arange(n) + 1.0))
        return np.moveaxis(L.legval(x, eye, tensor=True), 0, -1)
    raise ValueError("derivative must be 0, 1 or 2")


@lru_cache(maxsize=None)
def monomial_matrix(order: int) -> np.ndarray:
    """M of shape (order - 1, order + 1): phi_i(s) = sum_j M[i, j] s^j (so a_j = (c @ M)[j] / l^j)."""
    A, _ = legendre_tables()
    n = order - 1
    M = np.zeros((n, order + 1))
    for i in range(n):
        poly = L.Legendre(A[i, : i + 3], domain=[0.0, 1.0]).convert(kind=np.polynomial.Polynomial,
                                                                       domain=[0.0, 1.0], window=[0.0, 1.0])
        M[i, : poly.coef.size] = poly.coef
    M[:, :2] = 0.0  # exact clamp conditions (removes round-off of the conversion)
    M.setflags(write=False)
    return M


def quadrature_points(order: int, cos_term: bool) -> int:
    """Gauss points per layer that integrate the spring energy, gradient and Hessian exactly.

    With the cos term the integrand v^4 (1 + v'^2)^2 has degree 8p - 4, otherwise v^4 has degree 4p;
    n Gauss points are exact to degree 2n - 1.
    """
    return 4 * order - 1 if cos_term else 2 * order + 1


@lru_cache(maxsize=None)
def gauss_tables(nmax: int = 4 * (P_MAX + 1) - 1):
    """Gauss-Legendre nodes and weights on [-1, 1] for every n <= nmax, padded: rows X[n, :n], W[n, :n]."""
    X = np.zeros((nmax + 1, nmax))
    W = np.zeros((nmax + 1, nmax))
    for n in range(1, nmax + 1):
        X[n, :n], W[n, :n] = L.leggauss(n)
    X.setflags(write=False)
    W.setflags(write=False)
    return X, W


# Uniform grid in s on which the curve is sampled for the maximum and the error estimate.
GRID = np.linspace(0.0, 1.0, 65)
GRID.setflags(write=False)
