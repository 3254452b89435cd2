"""Per-Newton-iteration log of the anatomical model with the paper's interfaces (docs/contact.md).

    PYTHONPATH=src python benchmarks/pelvis_contact_log.py '{"out": "DIR", "mesh_size": 6, "needle_size": 3, "far_size": 18}'

The argument: PelvisConfig fields as JSON (default: the CLI's defaults but `mesher="box"` (the meshes the docs'
logs were measured on; give "mesher": "smooth" for the CLI's), `interfaces="paper"`, 100/200/300 N, no figures, no
thickness cross-check), and optionally "contact_tol" (the model's CONTACT_TOL for this run) and
"substeps" (fem.solve's SUBSTEPS: modified-Newton substeps per iteration, 0 for none). One JSON line per Newton iteration (relative residual, largest nodal
correction and where, smallest barrier distance per interface, CPU s of the process), one CONVERGED line
per increment, a SUMMARY at the end. With "out", OUT/solve_log.jsonl is the model's own per-increment log.
"""
import importlib
import json
import sys
import time

import felupe
import numpy as np

from needletissue.models.pelvis import PelvisConfig, run_pelvis_model
from needletissue.models.pelvis import model as pelvis_model
from needletissue.fem.contact.item import FrictionalContact


def main():
    kw = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    if "contact_tol" in kw:
        pelvis_model.CONTACT_TOL = float(kw.pop("contact_tol"))
    if "substeps" in kw:  # fem.solve's default number of modified-Newton substeps (0: none)
        importlib.import_module("needletissue.fem.solve").SUBSTEPS = int(kw.pop("substeps"))
    cfg = PelvisConfig(**{"mesher": "box", "interfaces": "paper", "forces": [100.0, 200.0, 300.0], "figures": False,
                          "crosscheck_thickness": False, **kw})
    newton = felupe.newtonraphson
    t0 = time.process_time()

    def logged(*args, plugins=None, **k):
        items = [i for i in k.get("items", []) if isinstance(i, FrictionalContact)]
        loads = [i for i in k.get("items", []) if isinstance(i, felupe.PointLoad)]
        class Log(felupe.Plugin):
            def after_iteration(self, context, st):
                dx = np.asarray(st.dx)[:st.x[0].values.size].reshape(-1, 3)
                at = int(np.argmax(np.linalg.norm(dx, axis=1)))
                print(json.dumps({"it": st.iteration, "r": float(st.fnorm),
                                  "dxmax": float(np.linalg.norm(dx, axis=1).max()),
                                  "at": [round(float(c), 1) for c in st.x[0].region.mesh.points[at]],
                                  "dmin": {i.surface.interfaces[0].name: i.results.info.get("min_distance_mm") for i in items},
                                  "cpu": round(time.process_time() - t0, 1)}), flush=True)
        try:
            res = newton(*args, plugins=[*(plugins or []), Log()], **k)
        except Exception as exc:
            print(f"FAILED {type(exc).__name__}: {exc} cpu={time.process_time()-t0:.1f}", flush=True)
            raise
        force = np.linalg.norm(sum(np.asarray(i.values).reshape(-1, 3).sum(0) for i in loads)) if loads else np.nan
        print(f"CONVERGED force={force:.3f} N it={res.iterations} success={res.success} cpu={time.process_time()-t0:.1f}", flush=True)
        return res

    felupe.newtonraphson = logged
    r = run_pelvis_model(cfg)
    print("SUMMARY", json.dumps({"cpu": time.process_time() - t0, "tets": r.mesh["tetrahedra"],
          "needle": [x.max_needle_deformation_mm for x in r.results], "timing": r.timing_s,
          "contact": r.contact}, default=str), flush=True)


if __name__ == "__main__":
    main()
