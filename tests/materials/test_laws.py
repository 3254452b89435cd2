"""The hand-coded isochoric laws (materials.laws) against tensortrax's automatic differentiation."""

import felupe as fem
import numpy as np
import pytest
import tensortrax.math as tm

from needletissue import materials
from needletissue.errors import InputError
from needletissue.materials.laws import InvariantPolynomial, Ogden

from law_cases import LAWS


def _random_F():
    """(3, 3, 4, 60): moderate random F, large stretches (0.3-3), near-singular-ish (det F ~ 0.003-0.06),
    large rotations, det F < 0. Eigenvalues of C distinct (AD's eigenvalue derivatives need that)."""
    rng = np.random.default_rng(18)
    F = np.eye(3)[:, :, None, None] + 0.3 * rng.standard_normal((3, 3, 4, 60))
    F[..., :10] = np.einsum("ij...,jk...->ik...", np.linalg.qr(rng.standard_normal((4, 10, 3, 3)))[0].transpose(2, 3, 0, 1),
                            np.eye(3)[:, :, None, None] * rng.uniform(0.3, 3.0, (3, 1, 4, 10)))
    F[..., 10:20] = np.eye(3)[:, :, None, None] * rng.uniform(0.15, 0.4, (3, 1, 4, 10))  # det 0.003-0.06
    F[..., 10:20] += 0.05 * rng.standard_normal((3, 3, 4, 10))
    F[0, :, :, 20:25] *= -1  # mirrored: det F < 0, where the energies stay defined (docs/fem.md)
    return F


def _exact_ogden(C, mu, alpha):
    """FElupe's ogden with tensortrax's eigenvalue perturbation off (exact for distinct eigenvalues)."""
    wC = tm.linalg.det(C) ** (-1 / 3) * tm.linalg.eigvalsh(C, eps=0)
    return sum(2 * m / a**2 * (tm.sum(wC ** (a / 2)) - 3) for m, a in zip(mu, alpha))


def _relative(a, ref):
    """max |a - ref| over each point's components / max |ref| of that point."""
    axes = tuple(range(ref.ndim - 2))
    return float(np.max(np.abs(a - ref).max(axis=axes) / np.abs(ref).max(axis=axes)))


@pytest.mark.parametrize("law", list(LAWS))
def test_closed_form_equals_automatic_differentiation(law):
    model, p = LAWS[law]
    mat = materials.Material("t", model, dict(p))
    fast = mat.isochoric()
    assert isinstance(fast, Ogden if model == "ogden" else InvariantPolynomial)
    ref = fem.Hyperelastic(_exact_ogden, **fast.kwargs) if model == "ogden" else mat.isochoric(ad=True)
    F = _random_F()
    assert np.sum(np.linalg.det(np.moveaxis(F, (0, 1), (-2, -1))) < 0) >= 20
    x = [F, np.zeros((0, *F.shape[2:]))]
    assert _relative(fast.gradient(x)[0], ref.gradient(x)[0]) < 1e-10
    assert _relative(fast.hessian(x)[0], ref.hessian(x)[0]) < 1e-10
    if model == "ogden":  # FElupe's own ogden, perturbed by sqrt(eps) |C|: its accuracy, not ours
        ad = mat.isochoric(ad=True)
        assert 1e-12 < _relative(fast.gradient(x)[0], ad.gradient(x)[0]) < 1e-5


@pytest.mark.parametrize("law", list(LAWS))
def test_small_strain_tangent_is_isochoric_linear_elasticity(law):
    """At F = I (all eigenvalues equal: Ogden's divided differences at their limit), A_iJkL =
    mu0 (d_ik d_JL + d_iL d_kJ - 2/3 d_iJ d_kL), and the stress is zero."""
    model, p = LAWS[law]
    mat = materials.Material("t", model, dict(p))
    F = np.eye(3)[:, :, None, None] * np.ones((1, 1, 2, 3))
    x = [F, np.zeros((0, 2, 3))]
    d = np.eye(3)
    A0 = mat.initial_shear_modulus * (np.einsum("ik,JL->iJkL", d, d) + np.einsum("iL,kJ->iJkL", d, d)
                                      - 2 / 3 * np.einsum("iJ,kL->iJkL", d, d))
    umat = mat.isochoric()
    np.testing.assert_allclose(umat.gradient(x)[0], 0, atol=1e-15 * mat.initial_shear_modulus)
    np.testing.assert_allclose(umat.hessian(x)[0], A0[..., None, None] * np.ones((2, 3)), rtol=0,
                               atol=1e-12 * mat.initial_shear_modulus)


@pytest.mark.parametrize("law", ["adipose", "ogden3"])
def test_ogden_tangent_with_repeated_eigenvalues_is_the_stress_derivative(law):
    """Uniaxial stretch, rotated (two equal eigenvalues), and nearly equal ones (1e-9 apart): the
    hessian equals central differences of the hand-coded stress (h = 1e-6: error O(h^2))."""
    model, p = LAWS[law]
    umat = materials.Material("t", model, dict(p)).isochoric()
    Q = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))[0]
    Fs = [Q @ np.diag([1.4, 1.4**-0.5, 1.4**-0.5]) @ Q.T, Q @ np.diag([0.8, 1.1, 1.1 * (1 + 1e-9)]) @ Q.T]
    for F0 in Fs:
        F0 = F0[:, :, None, None]
        A = umat.hessian([F0, None])[0][..., 0, 0]
        h = 1e-6
        dP = np.zeros((3, 3, 3, 3))
        for k in range(3):
            for L in range(3):
                E = np.zeros((3, 3, 1, 1))
                E[k, L] = h
                dP[:, :, k, L] = (umat.gradient([F0 + E, None])[0] - umat.gradient([F0 - E, None])[0])[..., 0, 0] / (2 * h)
        np.testing.assert_allclose(A, dP, rtol=0, atol=1e-6 * np.abs(A).max())


def test_invariant_polynomial_rejects_higher_powers():
    with pytest.raises(InputError, match="coefficients: powers"):
        InvariantPolynomial({(2, 2): 1.0})


@pytest.mark.parametrize("mode", ["uniaxial", "biaxial", "planar"])
@pytest.mark.parametrize("law", ["adipose", "ogden3"])
def test_ogden_matches_incompressible_closed_form(law, mode):
    """Exact eigenvalues: the hand-coded Ogden equals the closed-form nominal stress to 1e-10, where
    FElupe's AD Ogden is 1e-7 off (tests/materials/test_closed_form.py)."""
    from needletissue.materials import closed_form as cf

    model, p = LAWS[law]
    stretch = np.concatenate([np.linspace(0.6, 0.98, 12), np.linspace(1.02, 2.0, 25)])
    view = fem.ViewMaterialIncompressible(materials.Material("t", model, dict(p)).isochoric())
    _, P, _ = getattr(view, mode)(stretch)
    np.testing.assert_allclose(P, cf.nominal_stress(model, p, mode, stretch), rtol=1e-10, atol=0)


@pytest.mark.parametrize("chunk", [7, 16384])
def test_jacobi_eigen_decomposition_equals_lapack_on_degenerate_and_large_stretches(monkeypatch, chunk):
    """laws.eigh3 (cyclic Jacobi on blocks of matrices, Ogden's spectral decomposition) against LAPACK's eigh:
    the same eigenvalues and the same spectral projections (eigenvectors of repeated eigenvalues are arbitrary,
    the stress sum_a w_a N_a (x) N_a is not), at F = I, two nearly equal stretches, 5 % and 200 % strain."""
    from needletissue.materials import laws

    monkeypatch.setattr(laws, "EIGH_CHUNK", chunk)
    rng = np.random.default_rng(4)
    F = np.concatenate([np.broadcast_to(np.eye(3), (5, 3, 3)),
                        np.diag([1.1, 1.0, 1.0]) + 1e-9 * rng.normal(size=(20, 3, 3)),
                        np.eye(3) + 0.05 * rng.normal(size=(40, 3, 3)),
                        np.diag([3.0, 0.5, 0.6]) @ (np.eye(3) + 0.3 * rng.normal(size=(40, 3, 3)))])
    C = F.transpose(0, 2, 1) @ F
    lam, N = laws.eigh3(C)
    ref_lam, ref_N = np.linalg.eigh(C)
    scale = ref_lam.max(1)
    assert np.all(np.abs(np.sort(lam, 1) - ref_lam).max(1) <= 1e-14 * scale)
    np.testing.assert_allclose(N.transpose(0, 2, 1) @ N, np.broadcast_to(np.eye(3), C.shape), rtol=0, atol=1e-14)

    def power(lam, N, q=7.1):  # C^q, Ogden's dW/dC for alpha = 16.2
        return np.matmul(N * lam[:, None, :] ** q, N.transpose(0, 2, 1))

    ref = power(ref_lam, ref_N)
    assert np.all(np.abs(power(lam, N) - ref).max((1, 2)) <= 1e-13 * np.abs(ref).max((1, 2)))
