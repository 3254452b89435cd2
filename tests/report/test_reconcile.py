"""The reconciliation with the paper: each step of the chain changes the value the way the physics says,
the steps are the engines' own answers, the 300/100 N ratio is bounded by the linear value for every
elastic case, and every row that differs from the paper gets its measured reason."""

import json
import math

import numpy as np
import pytest

from needletissue import frame, ritz
from needletissue.report.config import load_config
from needletissue.report.paper import PAPER
from needletissue.report.pipeline import NO_REASON, Comparison, StageOutcome, StageResult, _attach_reasons, run_reproduce
from needletissue.report.reconcile import (_with, anatomical_frame_model, anatomical_setup, reconcile, row_reasons)
from needletissue.report.stages import ritz_model, stage_list

FORCES = [100.0, 200.0, 300.0]


def _pelvis(direction=(0.0, 0.0, -1.0), force=(0.0, 1.0, 0.0), entries=((0.0, 0.0, 0.0), (12.0, 0.0, 3.0)),
            free=(76.0, 77.0), layers=((22.0, 12.0), (20.0, 14.0))):
    """A pelvis stage result with the fields the reconciliation reads: a two-pin site (needle direction
    into the bone, entries), the force direction, the measured layers and lengths, and FE values (here the
    frame model's own, so the chain's start is a physical number; the tests assert relations only)."""
    per = [{"model": {"free_length_mm": lf, "layers": [{"name": "muscle", "thickness_mm": m, "k_N_per_mm2": 0.048},
                                                       {"name": "adipose", "thickness_mm": a, "k_N_per_mm2": 0.023}]},
            "max_deflection_mm": [], "max_deflection_half_force_mm": []} for lf, (m, a) in zip(free, layers)]
    data = {"site": {"entries_mm": [list(e) for e in entries], "direction": list(direction), "needle_diameter_mm": 5.0,
                     "depth_in_bone_mm": 40.0, "clamp_size_mm": [20.0, 20.0]},
            "ritz": {"per_needle": per}, "force_vector_unit": list(force / np.linalg.norm(force)),
            "results": [{"force_N": f, "max_needle_deformation_mm": 0.0} for f in FORCES]}
    s = anatomical_setup(data)
    m = anatomical_frame_model(s)
    for r in data["results"]:
        r["max_needle_deformation_mm"] = frame.solve(force=tuple(r["force_N"] * np.asarray(s.force_unit)),
                                                     model=m).max_needle_deflection_mm
    return data


@pytest.fixture(scope="module")
def rec():
    return reconcile(ritz.RitzModel(), _pelvis())


def _step(rec, name):
    return next(s for s in rec.chain + rec.checks if s.name == name)


def test_anatomical_setup_is_the_geometry_in_the_pins_frame():
    """Spacing = the entries' distance across the pin axis; the force keeps its length and its component
    along the pins (z out of the bone)."""
    u = np.array([0.3, -0.5, 0.8])
    d = np.array([0.2, -0.4, -1.0])
    data = _pelvis(direction=tuple(d), force=tuple(u), entries=((1.0, 2.0, 3.0), (10.0, 4.0, -2.0)))
    s = anatomical_setup(data)
    a = d / np.linalg.norm(d)
    gap = np.array([9.0, 2.0, -5.0])
    assert s.spacing_mm == pytest.approx(np.linalg.norm(gap - (gap @ a) * a), rel=1e-12)
    assert np.linalg.norm(s.force_unit) == pytest.approx(1.0, rel=1e-12)
    assert s.force_unit[2] == pytest.approx(-(u / np.linalg.norm(u)) @ a, rel=1e-12)
    assert s.free_length_mm == pytest.approx(76.5) and s.layers[0].thickness_mm == pytest.approx(21.0)


def test_first_frame_step_is_the_frame_model_run_directly(rec):
    s = anatomical_setup(_pelvis())
    m = anatomical_frame_model(s)
    direct = [frame.solve(force=tuple(f * np.asarray(s.force_unit)), model=m).max_needle_deflection_mm for f in FORCES]
    assert _step(rec, "frame model, same setup").values_mm == pytest.approx(direct, rel=1e-12)


def test_one_pin_carrying_the_force_roughly_doubles_it_sub_linearly(rec):
    """Two equal pins under a force across their plane each carry F/2, so the one-pin step over the two-pin
    step is w1(F)/w1(F/2): at most 2 (the springs and the rod's rotation stiffen), and not far below."""
    two, one = _step(rec, "frame model, same setup"), _step(rec, "one pin")
    ratio = np.array(one.values_mm) / np.array(two.values_mm)
    assert np.all(ratio <= 2.0 + 1e-9) and np.all(ratio > 1.8)
    # the invariant behind it, on the chain's last frame setup: two pins sharing F = one pin carrying F/2
    half = [frame.solve(force=(0.0, f / 2, 0.0), model=rec_models(rec)["rigid root"]).max_needle_deflection_mm
            for f in FORCES]
    assert _step(rec, "rigid root, two pins").values_mm == pytest.approx(half, rel=1e-6)


def rec_models(rec):
    from needletissue.report.reconcile import chain

    return chain(anatomical_setup(_pelvis()), ritz.RitzModel())[2]


def test_each_step_moves_the_value_the_way_its_change_does(rec):
    steps = {s.name: np.array(s.values_mm) for s in rec.chain + rec.checks}
    # a longer lever (load 66 mm from the bone in the clamp -> 84.18 mm at a bare end) bends more
    assert np.all(steps["paper's free length"] > steps["one pin"])
    # a rigid root is stiffer than the bone foundation it replaces
    assert np.all(steps["rigid root"] < steps["paper's layers"])
    assert np.all(steps["rigid root, two pins"] < steps["bone root, two pins"])
    # the linear beam has no geometric stiffening: above the exact rod at the largest force
    assert steps["Ritz model"][-1] > steps["rigid root"][-1]
    # every value and its distance from the paper are the ones reported
    for s in rec.chain + rec.checks:
        for f, v, p, r in zip(s.forces_N, s.values_mm, s.paper_mm, s.relative_percent):
            assert p == PAPER[f"fe_max_needle_deformation_{f:g}N_mm"].value
            assert r == pytest.approx(100 * (v / p - 1))


def test_ritz_step_is_ritz_run_directly(rec):
    direct = [r.tip_deflection_mm for r in ritz.solve_forces(FORCES, ritz.RitzModel())]
    assert _step(rec, "Ritz model").values_mm == pytest.approx(direct, rel=1e-12)


def test_conclusion_names_the_step_closest_to_the_paper(rec):
    runs = [s for s in rec.chain + rec.checks if s.model != "FE"]
    best = min(runs, key=lambda s: max(abs(r) for r in s.relative_percent))
    assert f"'{best.name}'" in rec.conclusion.split(":")[1]


def test_linear_limit_gives_plus_200_percent_and_elastic_cases_never_more(rec):
    lin = next(c for c in rec.ratio if c.setup.startswith("linear"))
    # k -> 0 leaves the bare cantilever, linear: w = F l^3 / (3 E I) (the cubic trial function is exact)
    m = ritz.RitzModel()
    assert lin.values_mm[0] == pytest.approx(100.0 * m.free_length_mm**3 / (3 * m.bending_stiffness_Nmm2), rel=1e-6)
    # the springs left (1e-6 of Table 1) change the stiffness by ~k T l^3 / (3 EI) of 1e-6: far below 1e-6 %
    assert lin.increase_percent == pytest.approx(200.0, abs=1e-6)
    for c in rec.ratio:
        if c.elastic:
            assert c.increase_percent <= 200.0 + 1e-9, c.setup
    paper_model = next(c for c in rec.ratio if c.model == "ritz" and not c.setup.startswith("linear"))
    assert paper_model.increase_percent < 200.0


def test_a_pin_that_yields_is_super_linear_and_one_that_does_not_is_elastic(rec):
    frames = [c for c in rec.ratio if c.model == "frame"]
    for plastic in (c for c in frames if not c.elastic and c.forces_N == [100.0, 300.0]):
        elastic = next(c for c in frames if c.elastic and c.setup == plastic.setup.replace(" (plastic=True)", ""))
        if elastic.yield_utilisation[1] > 1.0:  # the elastic pin would be past yield at 300 N
            assert plastic.values_mm[1] > elastic.values_mm[1] and plastic.increase_percent > 200.0
        else:
            assert plastic.values_mm == pytest.approx(elastic.values_mm, rel=1e-9)
    assert any(not c.elastic and c.increase_percent > 200.0 for c in frames)


def test_the_load_range_where_a_yielding_pin_gives_the_papers_ratio(rec):
    """Solved for F: the pin is elastic at F and yields before 3F, and the frame model run directly on
    that range gives the paper's +250.08 %."""
    solved = [c for c in rec.ratio if c.forces_N != [100.0, 300.0]]
    steps = {"rigid root": "chain step 'rigid root'", "paper's layers": "chain step 'paper's layers' (bone root)"}
    assert {s for s, name in steps.items() if any(c.setup.startswith(name + " ") for c in solved)} == set(steps)
    for c in solved:
        assert not c.elastic and c.yield_utilisation[0] < 1.0 < c.yield_utilisation[1]
        assert c.forces_N[1] == pytest.approx(3 * c.forces_N[0], rel=1e-12)
        assert c.increase_percent == pytest.approx(250.08, abs=0.05)
        step = next(s for s, name in steps.items() if c.setup.startswith(name + " "))
        m = _with(rec_models(rec)[step], plastic=True)
        w = [frame.solve(force=(0.0, f, 0.0), model=m).max_needle_deflection_mm for f in c.forces_N]
        assert w == pytest.approx(c.values_mm, rel=1e-9)
    assert 100 * (w[1] / w[0] - 1) == pytest.approx(PAPER["ritz_increase_300_vs_100N_percent"].value, abs=0.05)


def test_every_row_that_differs_gets_a_measured_reason(rec):
    data = _pelvis()
    data["thickness"] = [{"needle": "needle_2", "muscle_mm": 19.0, "adipose_mm": 15.5, "total_mm": 37.75,
                          "layers": [{"tissue": "void", "from_mm": 0.25, "to_mm": 3.5},
                                     {"tissue": "adipose", "from_mm": 3.5, "to_mm": 38.0}]}]
    for p in data["ritz"]["per_needle"]:
        p["max_deflection_mm"] = [0.0, 0.0, 11.0]
        p["max_deflection_half_force_mm"] = [0.0, 0.0, 5.5]
    fe = _step(rec, "anatomical FE (this run)").values_mm
    rows = [Comparison("FE max needle deformation at 300 N", fe[-1], "mm", "fe_max_needle_deformation_300N_mm"),
            Comparison("|FE - theory| difference at 300 N", 5.0, "mm", "theory_fe_difference_300N_mm"),
            Comparison("Adipose max deformation at 300 N", 2.0, "mm", "adipose_max_deformation_300N_mm"),
            Comparison("Ritz increase", 199.0, "%", "ritz_increase_300_vs_100N_percent"),
            Comparison("Soft tissue along needle_2", 37.75, "mm", "soft_tissue_thickness_mean_mm",
                       tolerance_percent=17.0),
            Comparison("Ritz tip deflection at 300 N", 17.63, "mm", "ritz_tip_deflection_300N_mm")]
    reasons = row_reasons(rows, rec, data)
    assert set(reasons) == {c.quantity for c in rows if c.verdict.startswith("differs")} and len(reasons) == 5
    one = _step(rec, "one pin").values_mm[-1]
    assert f"{one:.2f} mm" in reasons["FE max needle deformation at 300 N"]  # the chain's numbers, quoted
    assert f"|FE - theory| = {abs(fe[-1] - 5.5):.2f} mm" in reasons["|FE - theory| difference at 300 N"]
    assert "without it 34.5 mm" in reasons["Soft tissue along needle_2"]
    # and the pipeline: a differing row without a measurement says so; agreeing rows get none
    lone = Comparison("Adipose max deformation at 300 N (other)", 2.0, "mm", "adipose_max_deformation_300N_mm")
    ok = Comparison("Ritz tip deflection at 300 N", 17.63, "mm", "ritz_tip_deflection_300N_mm")
    out = [StageOutcome("a", "A", "ok", 0.0, result=StageResult(None, comparisons=rows + [lone, ok])),
           StageOutcome("reconciliation", "R", "ok", 0.0, result=StageResult(rec, reasons=reasons))]
    _attach_reasons(out)
    assert all(c.reason for c in rows if c.verdict.startswith("differs"))
    assert lone.reason == NO_REASON and ok.reason == ""


def test_reproduce_writes_the_reconciliation_without_the_anatomical_model(tmp_path):
    """Without the anatomical run the chain is left out (said so) and the ratio is still reconciled."""
    cfg = load_config(overrides={"traction": {"enabled": False}, "needle_fe": {"enabled": False},
                                 "pelvis": {"enabled": "off"}, "materials": {"enabled": False}})
    out = tmp_path / "res"
    assert run_reproduce(cfg, out, stage_list(), progress=False).ok
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    rec = data["reconciliation"]
    assert rec["chain"] == [] and "did not run" in rec["chain_note"]
    ritz_row = next(c for c in rec["ratio_300_vs_100N"] if c["model"] == "ritz" and c["setup"].startswith("the paper"))
    direct = ritz.solve_forces([100.0, 300.0], ritz_model(cfg), order=cfg.ritz.order)
    assert ritz_row["values_mm"] == pytest.approx([r.tip_deflection_mm for r in direct], rel=1e-12)
    row = next(c for c in data["comparison_with_paper"] if c["quantity"].startswith("Ritz tip deflection increase"))
    assert row["verdict"].startswith("differs") and row["reason"].startswith("measured")
    assert all(c["reason"] for c in data["comparison_with_paper"] if c["verdict"].startswith("differs"))
    md = (out / "comparison.md").read_text(encoding="utf-8")
    assert "**Reconciliation.**" in md and "+250.08 %" in md
    assert "id='reconciliation'" in (out / "report.html").read_text(encoding="utf-8")


@pytest.mark.browser
def test_reconciliation_tables_fit_a_phone(tmp_path, rec):
    """The report with the reconciliation does not scroll sideways at 390 px."""
    from test_viewer import open_in_browser

    from needletissue.report.html import reconciliation_html

    page = tmp_path / "rec.html"
    page.write_text("<!doctype html><html><head><meta charset='utf-8'><meta name='viewport' "
                    "content='width=device-width, initial-scale=1'><style>"
                    + __import__("needletissue.report.html", fromlist=["_CSS"])._CSS
                    + "</style></head><body>" + reconciliation_html(rec.to_json()) + "</body></html>",
                    encoding="utf-8")
    with open_in_browser(page, width=390) as (p, errors):
        assert p.evaluate("document.documentElement.scrollWidth") <= 390, "scrolls sideways"
        # and the tables themselves fit: nothing hidden in a table's own scroll box
        assert p.evaluate("Math.max(...[...document.querySelectorAll('table')].map(t => t.scrollWidth - "
                          "t.clientWidth))") <= 1
        assert not errors
