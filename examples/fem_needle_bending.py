"""Needle bending: which tetrahedra does a slender titanium pin need? (docs/fem.md)

A 5 mm pin, 60 mm long, clamped at one end, 10 N lateral load spread over the other end face.
Linear (tetra) and quadratic (tetra10) meshes of decreasing size against Timoshenko's closed form
for a circular section. Run: nice python examples/fem_needle_bending.py [--out results/bending.json]
"""

import argparse
import json
import time

import numpy as np

from needletissue import materials
from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve

D, L, P = 5.0, 60.0, 10.0


def pin_mesh(h, order=1):
    """order=2: gmsh's tetra10 with midside nodes ON the cylinder (curved boundary)."""
    import gmsh

    gmsh.initialize(["-nt", "1"])
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("pin")
        v = gmsh.model.occ.addCylinder(0, 0, 0, L, 0, 0, D / 2)
        gmsh.model.occ.synchronize()
        gmsh.model.addPhysicalGroup(3, [v], name="needle")
        for d, t in gmsh.model.getEntities(2):
            x = gmsh.model.occ.getCenterOfMass(d, t)[0]
            if abs(x) < 1e-6:
                gmsh.model.addPhysicalGroup(2, [t], name="clamped")
            elif abs(x - L) < 1e-6:
                gmsh.model.addPhysicalGroup(2, [t], name="tip")
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", h)
        gmsh.model.mesh.generate(3)
        if order == 2:
            gmsh.model.mesh.setOrder(2)
        return TaggedMesh.from_gmsh()
    finally:
        gmsh.finalize()


def timoshenko():
    E, nu = (materials.get("needle").parameters[k] for k in ("E", "nu"))
    I, A, G = np.pi * D**4 / 64, np.pi * D**2 / 4, E / (2 * (1 + nu))
    kappa = 6 * (1 + nu) / (7 + 6 * nu)  # Cowper, solid circle
    return P * L**3 / (3 * E * I) + P * L / (kappa * G * A)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out")
    a = ap.parse_args()
    ref = timoshenko()
    rows = []
    # tetra10 "straight": FElupe midpoints on straight edges (polygonal section, too small I);
    # "curved": gmsh order-2 nodes on the cylinder
    cases = [(1, "linear", (2.5, 1.25, 0.8, 0.5)), (2, "straight", (2.5, 1.25)), (2, "curved", (2.5, 1.25, 0.8))]
    for order, geom, sizes in cases:
        for h in sizes:
            mesh = pin_mesh(h, order=2 if geom == "curved" else 1)
            model = FEModel(mesh, {"needle": "needle"}, order=order)
            t = time.perf_counter()
            r = solve(model, [Fixed("clamped"), SurfaceForce("tip", (0.0, 0.0, P))], [1.0], progress=False,
                      results=False)[-1]
            tip = r.displacement[model.mesh.surface_nodes("tip"), 2].mean()
            row = {"order": order, "geometry": geom, "size_mm": h, "elements_across_diameter": D / h,
                   "tetrahedra": len(mesh.cells), "dofs": model.ndof, "tip_mm": float(tip),
                   "error_vs_timoshenko": float(tip / ref - 1), "solve_s": time.perf_counter() - t}
            rows.append(row)
            print(json.dumps(row), flush=True)
    out = {"timoshenko_tip_mm": ref, "diameter_mm": D, "length_mm": L, "load_N": P, "rows": rows}
    if a.out:
        from needletissue.runinfo import write_json

        write_json(a.out, out)


if __name__ == "__main__":
    main()
