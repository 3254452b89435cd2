"""Paper-scale anatomical pelvis model: linear tets, 1 mm needles, 2.45 mm tissue, ~1.33 M tets.

The paper meshed its (whole) pelvis with linear tets, 1 mm on the needles and 3 mm elsewhere, into
1,329,469 elements. Our hemipelvis crop at 1 mm / 3 mm has only 747 k tets, so the tissue size is
reduced to 2.45 mm (uniform, no far-field grading) to reach the paper's element count; see
docs/pelvis_model.md ("Paper-scale run"). Same as
`needletissue fe pelvis --mesher box --order 1 --needle-size 1 --mesh-size 2.45 --far-size 2.45 --force 300`
without the 3D render. Needs ../shared/data. Run with `nice`: measured 26.2 min wall on the busy shared
2-core machine (1527 s CPU), 8.2 GiB peak RSS, 1,345,969 tets, 752,010 dofs (docs/pelvis_model.md).

    PYTHONPATH=src nice python benchmarks/paper_scale_pelvis.py --out /tmp/pelvis_paperscale [--force 300]
        [--mesher smooth] [--interfaces paper]
"""

from __future__ import annotations

import argparse
import json
import resource
import time

from needletissue.fem.linsolve import SOLVERS
from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="/tmp/pelvis_paperscale", help="output folder (VTU, JSON, config)")
    ap.add_argument("--force", type=float, action="append", help="reduction force, N (repeat; default 300)")
    ap.add_argument("--mesh-size", type=float, default=2.45, help="tissue element size, mm")
    ap.add_argument("--needle-size", type=float, default=1.0, help="needle element size, mm")
    ap.add_argument("--solver", default="auto", choices=SOLVERS, help="linear solver (fem.linsolve)")
    ap.add_argument("--mesher", default="box", choices=("box", "smooth"),
                    help="box (the paper's element count) or smooth (the CT reconstruction; ~0.95 M tets at most)")
    ap.add_argument("--interfaces", default="bonded", choices=("bonded", "paper"),
                    help="bonded, or the paper's frictional contacts (docs/contact.md)")
    a = ap.parse_args()
    cfg = PelvisConfig(mesher=a.mesher, forces=a.force or [300.0], order=1, needle_size=a.needle_size,
                       mesh_size=a.mesh_size, far_size=a.mesh_size, out=a.out, figures=False, solver=a.solver,
                       interfaces=a.interfaces)
    t = time.perf_counter()
    res = run_pelvis_model(cfg)
    wall = time.perf_counter() - t
    ru = resource.getrusage(resource.RUSAGE_SELF)
    d = res.to_dict()
    print("tetrahedra", d["mesh"]["tetrahedra"], "nodes", d["mesh"]["nodes"], "dofs", d["mesh"]["dofs"])
    print(f"WALL {wall:.1f} s ({wall / 60:.1f} min); CPU {ru.ru_utime + ru.ru_stime:.0f} s; "
          f"peak RSS {ru.ru_maxrss / 1024**2:.2f} GiB")  # ru_maxrss is in KiB on Linux
    print("timing_s", json.dumps(d["timing_s"]))
    for r in d["results"]:
        print(f"{r['force_N']:.0f} N: max needle deformation {r['max_needle_deformation_mm']:.3f} mm, clamp "
              f"{r['clamp_displacement_mm']:.3f} mm, Newton iterations (cumulative) {r['newton_iterations']}, "
              f"Ritz {r['ritz_tip_deflection_mm']:.3f} mm")
        print("  max deformation by region (mm):",
              json.dumps({k: round(v, 4) for k, v in sorted(r["max_deformation_mm"].items(), key=lambda kv: -kv[1])}))
    print("ranking:", " > ".join(d["ranking"]))
    print("cells_by_region", json.dumps(d["mesh"]["cells_by_region"]))
    print("written:", a.out)
