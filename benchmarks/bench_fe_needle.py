"""The one-needle model of issue 18 (`fe needle --needles 1`, 100/200/300 N, 8,972 tet10, 37,677 free
dofs): wall, CPU, linear-solve time, Newton iterations and peak memory of this version against a
previous one, back to back, each run in its own process (honest peak RSS).

    nice python benchmarks/bench_fe_needle.py [--previous REF] [--repeat 2] [--write-docs]

The mesh is made once (gmsh, deterministic) and every run solves it from scratch. Variants:
- previous: the source of git revision REF (`git archive` into a temporary folder; its own defaults),
  only with --previous;
- current: the defaults of this version;
- *-mkl1: the same with MKL_NUM_THREADS=1 (Pardiso on one thread; FEBio was faster on one);
- *-mkl2: the same with MKL_NUM_THREADS=2 (Pardiso on both cores of the 2-core machine).
The displacement fields must agree (max |du| / max |u| against the previous version is printed;
<= 1e-6 required). Writes benchmarks/results/bench_fe_needle.json; --write-docs refreshes the table in
docs/bench.md. Reference figures (issue 18, same mesh and loads, 2 cores): needletissue 43.3 s, FEBio 32.5 s.
They were measured at the old tissue bulk modulus K = 100 mu0, so every variant here pins it
(`TISSUE_BULK_RATIO`; the default is 10 MPa since issue 16): like for like with FEBio.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
VARIANTS = ("previous", "previous-mkl1", "current", "current-mkl1")
EXTRA_VARIANTS = ("previous-mkl2", "current-mkl2")  # on request (--variants)
FORCES = (100.0, 200.0, 300.0)
ISSUE_TABLE = [  # issue 18, measured side by side on the shared 2-core machine
    ("needletissue (issue 18)", 43.3, 33.8, 18, 824),
    ("FEBio 4, 1 thread (issue 18)", 32.5, 26.8, 23, 333),
    ("FEBio 4, 2 threads (issue 18)", 40.2, 31.0, 23, 332),
]


def make_mesh(path: Path):
    from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model

    mesh_needle_model(NeedleGeometry(needles=1), path, order=2)


def run_one(variant: str, mesh_path: str, u_out: str) -> dict:
    """Solve the model as run_needle_model does (same materials, BCs, load path)."""
    from needletissue.fem import Fixed, FEModel, SurfaceForce, TaggedMesh, solve
    from needletissue.materials import TISSUE_BULK_RATIO, tissue_bulk
    from needletissue.models.needle.model import MATERIALS

    t0, c0 = time.perf_counter(), time.process_time()
    mesh = TaggedMesh.read(mesh_path)
    mats = {r: MATERIALS[r] for r in mesh.regions}
    bulk = tissue_bulk(mats, TISSUE_BULK_RATIO)  # the FEBio figures' K = 100 mu0
    model = FEModel(mesh, mats, order=2, formulation="mixed", bulk=bulk)
    fmax = max(FORCES)
    bcs = [Fixed("bone_fixed"), Fixed("tissue_far"), SurfaceForce("gripper", total=(0.0, fmax, 0.0))]
    res = solve(model, bcs, load_factors=[f / fmax for f in FORCES], progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    np.save(u_out, res[-1].displacement)
    last = res[-1]
    return {"variant": variant, "wall_s": wall, "cpu_s": cpu, "linear_solve_s": last.timing_s["linear_solve"],
            "newton_s": last.timing_s["newton"], "newton_iterations": last.newton_iterations, "steps": last.steps,
            "newton_substeps": last.newton_substeps,
            "free_dofs": int(model.ndof), "residual_norms": last.residual_norms,
            "iterations_per_force": [r.newton_iterations for r in res],
            "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def child(variant: str, mesh_path: str, u_out: str, previous: Path | None) -> dict:
    threads = {"-mkl1": "1", "-mkl2": "2"}.get(variant[-5:])
    env = {**os.environ, **({"MKL_NUM_THREADS": threads} if threads else {})}
    script = __file__
    if variant.startswith("previous"):  # that version's own run_one, on its own source
        env["PYTHONPATH"] = str(previous / "src")
        script = str(previous / "benchmarks" / "bench_fe_needle.py")
    out = subprocess.run([sys.executable, script, "--one", "current", mesh_path, u_out], check=True,
                         capture_output=True, text=True, env=env)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["variant"] = variant
    return res


def export(ref: str, dest: Path) -> Path:
    """src/ and benchmarks/ of git revision `ref`, for the "previous" variants."""
    dest.mkdir(parents=True, exist_ok=True)
    tar = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src", "benchmarks"], check=True,
                         capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=tar, check=True)
    return dest


def table(runs: list[dict]) -> str:
    rows = ["| | wall | CPU | linear solves | Newton iterations | peak memory |", "|---|---|---|---|---|---|"]
    for name, wall, lin, nit, mem in ISSUE_TABLE:
        rows.append(f"| {name} | {wall} s | | {lin} s | {nit} | {mem} MB |")
    for v in (*VARIANTS, *EXTRA_VARIANTS):
        rs = [r for r in runs if r["variant"] == v]
        if not rs:
            continue
        med = {k: float(np.median([r[k] for r in rs])) for k in ("wall_s", "cpu_s", "linear_solve_s")}
        mem = max(r["peak_rss_MB"] for r in rs)
        subs = f" + {rs[0]['newton_substeps']} substeps" if rs[0].get("newton_substeps") else ""
        rows.append(f"| this machine, {v} (median of {len(rs)}) | {med['wall_s']:.1f} s | {med['cpu_s']:.1f} s | "
                    f"{med['linear_solve_s']:.1f} s | {rs[0]['newton_iterations']}{subs} | {mem:.0f} MB |")
    return "\n".join(rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--one", nargs=3, metavar=("VARIANT", "MESH", "U_OUT"))
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--previous", metavar="REF", help="git revision to compare with (e.g. the last release)")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--from-json", action="store_true", help="only rewrite docs/bench.md from the last results")
    a = ap.parse_args()
    if a.one:
        print(json.dumps(run_one(*a.one)))
        return
    if a.from_json:
        write_docs(table(json.loads((HERE / "results" / "bench_fe_needle.json").read_text())["runs"]))
        return
    variants = [v for v in a.variants.split(",") if a.previous or not v.startswith("previous")]
    unknown = set(variants) - {*VARIANTS, *EXTRA_VARIANTS}
    if unknown:
        ap.error(f"--variants: unknown {sorted(unknown)}; known: {', '.join((*VARIANTS, *EXTRA_VARIANTS))}")
    with tempfile.TemporaryDirectory() as tmp:
        previous = export(a.previous, Path(tmp) / "previous") if a.previous else None
        msh = Path(tmp) / "needle1.msh"
        make_mesh(msh)
        runs, fields = [], {}
        # alternate the variants (A B A B): a drift of the shared machine's load hits both
        peak_note = "peak memory: ru_maxrss of each run's own process (imports, mesh read, solve)"
        for rep in range(a.repeat):
            for v in variants:
                u_out = str(Path(tmp) / f"u_{v}.npy")
                r = child(v, str(msh), u_out, previous)
                fields[v] = np.load(u_out)
                runs.append(r)
                print(f"{v:13s} wall {r['wall_s']:6.1f} s  cpu {r['cpu_s']:6.1f} s  linear {r['linear_solve_s']:6.1f} s  "
                      f"Newton {r['newton_iterations']} {r['iterations_per_force']}  peak {r['peak_rss_MB']} MB",
                      flush=True)
    ref = next((fields[v] for v in ("previous", "previous-mkl1") if v in fields), None)  # the same field
    diff = {v: float(np.abs(u - ref).max() / np.abs(ref).max()) for v, u in fields.items()} if ref is not None else {}
    for v, d in diff.items():
        print(f"field {v} vs previous: max |du| / max |u| = {d:.2e}")
    md = table(runs)
    print(md)
    res = {"runs": runs, "previous": a.previous, "field_difference_vs_previous": diff, "table_md": md,
           "note": peak_note}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "bench_fe_needle.json").write_text(json.dumps(res, indent=1))
    if a.write_docs:
        write_docs(md)


def write_docs(md: str):
    doc = ROOT / "docs" / "bench.md"
    text = doc.read_text()
    start, end = "<!-- bench_fe_needle:start -->", "<!-- bench_fe_needle:end -->"
    i, j = text.index(start) + len(start), text.index(end)
    doc.write_text(text[:i] + "\n" + md + "\n" + text[j:])


if __name__ == "__main__":
    main()
