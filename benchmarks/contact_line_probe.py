"""Where Newton's residual floor comes from: restart a contact run (contact_newton_log.py --restart),
run NIT Newton iterations of the next increment, then evaluate every item's residual along the Newton
step x + s dx (s = 1: the full step) and compare it with the tangent's prediction (1 - s) r; for the
bone-needle item also the collision counts per type and the jumps of its barrier and friction forces.

    python benchmarks/contact_line_probe.py 4 --needles 1 --forces 28 --restart STATES/lam_0.074882.pkl --initial-step 1

(docs/contact.md, "The residual floor": a jump of the bone-needle friction 2e-7 mm into the Newton
step; "Edge-edge friction with the mollifier": its cause, a nearly parallel edge-edge pair's friction
appearing in full where its mollifier reaches 1, and the fix.)
"""
import json
import sys

import felupe
import numpy as np
from felupe import solve as fesolve
from felupe.tools import _newton as N

import contact_newton_log as drv


class _Stop(Exception):
    pass


def main(nit, argv):
    real = felupe.newtonraphson

    def probe(*args, plugins=None, **kw):
        rec = {}

        class Grab(felupe.Plugin):
            def after_iteration(self, context, st):
                rec["x"] = st.x
                if st.iteration + 1 >= nit:
                    raise _Stop()
        try:
            real(*args, plugins=[*(plugins or []), Grab()], **kw)
            print("converged in fewer than NIT iterations")
            sys.exit(0)
        except _Stop:
            pass
        items, dof1, dof0, ext0, x = kw["items"], kw["dof1"], kw["dof0"], kw["ext0"], rec["x"]
        for i in items:  # exact Hessians (StallLinesearch may have switched the projection on)
            if hasattr(i, "project"):
                i.project = False
        bodies = [i for i in items if hasattr(i, "checkpoint") and not hasattr(i, "step_bound")]
        names = [f"{k}:{type(i).__name__}" + (f"/{i.surface.interfaces[0].name}" if hasattr(i, "surface") else "")
                 for k, i in enumerate(items)]
        shape = (int(np.sum(x.fieldsizes)), 1)

        def resid(xx):  # per item, from the bodies' states at x (the mixed bodies keep one)
            for b, c in zip(bodies, ck):
                b.restore(c)
            out = []
            for it in items:
                it.field.link(xx)
                r = it.assemble.vector(field=it.field)
                if it.assemble.multiplier is not None:
                    r = r * it.assemble.multiplier
                out.append(N.spresize(r, shape).toarray()[:, 0])
            return out

        ck = [b.checkpoint() for b in bodies]
        rs = resid(x)
        r0 = sum(rs)
        react = np.sum(np.linalg.norm(r0[dof0])) + 1e-3  # FElupe's norm
        K = N.jac_items(items, x)
        import pypardiso
        dx = -fesolve.solve(*fesolve.partition(x, K, dof1, dof0, -r0), ext0, solver=pypardiso.spsolve)
        print(json.dumps({"residual": float(np.linalg.norm(r0[dof1]) / react), "max_dx_mm": float(np.abs(dx).max()),
                          "linear_check": float(np.linalg.norm((K @ dx + r0)[dof1]) / np.linalg.norm(r0[dof1]))}))
        for s in [0.01, 0.1, 0.2, 0.3, 0.5, 0.9, 1.0]:
            rr = resid(N.update(x, s * dx))
            err = {n: float(np.linalg.norm((r - ri)[dof1]) / react) for n, r, ri in zip(names, rr, rs)}
            print(json.dumps({"s": s, "residual": float(np.linalg.norm(sum(rr)[dof1]) / react),
                              "minus_tangent_prediction": float(np.linalg.norm((sum(rr) - (1 - s) * r0)[dof1]) / react),
                              "change_per_item": {k: v for k, v in err.items() if v > 1e-9}}), flush=True)
        bn = next(i for i in items if hasattr(i, "surface") and i.surface.interfaces[0].name == "bone-needle")
        prev = None
        for s in [0.1, 0.2, 0.3, 0.5]:
            resid(N.update(x, s * dx))
            st = bn._evaluate()
            V, col, tan = st["V"], bn.collisions, bn.tangential
            gb = bn.barrier.gradient(col, bn.cmesh, V)
            gf = -bn.friction.force(tan, bn.cmesh, bn.rest, np.asfortranarray(V - bn.rest), st["slip"], bn.barrier)
            out = {"s": s, "vv": len(col.vv_collisions), "ev": len(col.ev_collisions), "ee": len(col.ee_collisions),
                   "fv": len(col.fv_collisions), "tangential": len(tan)}
            if prev is not None:
                for key, d in (("barrier", gb - prev[0]), ("friction", gf - prev[1])):
                    d = d.reshape(-1, 3)
                    k = int(np.argmax(np.linalg.norm(d, axis=1)))
                    out[f"jump_{key}_N"] = float(np.linalg.norm(d))
                    out[f"jump_{key}_at_mm"] = [round(float(v), 2) for v in bn.rest[k] - bn.surface.offset[k]]
            prev = (gb, gf)
            print("bone-needle", json.dumps(out), flush=True)
        sys.exit(0)

    felupe.newtonraphson = probe
    drv.main(argv)


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2:])
