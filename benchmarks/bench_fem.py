"""FE core: assembly and linear-solve time per Newton iteration, and peak memory, by size and solver.

Model (as in ../shared/reference/FE-STACK.md): a 60 x 60 mm block, muscle 0-22 mm and adipose
22-32 mm, a 5 mm needle (titanium) through it, base fixed, 100 N lateral load on the needle top.
Linear tetrahedra (the paper's element), one load step, real Newton iterations.

Two ways to run:
- `make bench` / pytest-benchmark: the ~20k case per solver (medians; ratio to Pardiso in extra_info).
- `nice python benchmarks/bench_fem.py scale [--sizes 20k 100k 300k]`: the scaling study; every
  (size, solver) case in its own subprocess for an honest peak RSS; fits time ~ a * tets^b and
  extrapolates to the paper's 1,329,469 tetrahedra; writes benchmarks/results/bench_fem.json.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
PAPER_TETS = 1_329_469
# (needle size, tissue size) in mm -> about 20k, 100k, 300k tetrahedra (FE-STACK.md)
SIZES = {"20k": (1.3, 4.0), "100k": (0.7, 2.2), "300k": (0.5, 1.5)}
SOLVERS = ("pardiso", "amg", "scipy")
SCIPY_MAX = "100k"  # SuperLU: 30 s per solve at 100k tets, out of reach beyond (FE-STACK.md)


def make_mesh(needle_size: float, tissue_size: float):
    """The benchmark mesh (gmsh, 1 thread: deterministic)."""
    import gmsh

    from needletissue.fem import TaggedMesh

    gmsh.initialize(["-nt", "1"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("bench")
        occ = gmsh.model.occ
        mus = occ.addBox(-30, -30, 0, 60, 60, 22)
        fat = occ.addBox(-30, -30, 22, 60, 60, 10)
        ndl = occ.addCylinder(0, 0, 0, 0, 0, 40, 2.5)
        out, _ = occ.fragment([(3, mus), (3, fat)], [(3, ndl)])
        occ.synchronize()
        vols = {}
        for d, t in out:
            c = occ.getCenterOfMass(d, t)
            bb = occ.getBoundingBox(d, t)
            key = "needle" if bb[3] - bb[0] < 6 else ("muscle" if c[2] < 22 else "adipose")
            vols.setdefault(key, []).append(t)
        for k, tags in vols.items():
            gmsh.model.addPhysicalGroup(3, tags, name=k)
        bottom, top = [], []
        for d, t in gmsh.model.getEntities(2):
            bb = gmsh.model.getBoundingBox(d, t)
            if abs(bb[2]) < 1e-6 and abs(bb[5]) < 1e-6:  # base, needle end included
                bottom.append(t)
            if abs(bb[2] - 40) < 1e-6 and abs(bb[5] - 40) < 1e-6:
                top.append(t)
        gmsh.model.addPhysicalGroup(2, bottom, name="bottom")
        gmsh.model.addPhysicalGroup(2, top, name="needle_top")
        gmsh.model.mesh.setSize(gmsh.model.getEntities(0), tissue_size)
        needle_pts = gmsh.model.getBoundary([(3, t) for t in vols["needle"]], recursive=True)
        gmsh.model.mesh.setSize(needle_pts, needle_size)
        f = gmsh.model.mesh.field
        dist = f.add("Distance")
        f.setNumbers(dist, "SurfacesList", [t for _, t in gmsh.model.getBoundary([(3, t) for t in vols["needle"]])])
        th = f.add("Threshold")
        f.setNumber(th, "InField", dist)
        f.setNumber(th, "SizeMin", needle_size)
        f.setNumber(th, "SizeMax", tissue_size)
        f.setNumber(th, "DistMin", 0.5)
        f.setNumber(th, "DistMax", 10.0)
        f.setAsBackgroundMesh(th)
        gmsh.model.mesh.generate(3)
        return TaggedMesh.from_gmsh()
    finally:
        gmsh.finalize()


def rss_gb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 2**20
    return float("nan")


def run_case(size: str, solver: str, mesh_dir: Path) -> dict:
    """One Newton load step; per-iteration times from the solver's own timers."""
    from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve

    path = mesh_dir / f"bench_{size}.vtu"
    t = time.perf_counter()
    if path.exists():
        import meshio

        m = meshio.read(path)
        meta = json.loads((mesh_dir / f"bench_{size}.json").read_text())
        mesh = TaggedMesh(m.points, m.cells_dict["tetra"],
                          {k: np.array(v) for k, v in meta["regions"].items()},
                          {k: np.array(v) for k, v in meta["surfaces"].items()})
    else:
        mesh = make_mesh(*SIZES[size])
        import meshio

        mesh_dir.mkdir(parents=True, exist_ok=True)
        meshio.write(path, meshio.Mesh(mesh.points, [("tetra", mesh.cells)]))
        (mesh_dir / f"bench_{size}.json").write_text(json.dumps(
            {"regions": {k: v.tolist() for k, v in mesh.regions.items()},
             "surfaces": {k: v.tolist() for k, v in mesh.surfaces.items()}}))
    t_mesh = time.perf_counter() - t
    rss_mesh = rss_gb()
    t = time.perf_counter()
    model = FEModel(mesh, {"muscle": "muscle", "adipose": "adipose", "needle": "needle"}, order=1)
    t_model = time.perf_counter() - t
    # assembly alone, at the undeformed state (vector + matrix of every body)
    t = time.perf_counter()
    for b in model.bodies.values():
        b.assemble.vector(field=b.field)
        b.assemble.matrix(field=b.field)
    t_assemble = time.perf_counter() - t
    cpu0 = time.process_time()
    res = solve(model, [Fixed("bottom"), SurfaceForce("needle_top", (100.0, 0.0, 0.0))], [1.0],
                solver=solver, progress=False, results=False)[-1]
    cpu = time.process_time() - cpu0  # all threads; less sensitive to the shared machine's load
    it = res.newton_iterations
    return {
        "size": size, "solver": solver, "tetrahedra": int(len(mesh.cells)), "nodes": int(len(mesh.points)),
        "free_dofs": int(model.ndof - 3 * len(mesh.surface_nodes("bottom"))),
        "newton_iterations": it, "steps": res.steps,
        "assembly_s": t_assemble,
        "assembly_and_update_per_iteration_s": res.timing_s["assembly_and_update"] / it,
        "linear_solve_per_iteration_s": res.timing_s["linear_solve"] / it,
        "newton_wall_s": res.timing_s["newton"], "newton_cpu_s": cpu, "mesh_s": t_mesh, "model_s": t_model,
        "load_average_1min": __import__("os").getloadavg()[0],
        "rss_after_mesh_GB": rss_mesh,
        "peak_rss_GB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "needle_tip_ux_mm": float(res.displacement[mesh.surface_nodes("needle_top"), 0].mean()),
    }


def fit(rows, key):
    """time = a * tets^b by least squares in log-log; returns (a, b)."""
    x = np.log([r["tetrahedra"] for r in rows])
    y = np.log([r[key] for r in rows])
    b, loga = np.polyfit(x, y, 1)
    return float(np.exp(loga)), float(b)


def scale(sizes, solvers, out: Path, mesh_dir: Path):
    rows = []
    for size in sizes:
        for solver in solvers:
            if solver == "scipy" and list(SIZES).index(size) > list(SIZES).index(SCIPY_MAX):
                continue
            cmd = [sys.executable, __file__, "case", size, solver, str(mesh_dir)]
            p = subprocess.run(cmd, capture_output=True, text=True)
            if p.returncode != 0:
                print(p.stderr[-2000:], file=sys.stderr)
                rows.append({"size": size, "solver": solver, "error": p.stderr.strip().splitlines()[-1:]})
                continue
            row = json.loads(p.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(json.dumps(row), flush=True)
    summarize(rows, solvers, out)


def summarize(rows, solvers, out: Path):
    """Fit growth exponents per solver and write the JSON (also used to combine separate runs)."""
    summary = {}
    for r in rows:
        if "error" not in r:
            r["cpu_per_iteration_s"] = r["newton_cpu_s"] / r["newton_iterations"]
    for solver in solvers:
        ok = [r for r in rows if r["solver"] == solver and "error" not in r]
        if len(ok) < 2:
            continue
        s = {}
        for key in ("linear_solve_per_iteration_s", "assembly_and_update_per_iteration_s", "cpu_per_iteration_s",
                    "peak_rss_GB"):
            a, b = fit(ok, key)
            s[key] = {"exponent": b, "extrapolated_to_paper": a * PAPER_TETS**b}
        summary[solver] = s
    result = {"paper_tetrahedra": PAPER_TETS, "cases": rows, "fits": summary,
              "machine": {"cores": __import__("os").cpu_count()}}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


# ---------------------------------------------------------------------- pytest-benchmark (20k)
@pytest.fixture(scope="module")
def model20k():
    return make_mesh(*SIZES["20k"])


@pytest.mark.parametrize("solver", ["pardiso", "amg", "scipy"])
def test_newton_step_20k(benchmark, model20k, solver):
    """One 100 N load step (all Newton iterations) on ~20k linear tets; ratio to Pardiso in extra_info."""
    from needletissue.fem import FEModel, Fixed, SurfaceForce, solve

    def run():
        model = FEModel(model20k, {"muscle": "muscle", "adipose": "adipose", "needle": "needle"})
        return solve(model, [Fixed("bottom"), SurfaceForce("needle_top", (100.0, 0.0, 0.0))], [1.0],
                     solver=solver, progress=False, results=False)[-1]

    res = benchmark.pedantic(run, rounds=3, iterations=1)
    it = res.newton_iterations
    benchmark.extra_info.update({
        "tetrahedra": len(model20k.cells), "newton_iterations": it,
        "linear_solve_per_iteration_s": res.timing_s["linear_solve"] / it,
        "assembly_and_update_per_iteration_s": res.timing_s["assembly_and_update"] / it,
    })
    if benchmark.stats is None:  # --benchmark-disable: ran once, nothing timed
        return
    _MEDIANS[solver] = benchmark.stats.stats.median
    if "pardiso" in _MEDIANS:
        benchmark.extra_info["ratio_to_pardiso"] = _MEDIANS[solver] / _MEDIANS["pardiso"]


_MEDIANS: dict[str, float] = {}


if __name__ == "__main__":
    if sys.argv[1] == "case":
        print(json.dumps(run_case(sys.argv[2], sys.argv[3], Path(sys.argv[4]))))
    elif sys.argv[1] == "scale":
        import argparse

        ap = argparse.ArgumentParser()
        ap.add_argument("cmd")
        ap.add_argument("--sizes", nargs="+", default=list(SIZES))
        ap.add_argument("--solvers", nargs="+", default=list(SOLVERS))
        ap.add_argument("--out", type=Path, default=HERE / "results" / "bench_fem.json")
        ap.add_argument("--mesh-dir", type=Path, default=Path("/tmp/needletissue_bench_meshes"))
        a = ap.parse_args()
        scale(a.sizes, a.solvers, a.out, a.mesh_dir)
    elif sys.argv[1] == "combine":  # combine OUT IN1 IN2 ...: one table and fit from separate runs
        rows = [r for f in sys.argv[3:] for r in json.loads(Path(f).read_text())["cases"]]
        summarize(rows, SOLVERS, Path(sys.argv[2]))
