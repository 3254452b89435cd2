"""Designs: fixed seeds reproduce, LHS is stratified, distributions have their stated moments, Saltelli layout."""

import numpy as np
import pytest
from scipy import stats

from needletissue.errors import InputError
from needletissue.studies.config import parse_study
from needletissue.studies.sampling import design, frozen_distribution


def _cfg(method, samples=200, seed=7, **params):
    return parse_study({"study": {"method": method, "samples": samples, "seed": seed}, "parameters": params})


THICK = {"distribution": "truncnorm", "mean": 31.82, "std": 5.43, "low": 15.0, "high": 50.0}
FORCE = {"distribution": "uniform", "low": 100.0, "high": 300.0}


@pytest.mark.parametrize("method", ["monte_carlo", "latin_hypercube", "sobol"])
def test_same_seed_same_cases_other_seed_other_cases(method):
    a = design(_cfg(method, tissue_thickness_mm=THICK, force_N=FORCE))
    b = design(_cfg(method, tissue_thickness_mm=THICK, force_N=FORCE))
    c = design(_cfg(method, seed=8, tissue_thickness_mm=THICK, force_N=FORCE))
    assert a.equals(b)
    assert not np.allclose(a["force_N"], c["force_N"])


def test_latin_hypercube_has_one_sample_per_stratum():
    n = 97
    df = design(_cfg("latin_hypercube", samples=n, tissue_thickness_mm=THICK, force_N=FORCE))
    for name, spec in (("tissue_thickness_mm", THICK), ("force_N", FORCE)):
        u = frozen_distribution(parse_study({"parameters": {name: spec}}).parameters[name]).cdf(df[name])
        strata = np.floor(u * n).astype(int)
        assert sorted(strata) == list(range(n))


def test_truncnorm_moments_and_bounds():
    n = 20000
    df = design(_cfg("monte_carlo", samples=n, tissue_thickness_mm=THICK))
    x = df["tissue_thickness_mm"]
    assert x.min() >= 15.0 and x.max() <= 50.0
    a, b = (15.0 - 31.82) / 5.43, (50.0 - 31.82) / 5.43
    m, v = stats.truncnorm.stats(a, b, loc=31.82, scale=5.43, moments="mv")
    assert abs(x.mean() - m) < 4 * np.sqrt(v / n)


def test_grid_is_cartesian_product():
    cfg = parse_study({"study": {"method": "grid"},
                       "parameters": {"force_N": {"values": [100, 200, 300]}, "diameter_mm": {"values": [4, 5]}}})
    df = design(cfg)
    assert len(df) == 6 and list(df["case_id"]) == list(range(6))
    assert set(zip(df.force_N, df.diameter_mm)) == {(f, d) for f in (100, 200, 300) for d in (4, 5)}


def test_saltelli_blocks():
    n, d = 64, 2
    df = design(_cfg("sobol", samples=n, tissue_thickness_mm=THICK, force_N=FORCE))
    assert len(df) == n * (d + 2)
    A, B = df[df.block == "A"], df[df.block == "B"]
    for j, name in enumerate(["tissue_thickness_mm", "force_N"]):
        AB = df[df.block == f"AB{j}"]
        assert np.array_equal(AB[name].to_numpy(), B[name].to_numpy())
        other = [x for x in ["tissue_thickness_mm", "force_N"] if x != name][0]
        assert np.array_equal(AB[other].to_numpy(), A[other].to_numpy())


@pytest.mark.parametrize("data, field", [
    ({"parameters": {"force_N": {"distribution": "normal", "mean": 1.0}}}, "parameters.force_N"),
    ({"parameters": {"force_N": {"distribution": "uniform", "low": 3.0, "high": 1.0}}}, "parameters.force_N"),
    ({"parameters": {"force_N": {"distribution": "normal", "mean": 1.0, "std": -1.0}}}, "parameters.force_N.std"),
    ({"parameters": {"force_N": {"values": [1.0]}}}, "parameters.force_N"),  # grid values with LHS
    ({"study": {"method": "grid"}, "parameters": {"force_N": FORCE}}, "parameters.force_N"),
    ({"study": {"samples": 1}, "parameters": {"force_N": FORCE}}, "study.samples"),
    ({"study": {"colour": "red"}, "parameters": {"force_N": FORCE}}, "study.colour"),
    ({"parameters": {}}, "parameters"),
    ({"study": {"method": "annealing"}, "parameters": {"force_N": FORCE}}, "study.method"),
])
def test_study_config_errors_name_the_field(data, field):
    with pytest.raises(InputError) as e:
        parse_study(data)
    assert e.value.field == field, str(e.value)
