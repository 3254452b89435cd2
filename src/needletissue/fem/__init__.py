"""Nonlinear finite elements on FElupe: tagged tetrahedral meshes, one SolidBody per region on a
shared global field, boundary conditions by surface name, load stepping with cut-back.

    mesh = TaggedMesh.read("model.msh")               # physical volumes -> regions, surfaces -> BCs
    model = FEModel(mesh, {"muscle": "muscle", "needle_1": "needle"}, order=2)
    results = solve(model, [Fixed("bone_fixed"), SurfaceForce("gripper", (300.0, 0, 0))],
                    load_factors=[1/3, 2/3, 1])
    results[-1].write_vtu("out.vtu"); results[-1].to_dict()

Units: mm, N, MPa. See docs/fem.md.
"""

from needletissue.fem.mesh import TaggedMesh
from needletissue.fem.model import FEModel, Fixed, LockingWarning, PrescribedDisplacement, SurfaceForce
from needletissue.fem.result import FEResult, write_results
from needletissue.fem.solve import solve

__all__ = ["TaggedMesh", "FEModel", "Fixed", "LockingWarning", "PrescribedDisplacement", "SurfaceForce", "FEResult", "solve", "write_results"]
