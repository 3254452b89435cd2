"""Sensitivity indices against closed forms: SRC of a linear model, Sobol indices of the Ishigami function."""

import numpy as np
import pandas as pd
import pytest

from needletissue.studies import analysis
from needletissue.studies.config import parse_study
from needletissue.studies.sampling import design


def test_src_of_linear_model_is_exact():
    rng = np.random.default_rng(0)
    x1, x2 = rng.uniform(0, 1, 5000), rng.normal(0, 3, 5000)
    y = 2.0 * x1 - 0.5 * x2
    df = pd.DataFrame({"x1": x1, "x2": x2, "y": y, "status": "ok"})
    res = analysis.src(df, ["x1", "x2"], ["y"])["y"]
    sy = y.std(ddof=1)
    assert res["r2"] == pytest.approx(1.0, abs=1e-12)
    assert res["indices"]["x1"] == pytest.approx(2.0 * x1.std(ddof=1) / sy, rel=1e-10)
    assert res["indices"]["x2"] == pytest.approx(-0.5 * x2.std(ddof=1) / sy, rel=1e-10)


def test_failed_cases_are_left_out_of_statistics():
    df = pd.DataFrame({"y": [1.0, 2.0, 3.0, np.nan], "status": ["ok", "ok", "ok", "failed"]})
    st = analysis.statistics(df, ["y"])["y"]
    assert st["n"] == 3 and st["mean"] == pytest.approx(2.0) and st["std"] == pytest.approx(1.0)


def test_sobol_indices_of_ishigami_match_closed_form():
    # Ishigami (a = 7, b = 0.1) on U(-pi, pi)^3: S1 = (0.3139, 0.4424, 0), ST = (0.5576, 0.4424, 0.2437)
    # (Ishigami & Homma 1990; Saltelli et al. 2008, Global Sensitivity Analysis, Sec. 4.6).
    a, b = 7.0, 0.1
    p = {"distribution": "uniform", "low": -np.pi, "high": np.pi}
    cfg = parse_study({"study": {"method": "sobol", "samples": 2**13, "seed": 3},
                       "parameters": {"x1": p, "x2": p, "x3": p}})
    df = design(cfg)
    df["y"] = np.sin(df.x1) + a * np.sin(df.x2) ** 2 + b * df.x3**4 * np.sin(df.x1)
    df["status"] = "ok"
    V = a**2 / 8 + b * np.pi**4 / 5 + b**2 * np.pi**8 / 18 + 0.5
    V1 = 0.5 * (1 + b * np.pi**4 / 5) ** 2
    V2 = a**2 / 8
    V13 = b**2 * np.pi**8 * (1 / 18 - 1 / 50)
    s1 = {"x1": V1 / V, "x2": V2 / V, "x3": 0.0}
    st = {"x1": (V1 + V13) / V, "x2": V2 / V, "x3": V13 / V}
    res = analysis.sobol(df, ["x1", "x2", "x3"], ["y"], seed=0)["y"]
    for k in s1:
        assert res["first_order"][k] == pytest.approx(s1[k], abs=0.03)
        assert res["total"][k] == pytest.approx(st[k], abs=0.03)
        lo, hi = res["total_ci95"][k]
        assert lo - 0.01 <= st[k] <= hi + 0.01  # the interval covers the exact value
