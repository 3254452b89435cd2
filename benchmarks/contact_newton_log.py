"""Per-Newton-iteration log of the needle model with the paper's frictional interfaces (docs/contact.md).

    python benchmarks/contact_newton_log.py --needles 1 --mesh-size 8 --needle-mesh-size 2.5 --far-mesh-size 30

One JSON line per Newton iteration: relative residual (FElupe's norm), step norm, largest nodal
correction (mm), the last CCD step fractions (< 1: the step was shortened so that no surface passes
another) and the smallest barrier distance per interface (mm; the sides start 0.9 dhat apart); one
"CONVERGED" line per load increment (force reached, iterations, CPU s of the process) and a summary
(per force: needle deformation, steps, iterations, cut-backs, gap opening, interpenetration). CPU
is time.process_time (all threads): state the load average beside it. --bonded runs the same model
bonded, for the cost ratio. --save DIR writes the converged state of every increment
(DIR/lam_<load factor>.pkl: fields, bodies' states); --restart FILE continues from one (the first
100 N of the default mesh cost ~760 s CPU) to the --forces given.
"""

from __future__ import annotations

import argparse
import json
import pickle
import time
from pathlib import Path

import felupe
import ipctk
from dataclasses import replace
import numpy as np

from needletissue.fem.contact import ContactSettings
from needletissue.fem.contact.item import CollisionFreeStep, StallLinesearch
from needletissue.models.contact import NEEDLE_EPS_V, NEEDLE_GAP_FRACTION, NeedleContact
from needletissue.models.needle import NeedleModelConfig, run_needle_model, with_geometry


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--needles", type=int, default=1)
    ap.add_argument("--mesh-size", type=float, default=4.0)
    ap.add_argument("--needle-mesh-size", type=float, default=2.0)
    ap.add_argument("--far-mesh-size", type=float, default=20.0)
    ap.add_argument("--forces", default="100,200,300", help="N, comma separated")
    ap.add_argument("--eps-v", type=float, default=NEEDLE_EPS_V)
    ap.add_argument("--gap-fraction", type=float, default=NEEDLE_GAP_FRACTION)
    ap.add_argument("--kappa-scale", default="", help="PAIR=FACTOR,...: barrier stiffness x FACTOR")
    ap.add_argument("--no-project", action="store_true", help="stalled Newton: line search without PSD projection")
    ap.add_argument("--bonded", action="store_true")
    ap.add_argument("--save", help="directory: the converged state of every increment")
    ap.add_argument("--restart", help="a state saved by --save: continue from its load")
    ap.add_argument("--initial-step", type=float, help="first increment (load factor of the largest force)")
    ap.add_argument("--max-step", type=float, help="largest increment (load factor): the increment study")
    ap.add_argument("--substeps", type=int, help="modified-Newton substeps per iteration (fem.solve substeps)")
    ap.add_argument("--no-predictor", action="store_true", help="each increment from the last converged state")
    a = ap.parse_args(argv)

    cfg = with_geometry(NeedleModelConfig(forces=tuple(float(f) for f in a.forces.split(",")), ritz=False),
                        needles=a.needles, mesh_size=a.mesh_size, needle_mesh_size=a.needle_mesh_size,
                        far_mesh_size=a.far_mesh_size)
    contact = NeedleContact("paper", settings=ContactSettings(eps_v=a.eps_v, gap_fraction=a.gap_fraction))
    if a.no_project:
        StallLinesearch.project = False
    scale = {k: float(v) for k, v in (x.split("=") for x in a.kappa_scale.split(",") if x)}
    build = contact.items

    def items(model):
        out = build(model)
        for i in out:
            f = scale.get(i.surface.interfaces[0].name)
            if f:
                i.settings = replace(i.settings, stiffness=f * i.settings.kappa)
                i.barrier = ipctk.BarrierPotential(i.settings.dhat, i.settings.kappa, True)
        return out

    contact.items = items
    fmax = max(cfg.forces)
    saved = pickle.loads(Path(a.restart).read_bytes()) if a.restart else None
    held = {}  # the model, for --save

    def items_restarted(model):
        out = items(model)
        held["model"] = model
        if saved is not None:
            for f, v in zip(model.field.fields, saved["fields"]):
                f.values[:] = v
            for name, c in saved["bodies"].items():
                model.bodies[name].restore(c)
            for i in out:  # the slip reference: the converged state
                i.results.statevars = np.asarray(model.field[0].values)[i.surface.vertices].copy()
        return out

    def save(rec):
        print("EVENT", json.dumps(rec), flush=True)
        if a.save and rec["event"] == "increment":
            m = held["model"]
            lam = rec["load_factor"]
            state = {"load_factor": lam, "force_N": lam * fmax, "fmax": fmax,
                     "fields": [f.values.copy() for f in m.field.fields],
                     "bodies": {k: b.checkpoint() for k, b in m.bodies.items() if hasattr(b, "checkpoint")}}
            Path(a.save).mkdir(parents=True, exist_ok=True)
            (Path(a.save) / f"lam_{lam:.6f}.pkl").write_bytes(pickle.dumps(state))

    import needletissue.fem as nfem
    solve0 = nfem.solve

    def solve_logged(*args, **kw):
        kw["log"] = save
        if saved is not None:
            kw["start"] = saved["load_factor"] * saved["fmax"] / fmax
        if a.initial_step:
            kw["initial_step"] = a.initial_step
        if a.max_step:
            kw["max_step"] = a.max_step
        if a.substeps is not None:
            kw["substeps"] = a.substeps
        if a.no_predictor:
            kw["predictor"] = False
        return solve0(*args, **kw)

    nfem.solve = solve_logged
    contact.items = items_restarted
    plugins_ = []  # the plugins of the running Newton solve

    class Log(felupe.Plugin):
        def after_iteration(self, context, st):
            ccd = next((p.alphas[-3:] for p in plugins_ if isinstance(p, CollisionFreeStep)), [])
            dx = np.asarray(st.dx)[:st.x[0].values.size].reshape(-1, 3)
            at = int(np.argmax(np.linalg.norm(dx, axis=1)))
            print(json.dumps({
                "it": st.iteration, "residual": float(st.fnorm), "step_norm": float(st.xnorm),
                "max_correction_mm": float(np.abs(np.asarray(st.dx)).max()),
                "max_correction_at_mm": [round(float(c), 2) for c in st.x[0].region.mesh.points[at]],
                "ccd_fractions": [round(float(x), 4) for x in ccd],
                "min_distance_mm": [i.results.info.get("min_distance_mm") for i in contact.item_list],
                "damped": next((p.level is not None for p in plugins_ if isinstance(p, StallLinesearch)), None),
                "alphas": next((p.alphas[-1][-1:] for p in plugins_ if isinstance(p, StallLinesearch) and p.alphas and p.alphas[-1]), None),
                "linear_residual": linres[-1] if linres else None,
                "cpu_s": round(time.process_time(), 1)}), flush=True)

    linres = []  # relative residual of the linear solve, |K dx + r| / |r| on the free dofs

    class LinCheck(felupe.Plugin):
        def after_linear_solve(self, context, st):
            if isinstance(st.jac, tuple):  # the bonded path's (upper K11, K10)
                return
            d1 = context.dof1
            K = st.jac.tocsr()
            dx = np.asarray(st.dx)
            r = (K @ dx)[d1] + st.fun[d1]
            linres.append(float(np.linalg.norm(r) / np.linalg.norm(st.fun[d1])))

    newton = felupe.newtonraphson

    def closest(item):
        """Rest position (mm) of the first vertex of the closest collision pair and its distance."""
        V, c, m = item.positions(), item.collisions, item.cmesh
        best = (np.inf, None)
        for i in range(len(c)):
            col = c[i]
            d = col.compute_distance(col.dof(V, m.edges, m.faces))
            if d < best[0]:
                best = (d, col.vertex_ids(m.edges, m.faces))
        if best[1] is None:
            return None
        v = [int(x) for x in best[1] if x >= 0]
        return {"d_mm": float(np.sqrt(best[0])),
                "at_mm": [round(float(x), 2) for x in item.rest[v[0]] - item.surface.offset[v[0]]]}

    def logged(*args, plugins=None, **kw):
        plugins_[:] = [LinCheck(), *(plugins or []), Log()]
        try:
            res = newton(*args, plugins=plugins_, **kw)
        except Exception as exc:
            print(f"FAILED {type(exc).__name__}: {exc} cpu={time.process_time():.1f} s", flush=True)
            raise
        loads = [i for i in kw.get("items", []) if isinstance(i, felupe.PointLoad)]
        force = np.linalg.norm(sum(np.asarray(i.values).reshape(-1, 3).sum(0) for i in loads)) if loads else np.nan
        print(f"CONVERGED force={force:.3f} N iterations={res.iterations} cpu={time.process_time():.1f} s "
              f"closest={json.dumps([closest(i) for i in contact.item_list])}", flush=True)
        return res

    felupe.newtonraphson = logged
    t0 = time.process_time()
    try:
        r = run_needle_model(cfg) if a.bonded else run_needle_model(cfg, **contact.hooks())
    finally:
        felupe.newtonraphson = newton
        nfem.solve = solve0
    per_force = r.extra.get("contact", {}).get("per_force", [{}] * len(r.results))
    print("SUMMARY", json.dumps({
        "cpu_s": time.process_time() - t0, "tetrahedra": r.mesh["tetrahedra"], "contact": not a.bonded,
        "per_force": [{"force_N": x.force_N, "needle_mm": x.max_needle_deformation_mm, "steps": x.steps,
                       "newton_iterations": x.newton_iterations, "cutbacks": x.fe.cutbacks, **c}
                      for x, c in zip(r.results, per_force)]}), flush=True)


if __name__ == "__main__":
    main()
