"""Mesh convergence of the anatomical model (issue 16): max needle deformation and clamp displacement at
three element sizes in a constant ratio, with the Richardson estimate of the converged value.

All element sizes scale together (tissue at the needles h, needles 2h/3, far field 4h: `fe pelvis`'s
defaults), so the three runs are one refinement family. With `--mesher box` tissue is assigned per tet by its
centroid's label (docs/pelvis_model.md): the tissue boundaries move with h too, so the observed order includes
that geometric error, not only the discretisation of one fixed geometry. With `--mesher smooth` the interfaces
are CGAL's approximations of the same label map's isosurfaces at every size (geometry.graded; pieces of a
tissue smaller than their local element are merged at each size, far from the needles).

    PYTHONPATH=src nice python benchmarks/pelvis_mesh_convergence.py [--sizes 4 3 2.25] \
        [--out src/needletissue/data/pelvis_convergence.json] [--interfaces paper --out benchmarks/results/pelvis_convergence_contact.json]
        [--mesher smooth --sizes 4.5 3.6 2.88 --out benchmarks/results/pelvis_convergence_smooth.json]

Each size runs in its own process (peak memory per size, a crash loses one size only). Needs ../shared/data.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

FORCES = (100.0, 200.0, 300.0)
KEYS = ("max_needle_deformation_mm", "clamp_displacement_mm")


def run_one(size: float, forces, interfaces: str, mesher: str = "box") -> dict:
    """One `fe pelvis` solve in this process: per-force results, mesh size, time, memory."""
    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    t = time.perf_counter()
    res = run_pelvis_model(PelvisConfig(forces=list(forces), mesh_size=size, interfaces=interfaces, figures=False,
                                        out=None, mesher=mesher))
    d = res.to_dict()
    ru = resource.getrusage(resource.RUSAGE_SELF)
    run = {"mesh_size_mm": size, "mesher": mesher, "tetrahedra": d["mesh"]["tetrahedra"], "dofs": d["mesh"]["dofs"],
           "wall_s": time.perf_counter() - t, "cpu_s": ru.ru_utime + ru.ru_stime,
           "solve_wall_s": d["timing_s"]["solve"], "peak_rss_GiB": ru.ru_maxrss / 1024**2,
           "results": [{k: r[k] for k in ("force_N", *KEYS, "newton_iterations")} for r in d["results"]]}
    if d.get("contact"):  # per force: equilibrium, interpenetration, per interface gaps / slip / pressure
        run["contact"] = [{k: x[k] for k in ("force_N", "equilibrium_error", "max_interpenetration_mm",
                                             "max_gap_opening_mm", "interfaces")} for x in d["contact"]["per_force"]]
    return run


def fit(h: list, f: list) -> dict:
    """Richardson through the three sizes (models.needle.convergence.richardson), as JSON; the GCI (Roache,
    safety factor 1.25) on the finest pair. Not monotone: no asymptotic range, say so."""
    from needletissue.errors import InputError
    from needletissue.models.needle.convergence import richardson

    try:
        r = richardson(*f, ratio=h[0] / h[1])
    except InputError as exc:
        return {"values": f, "order": None, "extrapolated": None, "note": str(exc)}
    return {"values": f, "ratio": r.ratio, "order": r.order, "extrapolated": r.extrapolated,
            "finest_error_rel": (f[2] - r.extrapolated) / r.extrapolated,
            "gci_fine": 1.25 * abs((f[2] - f[1]) / f[2]) / (r.ratio**r.order - 1)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs=3, default=[4.0, 3.0, 2.25],
                    help="three tissue element sizes at the needles, mm, in a constant ratio (coarse first)")
    ap.add_argument("--interfaces", default="bonded", help="bonded or paper (fe pelvis --interfaces)")
    ap.add_argument("--mesher", default="box", help="box or smooth (fe pelvis --mesher)")
    ap.add_argument("--out", default="src/needletissue/data/pelvis_convergence.json",
                    help="results JSON (package data: reproduce compares the frame model with its limits)")
    ap.add_argument("--refit", action="store_true", help="only redo the fits from the runs stored in --out")
    ap.add_argument("--resume", action="store_true", help="keep the runs stored in --out, run the other sizes")
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    a = ap.parse_args()
    if a.one is not None:
        print(json.dumps(run_one(a.one, FORCES, a.interfaces, a.mesher)))
        return
    h = sorted(a.sizes, reverse=True)
    if abs(h[0] / h[1] - h[1] / h[2]) > 1e-3 * h[0] / h[1]:
        ap.error(f"--sizes must be in a constant ratio, got {h}")
    runs = json.loads(Path(a.out).read_text())["runs"] if a.refit or (a.resume and Path(a.out).exists()) else []
    if a.refit:
        h = [r["mesh_size_mm"] for r in runs]
    for size in h[len(runs):]:
        p = subprocess.run([sys.executable, __file__, "--one", str(size), "--interfaces", a.interfaces,
                            "--mesher", a.mesher],
                           capture_output=True, text=True)
        if p.returncode:
            sys.exit(f"size {size} mm failed:\n{p.stderr[-3000:]}")
        runs.append(json.loads(p.stdout.strip().splitlines()[-1]))
        Path(a.out).write_text(json.dumps({"interfaces": a.interfaces, "mesher": a.mesher, "sizes_mm": h,
                                           "runs": runs}, indent=1) + "\n")   # a later failure keeps this run
        r = runs[-1]
        print(f"h = {size:g} mm: {r['tetrahedra']} tets, {r['dofs']} dofs, {r['wall_s']:.0f} s wall, "
              f"{r['cpu_s']:.0f} s CPU, {r['peak_rss_GiB']:.2f} GiB; max needle deformation "
              + " / ".join(f"{x['max_needle_deformation_mm']:.4f}" for x in r["results"]) + " mm", flush=True)
    study = {"interfaces": a.interfaces, "mesher": a.mesher, "sizes_mm": h, "runs": runs, "richardson": {}}
    for i, F in enumerate(FORCES):
        for key in KEYS:
            study["richardson"][f"{key}@{F:g}N"] = fit(h, [r["results"][i][key] for r in runs])
    Path(a.out).write_text(json.dumps(study, indent=1) + "\n")
    for name, v in study["richardson"].items():
        if v["order"] is None:
            print(f"{name}: {v['note']}; values {v['values']}")
        else:
            print(f"{name}: observed order {v['order']:.2f}, extrapolated {v['extrapolated']:.4f} mm, finest "
                  f"{v['values'][2]:.4f} mm ({100 * v['finest_error_rel']:+.2f} %), GCI {100 * v['gci_fine']:.2f} %")


if __name__ == "__main__":
    main()
