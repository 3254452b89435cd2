"""The plate bone law (bone_law="plate", docs/frame.md): its closed forms against independent computations
(energy integrals of the plate solutions, the exact plate-on-foundation solution in Kelvin functions), its
limits, and that the kernel applies the cortex's rocking spring as stated."""

import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import kv

from needletissue import frame
from needletissue.frame import FrameModel
from needletissue.frame.model import (
    PLATE_AXIAL_RADIUS, PLATE_ROCKING_RADIUS, confined_radius, lateral_foundation_k, plate_axial_k,
    plate_equivalent_radius, plate_rigidity, plate_rocking_k, subgrade_modulus,
)


@pytest.fixture(autouse=True)
def _quiet_quadrature(recwarn):
    """scipy.integrate warns about round-off at epsrel 1e-12; the closed forms are checked to 1e-7 anyway."""
    yield


def _energy(f, f1, f2, a, b, D, nu, order, k=0.0):
    """2U of w = f(r) cos(order theta) on a <= r <= b (plate bending, Kirchhoff, plus a Winkler foundation k)."""
    ang = math.pi if order == 1 else 2 * math.pi

    def dens(r):
        if order == 1:
            lap = f2(r) + f1(r) / r - f(r) / r**2
            gauss = f2(r) * (f1(r) / r - f(r) / r**2) - (f1(r) / r - f(r) / r**2) ** 2
        else:
            lap = f2(r) + f1(r) / r
            gauss = f2(r) * f1(r) / r
        return (D / 2 * (lap**2 - 2 * (1 - nu) * gauss) + k / 2 * f(r) ** 2) * ang * r

    pts = np.geomspace(a, b, 30)
    return 2 * sum(quad(dens, p, q, epsrel=1e-12, limit=200)[0] for p, q in zip(pts[:-1], pts[1:]))


def _annulus(order, a, b):
    """Coefficients of the clamped-annulus solution with the inclusion tilted by 1 rad (order 1) or pushed by
    1 mm (order 0): f, f', f'' as functions."""
    if order == 1:
        F = [lambda r: r, lambda r: r**3, lambda r: 1 / r, lambda r: r * math.log(r)]
        F1 = [lambda r: 1.0, lambda r: 3 * r**2, lambda r: -1 / r**2, lambda r: math.log(r) + 1]
        F2 = [lambda r: 0.0, lambda r: 6 * r, lambda r: 2 / r**3, lambda r: 1 / r]
        rhs = [a, 1.0, 0.0, 0.0]
    else:
        F = [lambda r: 1.0, lambda r: r**2, lambda r: math.log(r), lambda r: r**2 * math.log(r)]
        F1 = [lambda r: 0.0, lambda r: 2 * r, lambda r: 1 / r, lambda r: 2 * r * math.log(r) + r]
        F2 = [lambda r: 0.0, lambda r: 2.0, lambda r: -1 / r**2, lambda r: 2 * math.log(r) + 3]
        rhs = [1.0, 0.0, 0.0, 0.0]
    M = np.array([[g(a) for g in F], [g(a) for g in F1], [g(b) for g in F], [g(b) for g in F1]])
    c = np.linalg.solve(M, rhs)
    return (lambda r: sum(ci * g(r) for ci, g in zip(c, F)), lambda r: sum(ci * g(r) for ci, g in zip(c, F1)),
            lambda r: sum(ci * g(r) for ci, g in zip(c, F2)))


@pytest.mark.parametrize("beta", [1.5, 4.0, 24.0])
@pytest.mark.parametrize("nu", [0.0, 0.3])
def test_plate_springs_equal_the_energy_of_the_clamped_annulus(beta, nu):
    """K = 2U / theta^2 (tilt) and 2U / w^2 (push) of the exact annulus solution, integrated numerically."""
    a, D = 2.5, 5254.0
    b = beta * a
    f = _annulus(1, a, b)
    assert math.isclose(plate_rocking_k(D, a, b), _energy(*f, a, b, D, nu, 1), rel_tol=1e-7)
    g = _annulus(0, a, b)
    assert math.isclose(plate_axial_k(D, a, b), _energy(*g, a, b, D, nu, 0), rel_tol=1e-7)


@pytest.mark.parametrize("a_over_l", [0.1, 0.25, 0.45, 0.7, 1.0])
def test_plate_on_foundation_equivalent_radii(a_over_l):
    """Exact rigid inclusion in an infinite plate on a Winkler foundation (w = Re/Im K_n(r e^(i pi/4)/l)), by
    its energy: the clamped-annulus forms at the equivalent radii are within 0.5 % (tilt) and 1 % (push)."""
    l, D = 1.0, 1.0
    a = a_over_l * l
    k = D / l**4
    e = np.exp(1j * np.pi / 4) / l

    for order, closed, tol in ((1, plate_rocking_k(D, a, plate_equivalent_radius(PLATE_ROCKING_RADIUS, a, l)), 0.005),
                               (0, plate_axial_k(D, a, plate_equivalent_radius(PLATE_AXIAL_RADIUS, a, l)), 0.01)):
        def parts(r, order=order):
            h = 1e-5 * r
            K = [kv(order, x * e) for x in (r - h, r, r + h)]
            return (np.array([K[1].real, K[1].imag]), np.array([(K[2] - K[0]).real, (K[2] - K[0]).imag]) / (2 * h),
                    np.array([(K[2] - 2 * K[1] + K[0]).real, (K[2] - 2 * K[1] + K[0]).imag]) / h**2)

        f0, f1, _ = parts(a)
        c = np.linalg.solve(np.array([f0, f1]), [a, 1.0] if order == 1 else [1.0, 0.0])
        exact = _energy(lambda r: c @ parts(r)[0], lambda r: c @ parts(r)[1], lambda r: c @ parts(r)[2],
                        a, a + 30 * l, D, 0.3, order, k)
        assert abs(closed / exact - 1) < tol, (order, closed, exact)


def test_cortex_springs_follow_the_plate_and_not_the_depth():
    m = FrameModel()
    f = m.foundation
    a, t = m.diameter_mm / 2, m.cortex_mm
    D = plate_rigidity(m.cortical_E_MPa, m.cortical_nu, t)
    lp = (D / subgrade_modulus(m.cancellous_E_MPa, m.cancellous_nu, m.bone_thickness_mm - t)) ** 0.25
    assert math.isclose(f["cortex_plate_length_mm"], lp)
    assert math.isclose(f["cortex_rocking_Nmm_per_rad"],
                        plate_rocking_k(D, a, lp * (3.04 + 0.12 * a / lp + 0.33 * (a / lp) ** 2)))
    assert math.isclose(f["cortex_axial_N_per_mm"], plate_axial_k(D, a, lp * (2.47 + 0.47 * a / lp + 0.255 * (a / lp) ** 2)))
    assert math.isclose(f["cortex_rocking"] * t, f["cortex_rocking_Nmm_per_rad"])
    for depth in (15.0, 35.0):
        g = m.replace(depth_mm=depth).foundation
        for key in ("cortex_rocking", "cortex_axial", "cortex_lateral", "cortex_torsion"):
            assert g[key] == f[key]
    # a thicker cortex is stiffer in rocking, but less than D ~ t^3: its bending spreads further
    r = FrameModel(cortex_mm=3.0).foundation["cortex_rocking_Nmm_per_rad"] / f["cortex_rocking_Nmm_per_rad"]
    assert 1 < r < 8


def test_confined_cancellous_modulus():
    a, b = 2.5, 60.0
    # far from both held faces the field reaches the bone's radius: the plane-strain disc at b
    assert math.isclose(confined_radius(a, 1e9, 1e9, b), b, rel_tol=1e-6)
    # near a face it cannot reach further than the face: stiffer
    assert confined_radius(a, 2.0, 30.0, b) < confined_radius(a, 10.0, 30.0, b) < b
    # the profile: stiffest next to the cortex, and in a thick bone independent of how deep the pin goes
    thick = FrameModel(bone_thickness_mm=1e4)
    p30, p15 = thick.cancellous_profile, thick.replace(depth_mm=15.0).cancellous_profile
    assert p30[-1][2] > p30[0][2]
    assert math.isclose(p30[-1][1], p15[-1][1])
    for m in (thick, thick.replace(depth_mm=15.0)):  # the top sub-segment: the same law at the same distance
        z0, z1, kh = m.cancellous_profile[-1]
        xg, wg = np.polynomial.legendre.leggauss(8)
        zs = 0.5 * (z0 + z1) + 0.5 * (z1 - z0) * xg
        ref = sum(w * lateral_foundation_k(150.0, 0.2, a, confined_radius(a, -z - 0.75, 1e4 + z, b)) for w, z in
                  zip(wg, zs)) / 2
        assert math.isclose(kh, ref, rel_tol=1e-12)


def test_kernel_applies_the_rocking_spring():
    """A pure moment on one pin in a cortex over almost no cancellous bone: the pin turns at the cortex by
    M / (K_rock + k_h t^3 / 12) (the rocking spring plus the couple of the in-plane spring over the
    thickness); the pin above bends as a cantilever under the constant moment."""
    m = FrameModel(needles=1, tissue=False, cancellous_E_MPa=1e-3, clamp_length_mm=0.0, free_length_mm=60.0)
    M = 50.0  # N mm, linear range
    r = frame.solve((0, 0, 0), (M, 0, 0), model=m)
    f = m.foundation
    t = m.cortex_mm
    K = f["cortex_rocking_Nmm_per_rad"] + f["cortex_lateral"] * t**3 / 12
    theta_root = r.needles[0].root_rotation_rad[0]
    assert math.isclose(theta_root, M / K, rel_tol=0.02)
    # the clamp turns by that plus the pin's own bending M L / EI
    assert math.isclose(r.clamp_rotation_rad[0], M / K + M * m.free_length_mm / m.bending_stiffness_Nmm2,
                        rel_tol=0.02)


def test_stiff_bone_tends_to_rigid_root_plate_law():
    F = (0.0, 200.0, 0.0)
    rigid = frame.solve(F, model=FrameModel(needles=1, root="rigid"))
    prev = None
    for s in (1.0, 3.0, 10.0):
        m = FrameModel(needles=1, cortical_E_MPa=17000.0 * s, cancellous_E_MPa=150.0 * s)
        gap = frame.solve(F, model=m).max_needle_deflection_mm - rigid.max_needle_deflection_mm
        assert gap > 0 and (prev is None or gap < prev)
        first = gap if prev is None else first
        prev = gap
    assert prev < 0.5 * first  # the root's compliance falls slowly (a beam on a foundation: ~ modulus^(-1/4))


def test_plate_law_bad_input():
    from needletissue.errors import InputError

    for kw, name in ((dict(depth_mm=40.0), "depth_mm"), (dict(bone_law="glue"), "bone_law"),
                     (dict(cortex_factor=0.0), "cortex_factor"), (dict(confinement_factor=11.0), "confinement_factor"),
                     (dict(bone_thickness_mm=float("nan")), "bone_thickness_mm")):
        with pytest.raises(InputError) as e:
            FrameModel(**kw)
        assert e.value.field == name


def test_calibration_in_units_of_the_goal_recovers_the_factors():
    """tolerance=(mm, fraction): residuals divided by max(mm, fraction |measured|); on exact synthetic data
    from known plate-law factors the fit returns them, and its residuals are those quotients."""
    from needletissue.frame.fitting import CalibrationPoint, calibration

    truth = dict(cortex_factor=0.7, tissue_factor=0.4)
    pts = []
    for n, F in ((1, 60.0), (1, 250.0), (2, 150.0)):
        base = FrameModel(needles=n)
        r = frame.solve((0, F, 0), model=base.replace(**truth), error_estimate=False)
        pts.append(CalibrationPoint(base, (0, F, 0), clamp_displacement_mm=r.clamp_displacement_mm,
                                    max_needle_deflection_mm=r.max_needle_deflection_mm))
    c = calibration(pts, params=("cortex_factor", "tissue_factor"), tolerance=(0.432, 0.024))
    for k, v in truth.items():
        assert abs(c.params[k] / v - 1) < 1e-3
    assert c.max_abs_mm < 1e-3
    # at the physical factors the residual of the max deflection is (model - measured) / max(0.432, 2.4 %)
    c0 = calibration(pts[:1], params=("tissue_factor",), tolerance=(0.432, 0.024), x0=(0.4,))
    d = pts[0].max_needle_deflection_mm
    r1 = frame.solve((0, 60.0, 0), model=FrameModel(needles=1, tissue_factor=c0.params["tissue_factor"]),
                     error_estimate=False)
    assert math.isclose(c0.residuals_mm[-1], (r1.max_needle_deflection_mm - d) / max(0.432, 0.024 * d),
                        rel_tol=1e-6, abs_tol=1e-9)
