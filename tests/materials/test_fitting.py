"""Fitting recovers known parameters from synthetic closed-form data; bad CSVs name file, line and field."""

import numpy as np
import pytest

from needletissue import materials
from needletissue.errors import InputError
from needletissue.materials import closed_form as cf
from needletissue.materials import fitting, stability

LAM = np.linspace(0.75, 1.6, 30)
TRUE = {
    "neo_hooke": dict(mu=0.3),
    "mooney_rivlin": dict(C10=0.2, C01=0.05),
    "mooney_rivlin_5": dict(materials.get("muscle").parameters),
    "yeoh": dict(C10=0.1, C20=-0.01, C30=0.002),
    "ogden": dict(materials.get("adipose").parameters),
    "ogden2": dict(mu=[0.2, 0.01], alpha=[1.5, 6.0]),
    "ogden3": dict(mu=[0.1, 0.2, 0.003], alpha=[-3.0, 1.5, 9.0]),
}
IDENTIFIABLE = [(m, mode) for m in TRUE for mode in cf.MODES
                if not (mode == "planar" and m in ("mooney_rivlin", "mooney_rivlin_5"))]


def synthetic(model, mode, lam=LAM):
    law, _ = fitting.fit_model(model)
    return fitting.StressData(lam, cf.nominal_stress(law, TRUE[model], mode, lam), "synthetic")


@pytest.mark.filterwarnings("ignore::needletissue.materials.stability.UnstableMaterialWarning")
@pytest.mark.parametrize("model,mode", IDENTIFIABLE)
def test_recovers_known_parameters(model, mode):
    true = TRUE[model]
    if mode == "planar" and model.startswith("ogden"):
        a = np.abs(true["alpha"])  # planar sees only |alpha|; terms come back sorted by alpha
        true = {"mu": np.array(true["mu"])[np.argsort(a)], "alpha": np.sort(a)}
    r = fitting.fit(synthetic(model, mode), model, mode)
    for k, v in true.items():
        np.testing.assert_allclose(r.parameters[k], v, rtol=1e-6, err_msg=f"{model} {mode} {k}")
    assert r.rmse_MPa < 1e-9 * np.abs(synthetic(model, mode).nominal_stress_MPa).max()
    assert r.r2 == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("model", ["mooney_rivlin", "mooney_rivlin_5"])
def test_planar_data_cannot_separate_I1_and_I2_terms(model):
    # (lambda, 1, 1/lambda) has I1 = I2: only C10 + C01 is determined
    with pytest.raises(InputError, match="cannot determine all parameters"):
        fitting.fit(synthetic(model, "planar"), model, "planar")


def test_noisy_fit_statistics():
    rng = np.random.default_rng(3)
    d = synthetic("ogden", "uniaxial", np.linspace(1.0, 1.3, 200))
    sigma = 0.01 * np.abs(d.nominal_stress_MPa).max()
    noisy = fitting.StressData(d.stretch, d.nominal_stress_MPa + sigma * rng.standard_normal(200))
    r = fitting.fit(noisy, "ogden", "uniaxial")
    # least squares with 2 parameters: RMSE ~ sigma sqrt(1 - 2/n)
    assert r.rmse_MPa == pytest.approx(sigma, rel=0.15)
    assert 0.9 < r.r2 < 1.0
    assert r.parameters["alpha"][0] == pytest.approx(16.2, rel=0.05)


def test_unstable_fit_warns_with_range():
    d = synthetic("mooney_rivlin_5", "uniaxial", np.linspace(1.0, 1.5, 20))
    _, hi = stability.stable_range("mooney_rivlin_5", TRUE["mooney_rivlin_5"], "uniaxial")
    with pytest.warns(stability.UnstableMaterialWarning, match=rf"\[0\.2, {hi:.4g}\]"):
        r = fitting.fit(d, "mooney_rivlin_5", "uniaxial")
    assert r.stable_range[1] == pytest.approx(hi, abs=1e-4)  # fitted parameters equal TRUE to ~1e-6
    assert r.warnings


def write(tmp_path, text, name="d.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_csv_round_trip(tmp_path):
    d = synthetic("neo_hooke", "uniaxial")
    rows = "\n".join(f"{float(s)!r},{float(p)!r}" for s, p in zip(d.stretch, d.nominal_stress_MPa))
    back = fitting.read_csv(write(tmp_path, "# comment\nstretch,nominal_stress_MPa\n" + rows + "\n"))
    np.testing.assert_array_equal(back.stretch, d.stretch)
    np.testing.assert_array_equal(back.nominal_stress_MPa, d.nominal_stress_MPa)


@pytest.mark.parametrize("text,where,what", [
    ("stretch,nominal_stress_MPa\n1.0,0\n1.1,nan\n", "line 3, field nominal_stress_MPa", "finite"),
    ("stretch,nominal_stress_MPa\n1.0,0\n1.1,abc\n", "line 3, field nominal_stress_MPa", "expected a number"),
    ("stretch,nominal_stress_MPa\n1.0,0\n0,0.1\n", "line 3, field stretch", "> 0"),
    ("stretch,nominal_stress_MPa\n1.0,0\n-1.2,0.1\n", "line 3, field stretch", "> 0"),
    ("stretch,force\n1.0,0\n", "line 1, field nominal_stress_MPa", "missing column"),
    ("lambda,nominal_stress_MPa\n1.0,0\n", "line 1, field stretch", "missing column"),
    ("stretch,nominal_stress_MPa\n1.0\n", "line 2, field nominal_stress_MPa", "missing value"),
])
def test_bad_csv_names_file_line_field(tmp_path, text, where, what):
    p = write(tmp_path, text)
    with pytest.raises(InputError) as exc:
        fitting.read_csv(p)
    assert str(p) in str(exc.value) and where in str(exc.value) and what in str(exc.value)


def test_fewer_points_than_parameters(tmp_path):
    p = write(tmp_path, "stretch,nominal_stress_MPa\n1.0,0\n1.1,0.01\n1.2,0.02\n1.3,0.04\n")
    with pytest.raises(InputError, match=r"d\.csv, rows: 4 data points for 5 parameters"):
        fitting.fit(fitting.read_csv(p), "mooney_rivlin_5", "uniaxial")


def test_unknown_model_lists_known():
    with pytest.raises(InputError, match="known: neo_hooke, mooney_rivlin, mooney_rivlin_5, yeoh, ogden"):
        fitting.fit(synthetic("neo_hooke", "uniaxial"), "arruda_boyce", "uniaxial")
