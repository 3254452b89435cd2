"""Ritz solver speed (pytest-benchmark): medians and ratios against a plain SciPy baseline, one run.

    make bench    or    pytest -q benchmarks/bench_ritz.py --benchmark-only

Baseline: scipy.optimize.minimize(method="BFGS") with a finite-difference gradient of the SAME
order-3 energy (same basis and Gauss rule, energy evaluated in NumPy). Targets (issue #4): one warm
p = 3 solve <= 50 us through the Python API; >= 100,000 p = 3 solves per second vectorised; issue
#18: >= 1,000,000 per second on one core. The serial batch runs twice, on the reference kernel loops
(solver._FAST = False, the previous version) and on the fast path, and prints the CPU-time ratio.
The ratios are printed at the end of the session (and stored in the benchmark JSON extra_info).
"""

import numpy as np
import pytest
from scipy.optimize import minimize

from needletissue import ritz
from needletissue.ritz import basis, solver

MODEL = ritz.RitzModel()
N_BATCH = 200_000
_MEDIANS = {}
_CPU = {}  # CPU seconds per solve, serial batch


def _energy_numpy(model, order=3):
    """The order-p energy as a NumPy function of the basis coefficients (for the baseline)."""
    l, EI = model.free_length_mm, model.bending_stiffness_Nmm2
    nq = basis.quadrature_points(order, model.cos_term)
    x, w = np.polynomial.legendre.leggauss(nq)
    zs, ws, ks = [], [], []
    za = 0.0
    for la in model.layers:
        zs.append(za + la.thickness_mm * (x + 1) / 2)
        ws.append(w * la.thickness_mm / 2)
        ks.append(np.full(nq, la.k_N_per_mm2))
        za += la.thickness_mm
    z, wq, k = np.concatenate(zs), np.concatenate(ws), np.concatenate(ks)
    phi = basis.evaluate(z / l, order)
    dphi = basis.evaluate(z / l, order, 1) / l
    phi3 = basis.evaluate(np.array([model.z3_mm / l]), order)[0]
    kb = EI / l**3

    def energy(c, F):
        v, d = phi @ c, dphi @ c
        y = v * v * (1 + d * d) if model.cos_term else v * v
        return 0.5 * kb * c @ c + np.sum(wq * k * (0.5 * y + 0.25 * y * y)) - F * phi3 @ c

    return energy


def _report(name, seconds, per):
    _MEDIANS[name] = seconds / per


@pytest.fixture(scope="module", autouse=True)
def _summary():
    yield
    if {"api_single", "scipy_bfgs_single"} <= _MEDIANS.keys():
        s, b = _MEDIANS["api_single"], _MEDIANS["scipy_bfgs_single"]
        print(f"\nRitz p=3 single solve: median {s * 1e6:.1f} us (target <= 50 us); "
              f"SciPy BFGS baseline {b * 1e6:.0f} us; speed-up x{b / s:.0f}")
    if {"batch_serial", "batch_serial_reference"} <= _CPU.keys():
        r, f = _CPU["batch_serial_reference"], _CPU["batch_serial"]
        print(f"Ritz p=3 batch serial CPU: reference kernel {1 / r:,.0f} solves/s per core, fast path "
              f"{1 / f:,.0f} solves/s per core (target >= 1,000,000): x{r / f:.2f}")
    for key in ("batch_serial_reference", "batch_serial", "batch_parallel"):
        if key in _MEDIANS and "scipy_bfgs_single" in _MEDIANS:
            s = _MEDIANS[key]
            print(f"Ritz p=3 {key}: {1 / s:,.0f} solves/s (target >= 100,000); "
                  f"x{_MEDIANS['scipy_bfgs_single'] / s:.0f} vs SciPy BFGS")


def test_api_single_solve(benchmark):
    ritz.solve(300.0, MODEL)  # warm (compiled, cached)
    r = benchmark(ritz.solve, 300.0, MODEL)
    assert r.converged is False and abs(r.tip_deflection_mm - 17.63) < 0.005
    _report("api_single", benchmark.stats.stats.median, 1)
    benchmark.extra_info["median_us"] = benchmark.stats.stats.median * 1e6


def test_scipy_bfgs_baseline(benchmark):
    energy = _energy_numpy(MODEL)
    ref = ritz.solve(300.0, MODEL)

    def run():
        return minimize(energy, np.zeros(2), args=(300.0,), method="BFGS", options={"gtol": 1e-8})

    res = benchmark(run)
    tip = basis.evaluate(np.array([1.0]), 3)[0] @ res.x
    assert abs(tip - ref.tip_deflection_mm) < 1e-3  # same energy, same answer
    _report("scipy_bfgs_single", benchmark.stats.stats.median, 1)
    benchmark.extra_info["median_us"] = benchmark.stats.stats.median * 1e6


@pytest.mark.parametrize("parallel,fast", [(False, False), (False, True), (True, True)],
                         ids=["batch_serial_reference", "batch_serial", "batch_parallel"])
def test_batch_throughput(benchmark, monkeypatch, parallel, fast):
    monkeypatch.setattr(solver, "_FAST", fast)
    rng = np.random.default_rng(0)
    F = rng.uniform(-2000, 2000, N_BATCH)
    d = rng.uniform(4.0, 6.0, N_BATCH)
    l = rng.uniform(60.0, 120.0, N_BATCH)
    k = np.array([0.048, 0.023]) * rng.lognormal(0.0, 0.3, (N_BATCH, 2))
    ritz.solve_batch(F[:10], diameter_mm=d[:10], free_length_mm=l[:10], k_N_per_mm2=k[:10], parallel=parallel)
    b = benchmark.pedantic(ritz.solve_batch, args=(F,), kwargs=dict(diameter_mm=d, free_length_mm=l,
                           k_N_per_mm2=k, parallel=parallel), rounds=3, iterations=1)
    assert len(b) == N_BATCH
    name = "batch_parallel" if parallel else "batch_serial" if fast else "batch_serial_reference"
    if not parallel:  # CPU time per solve: the per-core rate, insensitive to other users of the machine
        import time

        t0 = time.process_time()
        ritz.solve_batch(F, diameter_mm=d, free_length_mm=l, k_N_per_mm2=k, parallel=False)
        cpu = (time.process_time() - t0) / N_BATCH
        print(f"\nRitz p=3 {name} CPU time: {cpu * 1e6:.2f} us/solve = {1 / cpu:,.0f} solves/s per core")
        _CPU[name] = cpu
        benchmark.extra_info["cpu_solves_per_s_per_core"] = 1 / cpu
    _report(name, benchmark.stats.stats.median, N_BATCH)
    benchmark.extra_info["solves_per_s"] = N_BATCH / benchmark.stats.stats.median
