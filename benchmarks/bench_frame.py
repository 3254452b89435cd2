"""Frame model speed (pytest-benchmark): medians, per-core rates and ratios, one run.

    make bench    or    pytest -q benchmarks/bench_frame.py --benchmark-only -s

Targets (issue #14): one 2-pin solve through the Python API <= 50 us warm; a compensation call <= 200 us;
>= 100,000 batched solves/s on one core. Ratios against scipy.optimize.root (MINPACK hybrd) on the SAME
residual (the compiled rod integration, called from Python), and against the FE model it replaces
(`fe needle`, default two pins, 100/200/300 N: 86 s CPU, docs/needle_model.md, i.e. ~29 s CPU per force;
not re-run here). CPU time (process_time) is printed beside the wall-clock medians: on a shared machine
the wall clock measures the other users too.
"""

import time

import numpy as np
import pytest
from scipy.optimize import root

from needletissue import frame
from needletissue.frame import kernel, solver

MODEL = frame.FrameModel()          # fe needle's defaults: two 5 mm pins, l = 100 mm, bone root, tissue
FORCE = (0.0, 300.0, 0.0)
FE_CPU_PER_FORCE_S = 86.0 / 3
N_BATCH = 2_000
BIG_BATCH = 100_000
_MED = {}
_STEPS = {}  # batch: mean quasi-Newton steps per solve, (auto, rest)


def _cpu(fn, n, rounds=7):
    """Median over rounds of the CPU time per call (one round of n calls is at the mercy of the other jobs)."""
    per = []
    for _ in range(rounds):
        t0 = time.process_time()
        for _ in range(n):
            fn()
        per.append((time.process_time() - t0) / n)
    return float(np.median(per))


@pytest.fixture(scope="module", autouse=True)
def _summary():
    yield
    print()
    for key, goal in (("pose", 50e-6), ("pose_warm", 50e-6), ("solve_no_estimate", 50e-6), ("solve_full", None), ("compensate", 200e-6)):
        if key in _MED:
            wall, cpu = _MED[key]
            extra = f" (goal <= {goal * 1e6:.0f} us: x{cpu / goal:.1f})" if goal else ""
            print(f"frame {key}: median {wall * 1e6:.0f} us wall, {cpu * 1e6:.0f} us CPU{extra}; "
                  f"x{FE_CPU_PER_FORCE_S / cpu:.1e} faster than the FE per force")
    for key in [k for k in _MED if k.startswith("batch ")]:
        auto, rest = _MED[key]
        rate = 1 / auto
        verdict = "met" if rate >= 100_000 else f"x{100_000 / rate:.1f} short"
        print(f"frame {key}: {rate:,.0f} solves/s per core, CPU median (goal >= 100,000: {verdict}), "
              f"{_STEPS[key][0]:.2f} steps per solve; x{rest / auto:.1f} the per-row solve from rest "
              f"({1 / rest:,.0f}/s, method='rest', {_STEPS[key][1]:.2f} steps)")
    if "scipy_root" in _MED and "pose" in _MED:
        print(f"scipy.optimize.root on the same residual: {_MED['scipy_root'][1] * 1e6:.0f} us CPU, "
              f"x{_MED['scipy_root'][1] / _MED['pose'][1]:.1f} the compiled quasi-Newton")


def test_pose(benchmark):
    frame.pose(FORCE, model=MODEL)
    out = benchmark(frame.pose, FORCE, None, MODEL)
    assert 10 < out[2] < 25
    _MED["pose"] = benchmark.stats.stats.median, _cpu(lambda: frame.pose(FORCE, model=MODEL), 200)


def test_pose_warm(benchmark):
    """The control loop: each solve starts from the previous answer (state and Broyden tangent)."""
    state = frame.pose(FORCE, model=MODEL)[3]
    forces = [np.array(FORCE) + (0.0, 2.0 * np.sin(i), 1.0) for i in range(64)]
    i = [0]

    def step():
        i[0] = (i[0] + 1) % 64
        return frame.pose(forces[i[0]], None, MODEL, initial=state)

    benchmark(step)
    _MED["pose_warm"] = benchmark.stats.stats.median, _cpu(step, 200)


def test_solve_full_results(benchmark):
    frame.solve(FORCE, model=MODEL)
    benchmark(frame.solve, FORCE, None, MODEL, error_estimate=False)
    _MED["solve_no_estimate"] = (benchmark.stats.stats.median,
                                 _cpu(lambda: frame.solve(FORCE, model=MODEL, error_estimate=False), 50))
    cpu_full = _cpu(lambda: frame.solve(FORCE, model=MODEL), 30)  # with the error estimate (two solves)
    _MED["solve_full"] = (cpu_full, cpu_full)


def test_compensate(benchmark):
    prev = frame.compensate((0, 5, 0), (0.01, 0, 0), FORCE, model=MODEL)
    benchmark(frame.compensate, (0, 5, 0), (0.01, 0, 0), FORCE, None, MODEL, initial=prev.state)
    _MED["compensate"] = (benchmark.stats.stats.median, _cpu(
        lambda: frame.compensate((0, 5, 0), (0.01, 0, 0), FORCE, model=MODEL, initial=prev.state), 50))


def _batches(n, seed=0):
    """(a) random full range: (+-300, +-300, +-100) N, no moment; (b) uncertainty: the nominal 300 N across with
    the robot's force-sensor noise, 2 N and 50 N mm (standard deviations) per component."""
    rng = np.random.default_rng(seed)
    Fa = np.column_stack([rng.uniform(-300, 300, n), rng.uniform(-300, 300, n), rng.uniform(-100, 100, n)])
    Fb = np.array(FORCE) + rng.normal(0.0, 2.0, (n, 3))
    return {"random": (Fa, np.zeros_like(Fa)), "uncertainty": (Fb, rng.normal(0.0, 50.0, (n, 3)))}


def test_batch(benchmark):
    """Both batches at N_BATCH rows, the anchored lanes (method 'auto') against the previous per-row solve from
    rest (method 'rest', same process, alternating rounds), then 'auto' on BIG_BATCH rows ('rest' there would take
    minutes; its rate does not depend on the batch size)."""
    small, big = _batches(N_BATCH), _batches(BIG_BATCH, seed=1)
    frame.solve_batch(*small["uncertainty"], model=MODEL)
    frame.solve_batch(*small["random"], model=MODEL, method="rest")
    b = benchmark.pedantic(frame.solve_batch, args=small["uncertainty"], kwargs=dict(model=MODEL), rounds=3,
                           iterations=1)
    assert b.max_needle_deflection_mm.shape == (N_BATCH,)
    for name, (F, M) in small.items():
        per = {"auto": [], "rest": []}
        steps = {}
        for _ in range(5):
            for method in per:
                t0 = time.process_time()
                out = frame.solve_batch(F, M, model=MODEL, method=method)
                per[method].append((time.process_time() - t0) / N_BATCH)
                steps[method] = float(out.iterations.mean())
        _MED[f"batch {name} {N_BATCH:,}"] = float(np.median(per["auto"])), float(np.median(per["rest"]))
        _STEPS[f"batch {name} {N_BATCH:,}"] = steps["auto"], steps["rest"]
    for name, (F, M) in big.items():
        per = []
        for _ in range(3):
            t0 = time.process_time()
            out = frame.solve_batch(F, M, model=MODEL)
            per.append((time.process_time() - t0) / BIG_BATCH)
        _MED[f"batch {name} {BIG_BATCH:,}"] = float(np.median(per)), _MED[f"batch {name} {N_BATCH:,}"][1]
        _STEPS[f"batch {name} {BIG_BATCH:,}"] = float(out.iterations.mean()), _STEPS[f"batch {name} {N_BATCH:,}"][1]


def test_scipy_root_baseline(benchmark):
    disc = solver._cached_disc(MODEL, False)
    nn = disc.NX.shape[0]
    W = np.array([*FORCE, 0.0, 0.0, 0.0])
    E = np.empty((nn, 18))
    dummy = np.empty((1, 18))
    res = np.empty(6 * nn + 6)

    def fun(y):
        for k in range(nn):
            kernel.integrate(y[6 * k: 6 * k + 6], disc.NX[k, 0], disc.NX[k, 1], disc.SZ, disc.SK, disc.SKH,
                             disc.SKZ, disc.SKT, disc.SN, disc.P, E[k], dummy, False)
        kernel.residual(E, y[6 * nn:], disc.NX, disc.P0, W, 1.0, disc.P, res)
        return res.copy()

    def run():
        return root(fun, np.zeros(6 * nn + 6), method="hybr", tol=1e-12)

    sol = benchmark(run)
    assert sol.success
    want = frame.solve(FORCE, model=MODEL).load_point_displacement_mm[1]
    assert abs(sol.x[6 * nn + 1] * disc.P[kernel.LS] - want) < 1e-6  # same equations, same answer
    _MED["scipy_root"] = benchmark.stats.stats.median, _cpu(run, 10)
