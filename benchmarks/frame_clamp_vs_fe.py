"""The elastic clamp (FrameModel.clamp = "elastic") against the rigid one, both against the FE needle model.

    PYTHONPATH=src python benchmarks/frame_clamp_vs_fe.py [--data benchmarks/frame_sweep/fe_sweep.json]
                                                          [--fe OUT/results.json ...]

Over the stored FE sweep (benchmarks/frame_sweep, 124 points; the frame built like benchmarks/frame_vs_fe.py,
physical parameters): per load class, the signed error of the clamp-centre displacement |u| and of the max
needle deflection (frame / FE - 1, %), and the vector error of the clamp displacement, rigid -> elastic.
--fe: also the results.json of `needletissue fe needle --direction 1,0,0 --force F ... --out OUT` runs at the
default geometry (the force in the pins' plane, where the bar's bending matters). Units mm, N, %. ~1 min.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from needletissue.frame import FrameModel
from needletissue.frame.solver import solve

HERE = Path(__file__).parent
CLASSES = {"r": "default geometry (r100 1 pin across, r200 2 across, r201 2 in plane)", "a": "1 pin across",
           "b": "2 pins across", "c": "2 pins in their plane (portal frame)", "d": "2 pins, oblique + moment",
           "e": "1 pin, oblique + moment"}


def sweep(path: Path):
    import sys

    sys.path.insert(0, str(HERE))
    from frame_vs_fe import compare  # noqa: E402

    data = json.loads(path.read_text())
    recs = [r for r in data["results"] if r.get("status", "ok") == "ok"]
    rows = {kind: compare(recs, clamp=kind) for kind in ("rigid", "elastic")}
    groups = {}
    for r, e in zip(rows["rigid"], rows["elastic"]):
        g = r["config_id"] if r["config_id"].startswith("r") else r["config_id"][0]
        groups.setdefault(g, []).append([
            100 * (r["frame_clamp_mm"] / r["fe_clamp_mm"] - 1), 100 * (e["frame_clamp_mm"] / e["fe_clamp_mm"] - 1),
            r["clamp_error_pct"], e["clamp_error_pct"],
            100 * (r["frame_max_needle_mm"] / r["fe_max_needle_mm"] - 1),
            100 * (e["frame_max_needle_mm"] / e["fe_max_needle_mm"] - 1),
            r["max_needle_error_pct"], e["max_needle_error_pct"]])
    print("class   points | clamp |u| signed mean (%) | clamp vector error mean (%) | max needle signed mean (%) "
          "| max needle |error| mean (%)   [rigid -> elastic]")
    for g, v in sorted(groups.items()):
        v = np.array(v)
        print(f"{g:6s} {len(v):4d}   | {v[:, 0].mean():+.3f} -> {v[:, 1].mean():+.3f}        "
              f"| {v[:, 2].mean():.3f} -> {v[:, 3].mean():.3f}              | {v[:, 4].mean():+.3f} -> {v[:, 5].mean():+.3f}"
              f"           | {v[:, 6].mean():.3f} -> {v[:, 7].mean():.3f}")
    for g in ("r201", "c"):
        for r, e in zip(rows["rigid"], rows["elastic"]):
            if r["config_id"].startswith(g) and r["force_N"] in (100.0, 300.0):
                print(f"  {r['config_id']} {r['force_N']:5.0f} N: clamp FE {r['fe_clamp_mm']:.4f}, rigid "
                      f"{r['frame_clamp_mm']:.4f} ({100 * (r['frame_clamp_mm'] / r['fe_clamp_mm'] - 1):+.2f} %), elastic "
                      f"{e['frame_clamp_mm']:.4f} ({100 * (e['frame_clamp_mm'] / e['fe_clamp_mm'] - 1):+.2f} %); max needle "
                      f"FE {r['fe_max_needle_mm']:.4f}, rigid {r['frame_max_needle_mm']:.4f}, elastic "
                      f"{e['frame_max_needle_mm']:.4f}")


def fresh(path: Path):
    d = json.loads(path.read_text())
    for r in d["results"]:
        F = r["force_N"]
        u_fe = np.array(r["clamp_displacement_vector_mm"])
        d_fe = r["max_needle_deformation_mm"]
        for kind in ("rigid", "elastic"):
            s = solve((F, 0.0, 0.0), model=FrameModel(clamp=kind))
            u = np.array(s.clamp_displacement_mm)
            print(f"{path.parent.name} {F:5.0f} N {kind:7s}: clamp u_x {u[0]:.4f} mm (FE {u_fe[0]:.4f}, "
                  f"{100 * (u[0] / u_fe[0] - 1):+.2f} %), |u - u_FE| {np.linalg.norm(u - u_fe):.4f} mm; max needle "
                  f"{s.max_needle_deflection_mm:.4f} mm (FE {d_fe:.4f}, {100 * (s.max_needle_deflection_mm / d_fe - 1):+.2f} %); "
                  f"clamp rotation y {s.clamp_rotation_rad[1]:.5f} rad (FE {r['clamp_rotation_rad'][1]:.5f})")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=HERE / "frame_sweep" / "fe_sweep.json")
    p.add_argument("--fe", type=Path, nargs="*", default=[])
    a = p.parse_args(argv)
    sweep(a.data)
    for f in a.fe:
        fresh(f)


if __name__ == "__main__":
    main()
