"""Measured, not kept (docs/bench.md): a finite-rotation correction of the clamp's Newton update on the
two-needle model. After each linear solve the clamp nodes' increment is split into a rigid part (least
squares) and the rest, and the rigid rotation is made finite (Rodrigues).

    python benchmarks/rotation_correction.py 8,3,30 off|on [displacements.npy]
"""


def main():
    import sys, time
    import numpy as np
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parent))
    import felupe as fem
    from newton_study import build, FORCES
    from needletissue.fem import solve

    mesh_sizes = tuple(float(v) for v in (sys.argv[1] if len(sys.argv) > 1 else "8,3,30").split(","))
    mode = sys.argv[2] if len(sys.argv) > 2 else "on"
    model, bcs = build(mesh_sizes)
    mesh = model.mesh
    S = np.unique(mesh.cells[mesh.regions["clamp"]])
    X = mesh.points[S]

    def skew(w):
        return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])

    class Rot(fem.Plugin):
        n = 0
        def after_linear_solve(self, context, st):
            u = st.x[0].values[S]
            d = st.dx.reshape(-1, 3)[S]
            y = X + u
            r = y - y.mean(0)
            t = d.mean(0)
            A = (r * r).sum() * np.eye(3) - r.T @ r
            w = np.linalg.solve(A, np.cross(r, d - t).sum(0))
            th = np.linalg.norm(w)
            if th == 0:
                return
            K = skew(w / th)
            R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
            corr = r @ (R - np.eye(3)).T - np.cross(w, r)
            dx = st.dx.reshape(-1, 3)
            dx[S] += corr
            self.n += 1

    newton = fem.newtonraphson
    counts = []
    def wrapped(*args, plugins=None, **kw):
        plugins = list(plugins or [])
        if mode == "on":
            plugins.insert(1, Rot())   # after the pressure plugin, before the substeps
        res = newton(*args, plugins=plugins, **kw)
        counts.append([float(f) for f in res.fnorms])
        return res
    fem.newtonraphson = wrapped
    c0 = time.process_time()
    res = solve(model, bcs, load_factors=[f / max(FORCES) for f in FORCES], progress=False, results=False)
    cpu = time.process_time() - c0
    print(mode, "dofs", model.ndof, "iterations", res[-1].newton_iterations, "substeps", res[-1].newton_substeps, f"CPU {cpu:.1f}")
    for c in counts:
        print("  |r|", " ".join(f"{v:.1e}" for v in c))
    if len(sys.argv) > 3:  # displacements per load, to compare the two modes
        np.save(sys.argv[3], np.array([r.displacement for r in res]))


if __name__ == "__main__":
    main()
