"""`needletissue materials list|curve|fit`: the JSON contract, warnings, errors with exit code 2."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from needletissue.cli import app, main
from needletissue import materials
from needletissue.materials import closed_form as cf
from needletissue.materials import stability

runner = CliRunner()


def cli(*args, env=None):
    """A real process through the entry point (InputError -> exit 2 is handled in main())."""
    return subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *args],
                          capture_output=True, text=True, timeout=120, env={**os.environ, **(env or {})})


def run_main(monkeypatch, capsys, *args):
    """The same entry point in this process (faster): returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["needletissue", *args])
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


def test_list_json_has_the_registry_and_stable_ranges():
    r = runner.invoke(app, ["materials", "list", "--json"])
    assert r.exit_code == 0, r.output
    rows = {row["name"]: row for row in json.loads(r.stdout)}
    assert set(rows) >= {"muscle", "adipose", "cortical_bone", "cancellous_bone", "needle", "clamp"}
    assert rows["muscle"]["initial_shear_modulus_MPa"] == pytest.approx(2 * (0.08556 - 0.05841))
    for name in ("muscle", "adipose"):
        m = materials.get(name)
        assert rows[name]["stable_range"] == {mode: list(stability.stable_range(m.model, m.parameters, mode))
                                              for mode in cf.MODES}


@pytest.mark.parametrize("stretch_max", [1.5, 0.8])
def test_curve_json_contract(stretch_max):
    r = runner.invoke(app, ["materials", "curve", "muscle", "--mode", "biaxial", "--stretch-max",
                            str(stretch_max), "--points", "11", "--json"])
    assert r.exit_code == 0, r.output
    d = json.loads(r.stdout)
    assert list(d) == ["material", "model", "parameters", "mode", "stretch", "nominal_stress_MPa", "stable_range"]
    assert d["material"] == "muscle" and d["model"] == "mooney_rivlin_5" and d["mode"] == "biaxial"
    s = np.array(d["stretch"])
    assert s[0] == 1.0 and s[-1] == stretch_max and s.size == 11
    np.testing.assert_allclose(d["nominal_stress_MPa"],
                               cf.nominal_stress("mooney_rivlin_5", d["parameters"], "biaxial", s), rtol=1e-15)
    assert d["stable_range"] == list(stability.stable_range("mooney_rivlin_5", d["parameters"], "biaxial"))


def test_curve_outside_stable_range_warns_on_stderr_and_writes_plot(tmp_path, monkeypatch, capsys):
    png = tmp_path / "c.png"
    code, out, err = run_main(monkeypatch, capsys, "materials", "curve", "muscle", "--stretch-max", "1.5",
                              "--points", "5", "--json", "--plot", str(png))
    assert code == 0, err
    json.loads(out)  # warnings stay off stdout
    assert "warning" in err and "not Drucker-stable" in err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_user_materials_from_toml_and_env(tmp_path, monkeypatch, capsys):
    toml = tmp_path / "mine.toml"
    toml.write_text('[my_fat]\nmodel = "ogden"\nparameters = { mu = [0.002], alpha = [12.0] }\n'
                    'density = 0.9\nsource = "test"\n')
    monkeypatch.setenv("NEEDLETISSUE_MATERIALS", str(toml))
    code, out, err = run_main(monkeypatch, capsys, "materials", "curve", "my_fat", "--points", "3", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["parameters"] == {"mu": [0.002], "alpha": [12.0]}
    np.testing.assert_allclose(d["nominal_stress_MPa"], cf.nominal_stress("ogden", d["parameters"], "uniaxial",
                                                                          d["stretch"]), rtol=1e-15)


def test_fit_cli_json(tmp_path):
    lam = np.linspace(1.0, 1.4, 15)
    P = cf.nominal_stress("yeoh", dict(C10=0.1, C20=0.02, C30=0.001), "uniaxial", lam)
    csv = tmp_path / "d.csv"
    csv.write_text("stretch,nominal_stress_MPa\n" + "\n".join(f"{a!r},{b!r}" for a, b in zip(lam.tolist(),
                                                                                                P.tolist())))
    png = tmp_path / "fit.png"
    r = runner.invoke(app, ["materials", "fit", str(csv), "--model", "yeoh", "--mode", "uniaxial", "--json",
                            "--plot", str(png)])
    assert r.exit_code == 0, r.output
    assert png.read_bytes()[:4] == b"\x89PNG"
    d = json.loads(r.stdout)
    assert d["parameters"]["C20"] == pytest.approx(0.02, rel=1e-6)
    assert d["r2"] == pytest.approx(1.0, abs=1e-12) and d["stable_range"][1] > 1.4


@pytest.mark.parametrize("args,expect", [
    (["materials", "curve", "skin"], "known: muscle, adipose"),
    (["materials", "curve", "muscle", "--stretch-max", "0"], "stretch_max"),
    (["materials", "fit", "nofile.csv", "--model", "foo"], "known: neo_hooke"),
])
def test_errors_exit_2_without_traceback(args, expect, monkeypatch, capsys):
    code, out, err = run_main(monkeypatch, capsys, *args)
    assert code == 2
    assert expect in " ".join(err.split()) and "Traceback" not in err


def test_bad_csv_exit_2_names_line_and_field(tmp_path):
    csv = tmp_path / "bad.csv"
    csv.write_text("stretch,nominal_stress_MPa\n1.0,0\n1.1,oops\n")
    r = cli("materials", "fit", str(csv), "--model", "neo_hooke")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    err = " ".join(r.stderr.split())  # rich wraps long lines
    assert "bad.csv" in err and "line 3" in err and "nominal_stress_MPa" in err
