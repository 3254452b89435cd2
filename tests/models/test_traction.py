"""Traction validation (paper Sec. 3.2, Eq. 16) and its CLI."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from needletissue.models import traction as tr


def test_theory_matches_independent_closed_forms():
    lam = np.linspace(1.0, 1.6, 13)
    # adipose: paper Eq. 7, nominal stress of W = 2 mu / alpha^2 sum(l_i^alpha - 3)
    mu, a = 1.1667e-3, 16.2
    eq7 = 2 * mu / a * (lam ** (a - 1) - lam ** (-a / 2 - 1))
    np.testing.assert_allclose(tr.theory_nominal_stress("adipose", lam), eq7, rtol=1e-6, atol=1e-14)  # FElupe perturbs equal eigenvalues
    # muscle: P = 2 (l - l^-2) (W1 + W2 / l) for the 5-parameter Mooney-Rivlin energy
    C10, C01, C20, C11, C02 = 0.08556, -0.05841, 0.03900, -0.02320, 0.00851
    a1, a2 = lam**2 + 2 / lam - 3, 2 * lam + lam**-2 - 3
    W1 = C10 + 2 * C20 * a1 + C11 * a2
    W2 = C01 + C11 * a1 + 2 * C02 * a2
    np.testing.assert_allclose(tr.theory_nominal_stress("muscle", lam), 2 * (lam - lam**-2) * (W1 + W2 / lam),
                               rtol=1e-6, atol=1e-14)  # FElupe perturbs equal eigenvalues


@pytest.mark.parametrize("material", ["muscle", "adipose"])
def test_fe_material_energy_matches_closed_form(material):
    """The FElupe energy the FE solves with (tensortrax) gives the theory's incompressible curve."""
    import felupe as fem

    from needletissue import materials

    lam = np.linspace(1.05, 1.6, 12)
    _, P, _ = fem.ViewMaterialIncompressible(materials.get(material).isochoric()).uniaxial(lam)
    np.testing.assert_allclose(P, tr.theory_nominal_stress(material, lam), rtol=1e-6)


@pytest.mark.parametrize("material", ["muscle", "adipose"])
def test_rmse_far_below_paper_and_converges_with_bulk(material):
    """Laterally free block: homogeneous, so any mesh is exact and the only error is compressibility,
    O(mu/K). Ten times K -> ten times smaller RMSE."""
    r1 = tr.run(tr.TractionConfig(material=material, elements=1))  # default K = 1e4 mu0
    r2 = tr.run(tr.TractionConfig(material=material, elements=1, bulk_ratio=1e5))
    assert r1.config["bulk_ratio"] == 1e4
    assert len(r1.displacement_mm) >= 11 and r1.displacement_mm[-1] == 10.0
    assert r1.rmse_MPa < 0.05 and r1.rmse_MPa < r1.paper_rmse_MPa / 10
    assert r1.rmse_MPa / r2.rmse_MPa == pytest.approx(10.0, rel=0.1)
    # nearly incompressible tissue is softer in tension than the incompressible limit
    assert np.all(np.array(r2.fe_nominal_stress_MPa[1:]) < np.array(r2.theory_nominal_stress_MPa[1:]))


def test_cli_json_and_plot(tmp_path):
    from needletissue.cli import app

    png = tmp_path / "f.png"
    res = CliRunner().invoke(app, ["validate", "traction", "--material", "adipose", "--json", "--plot", str(png),
                                   "--elements", "1", "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    d = json.loads(res.stdout)
    for key in ("material", "displacement_mm", "fe_nominal_stress_MPa", "theory_nominal_stress_MPa", "rmse_MPa"):
        assert key in d
    assert d["material"] == "adipose" and len(d["fe_nominal_stress_MPa"]) == len(d["displacement_mm"]) >= 11
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "run" / "results.json").read_text(encoding="utf-8"))["rmse_MPa"] == d["rmse_MPa"]
    # without --out the run files go next to the figure
    res2 = CliRunner().invoke(app, ["validate", "traction", "--material", "muscle", "--elements", "1",
                                    "--plot", str(tmp_path / "fig" / "m.png")])
    assert res2.exit_code == 0, res2.output
    assert {p.name for p in (tmp_path / "fig").iterdir()} >= {"m.png", "config.toml", "versions.json", "results.json"}
    bad = CliRunner().invoke(app, ["validate", "traction", "--material", "bone"])
    assert bad.exit_code != 0


def test_a_failed_validation_exits_non_zero(tmp_path):
    """Clamped ends on a squat block (40 mm wide, 10 mm high) bulge: the homogeneous closed form
    does not hold, the RMSE is far above 0.05 MPa, and the command says so by its exit code too, after
    writing and printing its results."""
    from needletissue.cli import app

    res = CliRunner().invoke(app, ["validate", "traction", "--material", "muscle", "--ends", "clamped",
                                   "--height", "10", "--width", "40", "--elements", "2", "--points", "3",
                                   "--json", "--out", str(tmp_path)])
    data = json.loads(res.stdout)
    assert data["passed"] is False and data["rmse_MPa"] > data["criterion_MPa"]
    assert res.exit_code == 1 and (tmp_path / "results.json").is_file()
