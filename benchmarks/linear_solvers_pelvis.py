"""Pardiso against AMG-CG on the anatomical model's first tangent (linear tets, the tissue's K = 10 MPa).

Builds `fe pelvis --order 1` at the given sizes, takes the first Newton tangent (its free dofs, upper
triangle) and solves it with each linear solver of `fem.linsolve` in its own process (peak RSS per
solver). This is what `linsolve.AUTO_DIRECT_MAX_DOFS` rests on (docs/fem.md, "Linear solvers").

    PYTHONPATH=src python benchmarks/linear_solvers_pelvis.py [--mesh-size 6 --needle-size 1.5] [--solvers pardiso,amg]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


class _Captured(Exception):
    pass


def capture(mesh_size: float, needle_size: float, folder: Path):
    """Save the first tangent (upper triangle), its right-hand side, the points and free dofs."""
    import scipy.sparse as sp

    from needletissue.fem import linsolve
    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    dofs = {}
    make = linsolve.make

    def spy(name, points=None, dof1=None, **kw):
        dofs.update(points=points, dof1=dof1)
        return make(name, points, dof1, **kw)

    def save(self, A, b, upper=False):
        sp.save_npz(folder / "A.npz", A.tocsr())
        np.savez(folder / "rest.npz", b=b, upper=upper, **dofs)
        raise _Captured

    linsolve.make, linsolve.TimedSolver.__call__ = spy, save
    cfg = PelvisConfig(mesher="box", forces=[100.0], order=1, needle_size=needle_size, mesh_size=mesh_size, far_size=mesh_size,
                       out=str(folder / "model"), figures=False, solver="pardiso", progress=False)
    try:
        run_pelvis_model(cfg)
    except _Captured:
        return
    raise RuntimeError("no linear solve reached")


def solve_one(name: str, folder: Path) -> dict:
    import scipy.sparse as sp

    from needletissue.fem import linsolve

    A = sp.load_npz(folder / "A.npz").tocsr()
    rest = np.load(folder / "rest.npz")
    b, upper = rest["b"], bool(rest["upper"])
    s = linsolve.make(name, rest["points"], rest["dof1"])
    with linsolve.thread_limits(name):
        t, c = time.perf_counter(), time.process_time()
        x = s(A, b, upper=upper)
        wall, cpu = time.perf_counter() - t, time.process_time() - c
    full = A + sp.triu(A, 1).T if upper else A
    return {"solver": name, "dofs": A.shape[0], "wall_s": wall, "cpu_s": cpu,
            "cg_iterations": getattr(s._fun, "cg_iterations", None),
            "relative_residual": float(np.linalg.norm(full @ x - b) / np.linalg.norm(b)),
            "peak_rss_MB": _peak_rss_mb()}


def _peak_rss_mb() -> float:
    """This process's own peak (VmHWM; ru_maxrss would carry the parent's peak across exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size", type=float, default=6.0, help="tissue element size, mm")
    ap.add_argument("--needle-size", type=float, default=1.5, help="needle element size, mm")
    ap.add_argument("--solvers", default="pardiso,amg")
    ap.add_argument("--one", nargs=2, help=argparse.SUPPRESS)  # child: solver, folder
    a = ap.parse_args()
    if a.one:
        print(json.dumps(solve_one(a.one[0], Path(a.one[1]))))
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        t = time.perf_counter()
        capture(a.mesh_size, a.needle_size, folder)
        print(f"model and first tangent: {time.perf_counter() - t:.1f} s", flush=True)
        print("| solver | free dofs | wall | CPU | CG iterations | relative residual | peak RSS |")
        print("|---|---|---|---|---|---|---|")
        for name in a.solvers.split(","):
            out = subprocess.run([sys.executable, __file__, "--one", name, tmp], capture_output=True, text=True,
                                 check=True)
            r = json.loads(out.stdout.strip().splitlines()[-1])
            print(f"| {name} | {r['dofs']:,} | {r['wall_s']:.1f} s | {r['cpu_s']:.1f} s | {r['cg_iterations'] or '-'} | "
                  f"{r['relative_residual']:.1e} | {r['peak_rss_MB']:.0f} MB |", flush=True)


if __name__ == "__main__":
    main()
