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
