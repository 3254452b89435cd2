"""FE needle model with a soft clamp bar, against the frame model's rigid and elastic clamps.

    OMP_NUM_THREADS=1 PYTHONPATH=src nice python benchmarks/frame_clamp/soft_clamp_fe.py [--run] [--E 2000]

The steel clamp of `fe needle` is ~800 x stiffer in bending than a pin, so its elasticity moves the answers by
0.1 % at most (docs/frame.md): too little to test the elastic clamp against the FE. Here the FE's clamp region
gets a modulus E (MPa; a user material registered under the name "clamp", which the registry prefers to the
built-in steel), default 2,000 MPa = steel / 100, and the default geometry (2 pins, d 5, l 100, depth 30,
bar 60 x 20 x 20 mm) is loaded with 100 N in the pins' plane (x) and across it (y), one run each (~2 min
each on the default mesh). --run solves the FE and adds the run to soft_clamp_fe.json beside this file (the key
numbers; a list of runs, one per E); without it the stored runs are compared. Units mm, N, MPa.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
OUT = HERE / "soft_clamp_fe.json"


def run_fe(E: float, force: float = 100.0, directions=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))) -> dict:
    from needletissue import materials
    from needletissue.materials.registry import Material
    from needletissue.models.needle.model import NeedleModelConfig, run_needle_model

    materials.register(Material("clamp", "elastic", dict(E=E, nu=0.30), density=7.85,
                                source=f"soft clamp for benchmarks/frame_clamp/soft_clamp_fe.py (steel / {200000 / E:g})"))
    out = {"clamp_E_MPa": E, "cases": []}
    for direction in directions:
        # K = 100 mu0: the K soft_clamp_fe.json was computed at (the default before issue 16)
        cfg = NeedleModelConfig(forces=(force,), direction=direction, ritz=False,
                                tissue_bulk_ratio=materials.TISSUE_BULK_RATIO)
        res = run_needle_model(cfg)
        r = res.results[0]
        out["cases"].append({"direction": list(direction), "force_N": force,
                             "clamp_displacement_vector_mm": list(r.clamp_displacement_vector_mm),
                             "clamp_centre_fit_mm": list(r.clamp_fit["centre_displacement_mm"]),
                             "clamp_fit_rms_mm": r.clamp_fit["rms_residual_mm"],
                             "clamp_rotation_rad": list(r.clamp_rotation_rad),
                             "max_needle_deformation_mm": r.max_needle_deformation_mm,
                             "mesh": res.mesh})
        print(out["cases"][-1], flush=True)
    return out


def compare(data: dict) -> list[dict]:
    from needletissue.frame import FrameModel
    from needletissue.frame.solver import solve

    E = data["clamp_E_MPa"]
    rows = []
    for c in data["cases"]:
        F = c["force_N"] * np.asarray(c["direction"])
        u_fe = np.asarray(c["clamp_displacement_vector_mm"])
        d_fe = c["max_needle_deformation_mm"]
        row = {"direction": c["direction"], "fe_clamp_mm": float(np.linalg.norm(u_fe)), "fe_max_needle_mm": d_fe}
        for kind in ("rigid", "elastic"):
            r = solve(F, model=FrameModel(clamp=kind, clamp_E_MPa=E))
            u = np.asarray(r.clamp_displacement_mm)
            row[kind] = {"clamp_mm": float(np.linalg.norm(u)), "clamp_error_pct": 100 * float(np.linalg.norm(u - u_fe))
                         / float(np.linalg.norm(u_fe)), "clamp_signed_pct": 100 * (np.linalg.norm(u) / np.linalg.norm(u_fe) - 1),
                         "max_needle_mm": r.max_needle_deflection_mm,
                         "max_needle_signed_pct": 100 * (r.max_needle_deflection_mm / d_fe - 1)}
        rows.append(row)
        print(f"E_clamp {E:g} MPa, direction {c['direction']}: FE clamp {row['fe_clamp_mm']:.4f} mm, max needle "
              f"{d_fe:.4f} mm; frame rigid clamp {row['rigid']['clamp_mm']:.4f} ({row['rigid']['clamp_signed_pct']:+.2f} %), "
              f"max needle {row['rigid']['max_needle_mm']:.4f} ({row['rigid']['max_needle_signed_pct']:+.2f} %); elastic "
              f"{row['elastic']['clamp_mm']:.4f} ({row['elastic']['clamp_signed_pct']:+.2f} %), max needle "
              f"{row['elastic']['max_needle_mm']:.4f} ({row['elastic']['max_needle_signed_pct']:+.2f} %)")
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", action="store_true")
    p.add_argument("--E", type=float, default=2000.0)
    p.add_argument("--in-plane-only", action="store_true", help="only the force along x")
    a = p.parse_args(argv)
    runs = json.loads(OUT.read_text()) if OUT.exists() else []
    if a.run:
        dirs = ((1.0, 0.0, 0.0),) if a.in_plane_only else ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
        runs = [r for r in runs if r["clamp_E_MPa"] != a.E] + [run_fe(a.E, directions=dirs)]
        OUT.write_text(json.dumps(runs, indent=1))
    for data in runs:
        compare(data)


if __name__ == "__main__":
    main()
