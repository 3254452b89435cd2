"""Drucker stability: theory for a known-unstable Ogden law, FElupe's stresses as an independent check."""

import warnings

import numpy as np
import pytest
from scipy.optimize import brentq

from needletissue import materials
from needletissue.materials import closed_form as cf
from needletissue.materials import curves, stability

V = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])

# Two-term Ogden, mu0 = 0.5 > 0, whose log-strain Hessian is diag(h(lambda_i)) with
# h(x) = sum 2 mu_p x^alpha_p = 2 x^2 - x^4: negative for x > sqrt(2). On the plane tr(de) = 0 the form
# sum h_i de_i^2 is positive definite iff h1 h2 + h2 h3 + h3 h1 > 0 and h1 + h2 + h3 > 0.
UNSTABLE = dict(mu=[1.0, -0.5], alpha=[2.0, 4.0])


def h(x):
    return 2 * x**2 - x**4


def test_known_unstable_ogden_biaxial_limit_is_sqrt2():
    # biaxial (l, l, l^-2): det = h(l) (h(l) + 2 h(l^-2)) changes sign at h(l) = 0, l = sqrt(2)
    lo, hi = stability.stable_range("ogden", UNSTABLE, "biaxial")
    assert hi == pytest.approx(np.sqrt(2), abs=1e-8)
    # compression: h(l) + 2 h(l^-2) = 0
    assert lo == pytest.approx(brentq(lambda x: h(x) + 2 * h(x**-2), 0.6, 0.95), abs=1e-8)


def test_known_unstable_ogden_uniaxial_and_planar_limits():
    lo, hi = stability.stable_range("ogden", UNSTABLE, "uniaxial")
    # tension: det = q (2 h(l) + q), q = h(l^-1/2) > 0  ->  h(l) = -q/2
    assert hi == pytest.approx(brentq(lambda x: h(x) + h(x**-0.5) / 2, 1.2, 2.0), abs=1e-8)
    # compression: q = 0 at l^-1/2 = sqrt(2)
    assert lo == pytest.approx(0.5, abs=1e-8)
    lo, hi = stability.stable_range("ogden", UNSTABLE, "planar")
    # (l, 1, 1/l): det = h(l) + h(1/l) + h(l) h(1/l) with h(1) = 1
    det = lambda x: h(x) + h(1 / x) + h(x) * h(1 / x)  # noqa: E731
    assert hi == pytest.approx(brentq(det, 1.2, 2.0), abs=1e-8)
    assert lo == pytest.approx(1 / hi, abs=1e-8)  # planar is symmetric under l -> 1/l


@pytest.mark.parametrize("model,p", [
    ("neo_hooke", dict(mu=0.3)), ("mooney_rivlin", dict(C10=0.2, C01=0.05)),
    ("ogden", dict(mu=[1.1667e-3], alpha=[16.2])), ("ogden", dict(mu=[0.4], alpha=[-3.0])),
])
def test_laws_with_positive_definite_hessian_are_stable_in_the_whole_window(model, p):
    # Neo-Hooke, MR with C10, C01 >= 0 and one-term Ogden with mu alpha > 0 are Drucker-stable everywhere
    for mode in cf.MODES:
        assert stability.stable_range(model, p, mode) == stability.STRETCH_WINDOW


def test_muscle_biaxial_compression_limit_is_the_uniaxial_tension_limit():
    m = materials.get("muscle")
    _, hi_u = stability.stable_range(m.model, m.parameters, "uniaxial")
    lo_b, _ = stability.stable_range(m.model, m.parameters, "biaxial")
    assert 1.0 < hi_u < 1.5  # the paper's MR5 (C01, C11 < 0) loses stability in moderate tension
    assert lo_b == pytest.approx(hi_u**-0.5, abs=1e-8)


def felupe_tangent(umat, e, h=1e-5):
    """2x2 incompressible tangent d(tau)/d(e) on the plane tr(de) = 0 from FElupe's stresses, by central differences."""
    def tau(ee):
        lam = np.exp(ee)
        F = np.diag(lam)[:, :, None, None]
        P = umat.gradient([F, None])[0][..., 0, 0]
        return np.diag(P) * lam  # principal Kirchhoff stresses (J = 1)
    cols = [(tau(e + h * V[:, b]) - tau(e - h * V[:, b])) / (2 * h) for b in range(2)]
    return V.T @ np.stack(cols, axis=1)


@pytest.mark.parametrize("mode", cf.MODES)
def test_muscle_hessian_matches_felupe_stress_increments(mode):
    m = materials.get("muscle")
    umat = m.isochoric()
    lam = np.array([0.6, 0.85, 1.1, 1.3, 1.45, 1.8, 2.6])
    L = cf.principal_stretches(mode, lam)
    H = cf.log_hessian(m.model, m.parameters, L)
    margins = stability.drucker_margin(m.model, m.parameters, L)
    for n in range(lam.size):
        M_fe = felupe_tangent(umat, np.log(L[:, n]))
        M = V.T @ H[:, :, n] @ V
        np.testing.assert_allclose(M_fe, M, rtol=1e-6, atol=1e-8 * np.abs(M).max())
        ev_fe = np.linalg.eigvalsh(0.5 * (M_fe + M_fe.T))[0]
        assert ev_fe == pytest.approx(margins[n], rel=1e-5, abs=1e-9)
    # the sample covers both stable and unstable states of the paper's MR5 in every load case
    assert (margins > 0).any() and (margins < 0).any()


@pytest.mark.parametrize("mode,bracket", [("uniaxial", (1.1, 1.5)), ("planar", (1.1, 1.6))])
def test_muscle_stable_end_is_where_felupe_tangent_loses_definiteness(mode, bracket):
    """The paper's MR5 stable end (1.2663 uniaxial, as README and docs state) is the root of the smallest
    eigenvalue of FElupe's own incompressible tangent, found independently of our Hessian by brentq."""
    m = materials.get("muscle")
    umat = m.isochoric()
    ev = lambda s: np.linalg.eigvalsh(felupe_tangent(umat, np.log(cf.principal_stretches(mode, s)[:, 0])))[0]  # noqa: E731
    root = brentq(ev, *bracket, xtol=1e-10)
    assert stability.stable_range(m.model, m.parameters, mode)[1] == pytest.approx(root, abs=1e-6)
    if mode == "uniaxial":
        assert root == pytest.approx(1.2663, abs=5e-5)


def test_drucker_implies_rising_cauchy_stress_along_the_path():
    """Uniaxial path: de = (1, -1/2, -1/2) de1, d(tau) = (d sigma, 0, 0), so Drucker gives d sigma / d e1 > 0."""
    m = materials.get("muscle")
    lo, hi = stability.stable_range(m.model, m.parameters, "uniaxial")
    lam = np.linspace(0.3, hi, 200)
    sigma = lam * cf.nominal_stress(m.model, m.parameters, "uniaxial", lam)
    assert np.all(np.diff(sigma) > 0)


def test_curve_warns_only_outside_the_stable_range():
    _, hi = stability.stable_range("mooney_rivlin_5", materials.get("muscle").parameters, "uniaxial")
    with warnings.catch_warnings():
        warnings.simplefilter("error", stability.UnstableMaterialWarning)
        c = curves.curve("muscle", "uniaxial", stretch_max=0.98 * hi, points=11)
    assert c.warning is None
    with pytest.warns(stability.UnstableMaterialWarning, match=rf"muscle .* uniaxial .*\[0\.2, {hi:.4g}\]"):
        c = curves.curve("muscle", "uniaxial", stretch_max=1.5, points=51)
    assert c.stable_range[1] == pytest.approx(hi)


def test_fe_states_check_isochoric_part():
    # a volumetric scaling does not change the isochoric stability verdict
    m = materials.get("muscle")
    L = cf.principal_stretches("uniaxial", [1.1, 1.4])
    np.testing.assert_allclose(stability.drucker_margin(m.model, m.parameters, 1.01 * L),
                               stability.drucker_margin(m.model, m.parameters, L), rtol=1e-12)


def test_stable_at_deformation_gradients_is_rotation_invariant():
    m = materials.get("muscle")
    lam = np.array([1.1, 1.35])  # stable, unstable in uniaxial tension (limit 1.266)
    L = cf.principal_stretches("uniaxial", lam)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    F = np.stack([R @ np.diag(L[:, n]) for n in range(2)], axis=-1)  # (3, 3, 2)
    np.testing.assert_array_equal(stability.stable_at("muscle", F), [True, False])
    np.testing.assert_array_equal(stability.stable_at("needle", F), [True, True])
    assert m.model == "mooney_rivlin_5"
