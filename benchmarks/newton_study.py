"""Why Newton converges slowly on the needle model (issue 18, docs/bench.md "Newton"): measurements.

    python benchmarks/newton_study.py tangent [--mesh 8,3,30]     # FD check of each body's tangent
    python benchmarks/newton_study.py trace [--mesh 8,3,30] [--substeps 0] [--tissue neo_hooke]
                                           [--clamp-E 2000] [--solver scipy] [--armijo]
                                           [--bulk-ratio 100] [--no-predictor]

The model is `fe needle`'s (two needles, 100/200/300 N lateral, tet10, mixed tissue), on a mesh of
--mesh "size,needle size,far size" mm (default 8,3,30: 31,032 free dofs; `fe needle`'s own is 4,2,20),
meshed once into benchmarks/results/. Options that change the model (--tissue, --clamp-E, --bulk-ratio:
tissue K/mu0, 100 = the K before issue 16) are diagnostics only. trace solves with the linear predictor
unless --no-predictor (the needle and pelvis models solve without it since issue 16).

tangent: at the converged 100 N state, |(r(x + h v) - r(x - h v)) / 2h - K v| / |K v| per body along a
  random direction v, for h = 1e-3 .. 1e-7 (O(h^2) down to round-off: a consistent tangent).
trace:   per load step and Newton iteration: |r| (FElupe's norm), the residual's largest regions, the
  error of the iterate against the converged state (max |u - u*| / max |u*|) and the clamp's rigid
  rotation error (Kabsch fit); the CPU seconds of the solve.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
FORCES = (100.0, 200.0, 300.0)


def build(mesh_sizes, formulation="mixed", tissue=None, clamp_E=None, bulk_ratio=None):
    from needletissue.fem import Fixed, FEModel, SurfaceForce, TaggedMesh
    from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model
    from needletissue.materials import Material, get, tissue_bulk
    from needletissue.models.needle.model import MATERIALS

    ms, nms, fms = mesh_sizes
    path = HERE / "results" / f"newton_study_{ms:g}_{nms:g}_{fms:g}.msh"
    if not path.exists():
        path.parent.mkdir(exist_ok=True)
        mesh_needle_model(NeedleGeometry(mesh_size=ms, needle_mesh_size=nms, far_mesh_size=fms), path, order=2)
    mesh = TaggedMesh.read(path)
    mats = {r: MATERIALS[r] for r in mesh.regions}
    if tissue:
        for r in ("muscle", "adipose"):
            m = get(r)
            mats[r] = Material(f"{r}_{tissue}", tissue, {"mu": m.initial_shear_modulus}, bulk_modulus=m.bulk)
    if clamp_E:
        mats["clamp"] = Material("clamp_E", "elastic", {"E": clamp_E, "nu": 0.3})
    model = FEModel(mesh, mats, order=2, formulation=formulation, bulk=tissue_bulk(mats, bulk_ratio))
    bcs = [Fixed("bone_fixed"), Fixed("tissue_far"), SurfaceForce("gripper", total=(0.0, max(FORCES), 0.0))]
    return model, bcs


def tangent(a):
    from felupe.tools._newton import fun_items, jac_items, update

    from needletissue.fem import solve

    model, bcs = build(a.mesh, formulation="displacement")
    solve(model, bcs, load_factors=[FORCES[0] / max(FORCES)], progress=False, results=False)
    x = model.field
    v = np.random.default_rng(0).normal(size=x[0].values.size)
    print(f"free dofs {model.ndof}; converged at {FORCES[0]:g} N, max |u| = {np.abs(x[0].values).max():.3f} mm")
    for name, body in model.bodies.items():
        fun_items([body], x)
        Kv = jac_items([body], x) @ v
        errs = []
        for h in (1e-3, 1e-4, 1e-5, 1e-6, 1e-7):
            d = (fun_items([body], update(x, h * v)) - fun_items([body], update(x, -h * v))) / (2 * h)
            errs.append(np.linalg.norm(d - Kv) / np.linalg.norm(Kv))
        fun_items([body], x)
        print(f"{name:16s} " + " ".join(f"{e:.1e}" for e in errs))


def trace(a):
    import felupe as fem

    from needletissue.errors import ConvergenceError
    from needletissue.fem import solve
    from needletissue.models.needle.model import rigid_fit

    model, bcs = build(a.mesh, tissue=a.tissue, clamp_E=a.clamp_E, bulk_ratio=a.bulk_ratio)
    mesh = model.mesh
    owner = np.full(len(mesh.points), "", dtype=object)
    for r, ids in mesh.regions.items():
        owner[np.unique(mesh.cells[ids])] = r
    clamp = np.unique(mesh.cells[mesh.regions["clamp"]])
    steps = []

    class Record(fem.Plugin):
        def before_newton(self, context, st):
            steps.append({"x0": st.x[0].values.copy(), "its": []})

        def after_iteration(self, context, st):
            f = np.zeros(st.fun.size)
            f[context.dof1] = st.fun[context.dof1]
            f0 = np.linalg.norm(st.fun[context.dof0])
            f = np.linalg.norm(f.reshape(-1, 3), axis=1)
            byreg = {r: np.linalg.norm(f[owner == r]) / f0 for r in mesh.regions}
            steps[-1]["its"].append((st.fnorm, st.x[0].values.copy(), byreg))

    newton, search = fem.newtonraphson, fem.LinesearchPlugin
    fem.newtonraphson = lambda *args, plugins=None, **kw: newton(*args, plugins=[*(plugins or []), Record()], **kw)
    if a.armijo:  # solve's line search with FElupe's sufficient decrease of |r| switched on
        fem.LinesearchPlugin = lambda **kw: search(**{**kw, "residual": True})
    c0 = time.process_time()
    try:
        res = solve(model, bcs, load_factors=[f / max(FORCES) for f in FORCES], progress=False, results=False,
                    substeps=0 if a.armijo else a.substeps, solver=a.solver, linesearch=a.armijo or None,
                    predictor=not a.no_predictor)
    except ConvergenceError as exc:  # e.g. --armijo
        print(f"failed after {time.process_time() - c0:.1f} s CPU: {exc}")
        return
    finally:
        fem.newtonraphson, fem.LinesearchPlugin = newton, search
    cpu = time.process_time() - c0
    last = res[-1]
    print(f"free dofs {model.ndof}; {last.newton_iterations} Newton iterations, {last.newton_substeps} substeps, "
          f"CPU {cpu:.1f} s")
    for k, s in enumerate(steps):
        xs = s["its"][-1][1]
        umax = np.linalg.norm(xs, axis=1).max()
        print(f"step {k + 1} (max |u*| = {umax:.3f} mm):")
        iterates = [("predictor", None, s["x0"], None)] + [(f"it {i + 1}", fn, x, br) for i, (fn, x, br) in
                                                         enumerate(s["its"])]
        for name, fn, x, br in iterates:
            e = x - xs
            err = np.linalg.norm(e, axis=1).max() / umax
            rot = rigid_fit(mesh.points[clamp] + xs[clamp], e[clamp], mesh.points[clamp].mean(0))[0]
            top = "" if br is None else ", ".join(f"{r} {v:.1e}" for r, v in sorted(br.items(), key=lambda t: -t[1])[:2])
            r = "" if fn is None else f"|r| {fn:.2e}  "
            print(f"  {name:9s} {r:16s}error {err:.1e}  clamp rotation error {rot[0]:+.1e} rad  {top}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("tangent", "trace"))
    ap.add_argument("--mesh", default="8,3,30", type=lambda t: tuple(float(v) for v in t.split(",")))
    ap.add_argument("--substeps", type=int, default=None)
    ap.add_argument("--tissue", default=None, help="e.g. neo_hooke: both tissues with their mu0 and bulk")
    ap.add_argument("--clamp-E", type=float, default=None)
    ap.add_argument("--solver", default="auto")
    ap.add_argument("--bulk-ratio", type=float, default=None, help="tissue K/mu0 (default: the materials' K)")
    ap.add_argument("--no-predictor", action="store_true", help="as the needle and pelvis models solve")
    ap.add_argument("--armijo", action="store_true", help="backtracking line search on |r| (plain Newton)")
    a = ap.parse_args()
    {"tangent": tangent, "trace": trace}[a.what](a)


if __name__ == "__main__":
    main()
