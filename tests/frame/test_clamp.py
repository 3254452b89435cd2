"""The elastic clamp (FrameModel.clamp = "elastic", issue #14 item 2): a Timoshenko bar along the pins,
condensed to a compliance at their attachments. Tests assert physics: the stiff limit is the rigid clamp,
closed-form portal frame and grillage with a flexible beam, never stiffer than the rigid clamp, bad input."""

import math

import numpy as np
import pytest

from needletissue import frame
from needletissue.errors import InputError
from needletissue.frame import FrameModel
from needletissue.frame.model import clamp_compliance

WRENCHES = [((0.0, 300.0, 0.0), None), ((300.0, 0.0, 0.0), None), ((0.0, 0.0, -300.0), None),
            ((60.0, 80.0, -40.0), (1500.0, -800.0, 2500.0))]


def _u(r):
    return np.array(r.load_point_displacement_mm + r.clamp_rotation_rad)


@pytest.mark.parametrize("force,moment", WRENCHES)
def test_stiff_elastic_clamp_is_the_rigid_clamp(force, moment):
    """Clamp E -> 1e9 x steel: the compliance ~1e-9 of steel's, so the answer is the rigid clamp's to the solver's
    tolerance (default model: bone root, tissue, 300 N in every direction and a wrench with a moment)."""
    rigid = frame.solve(force, moment, model=FrameModel(), error_estimate=False)
    stiff = frame.solve(force, moment, model=FrameModel(clamp="elastic", clamp_E_MPa=2e14), error_estimate=False)
    steel = frame.solve(force, moment, model=FrameModel(clamp="elastic"), error_estimate=False)
    for key in ("clamp_displacement_mm", "clamp_rotation_rad", "load_point_displacement_mm"):
        a, b, s = (np.array(getattr(r, key)) for r in (rigid, stiff, steel))
        scale = np.linalg.norm(a)
        assert np.linalg.norm(b - a) <= 1e-9 * scale + 1e-13, key
        # ... while the steel clamp does change it (the test could fail)
        if key == "load_point_displacement_mm":
            assert np.linalg.norm(s - a) > 1e-6 * scale
    assert abs(stiff.max_needle_deflection_mm - rigid.max_needle_deflection_mm) <= 1e-9 * rigid.max_needle_deflection_mm


# Closed-form frames: two Kirchhoff pins (shear=False: unshearable, inextensible), built in at the bone surface
# (root rigid, no tissue), height h to the clamp bottom, spacing s = 2a, into a soft clamp bar (E_b ~ 150 MPa
# makes the bar as flexible as the pins: 4 EI/h ~ 6 E_b I_b / s) of section 20 x 20 mm, its axis e = L_g/2
# above the clamp bottom, the load at the bar's centre on its axis.
H_PIN, LG, A_HALF = 80.0, 20.0, 20.0


def _portal(Eb):
    return FrameModel(needles=2, spacing_mm=2 * A_HALF, root="rigid", tissue=False, shear=False, clamp_length_mm=LG,
                      free_length_mm=H_PIN + LG, clamp="elastic", clamp_E_MPa=Eb, clamp_section_mm=(20.0, 20.0))


def _bar(m):
    s = m.clamp_section
    return s["E_MPa"], s["G_MPa"], s["area_mm2"], s["shear_factor"], s["Iy_mm4"], s["Iz_mm4"]


@pytest.mark.parametrize("Eb", [150.0, 1500.0])
def test_portal_frame_with_flexible_beam(Eb):
    """In the pins' plane (force H along x at the bar's centre): a fixed-base portal frame with a flexible beam.

    Complementary energy (Menabrea), per half by antisymmetry: each pin carries H/2 across and a bending moment
    M(z) = (H/2)(h + e - z) - M_b, M_b the (redundant) moment the bar takes at the joint; the rigid joint
    block carries the pin's top (z = h) up to the bar's axis (e = L_g/2). The bar's half a = s/2 from its
    centre (the inflection point, by antisymmetry) carries the bending moment M_b x/a, the shear M_b/a and the
    axial force H/2; the inextensible pins store no axial energy. So

        U* = 2 int_0^h M(z)^2 / (2 EI) dz + 2 [M_b^2 a / (6 E_b I_y) + M_b^2 / (2 a k G_b A_b) + H^2 a / (8 E_b A_b)],
        dU*/dM_b = 0:  M_b = (H/2)(h^2/2 + e h)/EI / (h/EI + a/(3 E_b I_y) + 1/(a k G_b A_b)),
        u = dU*/dH = [(H/2)((h + e)^3 - e^3)/3 - M_b (h^2/2 + e h)] / EI + H a / (2 E_b A_b).

    (= the slope-deflection portal K = (24 EI/h^3)(1 + 6 rho)/(4 + 6 rho), rho = (E_b I_b/s)/(EI/h), with the
    Timoshenko bar's joint stiffness 6 E_b I_b / (s (1 + Phi)), Phi = 12 E_b I_b / (k G_b A_b s^2), when e = 0;
    E_b -> inf: M_b = (H/2)(h/2 + e), u = H h^3 / (24 EI).) The clamp's rotation (its reference section, the
    bar's centre): the joint turns with the pin's top, theta = [(H/2)(h^2/2 + e h) - M_b h] / EI about y, and the
    bar's end turns against its centre by its bending alone, M_b a / (2 E_b I_y) (shear does not turn the
    sections): phi_y = theta - M_b a / (2 E_b I_y)."""
    m = _portal(Eb)
    H = 1.0
    h, e, a = H_PIN, LG / 2, A_HALF
    EI = m.bending_stiffness_Nmm2
    E_b, G_b, A_b, k, Iy, _ = _bar(m)
    Mb = (H / 2) * (h**2 / 2 + e * h) / EI / (h / EI + a / (3 * E_b * Iy) + 1 / (a * k * G_b * A_b))
    u = ((H / 2) * ((h + e)**3 - e**3) / 3 - Mb * (h**2 / 2 + e * h)) / EI + H * a / (2 * E_b * A_b)
    r = frame.solve((H, 0.0, 0.0), model=m, error_estimate=False)
    rigid = frame.solve((H, 0.0, 0.0), model=m.replace(clamp="rigid"), error_estimate=False)
    assert r.load_point_displacement_mm[0] == pytest.approx(u, rel=1e-5)
    assert rigid.load_point_displacement_mm[0] == pytest.approx(H * h**3 / (24 * EI), rel=1e-5)
    theta = ((H / 2) * (h**2 / 2 + e * h) - Mb * h) / EI
    assert r.clamp_rotation_rad[1] == pytest.approx(theta - Mb * a / (2 * E_b * Iy), rel=1e-5)
    # the clamp's own part: the elastic minus the rigid answer is the formula's
    du = r.load_point_displacement_mm[0] - rigid.load_point_displacement_mm[0]
    assert du == pytest.approx(u - H * h**3 / (24 * EI), rel=0.01) and du > 0.05 * u


@pytest.mark.parametrize("Eb", [150.0, 1500.0])
def test_grillage_across_the_plane_with_flexible_beam(Eb):
    """Across the pins' plane (force F along y at the bar's centre): a grillage - two vertical cantilevers and a
    horizontal bar bending in its own plane, coupled by the pins' torsion.

    By symmetry each pin carries F/2 across and, at its top, the moment F e / 2 (the force acts e above the
    clamp bottom; the bar carries no torsion: the pin's moment and its force's lever about the axis cancel).
    The bar's half (length a, from the centre outward) bends about z under the pin's force: M_z(x) = (F/2)(a - x)
    - T_p, T_p the pin's torsional moment (the redundant: the bar's end turns about z and twists the pin, GJ_p/h),
    with shear F/2. Complementary energy:

        U* = 2 [int_0^h (F/2)^2 (h + e - z)^2 / (2 EI) dz + T_p^2 h / (2 G J_p)]
           + 2 [int_0^a M_z(x)^2 / (2 E_b I_z) dx + (F/2)^2 a / (2 k G_b A_b)],
        dU*/dT_p = 0:  T_p = F a^2 / (4 E_b I_z) / (h / (G J_p) + a / (E_b I_z)),
        u = dU*/dF = F ((h + e)^3 - e^3) / (6 EI) + (F a^3 / 6 - T_p a^2 / 2) / (E_b I_z) + F a / (2 k G_b A_b).

    The first term alone is the rigid clamp (two cantilevers at F/2 with the lever e)."""
    m = _portal(Eb)
    F = 1.0
    h, e, a = H_PIN, LG / 2, A_HALF
    EI = m.bending_stiffness_Nmm2
    GJ = m.shear_modulus_MPa * 2 * m.second_moment_mm4
    E_b, G_b, A_b, k, _, Iz = _bar(m)
    Tp = F * a**2 / (4 * E_b * Iz) / (h / GJ + a / (E_b * Iz))
    u_rigid = F * ((h + e)**3 - e**3) / (6 * EI)
    u = u_rigid + (F * a**3 / 6 - Tp * a**2 / 2) / (E_b * Iz) + F * a / (2 * k * G_b * A_b)
    r = frame.solve((0.0, F, 0.0), model=m, error_estimate=False)
    rigid = frame.solve((0.0, F, 0.0), model=m.replace(clamp="rigid"), error_estimate=False)
    assert r.load_point_displacement_mm[1] == pytest.approx(u, rel=1e-5)
    assert rigid.load_point_displacement_mm[1] == pytest.approx(u_rigid, rel=1e-5)
    # the pins' torsion is felt: without it (T_p = 0) the formula would be off by more than the tolerance
    if Eb < 1000:
        assert abs(u + Tp * a**2 / 2 / (E_b * Iz) - r.load_point_displacement_mm[1]) > 3e-3 * u
    # the clamp's own part: the elastic minus the rigid answer is the formula's bar terms
    du = r.load_point_displacement_mm[1] - rigid.load_point_displacement_mm[1]
    assert du == pytest.approx(u - u_rigid, rel=0.01) and du > 2e-3 * u


def test_bar_compliance_is_a_timoshenko_cantilever():
    """clamp_compliance: a point on the bar's axis a from the load point's section, a force across, along, a
    moment about the axis: the cantilever's F a^3/(3 EI) + F a/(kGA), F a/(EA), T a/(GJ); symmetric, positive
    semi-definite; points on opposite sides of the reference are uncoupled."""
    m = FrameModel(clamp="elastic")
    s = m.clamp_section
    z = s["axis_z_mm"]
    pts = [(20.0, 0.0, z), (-20.0, 0.0, z), (10.0, 0.0, z)]
    C = clamp_compliance(m, pts)
    E, G, A, k = s["E_MPa"], s["G_MPa"], s["area_mm2"], s["shear_factor"]
    a = 20.0
    assert C[1, 1] == pytest.approx(a**3 / (3 * E * s["Iz_mm4"]) + a / (k * G * A), rel=1e-12)
    assert C[2, 2] == pytest.approx(a**3 / (3 * E * s["Iy_mm4"]) + a / (k * G * A), rel=1e-12)
    assert C[0, 0] == pytest.approx(a / (E * A), rel=1e-12)
    assert C[3, 3] == pytest.approx(a / (G * s["J_mm4"]), rel=1e-12)
    assert C[5, 1] == pytest.approx(a**2 / (2 * E * s["Iz_mm4"]), rel=1e-12)  # rotation about z per force along y
    # the point at 10 under the force at 20: v = F x^2 (3 a - x) / (6 EI) + F x/(kGA), x = 10
    x = 10.0
    assert C[13, 1] == pytest.approx(x**2 * (3 * a - x) / (6 * E * s["Iz_mm4"]) + x / (k * G * A), rel=1e-12)
    assert C[1, 13] == pytest.approx(C[13, 1], rel=1e-12)  # Maxwell-Betti
    assert np.allclose(C, C.T, rtol=0, atol=1e-15 * abs(C).max())
    assert np.linalg.eigvalsh(C).min() > -1e-12 * abs(C).max()
    assert not C[:6, 6:12].any()
    # the square section's torsion constant within 0.2 % of the exact series value 0.1406 a^4
    assert s["J_mm4"] == pytest.approx(0.140577 * 20.0**4, rel=2e-3)


@pytest.mark.parametrize("force,moment", WRENCHES)
@pytest.mark.parametrize("load_point", [None, (12.0, 5.0, 85.0)])
def test_elastic_clamp_is_never_stiffer(force, moment, load_point):
    """The work of the wrench on the load point's motion (F . c + M . phi): the elastic clamp's is never below the
    rigid clamp's, and grows as the clamp softens (steel, 1/10, 1/100 of steel)."""
    W = np.concatenate([force, np.zeros(3) if moment is None else moment])
    works = []
    for kind, E in (("rigid", 2e5), ("elastic", 2e5), ("elastic", 2e4), ("elastic", 2e3)):
        m = FrameModel(clamp=kind, clamp_E_MPa=E, load_point_mm=load_point)
        works.append(float(W @ _u(frame.solve(force, moment, model=m, error_estimate=False))))
    assert all(b > a for a, b in zip(works, works[1:])), works


def test_pose_and_batch_with_the_elastic_clamp():
    """pose() and solve_batch() run the same residual: the clamp pose equals solve()'s; their max deflection takes
    the gripped part of each pin with the clamp's reference section (no elastic term at the pin tops), within
    the clamp's own deflection (um at the default steel bar) of solve()'s."""
    m = FrameModel(clamp="elastic", clamp_E_MPa=2e4)
    r = frame.solve((200.0, 100.0, 0.0), model=m)
    u, rot, dmax, _ = frame.pose((200.0, 100.0, 0.0), model=m)
    assert np.allclose(u, r.clamp_displacement_mm, atol=1e-8) and np.allclose(rot, r.clamp_rotation_rad, atol=1e-10)
    assert abs(dmax - r.max_needle_deflection_mm) < 0.01
    b = frame.solve_batch([(200.0, 100.0, 0.0)], model=m)
    assert np.allclose(b.clamp_displacement_mm[0], r.clamp_displacement_mm, atol=1e-8)


def test_defaults_are_fe_needles_clamp_bar():
    """The elastic clamp's defaults are fe needle's bar: steel of the materials registry ("clamp"), the section
    clamp_width (y) x grip length (z)."""
    from needletissue import materials
    from needletissue.geometry.needle import NeedleGeometry
    from needletissue.models.needle import MATERIALS

    g, m = NeedleGeometry(), FrameModel(clamp="elastic")
    steel = materials.get(MATERIALS["clamp"]).parameters
    assert (m.clamp_E_MPa, m.clamp_nu) == (steel["E"], steel["nu"])
    s = m.clamp_section
    assert (s["width_mm"], s["height_mm"]) == (g.clamp_width, g.grip_length)
    assert s["axis_z_mm"] == g.gripper_centre
    assert FrameModel().clamp == "rigid"


@pytest.mark.parametrize("kw,field", [
    (dict(clamp="glue"), "clamp"), (dict(clamp="elastic", clamp_E_MPa=0.0), "clamp_E_MPa"),
    (dict(clamp_E_MPa=float("nan")), "clamp_E_MPa"), (dict(clamp="elastic", clamp_nu=0.5), "clamp_nu"),
    (dict(clamp="elastic", clamp_section_mm=(20.0, -1.0)), "clamp_section_mm"),
    (dict(clamp="elastic", clamp_section_mm=(20.0,)), "clamp_section_mm"),
    (dict(clamp="elastic", clamp_section_mm=5.0), "clamp_section_mm"),
    (dict(clamp="elastic", needles=1, root="rigid", tissue=False, clamp_length_mm=0.0), "clamp_section_mm"),
    (dict(clamp="elastic", needles=3, needle_xy=((0, 0), (30, 0), (15, 20))), "needle_xy"),
])
def test_bad_clamp_input_names_the_field(kw, field):
    with pytest.raises(InputError) as exc:
        FrameModel(**kw)
    assert exc.value.field == field


def test_pins_off_the_bar_axis_within_its_width():
    """3 pins not quite on a line: held by the bar through rigid arms while inside its width (the answer close to
    the collinear one), refused beyond it."""
    F = (80.0, 40.0, 0.0)
    kw = dict(needles=3, root="rigid", tissue=False, clamp="elastic", clamp_E_MPa=2e4)
    line = frame.solve(F, model=FrameModel(needle_xy=((-30.0, 0.0), (0.0, 0.0), (30.0, 0.0)), **kw),
                       error_estimate=False)
    bent = frame.solve(F, model=FrameModel(needle_xy=((-30.0, 0.0), (0.0, 0.3), (30.0, 0.0)), **kw),
                       error_estimate=False)
    assert np.allclose(bent.clamp_displacement_mm, line.clamp_displacement_mm, rtol=0.02, atol=1e-3)
    with pytest.raises(InputError, match="off its axis"):
        FrameModel(needle_xy=((-30.0, 0.0), (0.0, 20.0), (30.0, 0.0)), **kw)  # 13.3 mm off the axis


def test_elastic_clamp_on_a_line_of_pins_and_one_pin():
    """Three pins on an oblique line are a bar; one pin under its load point has nothing to bend (rigid answer)."""
    xy = ((0.0, 0.0), (24.0, 18.0), (48.0, 36.0))
    m = FrameModel(needles=3, needle_xy=xy, root="rigid", tissue=False, clamp="elastic", clamp_E_MPa=2e3)
    r = frame.solve((50.0, -30.0, 0.0), model=m, error_estimate=False)
    rr = frame.solve((50.0, -30.0, 0.0), model=m.replace(clamp="rigid"), error_estimate=False)
    assert np.linalg.norm(r.load_point_displacement_mm) > np.linalg.norm(rr.load_point_displacement_mm)
    one = dict(needles=1, root="rigid", tissue=False)
    a = frame.solve((0.0, 100.0, 0.0), model=FrameModel(clamp="elastic", **one), error_estimate=False)
    b = frame.solve((0.0, 100.0, 0.0), model=FrameModel(**one), error_estimate=False)
    assert a.clamp_displacement_mm == pytest.approx(b.clamp_displacement_mm, rel=1e-12, abs=1e-14)


def test_cli_clamp_option_json_and_config_reads_back(run_cli, tmp_path):
    """`needletissue frame --clamp elastic ...`: the JSON equals the API's answer, the model echoes the clamp
    fields, and the resolved config.toml a --plot run writes builds the same FrameModel again."""
    import json
    import tomllib

    from needletissue.ritz.model import Layer

    png = tmp_path / "f.png"
    code, out, err = run_cli("frame", "--clamp", "elastic", "--clamp-modulus", "20000", "--clamp-section", "16,12",
                             "--force", "200,0,0", "--json", "--plot", png)
    assert code == 0, err
    d = json.loads(out)
    m = FrameModel(clamp="elastic", clamp_E_MPa=20000.0, clamp_section_mm=(16.0, 12.0))
    want = frame.solve((200.0, 0.0, 0.0), model=m)
    assert d["results"][0]["clamp_displacement_mm"] == list(want.clamp_displacement_mm)
    assert d["model"]["clamp"] == "elastic" and d["model"]["clamp_section_mm"] == [16.0, 12.0]
    assert d["model"]["clamp_bar"]["Iy_mm4"] == pytest.approx(16 * 12**3 / 12)
    cfg = tomllib.loads((tmp_path / "config.toml").read_text())
    fields = {f for f in FrameModel.__dataclass_fields__}
    kw = {k: v for k, v in cfg.items() if k in fields}
    kw["layers"] = tuple(Layer(**la) for la in kw["layers"])
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()}
    assert FrameModel(**kw) == m
    # the rigid default writes and reads back too (no section: the derived one)
    code, out, err = run_cli("frame", "--force", "0,100,0", "--json")
    assert code == 0 and json.loads(out)["model"]["clamp"] == "rigid"


@pytest.mark.parametrize("args,field", [(["--clamp", "glue"], "clamp"), (["--clamp-modulus", "-5"], "clamp_E_MPa"),
                                        (["--clamp", "elastic", "--clamp-section", "20"], "--clamp-section"),
                                        (["--clamp", "elastic", "--clamp-section", "20,0"], "clamp_section_mm"),
                                        (["--clamp-poisson", "0.7"], "clamp_nu")])
def test_cli_bad_clamp_input_exit_2(run_cli, args, field):
    code, out, err = run_cli("frame", *args)
    assert code == 2 and field in err and "Traceback" not in err


def test_elastic_clamp_with_the_plastic_section():
    """The compliance sits after the moment-curvature table in the constants: with plastic=True the stiff clamp is
    still the rigid one, and the steel clamp still softens the portal frame."""
    F = (300.0, 0.0, 0.0)
    rigid = frame.solve(F, model=FrameModel(plastic=True), error_estimate=False)
    stiff = frame.solve(F, model=FrameModel(plastic=True, clamp="elastic", clamp_E_MPa=2e14), error_estimate=False)
    steel = frame.solve(F, model=FrameModel(plastic=True, clamp="elastic"), error_estimate=False)
    a, b, c = (np.array(r.load_point_displacement_mm) for r in (rigid, stiff, steel))
    assert np.linalg.norm(b - a) <= 1e-9 * np.linalg.norm(a)
    assert c[0] > a[0] * (1 + 2e-4)
