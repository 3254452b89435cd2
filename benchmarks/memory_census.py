"""Where the memory is at Pardiso's second factorisation (the solve's peak): process RSS, Pardiso's own
(iparm 15-17) and the NumPy arrays alive, largest first (tracemalloc, started before the model is built).
docs/bench.md ("Memory") and docs/pelvis_model.md ("The paper-scale load history").

    python benchmarks/memory_census.py needle                  # issue 18's one-needle model (8,972 tet10)
    python benchmarks/memory_census.py pelvis --mesh-size 4    # the paper-scale model's setup at a quarter size

tracemalloc slows the run ~2x; the figures are memory, not time. The pelvis model needs ../shared/data.
"""

from __future__ import annotations

import argparse
import tempfile
import tracemalloc
from pathlib import Path


def rss_mb() -> float:
    for line in open("/proc/self/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    return float("nan")


def census(top: int):
    """Wrap Pardiso's factorise-and-solve: print the census after its second call."""
    from needletissue.fem import linsolve

    solve, calls = linsolve._Pardiso._solve, [0]

    def wrapped(self, mtype, M, b):
        x = solve(self, mtype, M, b)
        calls[0] += 1
        if calls[0] == 2:
            ps = self.solvers[mtype]
            print(f"free dofs {M.shape[0]:,}; RSS {rss_mb():.0f} MB; NumPy arrays alive "
                  f"{tracemalloc.get_traced_memory()[0] / 2**20:.0f} MB; Pardiso: analysis peak "
                  f"{ps.iparm[14] / 1024:.0f} MB, kept {ps.iparm[15] / 1024:.0f} MB, factor and solve "
                  f"{ps.iparm[16] / 1024:.0f} MB ({ps.iparm[17]:,} nonzeros)", flush=True)
            for st in tracemalloc.take_snapshot().statistics("traceback")[:top]:
                where = " <- ".join(f"{f.filename.split('site-packages/')[-1].split('src/')[-1]}:{f.lineno}"
                                    for f in list(st.traceback)[-3:][::-1])
                print(f"{st.size / 2**20:8.1f} MB  {where}", flush=True)
        return x

    linsolve._Pardiso._solve = wrapped


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", choices=("needle", "pelvis"))
    ap.add_argument("--mesh-size", type=float, default=4.0, help="pelvis: tissue element size, mm (linear tets)")
    ap.add_argument("--top", type=int, default=15, help="how many allocation sites to list")
    a = ap.parse_args()
    tracemalloc.start(6)
    census(a.top)
    if a.model == "needle":
        import sys

        sys.path.insert(0, str(Path(__file__).parent))
        import bench_fe_needle

        mesh = Path(tempfile.mkdtemp()) / "one_needle.msh"
        bench_fe_needle.make_mesh(mesh)
        bench_fe_needle.run_one("current", str(mesh), str(mesh.with_suffix(".npy")))
    else:
        from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

        run_pelvis_model(PelvisConfig(mesher="box", forces=[300.0], order=1, needle_size=a.mesh_size / 2.45, mesh_size=a.mesh_size,
                                      far_size=a.mesh_size, out=None, figures=False))


if __name__ == "__main__":
    main()
