"""FE sweep for the needle-frame model (issue 14): run the study configs in studies/ through the project's
study runner (Dask), and export every (case, force) point as fe_sweep.csv / fe_sweep.json (+ the axis
curves in fe_sweep_curves.json). README.md documents the design and the schema.

    PYTHONPATH=src nice python benchmarks/frame_sweep/run_sweep.py            # run (resumes) + export
    PYTHONPATH=src python benchmarks/frame_sweep/run_sweep.py --export-only   # export what is on disk
    ... --scheduler tcp://host:8786                                           # an existing Dask cluster

Study folders go to benchmarks/frame_sweep/runs/<study> (not committed: chunks, figures, parquet); a
rerun skips every case already on disk. While the sweep runs the export is refreshed every minute,
so the data files always hold every finished case.
"""

from __future__ import annotations

import argparse
import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
# Submission (= priority) order: the reference configs, then the load classes that have no FE result
# elsewhere in the project (in-plane, moment), the across cases last.
ORDER = ("r1", "r2", "c", "d", "e", "b", "a")
STUDIES = sorted((HERE / "studies").glob("*.toml"), key=lambda p: ORDER.index(p.stem.split("_")[0]))
RUNS = HERE / "runs"
GROUPS = {p.stem: p.stem.split("_")[0] for p in STUDIES}


def _records(study: Path):
    """(row, curves) for every finished case of one study folder, read from its chunk files."""
    out_dir = RUNS / study.stem
    cases_path = out_dir / "cases.parquet"
    if not cases_path.exists():
        return []
    cases = pd.read_parquet(cases_path)
    parts = [pd.read_parquet(p) for p in sorted((out_dir / "chunks").glob("chunk_*.parquet"))]
    if not parts:
        return []
    done = cases.merge(pd.concat(parts, ignore_index=True), on="case_id", how="inner")
    out = []
    for _, row in done.sort_values("case_id").iterrows():
        if row["status"] != "ok":
            out.append(({"group": GROUPS[study.stem], "study": study.stem, "case_id": int(row["case_id"]),
                         "status": "failed", "error": row["error"]}, None))
            continue
        out.extend(_points(study.stem, int(row["case_id"]), json.loads(row["per_force_json"]),
                           float(row["case_wall_time_s"])))
    return out


def _points(study: str, case_id: int, info: dict, case_wall: float):
    g = info["geometry"]
    n = g["needles"]
    needles = [f"needle_{i + 1}" for i in range(n)]
    base = {
        "group": GROUPS[study], "study": study, "case_id": case_id, "config_id": f"{GROUPS[study]}{case_id:02d}",
        "status": "ok", "needles": n, "diameter_mm": g["diameter"], "free_length_mm": g["free_length"],
        "spacing_mm": g["spacing"] if n == 2 else math.nan,
        "needle_x_mm": [0.0] if n == 1 else [-g["spacing"] / 2, g["spacing"] / 2],
        "depth_mm": g["depth"], "cortical_thickness_mm": g["cortical_thickness"],
        "bone_thickness_mm": g["bone_thickness"], "muscle_thickness_mm": g["muscle_thickness"],
        "adipose_thickness_mm": g["adipose_thickness"],
        "tissue_thickness_mm": g["muscle_thickness"] + g["adipose_thickness"],
        "grip_length_mm": g["grip_length"], "clamp_width_mm": g["clamp_width"],
        "clamp_overhang_mm": g["clamp_overhang"], "half_width_mm": g["half_width"],
        "gripper_centre_z_mm": g["free_length"] - g["grip_length"] / 2,
        "direction": info["direction"], "load_offset_mm": info["load_offset_mm"],
        "needle_mesh_size_mm": g["needle_mesh_size"], "mesh_size_mm": g["mesh_size"],
        "far_mesh_size_mm": g["far_mesh_size"], "tetrahedra": info["mesh"]["tetrahedra"],
        "dofs": info["mesh"]["dofs"], "case_wall_time_s": case_wall,
        "mesh_time_s": info["timing_s"].get("mesh"),
    }
    out, prev_it, prev_t = [], 0, 0.0
    for p in info["per_force"]:
        st = p.get("strength_utilisation", {})
        vm = p.get("max_von_mises_MPa", {})
        rec = {**base,
               "force_N": p["force_N"], "force_vector_N": p["force_vector_N"], "moment_Nmm": p["moment_Nmm"],
               "load_point_mm": p["load_point_mm"],
               "clamp_displacement_mm": p["clamp_displacement_mm"],
               "clamp_displacement_vector_mm": p["clamp_displacement_vector_mm"],
               "clamp_centre_displacement_mm": p["clamp_fit"]["centre_displacement_mm"],
               "clamp_rotation_rad": p["clamp_rotation_rad"],
               "clamp_fit_rms_mm": p["clamp_fit"]["rms_residual_mm"],
               "max_needle_deformation_mm": p["max_needle_deformation_mm"],
               "needle_max_deformation_mm": [p["max_deformation_mm"][k] for k in needles],
               "needle_end_deflection_mm": [p["needle_end_deflection_mm"][k] for k in needles],
               "root_slope": [p["root_slope"][k] for k in needles],
               "root_displacement_mm": [p["root_displacement_mm"][k] for k in needles],
               "max_deformation_muscle_mm": p["max_deformation_mm"].get("muscle"),
               "max_deformation_adipose_mm": p["max_deformation_mm"].get("adipose"),
               "max_deformation_bone_mm": max(p["max_deformation_mm"].get(k, 0.0)
                                              for k in ("cortical_bone", "cancellous_bone")),
               "needle_yield_utilisation": p.get("needle_yield_utilisation"),
               "bone_strength_utilisation": p.get("bone_strength_utilisation"),
               "cortical_strength_utilisation": st.get("cortical_bone"),
               "cancellous_strength_utilisation": st.get("cancellous_bone"),
               "max_von_mises_needle_MPa": max(vm.get(k, 0.0) for k in needles),
               "validity_warnings": len(p.get("validity_warnings", [])),
               "ritz_tip_deflection_mm": p.get("ritz_tip_deflection_mm"),
               "ritz_force_per_needle_tip_deflection_mm": p.get("ritz_force_per_needle_tip_deflection_mm"),
               "newton_iterations": p["newton_iterations"] - prev_it,
               "newton_iterations_cumulative": p["newton_iterations"],
               "solve_wall_time_s": p["solve_wall_time_s"] - prev_t,
               "solve_wall_time_cumulative_s": p["solve_wall_time_s"]}
        prev_it, prev_t = p["newton_iterations"], p["solve_wall_time_s"]
        curves = {"config_id": base["config_id"], "force_N": p["force_N"], "curves": p["curves"]}
        out.append((rec, curves))
    return out


VECTORS = {"force_vector_N": ("force_{}_N", "xyz"), "moment_Nmm": ("moment_{}_Nmm", "xyz"),
           "load_point_mm": ("load_point_{}_mm", "xyz"), "direction": ("direction_{}", "xyz"),
           "load_offset_mm": ("load_offset_{}_mm", "xyz"),
           "clamp_displacement_vector_mm": ("clamp_u{}_mm", "xyz"),
           "clamp_centre_displacement_mm": ("clamp_centre_u{}_mm", "xyz"),
           "clamp_rotation_rad": ("clamp_rot_{}_rad", "xyz")}


def _flat(rec: dict) -> dict:
    """One CSV row: vectors split into components, per-needle lists into needle_1_/needle_2_ columns."""
    out = {}
    for k, v in rec.items():
        if k in VECTORS:
            fmt, comps = VECTORS[k]
            out.update({fmt.format(c): x for c, x in zip(comps, v)})
        elif k == "needle_x_mm":
            for i in range(2):
                out[f"needle_{i + 1}_x_mm"] = v[i] if i < len(v) else math.nan
        elif k in ("needle_max_deformation_mm", "needle_end_deflection_mm"):
            for i in range(2):
                out[f"needle_{i + 1}_{k.removeprefix('needle_')}"] = v[i] if i < len(v) else math.nan
        elif k == "root_slope":
            for i in range(2):
                s = v[i] if i < len(v) else [math.nan, math.nan]
                out[f"needle_{i + 1}_root_slope_x"], out[f"needle_{i + 1}_root_slope_y"] = s
        elif k == "root_displacement_mm":
            for i in range(2):
                s = v[i] if i < len(v) else [math.nan] * 3
                for c, x in zip("xyz", s):
                    out[f"needle_{i + 1}_root_u{c}_mm"] = x
        else:
            out[k] = v
    return out


def export() -> dict:
    from needletissue.runinfo import write_atomic

    rows, curves, failed = [], [], []
    for s in STUDIES:
        for rec, cur in _records(s):
            if rec["status"] != "ok":
                failed.append(rec)
                continue
            rows.append(rec)
            curves.append(cur)
    conv = HERE / "convergence.json"
    payload = {"schema": "benchmarks/frame_sweep/README.md", "generated_unix": time.time(),
               "configs": len({r["config_id"] for r in rows}), "points": len(rows), "failed": failed,
               "convergence": json.loads(conv.read_text()) if conv.exists() else None, "results": rows}
    write_atomic(HERE / "fe_sweep.json", json.dumps(payload, indent=1, allow_nan=True).encode())
    write_atomic(HERE / "fe_sweep_curves.json", json.dumps(curves).encode())
    if rows:
        write_atomic(HERE / "fe_sweep.csv", pd.DataFrame([_flat(r) for r in rows]).to_csv(index=False).encode())
    for name in ("fe_sweep.json", "fe_sweep_curves.json", "fe_sweep.csv"):
        if (HERE / name).exists():
            (HERE / name).chmod(0o644)   # the atomic temp file is private; the data is for everyone
    return {"configs": payload["configs"], "points": len(rows), "failed": len(failed)}


def summary() -> str:
    """Markdown tables of the exported data (pasted into README.md)."""
    df = pd.read_csv(HERE / "fe_sweep.csv")
    lines = ["| group | configs | points | max needle deformation at 300 N (mm) | clamp at 300 N (mm) | "
             "needle yield utilisation at 300 N | bone strength utilisation at 300 N | case wall (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for grp, d in df.groupby("group", sort=False):
        top = d[d["force_N"] == d["force_N"].max()]
        rng = lambda c: f"{top[c].min():.3g}-{top[c].max():.3g}" if len(top) > 1 else f"{top[c].iloc[0]:.3g}"
        lines.append(f"| {grp} | {d['config_id'].nunique()} | {len(d)} | {rng('max_needle_deformation_mm')} | "
                     f"{rng('clamp_displacement_mm')} | {rng('needle_yield_utilisation')} | "
                     f"{rng('bone_strength_utilisation')} | {d.groupby('config_id')['case_wall_time_s'].first().median():.0f} |")
    # force at which a utilisation reaches 1, per config (linear interpolation along the load path)
    def onset(d, col):
        f, u = d["force_N"].to_numpy(), d[col].to_numpy()
        if u.max() < 1:
            return math.inf
        if u[0] >= 1:
            return f[0] * 1 / u[0]   # ~ linear from zero: below the first force
        return float(np.interp(1.0, u, f))

    lines += ["", "| group | configs | needle yields at (N): min / median / max | cortical bone strength reached at (N) | "
              "cancellous bone strength reached at (N) |", "|---|---|---|---|---|"]
    for grp, d in df.groupby("group", sort=False):
        cells = []
        for col in ("needle_yield_utilisation", "cortical_strength_utilisation", "cancellous_strength_utilisation"):
            v = np.array([onset(c, col) for _, c in d.groupby("config_id")])
            txt = lambda x: "> 300" if math.isinf(x) else f"{x:.0f}"
            cells.append(f"{txt(v.min())} / {txt(np.median(v))} / {txt(v.max())}")
        lines.append(f"| {grp} | {d['config_id'].nunique()} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--export-only", action="store_true")
    ap.add_argument("--summary", action="store_true", help="print the README's result tables")
    ap.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", nargs="*", help="study names (file stems) to run, default all")
    a = ap.parse_args()
    if a.summary:
        print(summary())
        return
    if a.export_only:
        print(export())
        return
    from dask.distributed import Client, LocalCluster

    from needletissue.studies.config import load_study
    from needletissue.studies.runner import run_study

    cluster = None
    if a.scheduler is None:   # one cluster for all studies: workers start once
        cluster = LocalCluster(n_workers=a.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=40)
    address = a.scheduler or cluster.scheduler_address
    stop = threading.Event()

    def refresh():
        while not stop.wait(60):
            try:
                export()
            except Exception as exc:  # a half-written study folder: next minute
                print(f"export skipped: {exc}")

    threading.Thread(target=refresh, daemon=True).start()
    t0 = time.perf_counter()

    def one(s):
        t = time.perf_counter()
        res = run_study(load_study(s), RUNS / s.stem, scheduler=address, progress=False)
        print(f"{s.stem}: {res.n_ok} ok, {res.n_failed} failed, {res.computed_this_run} computed, "
              f"{time.perf_counter() - t:.0f} s; timing {json.dumps(res.timing)}", flush=True)

    # All studies at once on the one cluster (a client each, submitted in order): the workers stay busy
    # across study boundaries instead of idling while a small study finishes its last case.
    todo = [s for s in STUDIES if not a.only or s.stem in a.only]
    threads = []
    try:
        for s in todo:
            th = threading.Thread(target=one, args=(s,))
            th.start()
            threads.append(th)
            time.sleep(2)  # submission order = priority order
        for th in threads:
            th.join()
        print(export(), flush=True)
    finally:
        stop.set()
        if cluster is not None:
            cluster.close()
    print(f"sweep wall time {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
