"""The frame model against the project's FE needle model, point by point, over the FE sweep.

    PYTHONPATH=src python benchmarks/frame_vs_fe.py [--data benchmarks/frame_sweep/fe_sweep.json]
                                                    [--calibrate] [--out benchmarks/frame_vs_fe.json]

Data: `fe_sweep.json` of benchmarks/frame_sweep (schema in its README.md): one record per
(configuration, force) with the FE inputs and outputs. For each record the frame model is built with
the same geometry, layers (paper Table 1 k) and clamp, loaded like the FE: the force at the gripper centre
and the FE's moment about it as a dead moment. (The FE applies the moment as a dead, self-equilibrated
traction on the gripper faces. Statically that is the force acting at `load_point_mm`, but only in the
undeformed state: at the clamp rotations of the moment cases (up to 0.67 rad, e00 at 300 N) the force at
the offset point turns its arm with the clamp and the FE's traction does not; the dead moment is the
closer like-for-like, 1.4 % against 2.5 % on e00 at 300 N.) Compared on
- the clamp-centre displacement vector (FE: best rigid motion of the clamp nodes), error |u_frame - u_FE|,
- the max needle deflection (FE `max_needle_deformation_mm`, the part in the clamp included).
Goal (issue #14): every point within max(0.432 mm, 2.4 % of the FE value), median below 1 %.
--calibrate: also fit the factors (default: tissue_factor alone; --params a,b,... for others) to all points
by least squares in units of the goal, residual / max(0.432 mm, 2.4 % of the FE value)
(needletissue.frame.calibration), and report the errors with the fitted factors (in sample) and their
95 % intervals; --cross-validate: leave one configuration out, fit on the others, predict it. Seconds
(about 3 min with --cross-validate).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from needletissue.frame import FrameModel
from needletissue.frame.solver import solve
from needletissue.ritz.model import DEFAULT_LAYERS, Layer

HERE = Path(__file__).parent
GOAL_MM, GOAL_REL, GOAL_MEDIAN = 0.432, 0.024, 0.01
# With the plate bone law the bone's factors fit close to 1 (beside the tissue factor: cortex_factor 0.967
# (95 % 0.950-0.984), axial_factor 0.86 (0.74-1.00), docs/frame.md): the bone stays physical and only the
# tissue springs' factor is fitted.
FIT_PARAMS = ("tissue_factor",)


def model_of(rec: dict, **factors) -> FrameModel:
    k = {la.name: la.k_N_per_mm2 for la in DEFAULT_LAYERS}
    layers = (Layer("muscle", rec["muscle_thickness_mm"], k["muscle"]),
              Layer("adipose", rec["adipose_thickness_mm"], k["adipose"]))
    return FrameModel(needles=int(rec["needles"]), needle_xy=tuple((x, 0.0) for x in rec["needle_x_mm"]),
                      diameter_mm=rec["diameter_mm"], free_length_mm=rec["free_length_mm"],
                      depth_mm=rec["depth_mm"], cortex_mm=rec["cortical_thickness_mm"],
                      bone_thickness_mm=rec["bone_thickness_mm"],
                      clamp_length_mm=rec["grip_length_mm"], clamp_width_mm=rec["clamp_width_mm"],
                      clamp_overhang_mm=rec["clamp_overhang_mm"], layers=layers,
                      **factors)  # the load at the gripper centre (the default), the FE's moment about it


def compare(records, **factors):
    rows = []
    for rec in records:
        m = model_of(rec, **factors)
        r = solve(rec["force_vector_N"], rec["moment_Nmm"], m)
        u_fe = np.array(rec["clamp_centre_displacement_mm"])
        u = np.array(r.clamp_displacement_mm)
        e_c = float(np.linalg.norm(u - u_fe))
        d_fe = rec["max_needle_deformation_mm"]
        e_d = abs(r.max_needle_deflection_mm - d_fe)
        rows.append({"config_id": rec["config_id"], "force_N": rec["force_N"], "needles": rec["needles"],
                     "direction": rec["direction"], "fe_clamp_mm": float(np.linalg.norm(u_fe)),
                     "frame_clamp_mm": float(np.linalg.norm(u)), "clamp_error_mm": e_c,
                     "clamp_error_pct": 100 * e_c / np.linalg.norm(u_fe),
                     "fe_max_needle_mm": d_fe, "frame_max_needle_mm": r.max_needle_deflection_mm,
                     "max_needle_error_mm": e_d, "max_needle_error_pct": 100 * e_d / d_fe,
                     "fe_rotation_rad": rec["clamp_rotation_rad"], "frame_rotation_rad": list(r.clamp_rotation_rad),
                     "within_goal": bool(e_c <= max(GOAL_MM, GOAL_REL * np.linalg.norm(u_fe))
                                         and e_d <= max(GOAL_MM, GOAL_REL * d_fe)),
                     "frame_error_estimate_mm": r.error_estimate_mm,
                     # not in the goal: the pins' tilt at the bone surface (FE: cubic fit of the axis near z = 0)
                     "fe_root_slope_rad": [math.atan(math.hypot(*sl)) for sl in rec["root_slope"]],
                     "frame_root_slope_rad": [n.root_slope_rad for n in r.needles]})
    return rows


def summary(rows) -> dict:
    out = {"points": len(rows), "within_goal": int(sum(r["within_goal"] for r in rows))}
    for key in ("clamp_error", "max_needle_error"):
        mm = np.array([r[f"{key}_mm"] for r in rows])
        pct = np.array([r[f"{key}_pct"] for r in rows])
        out[key] = {"max_mm": float(mm.max()), "median_mm": float(np.median(mm)), "max_pct": float(pct.max()),
                    "median_pct": float(np.median(pct))}
    ds = np.array([abs(a - b) for r in rows for a, b in zip(r["frame_root_slope_rad"], r["fe_root_slope_rad"])])
    fs = np.array([b for r in rows for b in r["fe_root_slope_rad"]])
    out["root_slope"] = {"max_error_rad": float(ds.max()), "median_error_rad": float(np.median(ds)),
                         "max_fe_rad": float(fs.max())}
    out["goal_met"] = bool(out["within_goal"] == len(rows) and out["clamp_error"]["median_pct"] < 100 * GOAL_MEDIAN
                           and out["max_needle_error"]["median_pct"] < 100 * GOAL_MEDIAN)
    return out


def _print(title, s):
    print(f"{title}: {s['points']} points, {s['within_goal']} within max(0.432 mm, 2.4 %); goal met: {s['goal_met']}")
    for key in ("clamp_error", "max_needle_error"):
        v = s[key]
        print(f"  {key:17s} max {v['max_mm']:.3f} mm ({v['max_pct']:.2f} %), median {v['median_mm']:.3f} mm "
              f"({v['median_pct']:.2f} %)")
    v = s["root_slope"]
    print(f"  root slope        max error {v['max_error_rad']:.4f} rad, median {v['median_error_rad']:.4f} rad "
          f"(FE slopes up to {v['max_fe_rad']:.4f} rad)")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=HERE / "frame_sweep" / "fe_sweep.json")
    p.add_argument("--calibrate", action="store_true")
    p.add_argument("--fit-tissue", action="store_true", help="fit the tissue factor too")
    p.add_argument("--params", default=None,
                   help="comma-separated factors to fit (default: FIT_PARAMS)")
    p.add_argument("--cross-validate", action="store_true",
                   help="leave one configuration out: fit on the others, predict it (out-of-sample errors)")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    global FIT_PARAMS
    if a.params:
        FIT_PARAMS = tuple(x.strip() for x in a.params.split(",") if x.strip())
    if a.fit_tissue and "tissue_factor" not in FIT_PARAMS:
        FIT_PARAMS = (*FIT_PARAMS, "tissue_factor")
    data = json.loads(a.data.read_text())
    records = [r for r in data["results"] if r.get("status", "ok") == "ok"]
    if not records:
        raise SystemExit(f"no FE results in {a.data}")
    import hashlib

    report = {"data": a.data.name, "data_sha256": hashlib.sha256(a.data.read_bytes()).hexdigest(),
              "configurations": len({r["config_id"] for r in records}), "physical": {}, "calibrated": None}
    rows = compare(records)
    report["physical"] = {"summary": summary(rows), "rows": rows}
    _print("frame (physical parameters, factors 1)", report["physical"]["summary"])
    if a.calibrate:
        from needletissue.frame.fitting import CalibrationPoint, calibration

        pts = [CalibrationPoint(model_of(r), tuple(r["force_vector_N"]), tuple(r["moment_Nmm"]),
                                clamp_displacement_mm=tuple(r["clamp_centre_displacement_mm"]),
                                max_needle_deflection_mm=r["max_needle_deformation_mm"]) for r in records]
        c = calibration(pts, params=FIT_PARAMS, tolerance=(GOAL_MM, GOAL_REL))
        rows_c = compare(records, **c.params)
        report["calibrated"] = {"params": c.params, "intervals_95": c.intervals, "rms_mm": c.rms_mm,
                                "summary": summary(rows_c), "rows": rows_c}
        print("fitted: " + ", ".join(f"{k} = {v:.4g} (95 % {c.intervals[k][0]:.4g} .. {c.intervals[k][1]:.4g})"
                                     for k, v in c.params.items()))
        _print("frame (fitted factors, in-sample)", report["calibrated"]["summary"])
    if a.cross_validate:
        from needletissue.frame.fitting import CalibrationPoint, calibration

        rows_cv = []
        configs = sorted({r["config_id"] for r in records})
        for cid in configs:
            train = [r for r in records if r["config_id"] != cid]
            test = [r for r in records if r["config_id"] == cid]
            pts = [CalibrationPoint(model_of(r), tuple(r["force_vector_N"]), tuple(r["moment_Nmm"]),
                                    clamp_displacement_mm=tuple(r["clamp_centre_displacement_mm"]),
                                    max_needle_deflection_mm=r["max_needle_deformation_mm"]) for r in train]
            c = calibration(pts, params=FIT_PARAMS, tolerance=(GOAL_MM, GOAL_REL))
            rows_cv += compare(test, **c.params)
        report["cross_validated"] = {"summary": summary(rows_cv), "rows": rows_cv}
        _print(f"frame (leave one of {len(configs)} configurations out)", report["cross_validated"]["summary"])
    worst = sorted(rows, key=lambda r: -r["max_needle_error_pct"])[:5]
    print("worst points (physical):")
    for r in worst:
        print(f"  {r['config_id']} {r['force_N']:g} N: max needle FE {r['fe_max_needle_mm']:.3f} frame "
              f"{r['frame_max_needle_mm']:.3f} mm; clamp FE {r['fe_clamp_mm']:.3f} frame {r['frame_clamp_mm']:.3f} mm")
    if a.out:
        a.out.write_text(json.dumps(report, indent=1, default=float) + "\n")
    return report


if __name__ == "__main__":
    main()
