"""Per-Newton-iteration log of the needle model with the paper's frictional interfaces (docs/contact.md).

    python benchmarks/contact_newton_log.py --needles 1 --mesh-size 8 --needle-mesh-size 2.5 --far-mesh-size 30

One JSON line per Newton iteration: relative residual (FElupe's norm), step norm, largest nodal
correction (mm), the last CCD step fractions (< 1: the step was shortened so that no surface passes
another) and the smallest barrier distance per interface (mm; the sides start 0.9 dhat apart); one
"CONVERGED" line per load increment (force reached, iterations, CPU s of the process) and a summary
(per force: needle deformation, steps, iterations, cut-backs, gap opening, interpenetration). CPU
is time.process_time (all threads): state the load average beside it. --bonded runs the same model
bonded, for the cost ratio.
"""

from __future__ import annotations

import argparse
import json
import time

import felupe
import numpy as np

from needletissue.fem.contact import ContactSettings
from needletissue.fem.contact.item import CollisionFreeStep
from needletissue.models.contact import NeedleContact
from needletissue.models.needle import NeedleModelConfig, run_needle_model, with_geometry


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--needles", type=int, default=1)
    ap.add_argument("--mesh-size", type=float, default=4.0)
    ap.add_argument("--needle-mesh-size", type=float, default=2.0)
    ap.add_argument("--far-mesh-size", type=float, default=20.0)
    ap.add_argument("--forces", default="100,200,300", help="N, comma separated")
    ap.add_argument("--eps-v", type=float, default=ContactSettings().eps_v)
    ap.add_argument("--bonded", action="store_true")
    a = ap.parse_args(argv)

    cfg = with_geometry(NeedleModelConfig(forces=tuple(float(f) for f in a.forces.split(",")), ritz=False),
                        needles=a.needles, mesh_size=a.mesh_size, needle_mesh_size=a.needle_mesh_size,
                        far_mesh_size=a.far_mesh_size)
    contact = NeedleContact("paper", settings=ContactSettings(eps_v=a.eps_v))
    plugins_ = []  # the plugins of the running Newton solve

    class Log(felupe.Plugin):
        def after_iteration(self, context, st):
            ccd = next((p.alphas[-3:] for p in plugins_ if isinstance(p, CollisionFreeStep)), [])
            print(json.dumps({
                "it": st.iteration, "residual": float(st.fnorm), "step_norm": float(st.xnorm),
                "max_correction_mm": float(np.abs(np.asarray(st.dx)).max()),
                "ccd_fractions": [round(float(x), 4) for x in ccd],
                "min_distance_mm": [i.results.info.get("min_distance_mm") for i in contact.item_list],
                "cpu_s": round(time.process_time(), 1)}), flush=True)

    newton = felupe.newtonraphson

    def logged(*args, plugins=None, **kw):
        plugins_[:] = [*(plugins or []), Log()]
        try:
            res = newton(*args, plugins=plugins_, **kw)
        except Exception as exc:
            print(f"FAILED {type(exc).__name__}: {exc} cpu={time.process_time():.1f} s", flush=True)
            raise
        loads = [i for i in kw.get("items", []) if isinstance(i, felupe.PointLoad)]
        force = np.linalg.norm(sum(np.asarray(i.values).reshape(-1, 3).sum(0) for i in loads)) if loads else np.nan
        print(f"CONVERGED force={force:.3f} N iterations={res.iterations} cpu={time.process_time():.1f} s", flush=True)
        return res

    felupe.newtonraphson = logged
    t0 = time.process_time()
    try:
        r = run_needle_model(cfg) if a.bonded else run_needle_model(cfg, **contact.hooks())
    finally:
        felupe.newtonraphson = newton
    per_force = r.extra.get("contact", {}).get("per_force", [{}] * len(r.results))
    print("SUMMARY", json.dumps({
        "cpu_s": time.process_time() - t0, "tetrahedra": r.mesh["tetrahedra"], "contact": not a.bonded,
        "per_force": [{"force_N": x.force_N, "needle_mm": x.max_needle_deformation_mm, "steps": x.steps,
                       "newton_iterations": x.newton_iterations, "cutbacks": x.fe.cutbacks, **c}
                      for x, c in zip(r.results, per_force)]}), flush=True)


if __name__ == "__main__":
    main()
