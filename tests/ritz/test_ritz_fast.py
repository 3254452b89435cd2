"""The fast kernel path (unrolled, vectorised orders 3 and 4) against the generic reference loops.

Both paths run the same Newton iteration; the fast one only sums over Gauss points in another order
and with fused multiply-adds, so every result must agree to round-off (1e-12 of the field's scale),
iteration counts and failure reports included.
"""

import numpy as np
import pytest

from needletissue import ritz
from needletissue.errors import ConvergenceError
from needletissue.ritz import RitzModel, solver

FIELDS = ("tip_deflection_mm", "load_point_deflection_mm", "max_deflection_mm", "z_max_mm", "tip_slope_rad",
          "spring_reaction_N", "energy_Nmm", "bending_energy_Nmm", "spring_energy_Nmm", "work_Nmm",
          "basis_coefficients_mm")


def _both(monkeypatch, fn):
    out = []
    for fast in (False, True):
        monkeypatch.setattr(solver, "_FAST", fast)
        out.append(fn())
    return out


def _random_batch(rng, n):
    return dict(force=rng.uniform(-2000, 2000, n), diameter_mm=rng.uniform(3, 6, n),
                free_length_mm=rng.uniform(35, 150, n),
                thickness_mm=np.stack([rng.uniform(5, 25, n), rng.uniform(2, 10, n)], 1),
                k_N_per_mm2=np.array([0.048, 0.023]) * np.exp(rng.uniform(np.log(0.1), np.log(100), (n, 2))),
                load_point_mm=None)


@pytest.mark.parametrize("order", [3, 4, "auto"])
@pytest.mark.parametrize("cos", [True, False])
def test_fast_path_equals_reference(monkeypatch, order, cos):
    rng = np.random.default_rng(7)
    kw = _random_batch(rng, 400)
    kw["load_point_mm"] = kw["free_length_mm"] * rng.uniform(0.5, 1.0, 400)
    ref, fast = _both(monkeypatch, lambda: ritz.solve_batch(**kw, model=RitzModel(cos_term=cos), order=order,
                                                            parallel=False))
    assert np.array_equal(ref.order, fast.order)
    assert np.array_equal(ref.iterations, fast.iterations)
    assert np.array_equal(ref.converged, fast.converged)
    for f in FIELDS:
        a, b = getattr(ref, f), getattr(fast, f)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max(), err_msg=f)
    # the estimate is a difference of two deflections: round-off relative to the deflection
    np.testing.assert_allclose(fast.error_estimate_mm, ref.error_estimate_mm, rtol=1e-12,
                               atol=1e-12 * np.abs(ref.max_deflection_mm).max())


def test_fast_path_single_solve_and_failure_report(monkeypatch):
    ref, fast = _both(monkeypatch, lambda: ritz.solve(300.0))
    assert fast.iterations == ref.iterations and fast.converged == ref.converged
    assert fast.tip_deflection_mm == pytest.approx(ref.tip_deflection_mm, rel=1e-12)
    # a batch with one sample that cannot converge: the same error, naming the same sample
    msgs = []
    for fast_path in (False, True):
        monkeypatch.setattr(solver, "_FAST", fast_path)
        with pytest.raises(ConvergenceError) as exc:
            ritz.solve_batch(np.array([100.0, 1e200, 300.0, 1e250]), parallel=False)
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1] and "2 of 4 samples" in msgs[1] and "sample 1" in msgs[1]
