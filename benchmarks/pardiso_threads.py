"""The default `fe needle` tangent at the rest state, captured: Pardiso Cholesky analysis / factorisation /
solve on one and on two MKL threads, CPU and wall per phase (docs/bench.md).

    python benchmarks/pardiso_threads.py [REPEATS]
"""


def main():
    import sys, time, tempfile
    import numpy as np
    from pathlib import Path
    from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model
    from needletissue.fem import TaggedMesh, FEModel, Fixed, SurfaceForce
    import importlib; S = importlib.import_module("needletissue.fem.solve"); from needletissue.fem import linsolve
    from needletissue.models.needle.model import MATERIALS
    from needletissue.materials import tissue_bulk
    msh = Path(tempfile.mkdtemp()) / "default.msh"
    mesh_needle_model(NeedleGeometry(), msh, order=2, cache=True)
    mesh = TaggedMesh.read(msh)
    mats = {r: MATERIALS[r] for r in mesh.regions}
    model = FEModel(mesh, mats, order=2, formulation="mixed", bulk=tissue_bulk(mats, None))
    bcs = [Fixed("bone_fixed"), Fixed("tissue_far"), SurfaceForce("gripper", total=(0, 300.0, 0))]
    loads = S._Loads(model, bcs)
    bodies = list(model.bodies.values())
    b = S._Bodies(bodies, bodies, loads.dof1, loads.dof0, model.ndof)
    x = model.field
    b.fun(x)
    upper, _ = b.jac(x)
    print("dofs", upper.shape[0], "nnz upper", upper.nnz, flush=True)
    rhs = np.random.default_rng(0).normal(size=upper.shape[0])
    from threadpoolctl import ThreadpoolController
    linsolve._Pardiso().close()  # loads MKL's runtime first: the controller sees only loaded libraries
    ctl = ThreadpoolController()
    print("MKL:", [(i["internal_api"], i["num_threads"]) for i in ctl.info() if i["internal_api"] == "mkl"], flush=True)
    for rep in range(int(sys.argv[1]) if len(sys.argv) > 1 else 2):
        for nt in (1, 2):
            lin = linsolve._Pardiso()
            with ctl.select(internal_api="mkl").limit(limits=nt):
                ps = lin.solvers[2]
                ps._check_A(upper); bb = ps._check_b(upper, rhs)
                out = []
                for ph in (11, 22, 33):
                    ps.set_phase(ph); c, w = time.process_time(), time.perf_counter()
                    xs = ps._call_pardiso(upper, bb)
                    out.append((time.process_time() - c, time.perf_counter() - w))
                print(f"threads {nt}: " + ", ".join(f"phase {p}: CPU {c:.2f} s wall {w:.2f} s" for p, (c, w) in zip((11, 22, 33), out)),
                      "factor nnz", ps.iparm[17], "residual", np.linalg.norm(upper @ xs + upper.T @ xs - upper.diagonal() * xs - rhs) / np.linalg.norm(rhs), flush=True)
            lin.close()


if __name__ == "__main__":
    main()
