"""`needletissue ritz` CLI: the JSON contract, --plot files, calibrate, bad input -> exit code 2."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from needletissue import ritz
from needletissue.cli import app
from needletissue.errors import InputError

RESULT_KEYS = {"force_N", "tip_deflection_mm", "load_point_deflection_mm", "max_deflection_mm",
               "tip_slope_rad", "coefficients", "order", "iterations", "converged", "order_converged",
               "newton_converged", "error_estimate_mm", "deflection_to_free_length", "within_validity_range"}


def _cli(*args):
    env = dict(os.environ, PYTHONPATH=str(Path(ritz.__file__).parents[2]), MPLBACKEND="Agg")
    return subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *args],
                          capture_output=True, text=True, env=env, timeout=120)


def test_json_contract_and_values():
    r = CliRunner().invoke(app, ["ritz", "--force", "100", "--force", "-300", "--diameter", "5.5",
                                 "--free-length", "90", "--layer", "muscle:20:0.05", "--layer", "fat:12:0.02",
                                 "--order", "auto", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert set(out) == {"model", "results"}
    m = out["model"]
    assert m["diameter_mm"] == 5.5 and m["free_length_mm"] == 90 and m["load_point_mm"] == 90
    assert [la["name"] for la in m["layers"]] == ["muscle", "fat"] and m["cos_term"] is True
    assert [set(x) for x in out["results"]] == [RESULT_KEYS, RESULT_KEYS]
    model = ritz.RitzModel(diameter_mm=5.5, free_length_mm=90.0,
                           layers=(ritz.Layer("muscle", 20, 0.05), ritz.Layer("fat", 12, 0.02)))
    for x, F in zip(out["results"], (100.0, -300.0)):
        assert x == ritz.solve(F, model, order="auto").to_json()


def test_no_cos_and_order(tmp_path):
    r = CliRunner().invoke(app, ["ritz", "--force", "300", "--no-cos", "--order", "7", "--json",
                                 "--load-point", "60"])
    out = json.loads(r.output)
    assert out["model"]["cos_term"] is False and out["model"]["load_point_mm"] == 60
    assert out["results"][0]["order"] == 7 and len(out["results"][0]["coefficients"]) == 6
    want = ritz.solve(300.0, ritz.RitzModel(cos_term=False, load_point_mm=60.0), order=7)
    assert out["results"][0]["tip_deflection_mm"] == want.tip_deflection_mm


def test_plot_writes_figure_and_run_files(tmp_path):
    png = tmp_path / "fig5.png"
    r = CliRunner().invoke(app, ["ritz", "--force", "100", "--force", "200", "--force", "300", "--plot", str(png)])
    assert r.exit_code == 0, r.output
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for f in ("config.toml", "versions.json", "results.json"):
        assert (tmp_path / f).is_file()
    assert len(json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))["results"]) == 3


def test_calibrate_cli_round_trip():
    w = ritz.solve(300.0, ritz.RitzModel(free_length_mm=100.0)).tip_deflection_mm
    r = CliRunner().invoke(app, ["ritz", "calibrate", "--parameter", "free-length", "--force", "300",
                                 "--deflection", str(w), "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)
    assert out["value"] == pytest.approx(100.0, rel=1e-8) and out["unit"] == "mm"
    r = CliRunner().invoke(app, ["ritz", "calibrate", "--parameter", "force", "--deflection", str(-w),
                                 "--free-length", "100", "--json"])
    assert json.loads(r.output)["value"] == pytest.approx(-300.0, rel=1e-8)


@pytest.mark.parametrize("args,field", [
    (["--force", "100", "--diameter", "0"], "diameter_mm"),
    (["--force", "100", "--youngs-modulus", "nan"], "youngs_modulus_MPa"),
    (["--force", "100", "--layer", "muscle:90:0.05"], "layers"),
    (["--force", "100", "--load-point", "85"], "load_point_mm"),
    (["--force", "100", "--order", "2"], "order"),
    (["--force", "100", "--layer", "muscle:-1:0.05"], "thickness_mm"),
])
def test_bad_input_names_field(args, field):
    r = CliRunner().invoke(app, ["ritz", *args])
    assert isinstance(r.exception, InputError) and field in str(r.exception)  # main() maps it to exit 2


def test_bad_input_exit_code_2_without_traceback():
    p = _cli("ritz", "--force", "100", "--diameter", "-5")
    assert p.returncode == 2 and "diameter_mm" in p.stderr and "> 0" in p.stderr
    assert "Traceback" not in p.stderr


@pytest.mark.parametrize("args", [["ritz", "--help"], ["ritz", "calibrate", "--help"]])
def test_help_states_units(args):
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0 and "mm" in r.output


def test_missing_force_is_input_error():
    r = CliRunner().invoke(app, ["ritz"])
    assert isinstance(r.exception, InputError) and "--force" in str(r.exception)


def test_plot_deflection_accepts_batch_and_axes(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    b = ritz.solve_batch([100.0, 200.0, 300.0], parallel=False)
    fig, ax = plt.subplots()
    out = ritz.plot_deflection(b, ax=ax, model=ritz.RitzModel())
    assert out is fig and len(ax.lines) == 3 + 1  # three forces and the zero line
    top = max(float(np.max(line.get_ydata())) for line in ax.lines)
    assert top == pytest.approx(b.tip_deflection_mm.max(), rel=1e-12)
    plt.close(fig)


def test_unwritable_plot_path_is_input_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    r = CliRunner().invoke(app, ["ritz", "--force", "100", "--plot", str(blocker / "fig5.png")])
    assert isinstance(r.exception, InputError) and str(blocker) in str(r.exception)


def test_error_line_prints_the_message_verbatim(monkeypatch, capsys):
    """Rich must not read ':b:' as an emoji code or '[...]' as markup, nor wrap a long message (a path)."""
    from needletissue.cli import main

    text = "a:b:c[/x]" + "y" * 120
    monkeypatch.setattr(sys, "argv", ["needletissue", "ritz", "--force", "1", "--layer", text])
    with pytest.raises(SystemExit) as e:
        main()
    err = capsys.readouterr().err
    assert e.value.code == 2 and f"'{text}'" in err and err.count("\n") == 1


def test_order_convergence_is_not_read_as_a_failed_solve():
    """The paper's cubic at 300 N: Newton converged, the order p = 3 is not (estimate 3.7e-3 mm > 1e-4):
    JSON says which is which (`converged` kept as the old name), the table says Newton ok."""
    r = CliRunner().invoke(app, ["ritz", "--force", "300", "--json"])
    x = json.loads(r.output)["results"][0]
    assert x["newton_converged"] is True
    assert x["order_converged"] is x["converged"] is (x["error_estimate_mm"] <= 1e-4) is False
    assert ritz.solve(300.0, ritz.RitzModel()).order_converged is False
    t = CliRunner().invoke(app, ["ritz", "--force", "300"], env={"COLUMNS": "120"}).output
    assert "Newton" in t and "ok (" in t and "p ok" in t and "the solve converged" in t


def test_one_force_range_and_the_validity_range():
    """|F| > 2000 N is refused by every model and command alike (one line naming --force, exit 2, nothing
    written); within it, a Ritz answer beyond |v|max / l = 0.25 (small rotations) comes with a warning."""
    from needletissue.errors import FORCE_LIMIT_N
    from needletissue.models.needle import NeedleModelConfig
    from needletissue.models.pelvis import PelvisConfig
    from needletissue.report.config import load_config

    for args in (["ritz", "--force", "1e6"], ["fe", "needle", "--force", "2500"], ["fe", "pelvis", "--force", "3000"]):
        r = _cli(*args)
        assert r.returncode == 2 and r.stderr.startswith("error: ") and "force" in r.stderr, r.stderr
        assert f"{FORCE_LIMIT_N:g} N" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    for make in (lambda: NeedleModelConfig(forces=(2001.0,)), lambda: PelvisConfig(forces=[2001.0])):
        with pytest.raises(InputError, match="2000 N"):
            make()
    with pytest.raises(InputError, match="2000"):
        load_config(overrides={"ritz": {"forces_N": [2001.0]}})
    for args in (["ritz", "--help"], ["fe", "needle", "--help"], ["fe", "pelvis", "--help"]):
        assert "2000 N" in CliRunner().invoke(app, args, env={"COLUMNS": "200"}).output
    r = _cli("ritz", "--force", "300", "--force", "500", "--json")
    x = {v["force_N"]: v for v in json.loads(r.stdout)["results"]}
    assert x[300.0]["within_validity_range"] and not x[500.0]["within_validity_range"]
    assert x[500.0]["deflection_to_free_length"] == pytest.approx(x[500.0]["max_deflection_mm"] / 84.18)
    assert r.returncode == 0 and r.stderr.startswith("warning: --force 500 N") and "0.25" in r.stderr


def test_written_config_is_accepted_back(tmp_path):
    """`ritz --plot` writes config.toml (model, order, forces); `ritz --config` solves the same again, and
    options typed on the command line override the file."""
    args = ["--force", "100", "--force", "250", "--diameter", "5.5", "--layer", "m:20:0.05", "--layer", "f:12:0.02",
            "--order", "auto", "--no-cos"]
    first = CliRunner().invoke(app, ["ritz", *args, "--plot", str(tmp_path / "f.png"), "--json"])
    assert first.exit_code == 0, first.output
    again = CliRunner().invoke(app, ["ritz", "--config", str(tmp_path / "config.toml"), "--json"])
    assert again.exit_code == 0, again.output
    assert json.loads(again.stdout) == json.loads(first.stdout)
    other = json.loads(CliRunner().invoke(app, ["ritz", "--config", str(tmp_path / "config.toml"), "--force", "10",
                                                "--json"]).stdout)
    assert [r["force_N"] for r in other["results"]] == [10.0] and other["model"]["diameter_mm"] == 5.5
    assert other["model"]["cos_term"] is False
    bad = tmp_path / "bad.toml"
    bad.write_text("diameter_mm = 5.0\ncolour = 'red'\n")
    r = CliRunner().invoke(app, ["ritz", "--config", str(bad)])
    assert isinstance(r.exception, InputError) and "colour" in str(r.exception)
