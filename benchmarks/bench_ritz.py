"""Ritz solver speed (pytest-benchmark): medians and ratios against a plain SciPy baseline, one run.

    make bench    or    pytest -q benchmarks/bench_ritz.py --benchmark-only -s
    python benchmarks/bench_ritz.py [--n 200000] [--repeat 5]     (the per-core table only)
    python benchmarks/bench_ritz.py --previous REF [--n 200000] [--repeat 9]
        (solve_batch of git revision REF against this version, alternating in one process)
    python benchmarks/bench_ritz.py --latency
        (one order-3 energy with its Hessian: independent calls against a dependent chain)

Baseline: scipy.optimize.minimize(method="BFGS") with a finite-difference gradient of the SAME
order-3 energy (same basis and Gauss rule, energy evaluated in NumPy). Targets (issue #4): one warm
p = 3 solve <= 50 us through the Python API; >= 100,000 p = 3 solves per second vectorised; issue
#18: >= 1,000,000 per second on one core.

The per-core table runs, in one process and alternating (repeats interleaved, medians of CPU time),
the serial p = 3 batch on six kernel paths: the reference loops (solver._FAST = False), the unrolled
Gauss-point path (solver._CLOSED = False), the closed-form order 3 with its order-4 error estimate on
the unrolled Gauss-point path (solver._MONOMIAL4 = False), the same with the order-4 Newton solve in
monomial form (solver._STEP4 = False; the previous version), the same with one closed-form order-4
Newton step instead (the default) and the closed form with error_estimate=False. Each on three
batches of 200,000: every parameter random (diameter, free length, both k; the studies' case; forces
up to 2,000 N as in the earlier versions of this benchmark, 4.8 Newton iterations on average; only
19 % of its rows are within the model's validity range |v|max / l <= 0.25, the median row is at 0.66),
the same parameters with forces drawn from the valid range (|F| <= 0.75 EI / l^2, the force that
bends the needle without tissue to |v| / l = 0.25: every row valid, 3.2 iterations) and the force only
(one model, one table for the batch; forces up to 300 N, 3.1 iterations). Ratios are against the
previous version (closed-form order 3, order-4 Newton estimate in monomial form).
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
# (name, solver._FAST, solver._CLOSED, solver._MONOMIAL4, solver._STEP4, error_estimate)
PATHS = (("reference loops", False, False, False, False, True), ("unrolled", True, False, False, False, True),
         ("closed form, Gauss order-4 estimate", True, True, False, False, True),
         ("closed form, order-4 Newton estimate (previous)", True, True, True, False, True),
         ("closed form, one-step order-4 estimate", True, True, True, True, True),
         ("closed form, no estimate", True, True, True, True, False))
BASE = "closed form, order-4 Newton estimate (previous)"
FLAGS = ("_FAST", "_CLOSED", "_MONOMIAL4", "_STEP4")

def batches(n=N_BATCH, seed=0):
    """{kind: (force, kwargs)}: every parameter random (forces to 2,000 N, or within the validity
    range), or the force only (one model)."""
    rng = np.random.default_rng(seed)
    F = rng.uniform(-2000, 2000, n)
    d = rng.uniform(4.0, 6.0, n)
    l = rng.uniform(60.0, 120.0, n)
    k = np.array([0.048, 0.023]) * rng.lognormal(0.0, 0.3, (n, 2))
    kw = dict(diameter_mm=d, free_length_mm=l, k_N_per_mm2=k)
    out = {"all parameters": (F, kw), "force only": (rng.uniform(-300, 300, n), {})}
    EI = MODEL.youngs_modulus_MPa * np.pi * d**4 / 64
    out["all parameters, valid range"] = (rng.uniform(-1.0, 1.0, n) * 0.75 * EI / l**2, kw)
    return out


def _set(path):
    for flag, value in zip(FLAGS, path[1:5]):
        setattr(solver, flag, value)

def cpu_table(n=N_BATCH, repeat=5):
    """Median CPU seconds per solve {(kind, path): s}, serial, paths alternating within each repeat."""
    import time

    saved = [getattr(solver, f) for f in FLAGS]
    times = {}
    try:
        for kind, (F, kw) in batches(n).items():
            for path in PATHS:  # compile and warm every path first
                _set(path)
                ritz.solve_batch(F[:10], **{a: v[:10] for a, v in kw.items()}, parallel=False,
                                 error_estimate=path[5])
            for _ in range(repeat):
                for path in PATHS:
                    _set(path)
                    t0 = time.process_time()
                    ritz.solve_batch(F, **kw, parallel=False, error_estimate=path[5])
                    times.setdefault((kind, path[0]), []).append((time.process_time() - t0) / F.size)
    finally:
        for f, v in zip(FLAGS, saved):
            setattr(solver, f, v)
    return {key: float(np.median(v)) for key, v in times.items()}


def previous_ritz(ref: str):
    """needletissue.ritz of git revision ref: its src exported by `git archive` into a temporary
    folder and imported as the package needletissue_prev (its own Numba cache: compiles once)."""
    import importlib
    import re
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    tmp = Path(tempfile.mkdtemp(prefix="bench_ritz_"))
    root = Path(__file__).resolve().parents[1]
    tar = subprocess.run(["git", "archive", ref, "src/needletissue"], cwd=root, check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(tmp)], input=tar.stdout, check=True)
    pkg = tmp / "src" / "needletissue"
    for f in pkg.rglob("*.py"):
        f.write_text(re.sub(r"\bneedletissue(?=[. \n])", "needletissue_prev", f.read_text()))
    pkg.rename(pkg.with_name("needletissue_prev"))
    sys.path.insert(0, str(tmp / "src"))
    return importlib.import_module("needletissue_prev.ritz")


def ab_table(prev, n=N_BATCH, repeat=9) -> str:
    """solve_batch (serial, default paths) of `prev` and of this version, alternating per batch
    (order swapped every repeat): median CPU ns per solve and the median of the pair ratios."""
    import time

    mods = {"previous": prev, "this": ritz}
    res = {}
    for kind, (F, kw) in batches(n).items():
        for est in (True, False):
            for m in mods.values():  # compile and warm
                m.solve_batch(F[:10], **{a: v[:10] for a, v in kw.items()}, parallel=False, error_estimate=est)
    for r in range(repeat):
        for kind, (F, kw) in batches(n).items():
            for est in (True, False):
                for name in (("previous", "this") if r % 2 == 0 else ("this", "previous")):
                    t0 = time.process_time()
                    mods[name].solve_batch(F, **kw, parallel=False, error_estimate=est)
                    res.setdefault((kind, est, name), []).append((time.process_time() - t0) / F.size)
    rows = ["| batch | estimate | previous | this | pairs |", "|---|---|---|---|---|"]
    for kind, est, name in res:
        if name == "this":
            a, b = np.array(res[(kind, est, "previous")]), np.array(res[(kind, est, "this")])
            rows.append(f"| {kind} | {'yes' if est else 'no'} | {np.median(a) * 1e9:,.0f} ns | "
                        f"{np.median(b) * 1e9:,.0f} ns | x{np.median(a / b):.2f} |")
    return "\n".join(rows)


def latency_table(n=1_000_000, repeat=7) -> str:
    """CPU ns per order-3 energy with gradient and Hessian (kernel._energy3c, the body of a Newton
    iteration), on independent inputs (throughput) and as a chain whose next input depends on the
    last output (latency, as in Newton). Equal times: the work is throughput-bound, and interleaving
    rows cannot hide anything."""
    import time

    from numba import njit

    from needletissue.ritz import kernel

    @njit
    def run(tab, c0, c1, chain):
        pw = np.empty(18)
        acc = 0.0
        x0, x1 = c0[0], c1[0]
        for i in range(c0.shape[0]):
            r = kernel._energy3c(x0, x1, tab, 40.0, 300.0, True, pw)
            acc += r[4]
            x0 = c0[i] + (1e-300 * r[4] if chain else 0.0)  # a data dependence, no change
            x1 = c1[i] + (1e-300 * r[5] if chain else 0.0)
        return acc

    tab = np.empty(kernel._NTAB)
    kernel.cubic_table(84.18, np.array([22.0, 10.0]), np.array([0.048, 0.023]), 84.18, True, tab,
                       np.empty(kernel._NMU))
    rng = np.random.default_rng(0)
    c0, c1 = rng.uniform(1, 20, n), rng.uniform(-5, 5, n)
    res = {False: [], True: []}
    for chain in res:
        run(tab, c0[:10], c1[:10], chain)
    for _ in range(repeat):
        for chain in res:
            t0 = time.process_time()
            run(tab, c0, c1, chain)
            res[chain].append((time.process_time() - t0) / n)
    return (f"order-3 energy + gradient + Hessian: {np.median(res[False]) * 1e9:.1f} ns independent, "
            f"{np.median(res[True]) * 1e9:.1f} ns chained (medians of {repeat})")


def format_table(cpu) -> str:
    rows = ["| batch | path | CPU per solve | solves/s per core | vs previous |", "|---|---|---|---|---|"]
    for (kind, name), s in cpu.items():
        rows.append(f"| {kind} | {name} | {s * 1e6:.3f} us | {1 / s:,.0f} | x{cpu[(kind, BASE)] / s:.2f} |")
    return "\n".join(rows)


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
    if "table" in _CPU:
        print("\nRitz p=3 serial batch, CPU time per core (target >= 1,000,000 solves/s):\n"
              + format_table(_CPU["table"]))
    for key in ("batch_serial_no_estimate", "batch_serial", "batch_parallel"):
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


@pytest.mark.parametrize("parallel,path", [(False, "closed form, no estimate"),
                                           (False, "closed form, one-step order-4 estimate"),
                                           (True, "closed form, one-step order-4 estimate")],
                         ids=["batch_serial_no_estimate", "batch_serial", "batch_parallel"])
def test_batch_throughput(benchmark, monkeypatch, parallel, path):
    """Wall-clock medians of the whole solve_batch call (every parameter random)."""
    p = next(p for p in PATHS if p[0] == path)
    for flag, value in zip(FLAGS, p[1:5]):
        monkeypatch.setattr(solver, flag, value)
    est = p[5]
    F, kw = batches()["all parameters"]
    ritz.solve_batch(F[:10], **{a: v[:10] for a, v in kw.items()}, parallel=parallel, error_estimate=est)
    b = benchmark.pedantic(ritz.solve_batch, args=(F,),
                           kwargs=dict(**kw, parallel=parallel, error_estimate=est), rounds=3, iterations=1)
    assert len(b) == N_BATCH and b.error_estimated == est
    name = benchmark.name.split("[")[-1].rstrip("]")
    _report(name, benchmark.stats.stats.median, N_BATCH)
    benchmark.extra_info["solves_per_s"] = N_BATCH / benchmark.stats.stats.median


def test_batch_cpu_per_core(benchmark):
    """The per-core table: six kernel paths x three batches, CPU time, alternating in one process."""
    cpu = benchmark.pedantic(cpu_table, rounds=1, iterations=1)
    _CPU["table"] = cpu
    for (kind, name), s in cpu.items():
        benchmark.extra_info[f"{kind} / {name}: solves_per_s_per_core"] = 1 / s
    # same answers on every path (the tests check this to 1e-12; here only that the run is sane)
    assert all(s > 0 for s in cpu.values())


if __name__ == "__main__":
    import argparse
    import os
    import sys

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=N_BATCH)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--previous", metavar="REF", help="git revision to compare solve_batch against")
    ap.add_argument("--latency", action="store_true", help="energy evaluations: independent vs chained")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; N = {args.n:,}, "
          f"{args.repeat} repeats; {sys.version.split()[0]}")
    if args.latency:
        print(latency_table(repeat=args.repeat))
        print(f"load average {os.getloadavg()[0]:.2f} at the end")
        sys.exit(0)
    if args.previous:
        print(f"previous = {args.previous}")
        print(ab_table(previous_ritz(args.previous), args.n, args.repeat))
        print(f"load average {os.getloadavg()[0]:.2f} at the end")
        sys.exit(0)
    print(format_table(cpu_table(args.n, args.repeat)))
    for kind, (F, kw) in batches(args.n).items():
        b = ritz.solve_batch(F, **kw, parallel=False)
        print(f"{kind}: {b.iterations.mean():.2f} Newton iterations on average, "
              f"{np.mean(np.abs(b.max_deflection_mm) / b.free_length_mm <= 0.25):.0%} of rows within "
              "|v|max / l <= 0.25")
    print(f"load average {os.getloadavg()[0]:.2f} at the end")
