"""Tissue bulk modulus (issue 16, item 3): the needle and pelvis models at the old K = 100 mu0 and at the
materials' default K, back to back in one process. Prints per run: CPU (process_time), wall, Newton
iterations, accepted increments, cut-backs, needle deflection, per tissue region the max |u|, the largest
principal stretch and the largest |J - 1| (cell means), at the largest force.

    PYTHONPATH=src python benchmarks/bulk_study.py needle2 [--order 1] [--repeat 2]   # fe needle default
    PYTHONPATH=src python benchmarks/bulk_study.py needle1                             # --needles 1
    PYTHONPATH=src python benchmarks/bulk_study.py pelvis [--formulation displacement]
    PYTHONPATH=src python benchmarks/bulk_study.py r1      # the frame sweep's reference case (stored at 100 mu0)

Locking of the order-1 (linear tet) path: compare `--order 1` with the order-2 rows (same geometry).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from needletissue.materials import TISSUE_BULK_RATIO

SWEEP = Path(__file__).resolve().parent / "frame_sweep" / "studies"


def tissue_state(fe, materials: dict) -> dict:
    """Per tissue region: max |u| (mm), largest principal stretch, largest |J - 1| (cell means)."""
    from needletissue import materials as mats

    lam, tag = fe.cell_data["principal_stretches"], fe.cell_data["region"]
    out = {}
    for region, i in fe.region_tags.items():
        if mats.get(materials[region]).model == "elastic":
            continue
        s = lam[tag == i]
        out[region] = {"max_u_mm": round(fe.max_displacement_by_region[region], 5),
                       "max_stretch": round(float(s.max()), 5), "min_stretch": round(float(s.min()), 5),
                       "max_abs_J_minus_1": float(np.abs(s.prod(axis=1) - 1).max())}
    return out


def run(model: str, ratio, order: int, formulation: str | None) -> dict:
    c0, t0 = time.process_time(), time.perf_counter()
    if model.startswith(("needle", "r1", "r2")):
        from needletissue.geometry.needle import NeedleGeometry
        from needletissue.models.needle import NeedleModelConfig, run_needle_model
        from needletissue.models.needle.model import MATERIALS

        if model.startswith("needle"):
            cfg = NeedleModelConfig(geometry=NeedleGeometry(needles=int(model[-1])), order=order)
        else:  # the frame sweep's reference case (benchmarks/frame_sweep/studies/r*.toml, case 0)
            from needletissue.studies.case_fe_needle import case_config
            from needletissue.studies.config import load_study

            study = load_study(SWEEP / f"{model}_{'one_needle' if model == 'r1' else 'two_needles'}_default.toml")
            case = {k: v.values[0] for k, v in study.parameters.items()}
            cfg = case_config({**study.fixed, **case})
        cfg = replace(cfg, ritz=False, tissue_bulk_ratio=ratio)
        if formulation:
            cfg = replace(cfg, formulation=formulation)
        res = run_needle_model(cfg)
        last = res.results[-1]
        fe, needle = last.fe, last.max_needle_deformation_mm
        dofs = res.mesh["dofs"]
        per_force = [{"force_N": r.force_N, "needle_max_mm": round(r.max_needle_deformation_mm, 4),
                      "clamp_mm": round(r.clamp_displacement_mm, 4),
                      "tissue_max_mm": {k: round(r.max_deformation_mm[k], 4) for k in ("adipose", "muscle")}}
                     for r in res.results]
    else:
        import needletissue.fem as nfem
        from needletissue.models.pelvis import PelvisConfig, run_pelvis_model
        from needletissue.models.pelvis.model import MATERIALS

        cfg = PelvisConfig(mesher="box", order=order, figures=False, crosscheck_thickness=False, tissue_bulk_ratio=ratio,
                           **({"formulation": formulation} if formulation else {}))
        solved, solve = [], nfem.solve
        nfem.solve = lambda *a, **k: solved.append(solve(*a, **k)) or solved[-1]  # keep the FEResults
        try:
            res = run_pelvis_model(cfg)
        finally:
            nfem.solve = solve
        fe = solved[-1][-1]
        needle = res.results[-1].max_needle_deformation_mm
        dofs = res.mesh["dofs"]
        per_force = [{"force_N": r.force_N, "needle_max_mm": round(r.max_needle_deformation_mm, 4),
                      "clamp_mm": round(r.clamp_displacement_mm, 4),
                      "tissue_max_mm": {k: round(v, 4) for k, v in r.max_deformation_mm.items()}}
                     for r in res.results]
    return {"model": model, "order": order, "K": "100 mu0" if ratio else "default",
            "formulation": formulation or "default", "dofs": dofs,
            "cpu_s": round(time.process_time() - c0, 1), "wall_s": round(time.perf_counter() - t0, 1),
            "newton_iterations": fe.newton_iterations, "steps": fe.steps, "cutbacks": fe.cutbacks,
            "needle_max_mm": round(needle, 5), "tissue": tissue_state(fe, MATERIALS), "per_force": per_force,
            "load": os.getloadavg()[0]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("model", choices=("needle1", "needle2", "pelvis", "r1", "r2"))
    ap.add_argument("--order", type=int, default=2)
    ap.add_argument("--formulation", default=None)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--only", choices=("old", "new"), default=None)
    a = ap.parse_args()
    ratios = {"old": TISSUE_BULK_RATIO, "new": None}
    keys = [a.only] if a.only else ["old", "new"]
    for i in range(a.repeat):
        for k in (keys if i % 2 == 0 else keys[::-1]):  # alternate the order: load drifts
            print(json.dumps(run(a.model, ratios[k], a.order, a.formulation)), flush=True)


if __name__ == "__main__":
    main()
