"""Strain-energy functions FElupe lacks, and hand-coded isochoric tissue laws.

`mooney_rivlin_5` is in FElupe's form W(C, **parameters) on tensortrax tensors (automatic
differentiation: the reference, and the fallback for laws without a hand-coded class).

`InvariantPolynomial` and `Ogden` are the same isochoric laws with closed-form stress and elasticity,
FElupe materials (`gradient` -> [P, statevars], `hessian` -> [A], A_iJkL = d2W/dF_iJ dF_kL, trailing axes
(q, c), evaluated in FElupe's chunks of cells). tensortrax costs 5-50 ms a call on the needle model's
tissue bodies, these 3-16 ms (docs/bench.md, "Tissue laws without tensortrax"). Derivation: S = 2 dW/dC
and C4 = 4 d2W/dCdC of W(det(C)^(-1/3) C), pushed forward, A_iJkL = F_iI F_kK C4_IJKL + delta_ik S_JL, with
F (X (x) Y) F -> (F X) (x) (F Y), F (Ci (.) Ci) F -> (delta_ik Ci_JL + G_iL G_kJ) / 2 and
F I4s F -> (B_ik delta_JL + F_iL F_kJ) / 2 (G = F^-T, B = F F^T, (.) the symmetrised product).
"""

from __future__ import annotations

import numpy as np
from felupe import ConstitutiveMaterial
from tensortrax.math import trace
from tensortrax.math.linalg import det

from needletissue.errors import InputError


def mooney_rivlin_5(C, C10, C01, C20, C11, C02):
    """Isochoric 5-parameter Mooney-Rivlin (as in ANSYS), on the distortional invariants of C.

    W = C10 (I1-3) + C01 (I2-3) + C20 (I1-3)^2 + C11 (I1-3)(I2-3) + C02 (I2-3)^2.
    Initial shear modulus mu0 = 2 (C10 + C01).
    """
    J3 = det(C) ** (-1 / 3)
    I1 = J3 * trace(C)
    I2 = (I1**2 - J3**2 * trace(C @ C)) / 2
    a, b = I1 - 3, I2 - 3
    return C10 * a + C01 * b + C20 * a**2 + C11 * a * b + C02 * b**2


def _points(F):
    """(3, 3, *trailing) -> (n, 3, 3): NumPy's batched matmul on small matrices is 10-30x faster than
    einsum over trailing axes."""
    return np.ascontiguousarray(np.moveaxis(F.reshape(3, 3, -1), -1, 0))


def _back(X, trailing):
    """(n, *s) -> (*s, *trailing), contiguous."""
    return np.ascontiguousarray(np.moveaxis(X, 0, -1)).reshape(*X.shape[1:], *trailing)


def _kinematics(F):
    """C, J, G = F^-T, Ci = C^-1 of F (n, 3, 3)."""
    C = np.matmul(F.transpose(0, 2, 1), F)
    cof = np.empty_like(F)  # J F^-T
    for i in range(3):
        i1, i2 = (i + 1) % 3, (i + 2) % 3
        for j in range(3):
            j1, j2 = (j + 1) % 3, (j + 2) % 3
            cof[:, i, j] = F[:, i1, j1] * F[:, i2, j2] - F[:, i1, j2] * F[:, i2, j1]
    J = np.einsum("nij,nij->n", F, cof) / 3
    G = cof / J[:, None, None]
    return C, J, G, np.matmul(G.transpose(0, 2, 1), G)


def _push(F, G, Ci, V, T, S, ci, i4):
    """A_iJkL = sum_m V_m (x) T_m + delta_ik (S + ci Ci)_JL + ci G_iL G_kJ + i4 (B_ik delta_JL + F_iL F_kJ)
    (n points; V, T (n, m, 3, 3); ci, i4 (n,): halved already) as (n, 3, 3, 3, 3)."""
    n, m = V.shape[:2]
    A = np.matmul(V.reshape(n, m, 9).transpose(0, 2, 1), T.reshape(n, m, 9)).reshape(n, 3, 3, 3, 3)
    X = [G] if i4 is None else [G, F]  # the swapped products X_iL X_kJ: an outer product in [iL, kJ]
    c = [ci] if i4 is None else [ci, i4]
    W = np.matmul(np.stack([k[:, None, None] * x for k, x in zip(c, X)], axis=-1).reshape(n, 9, -1),
                  np.stack(X, axis=1).reshape(n, -1, 9))
    A += W.reshape(n, 3, 3, 3, 3).transpose(0, 1, 4, 3, 2)
    Y = S + ci[:, None, None] * Ci
    for i in range(3):
        A[:, i, :, i, :] += Y
    if i4 is not None:
        B = i4[:, None, None] * np.matmul(F, F.transpose(0, 2, 1))
        for J in range(3):
            A[:, :, J, :, J] += B
    return A


class InvariantPolynomial(ConstitutiveMaterial):
    """Isochoric W = sum c_mn (I1b - 3)^m (I2b - 3)^n, m + n <= 3: Neo-Hooke (c10 = mu/2), Mooney-Rivlin,
    its 5-parameter form, Yeoh. `coefficients` {(m, n): c} in MPa."""

    def __init__(self, coefficients: dict, parallel: bool = False):
        self.coefficients = {(int(m), int(n)): float(c) for (m, n), c in coefficients.items() if c != 0}
        if any(m < 0 or n < 0 or m + n > 3 for m, n in self.coefficients):
            raise InputError("coefficients", f"powers (m, n) with m + n <= 3, got {sorted(self.coefficients)}")
        self.kwargs = {f"C{m}{n}": c for (m, n), c in self.coefficients.items()}
        self.parallel = parallel
        self.x = [np.eye(3), np.zeros(0)]

    def _derivatives(self, a, b, order):
        """W_a, W_b (and W_aa, W_ab, W_bb) of the polynomial at (a, b)."""
        d = [np.zeros_like(a) for _ in range(2 if order == 1 else 5)]
        for (m, n), c in self.coefficients.items():
            if m:
                d[0] += c * m * a ** (m - 1) * b**n
            if n:
                d[1] += c * n * a**m * b ** (n - 1)
            if order == 2:
                if m > 1:
                    d[2] += c * m * (m - 1) * a ** (m - 2) * b**n
                if m and n:
                    d[3] += c * m * n * a ** (m - 1) * b ** (n - 1)
                if n > 1:
                    d[4] += c * n * (n - 1) * a**m * b ** (n - 2)
        return d

    def _state(self, F, order):
        C, J, G, Ci = _kinematics(F)
        I1 = np.einsum("nii->n", C)
        I2 = (I1**2 - np.einsum("nij,nij->n", C, C)) / 2
        j = np.abs(J) ** (-2 / 3)  # det(C)^(-1/3) as in the AD laws: defined for det F < 0 too (docs/fem.md)
        d = self._derivatives(j * I1 - 3, j**2 * I2 - 3, order)
        T = np.stack([F, np.matmul(F, C), G], axis=1)  # two-point basis: F U1 = F - I1/3 G,
        z, one = np.zeros_like(I1), np.ones_like(I1)  # F U2 = I1 F - F C - 2/3 I2 G
        u1 = np.stack([one, z, -I1 / 3], axis=1)
        u2 = np.stack([I1, -one, -2 / 3 * I2], axis=1)
        s = 2 * (d[0] * j)[:, None] * u1 + 2 * (d[1] * j**2)[:, None] * u2  # S = 2 dW/dC: P = F S = s . T
        return C, G, Ci, I1, I2, j, d, T, u1, u2, s

    def _gradient(self, x):
        F, statevars = x[0], x[-1]
        Fp = _points(F)
        *_, T, _, _, s = self._state(Fp, 1)
        return [_back(np.matmul(s[:, None], T.reshape(len(s), 3, 9)).reshape(-1, 3, 3), F.shape[2:]), statevars]

    def _hessian(self, x):
        F = x[0]
        Fp = _points(F)
        C, G, Ci, I1, I2, j, (Wa, Wb, Waa, Wab, Wbb), T, u1, u2, s = self._state(Fp, 2)
        eye = np.eye(3)
        S = (2 * Wa * j)[:, None, None] * (eye - (I1 / 3)[:, None, None] * Ci) + (2 * Wb * j**2)[:, None, None] * (
            I1[:, None, None] * eye - C - (2 / 3 * I2)[:, None, None] * Ci)

        n = len(I1)
        H = np.empty((n, 2, 2))  # W's second derivatives in (u1, u2), then the sparse terms
        H[:, 0, 0], H[:, 1, 1] = Waa * j**2, Wbb * j**4
        H[:, 0, 1] = H[:, 1, 0] = Wab * j**3
        U = np.stack([u1, u2], axis=1)
        M = np.matmul(U.transpose(0, 2, 1), np.matmul(H, U))
        a, b = Wa * j, Wb * j**2
        M[:, 0, 0] += b
        M[:, 0, 2] -= a / 3 + 2 / 3 * b * I1  # -(e1 e3 + e3 e1) a/3 - 2/3 b (v2 e3 + e3 v2), v2 = F (I1 I - C)
        M[:, 1, 2] += 2 / 3 * b
        M[:, 2, 0], M[:, 2, 1] = M[:, 0, 2], M[:, 1, 2]
        M[:, 2, 2] += a * I1 / 9 + 4 / 9 * b * I2
        V = 4 * np.matmul(M, T.reshape(n, 3, 9)).reshape(n, 3, 3, 3)  # M is symmetric
        ci = 2 * (Wa * j * I1 / 3 + Wb * j**2 * 2 / 3 * I2)
        return [_back(_push(Fp, G, Ci, V, T, S, ci, -2 * Wb * j**2), F.shape[2:])]


EIGH_CHUNK = 16384  # matrices per Jacobi block: its ~40 work arrays stay in cache (4096: 1.4x slower, 900 k at once: 1.8x)


def eigh3(C):
    """Eigenvalues (n, 3), unsorted, and orthonormal eigenvectors N[:, I, a] of symmetric C (n, 3, 3) by cyclic
    Jacobi rotations on all matrices at once, in blocks that stay in cache. NumPy's eigh calls LAPACK once per
    3x3 matrix: 1.2-1.3 s for 900 k of them (the paper-scale adipose, at every residual), this 0.37-0.45 s, to
    the same 1e-15 (quadratic convergence, 4 sweeps at 5 % strain; tests/materials/test_laws.py)."""
    n = C.shape[0]
    lam, N = np.empty((n, 3)), np.empty((n, 3, 3))
    for i in range(0, n, EIGH_CHUNK):
        lam[i:i + EIGH_CHUNK], N[i:i + EIGH_CHUNK] = _jacobi3(C[i:i + EIGH_CHUNK])
    return lam, N


def _jacobi3(C, sweeps: int = 10):
    n = C.shape[0]
    A = np.moveaxis(C, 0, -1).copy()  # a[i][j]: (n,) rows of a (3, 3, n) array, both triangles kept
    a = [[A[i, j] for j in range(3)] for i in range(3)]
    V = np.zeros((3, 3, n))
    V[0, 0] = V[1, 1] = V[2, 2] = 1.0
    v = [[V[i, j] for j in range(3)] for i in range(3)]
    tiny = np.finfo(float).eps ** 2 * (a[0][0] ** 2 + a[1][1] ** 2 + a[2][2] ** 2)
    t, c, s, w, u = (np.empty(n) for _ in range(5))
    for _ in range(sweeps):
        if np.all(a[0][1] ** 2 + a[0][2] ** 2 + a[1][2] ** 2 <= tiny):
            break
        for p, q, r in ((0, 1, 2), (0, 2, 1), (1, 2, 0)):
            apq = a[p][q]  # the rotation zeroing a_pq: t = tan, c = cos, s = sin (Golub & Van Loan 8.5.2)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                theta = (a[q][q] - a[p][p]) / (2 * apq)
                np.hypot(theta, 1.0, out=w)
                np.abs(theta, out=t)
                t += w
                np.divide(np.copysign(1.0, theta), t, out=t)
            t[apq == 0] = 0.0
            np.divide(1.0, np.sqrt(t * t + 1), out=c)
            np.multiply(t, c, out=s)
            np.multiply(t, apq, out=w)
            a[p][p] -= w
            a[q][q] += w
            apq[:] = a[q][p][:] = 0.0
            for x in (a[r], *v):  # row r of a (column r follows by symmetry), every row of V
                xp, xq = x[p], x[q]
                np.multiply(c, xp, out=u)
                u -= s * xq
                xq *= c
                xq += s * xp
                xp[:] = u
            a[p][r][:], a[q][r][:] = a[r][p], a[r][q]
    else:  # not converged in `sweeps` (NaN input): LAPACK decides
        return np.linalg.eigh(C)
    return np.stack([a[0][0], a[1][1], a[2][2]], axis=1), np.moveaxis(V, -1, 0)


def _divided_difference(lam, q):
    """(la^q - lb^q) / (la - lb) for the pairs of eigenvalues lam (n, 3) -> (n, 3, 3), q la^(q-1) where
    equal: lb^(q-1) expm1(q t) / expm1(t), t = ln(la / lb), accurate for nearly equal ones too."""
    la, lb = lam[:, :, None], lam[:, None, :]
    t = np.log(la) - np.log(lb)
    same = t == 0
    t1 = np.where(same, 1.0, t)
    return lb ** (q - 1) * np.where(same, q, np.expm1(q * t1) / np.expm1(t1))


class Ogden(ConstitutiveMaterial):
    """Isochoric Ogden W = sum 2 mu_k / alpha_k^2 (sum_a lambda_a-bar^alpha_k - 3) (FElupe's `ogden`), on the
    eigenvalues of C exactly: FElupe's AD version perturbs them by sqrt(eps) |C| (tensortrax), which
    differs from this by ~1e-7 relative."""

    def __init__(self, mu, alpha, parallel: bool = False):
        self.mu, self.alpha = np.atleast_1d(mu).astype(float), np.atleast_1d(alpha).astype(float)
        if self.mu.shape != self.alpha.shape or np.any(self.alpha == 0):
            raise InputError("alpha", "as many terms as mu, every alpha non-zero")
        self.kwargs = {"mu": list(self.mu), "alpha": list(self.alpha)}
        self.parallel = parallel
        self.x = [np.eye(3), np.zeros(0)]

    def _state(self, F, hessian):
        C, J, G, Ci = _kinematics(F)
        lam, N = eigh3(C)  # (n, 3), N[:, I, a]
        f = np.matmul(F, N)  # f[:, :, a] = F N_a
        j = np.abs(J) ** (-2 / 3)  # det(C)^(-1/3) as in the AD laws: defined for det F < 0 too (docs/fem.md)
        w, g, Y, gg, ci, gamma = 0, 0, 0, 0, 0, 0
        for mu, alpha in zip(self.mu, self.alpha):
            p = alpha / 2
            c = 2 * mu / alpha**2 * p * j**p  # dW/dC = c (C^(p-1) - T/3 Ci), T = tr C^p
            lq, T = lam ** (p - 1), np.sum(lam**p, axis=1)
            w = w + 2 * c[:, None] * lq  # S = N diag(w) N^T + g Ci
            g = g - 2 * c * T / 3
            if hessian:  # C4 = 4 c (DK - p/3 (C^(p-1) (x) Ci + Ci (x) C^(p-1)) + p T/9 Ci (x) Ci + T/3 Ci (.) Ci)
                Y = Y - 4 / 3 * (c * p)[:, None] * lq
                gg = gg + 4 / 9 * c * p * T
                ci = ci + 2 / 3 * c * T
                gamma = gamma + 4 * c[:, None, None] * _divided_difference(lam, p - 1)  # DK = d C^(p-1) / dC
        return G, Ci, N, f, w, g, Y, gg, ci, gamma

    def _gradient(self, x):
        F, statevars = x[0], x[-1]
        G, Ci, N, f, w, g, *_ = self._state(_points(F), False)
        P = np.matmul(f * w[:, None], N.transpose(0, 2, 1)) + g[:, None, None] * G
        return [_back(P, F.shape[2:]), statevars]

    def _hessian(self, x):
        F = x[0]
        Fp = _points(F)
        G, Ci, N, f, w, g, Y, gg, ci, gamma = self._state(Fp, True)
        Nt = N.transpose(0, 2, 1)
        S = np.matmul(N * w[:, None], Nt) + g[:, None, None] * Ci
        Xp = np.matmul(f * Y[:, None], Nt) + (gg / 2)[:, None, None] * G  # Xp (x) G + G (x) Xp
        A = _push(Fp, G, Ci, np.stack([Xp, G], axis=1), np.stack([G, Xp], axis=1), S, ci, None)
        n = len(g)
        # Daleckii-Krein, pushed forward: sum_ab gamma_ab / 2 Q_ab (x) (Q_ab + Q_ba), Q_ab = F N_a (x) N_b
        Q = (f.transpose(0, 2, 1)[:, :, None, :, None] * Nt[:, None, :, None, :])  # [n, a, b, i, J]
        Qs = (Q + Q.transpose(0, 2, 1, 3, 4)).reshape(n, 9, 9)
        Q = Q.reshape(n, 9, 9) * (gamma / 2).reshape(n, 9, 1)
        A += np.matmul(Q.transpose(0, 2, 1), Qs).reshape(n, 3, 3, 3, 3)
        return [_back(A, F.shape[2:])]
