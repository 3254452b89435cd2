"""The anatomical model's contact reporting and muscle attachments (models.contact.interface_state,
models.pelvis.split_contact; docs/contact.md "Anatomical model with contact")."""

from __future__ import annotations

import numpy as np
import pytest

from needletissue.fem.contact import ContactSettings, unit_pressure
from needletissue.models.contact import interface_state
from needletissue.models.contact_verify import build_model, stacked_boxes


@pytest.fixture(scope="module")
def block():
    """10 x 10 x 5 mm block (side b) on a 20 x 20 x 5 mm plate (side a), interface z = 0, h = 2.5 mm."""
    import felupe as fem

    mesh = stacked_boxes({"plate": ((0, 0, -5), (20, 20, 0)), "block": ((5, 5, 0), (15, 15, 5))}, 2.5)
    mats = {"plate": fem.NeoHooke(mu=10.0, bulk=50.0), "block": fem.NeoHooke(mu=1.0, bulk=5.0)}
    m = build_model(mesh, mats, {"plate-block": 0.3}, ContactSettings(youngs_modulus=3.0))
    return m, np.unique(m.mesh.cells[m.mesh.regions["block"]])


def _moved(m, nodes, shift):
    u = np.zeros_like(m.mesh.points)
    u[nodes] = shift
    return interface_state(m.contact, u)["plate-block"]


def test_rigid_moves_give_their_slip_gap_and_overlap(block):
    """The block moved rigidly: every node pair slips by the tangential part of the move and opens
    (or overlaps) by its normal part; beyond the barrier's reach (gap > dhat) no pressure."""
    m, nodes = block
    s = _moved(m, nodes, (0.3, -0.4, 0.0))
    assert s["max_slip_mm"] == pytest.approx(0.5, abs=1e-12) and s["mean_slip_mm"] == pytest.approx(0.5, abs=1e-12)
    assert s["max_gap_opening_mm"] == pytest.approx(0.0, abs=1e-12) and s["pairs"] == 5 * 5
    assert s["area_mm2"] == pytest.approx(100.0)
    s = _moved(m, nodes, (0.0, 0.0, 0.5))
    assert s["max_gap_opening_mm"] == pytest.approx(0.5) and s["max_slip_mm"] == pytest.approx(0.0, abs=1e-12)
    assert s["normal_force_N"] == 0 and s["max_pressure_MPa"] == 0
    s = _moved(m, nodes, (0.0, 0.0, -0.03))
    assert s["max_pair_interpenetration_mm"] == pytest.approx(0.03)
    assert s["max_interpenetration_mm"] == pytest.approx(0.03, abs=1e-9)


def test_pressure_is_the_barriers_flat_contact_pressure(block):
    """Pressed by 0.03 mm (barrier distance 0.06 mm) the interior of the interface carries the pressure
    of the barrier law on a flat patch (unit_pressure x stiffness); the mean over the footprint is the
    normal force over its area, below the interior value (the rim vertices have pairs on one side only),
    and more than at rest (distance 0.09 mm)."""
    m, nodes = block
    st = m.contact.settings
    pressed, rest = _moved(m, nodes, (0.0, 0.0, -0.03)), _moved(m, nodes, (0.0, 0.0, 0.0))
    p = st.kappa * unit_pressure(st.dhat, st.gap - 0.03)
    assert pressed["max_pressure_MPa"] == pytest.approx(p, rel=0.05)
    assert pressed["mean_pressure_MPa"] == pytest.approx(pressed["normal_force_N"] / pressed["area_mm2"])
    assert 0.5 * p < pressed["mean_pressure_MPa"] <= p * 1.05
    assert rest["mean_pressure_MPa"] < pressed["mean_pressure_MPa"]


@pytest.mark.parametrize("materials", [None, {"hip_cancellous": "cancellous_bone", "needle_1": "needle"}])
def test_bone_needle_barrier_carries_the_bones_modulus_at_half_dhat(materials):
    """One barrier rule for the needle model (materials None) and the anatomical model (region ->
    material): a flat bone-needle contact at d = dhat/2 carries PRESSURE_FRACTION x 3 mu0 of the bone
    (the softer side), not 0.1 of it (the anatomical model's cortical rim squeezed that barrier to 9e-5 mm)."""
    from types import SimpleNamespace

    import felupe as fem

    from needletissue import materials as registry
    from needletissue.models.contact import PRESSURE_FRACTION, NeedleContact, needle_settings

    bone, pin = ("cancellous_bone", "needle_1") if materials is None else tuple(materials)
    mesh = stacked_boxes({bone: ((0, 0, -5), (20, 20, 0)), pin: ((5, 5, 0), (15, 15, 5))}, 2.5)
    contact = NeedleContact("paper", settings=needle_settings(), materials=materials)
    mesh = contact.prepare(mesh)
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(fem.Mesh(mesh.points, mesh.cells, "tetra")), dim=3)])
    (item,) = contact.items(SimpleNamespace(mesh=mesh, field=field))
    st = item.settings
    modulus = 3.0 * registry.get("cancellous_bone").initial_shear_modulus
    assert PRESSURE_FRACTION["bone-needle"] == 1.0
    assert st.kappa * unit_pressure(st.dhat, 0.5 * st.dhat) == pytest.approx(modulus, rel=1e-9)
    assert st.gap == pytest.approx(needle_settings().gap) and st.eps_v == needle_settings().eps_v


@pytest.mark.slow
@pytest.mark.data
def test_paper_interfaces_converge_in_equilibrium_and_report_each_interface(tmp_path):
    """Coarse anatomical model at 20 N with all of the paper's interfaces (muscle attachments bonded beyond
    35 mm): converges, the supports carry the clamp force (1 %), and per interface the gaps and slip are
    >= 0, the overlap of the originally coincident pairs and the barrier interpenetration stay below dhat,
    the muscle-bone contact carries a pressure; the pairs slip (friction, not a bond) by less than the
    needles move."""
    import json

    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    res = run_pelvis_model(PelvisConfig(mesher="box", mesh_size=6.0, needle_size=3.0, far_size=18.0, forces=[20.0],
                                        interfaces="paper", figures=False, crosscheck_thickness=False,
                                        out=str(tmp_path)))
    contact = json.loads((tmp_path / "pelvis_results.json").read_text(encoding="utf-8"))["contact"]
    assert set(contact["interfaces"]) == {"needle-muscle", "muscle-bone", "bone-needle"}
    a = contact["attachments"]
    assert a["muscle_bone_faces_bonded"] > 0 and a["muscle_bone_faces_sliding"] > 0
    (x,) = contact["per_force"]
    assert set(contact["rest"]) == set(contact["interfaces"])
    assert x["equilibrium_error"] < 0.01
    for name, s in x["interfaces"].items():
        dhat = contact["settings"][name]["dhat_mm"]
        assert s["max_gap_opening_mm"] >= 0 and 0 <= s["mean_slip_mm"] <= s["max_slip_mm"], name
        assert s["max_pair_interpenetration_mm"] < dhat and 0 <= s["max_interpenetration_mm"] < dhat, name
        assert 0 < s["mean_pressure_MPa"] <= s["max_pressure_MPa"], name
        assert s["max_slip_mm"] < res.results[0].max_needle_deformation_mm, name
    # the progress log in --out: the increments reach 20 N, with each interface's barrier distance in (0, dhat)
    from needletissue.fem.solvelog import read_log
    from needletissue.models.pelvis.model import SOLVE_LOG

    ev = read_log(tmp_path / SOLVE_LOG)
    inc = [e for e in ev if e["event"] == "increment"]
    assert ev[0]["event"] == "start" and ev[-1]["event"] == "done"
    assert inc[-1]["force_N"] == pytest.approx(20.0) and inc[-1]["cpu_s"] > 0
    assert sum(e["iterations"] for e in inc) == x["newton_iterations"]
    for e in inc:
        assert set(e["min_distance_mm"]) == set(contact["interfaces"])
        assert all(0 < d < contact["settings"][n]["dhat_mm"] for n, d in e["min_distance_mm"].items())
