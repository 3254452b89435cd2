"""Anatomical pelvic reduction model: example CT, supra-acetabular pins, 100/200/300 N.

    PYTHONPATH=src python examples/pelvis_model.py results/pelvis

Writes VTU files, figures, pelvis_results.json and pelvis_comparison.md to the folder given.
"""

import sys

from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

if __name__ == "__main__":
    out = sys.argv[1] if len(sys.argv) > 1 else "results/pelvis"
    res = run_pelvis_model(PelvisConfig(forces=[100.0, 200.0, 300.0], out=out, progress=True))
    for r in res.results:
        print(f"{r.force_N:5.0f} N: needle {r.max_needle_deformation_mm:.3f} mm, "
              f"Ritz {r.ritz_tip_deflection_mm:.3f} mm, clamp {r.clamp_displacement_mm:.3f} mm")
    print("ranking:", " > ".join(res.ranking))
