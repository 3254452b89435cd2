"""`needletissue frame` CLI and the API around it: the JSON contract, bad input -> exit 2, compensate,
calibrate."""

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from needletissue import frame
from needletissue.cli import app
from needletissue.frame import FrameModel

RESULT_KEYS = {"force_N", "moment_Nmm", "clamp_displacement_mm", "clamp_rotation_rad", "max_needle_deflection_mm",
               "needle_yield_utilisation", "needles", "iterations", "error_estimate_mm"}
NEEDLE_KEYS = {"root_slope_rad", "max_deflection_mm", "curve"}


def test_json_contract_bare_cantilever_and_values():
    r = CliRunner().invoke(app, ["frame", "--needles", "1", "--root", "rigid", "--no-tissue", "--clamp-length", "0",
                                 "--free-length", "84", "--force", "0,300,0", "--force", "0,-100,0", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert set(out) == {"model", "results"}
    assert len(out["results"]) == 2
    for x in out["results"]:
        assert RESULT_KEYS <= set(x)
        assert all(len(x[k]) == 3 for k in ("force_N", "moment_Nmm", "clamp_displacement_mm", "clamp_rotation_rad"))
        assert NEEDLE_KEYS <= set(x["needles"][0]) and len(x["needles"]) == 1
    m = out["model"]
    assert m["needles"] == 1 and m["root"] == "rigid" and m["tissue"] is False and m["load_point_mm"] == [0, 0, 84]
    want = frame.solve((0, 300, 0), model=FrameModel(needles=1, root="rigid", tissue=False, clamp_length_mm=0,
                                                     free_length_mm=84))
    assert out["results"][0]["clamp_displacement_mm"] == list(want.clamp_displacement_mm)


def test_defaults_two_needles_with_moment_and_plot(tmp_path):
    png = tmp_path / "frame.png"
    r = CliRunner().invoke(app, ["frame", "--force", "100,50,0", "--moment", "0,0,2000", "--layer", "muscle:20:0.05",
                                 "--json", "--plot", str(png)])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert out["results"][0]["moment_Nmm"] == [0, 0, 2000] and len(out["results"][0]["needles"]) == 2
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert all((tmp_path / f).is_file() for f in ("config.toml", "versions.json", "results.json"))


BAD = [
    (["--diameter", "0"], "diameter_mm"), (["--spacing", "4"], "spacing_mm"), (["--depth", "1"], "depth_mm"),
    (["--load-point", "0,0,300"], "load_point_mm"), (["--force", "0,nan,0"], "force_N"),
    (["--force", "1,2"], "--force"), (["--needles", "5"], "needles"), (["--youngs-modulus", "-1"], "youngs_modulus_MPa"),
    (["--root", "glue"], "root"), (["--force", "0,1e6,0"], "force_N"), (["--layer", "m:-2:0.1"], "thickness_mm"),
    (["--cortex", "inf"], "cortex_mm"),
]


@pytest.mark.parametrize("args,field", BAD)
def test_bad_input_is_an_input_error_naming_the_field(args, field):
    from needletissue.errors import InputError

    r = CliRunner().invoke(app, ["frame", *args])
    assert isinstance(r.exception, InputError), r.output
    assert field in str(r.exception)


@pytest.mark.parametrize("args,field", [BAD[1], BAD[4]])
def test_bad_input_exit_2_one_line(args, field):
    """Through the console entry point: exit code 2, one line naming the field, no traceback."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, PYTHONPATH=str(Path(frame.__file__).parents[2]), MPLBACKEND="Agg")
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "frame", *args],
                       capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 2, p.stderr
    assert field in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_compensate_reaches_the_target():
    """Command the clamp, then solve forward from the command: the bone lands on its target."""
    m = FrameModel()
    t, rot, F = np.array([1.0, 5.0, -2.0]), np.array([0.02, -0.01, 0.03]), np.array([30.0, 250.0, 10.0])
    for frame_name in ("world", "clamp"):
        c = frame.compensate(t, rot, F, (0, 0, 500.0), m, wrench_frame=frame_name)
        assert np.abs(c.residual_mm).max() < 1e-6 and np.abs(c.residual_rad).max() < 1e-9
        # independent forward check: bone pose implied by the commanded clamp pose and the deflection
        from needletissue.frame.solver import expm, logm

        R_cmd = expm(c.clamp_rotation_rad)
        R_b = expm(rot)
        Q = R_b.T @ R_cmd                        # clamp relative to bone
        W = R_b.T @ F if frame_name == "world" else Q @ F
        Mw = R_b.T @ np.array([0, 0, 500.0]) if frame_name == "world" else Q @ np.array([0, 0, 500.0])
        r = frame.solve(W, Mw, m)
        assert np.allclose(logm(expm(r.clamp_rotation_rad)), logm(Q), atol=1e-7)
        B, C = np.array([0, 0, 0.0]), np.array(m.clamp_centre_mm)
        C_cmd = C + np.array(c.clamp_displacement_mm)
        B_pred = C_cmd - R_b @ (C + np.array(r.clamp_displacement_mm) - B)
        assert np.allclose(B_pred, B + t, atol=1e-6)
    # no load: the rigid answer; the correction grows with the force
    c0 = frame.compensate(t, rot, (0, 0, 0), model=m)
    assert np.abs(c0.correction_mm).max() < 1e-12
    assert np.linalg.norm(frame.compensate(t, rot, 2 * F, model=m).correction_mm) > \
        np.linalg.norm(frame.compensate(t, rot, F, model=m).correction_mm)


@pytest.mark.parametrize("args", [["frame"], ["frame", "compensate"]])
def test_help(args):
    r = CliRunner().invoke(app, [*args, "--help"])
    assert r.exit_code == 0 and "Usage" in r.output


def test_compensate_cli():
    r = CliRunner().invoke(app, ["frame", "compensate", "--target", "0,5,0", "--force", "0,200,0", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.stdout)
    assert {"clamp_displacement_mm", "clamp_rotation_rad", "residual_mm", "result"} <= set(out)


def test_calibrate_recovers_known_factors():
    """Synthetic data from known factors + noise: the fit recovers them inside its 95 % intervals."""
    from needletissue.frame.fitting import CalibrationPoint, calibration

    truth = dict(foundation_factor=2.0, tissue_factor=3.0)
    rng = np.random.default_rng(1)
    pts = []
    for n, F in ((1, 100.0), (1, 250.0), (2, 150.0), (2, 300.0)):
        base = FrameModel(needles=n)
        r = frame.solve((0, F, 0), model=base.replace(**truth), error_estimate=False)
        noisy = np.array(r.clamp_displacement_mm) + rng.normal(0, 0.01, 3)
        pts.append(CalibrationPoint(base, (0, F, 0), clamp_displacement_mm=tuple(noisy),
                                    max_needle_deflection_mm=r.max_needle_deflection_mm + rng.normal(0, 0.01)))
    c = calibration(pts)
    for k, v in truth.items():
        lo, hi = c.intervals[k]
        assert lo < v < hi and abs(c.params[k] - v) / v < 0.2
    assert c.rms_mm < 0.03
    params, ci = frame.calibrate(pts)
    assert params == c.params and math.isfinite(ci["tissue_factor"][1])
