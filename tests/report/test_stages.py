"""The real stages: numbers in results.json and the report are the engines' own, and the comparison
table uses the paper's published values."""

import json

import pytest

from needletissue import ritz
from needletissue.report.config import load_config
from needletissue.report.pipeline import run_reproduce
from needletissue.report.stages import ritz_model, stage_list

QUICK = {"traction": {"enabled": False}, "needle_fe": {"enabled": False}, "pelvis": {"enabled": "off"}}


def test_ritz_and_materials_stages(tmp_path):
    cfg = load_config(overrides=QUICK)
    out = tmp_path / "res"
    res = run_reproduce(cfg, out, stage_list(), progress=False)
    assert res.ok
    data = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert data["stages"]["traction"]["status"] == "skipped"
    direct = ritz.solve_forces([300.0], ritz_model(cfg), order=cfg.ritz.order)[0]
    row = next(c for c in data["comparison_with_paper"] if c["quantity"].startswith("Ritz tip deflection at 300 N ("))
    # labelled with what it is (like for like with the paper's Ritz number), and read against it
    assert "1 needle carrying the force, free length 84.18 mm" in row["quantity"]
    assert row["verdict"] == "agrees (within 5 %)"
    assert row["ours"] == pytest.approx(direct.tip_deflection_mm, rel=1e-12)
    assert row["paper"] == 17.63 and row["difference"] == pytest.approx(direct.tip_deflection_mm - 17.63)
    for name in ("materials", "ritz"):
        for fig in data["stages"][name]["figures"]:
            assert (out / fig).stat().st_size > 1000
    html = (out / "report.html").read_text(encoding="utf-8")
    assert html.count("data:image/png;base64,") >= 2


def test_mesh_converged_limits_of_the_anatomical_model():
    """The stored convergence study (benchmarks/pelvis_mesh_convergence.py): a coarser mesh is stiffer, so the
    max needle deformation grows as the mesh is refined and its Richardson limit lies above the finest level,
    at an observed order between 1 and 3 (tetra10, tissue boundaries by centroid); the limits apply only to a
    run that is one of the study's levels."""
    import json
    from importlib.resources import files

    from needletissue.report.stages import mesh_converged_limits

    study = json.loads(files("needletissue").joinpath("data/pelvis_convergence.json").read_text())
    lim = mesh_converged_limits("ct", None, None, 4.0)
    assert sorted(lim) == [100.0, 200.0, 300.0]
    for i, F in enumerate(sorted(lim)):
        levels = [r["results"][i]["max_needle_deformation_mm"] for r in study["runs"]]
        assert study["runs"][0]["results"][i]["force_N"] == F
        assert levels[0] < levels[1] < levels[2] < lim[F]["limit_mm"] < 1.1 * levels[2]
        assert 1.0 < lim[F]["order"] < 3.0
    for args in (("ct", "my_ct.nii.gz", None, 4.0), ("ssm", None, None, 4.0), ("ct", None, None, 3.5)):
        assert mesh_converged_limits(*args) is None


def test_frame_beside_the_pelvis_against_the_mesh_converged_fe():
    """With the limits, one more row per force: |frame - FE limit| with the same goal as the demo-mesh row."""
    from needletissue.report.stages import _frame_beside_pelvis
    from test_reconcile import _pelvis

    data = _pelvis()
    lim = {F: {"limit_mm": 1.05 * r["max_needle_deformation_mm"], "order": 1.8, "sizes_mm": [4.0, 3.0, 2.25]}
           for F, r in zip((100.0, 200.0, 300.0), data["results"])}
    comps = []
    out = _frame_beside_pelvis(data, comps, lim)
    conv = [c for c in comps if "mesh-converged" in c.quantity]
    assert len(conv) == 3 and len(comps) == 6
    for c, o in zip(conv, out):
        assert c.ours == pytest.approx(abs(o["frame_max_needle_deflection_mm"] - o["fe_mesh_converged_mm"]), rel=1e-12)
        assert o["fe_mesh_converged_mm"] == pytest.approx(1.05 * o["fe_max_needle_deformation_mm"], rel=1e-12)
    comps = []
    _frame_beside_pelvis(data, comps)
    assert not [c for c in comps if "mesh-converged" in c.quantity]
