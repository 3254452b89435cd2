"""FElupe model of a tagged mesh: one global displacement field, one SolidBody per region.

Built the way FE-STACK.md prescribes: one Mesh per region sharing the global points array, a
FieldContainer per region linked to the global field over all cells, boundaries on the global field.
"""

from __future__ import annotations

from dataclasses import dataclass


from needletissue import materials as _materials
from needletissue.errors import InputError
from needletissue.fem.mesh import TaggedMesh

FORMULATIONS = ("displacement", "mixed")


class LockingWarning(UserWarning):
    """Linear tetrahedra with nearly incompressible tissue: the result is too stiff (volumetric locking)."""


# ---------------------------------------------------------------------- boundary conditions
@dataclass(frozen=True)
class Fixed:
    """Zero displacement of the given components (0=x, 1=y, 2=z) on every node of a named surface."""

    surface: str
    components: tuple[int, ...] = (0, 1, 2)


@dataclass(frozen=True)
class PrescribedDisplacement:
    """Displacement (ux, uy, uz) in mm of every node of a surface, scaled by the load factor.
    A component given as None is left free. `value` may also be a callable X (k,3) -> u (k,3) mm
    evaluated at the surface's nodes (sorted node ids), e.g. an affine field for a patch test."""

    surface: str
    value: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SurfaceForce:
    """A total force (Fx, Fy, Fz) in N spread uniformly over the reference area of a surface
    (a dead load: fixed direction and distribution), scaled by the load factor.

    `moment` (Mx, My, Mz) in N mm about the surface's area centroid adds a self-equilibrated
    traction that varies linearly over the surface, t = omega x r (r from the centroid), with omega
    chosen so that the nodal forces' moment is exactly `moment` and their sum stays `total`: force
    and moment together are any wrench at the centroid (a force at an offset point: moment = r x F).
    """

    surface: str
    total: tuple = (0.0, 0.0, 0.0)
    moment: tuple = (0.0, 0.0, 0.0)


BoundaryCondition = Fixed | PrescribedDisplacement | SurfaceForce


def _lean_indices(field):
    """FElupe keeps a column index of zeros (int64) beside each value's row for its COO vectors: a broadcast zero
    instead (SciPy copies it only while it converts one; paper scale: 260 MB less for the whole solve)."""
    import numpy as np

    indices = field[0].indices
    rows = indices.ai[0]
    indices.ai = (rows, np.broadcast_to(np.zeros((), rows.dtype), rows.shape))


class FEModel:
    """A nonlinear FE model: tagged mesh + material per region.

    mesh        : TaggedMesh (or anything TaggedMesh.read accepts: a path or a meshio.Mesh)
    materials   : {region: material name | needletissue.materials.Material}, every region
    order       : 1 (tetra) or 2 (tetra10; a linear mesh is converted with to_quadratic)
    formulation : "displacement" (tissue with its volumetric term, K = bulk) or "mixed" (tissue as
                  SolidBodyNearlyIncompressible: condensed constant pressure per cell, i.e. P2/P0 on
                  tetra10, P1/P0 on tetra). Stiff elastic parts (bone, needle, clamp) are always
                  displacement-based compressible Neo-Hooke.
    bulk        : {region: K in MPa} overrides the materials' default bulk modulus.

    Attributes after construction: `field` (global FieldContainer), `bodies` {region: FElupe item},
    `region` (global FElupe region), `mesh` (the TaggedMesh actually used).
    """

    def __init__(self, mesh, materials: dict, order: int = 1, formulation: str = "displacement",
                 bulk: dict | None = None, quadrature_order: int | None = None):
        import felupe as fem

        if not isinstance(mesh, TaggedMesh):
            mesh = TaggedMesh.read(mesh)
        if order not in (1, 2):
            raise InputError("order", f"must be 1 (tetra) or 2 (tetra10), got {order!r}")
        if formulation not in FORMULATIONS:
            raise InputError("formulation", f"must be one of {FORMULATIONS}, got {formulation!r}")
        if order == 2:
            mesh = mesh.to_quadratic()
        elif mesh.order == 2:
            raise InputError("order", "order=1 given for a quadratic (tetra10) mesh")
        mesh.check()
        missing = [r for r in mesh.regions if r not in materials]
        if missing:
            raise InputError("materials", f"no material for region(s) {missing}; regions: {list(mesh.regions)}")
        unknown = [r for r in materials if r not in mesh.regions]
        if unknown:
            raise InputError("materials", f"unknown region(s) {unknown}; regions: {list(mesh.regions)}")
        bulk = dict(bulk or {})
        self.mesh = mesh
        self.order = order
        self.formulation = formulation
        self.materials = {r: _materials.get(m) for r, m in materials.items()}
        self.bulk = {r: float(bulk.get(r, self.materials[r].bulk)) for r in mesh.regions}
        tissue = {r: self.bulk[r] / m.initial_shear_modulus for r, m in self.materials.items() if m.model != "elastic"}
        if order == 1 and tissue:
            import warnings

            ratios = ", ".join(f"{r} {k:.3g}" for r, k in tissue.items())
            warnings.warn(f"order=1: linear tetrahedra lock with nearly incompressible tissue (K/mu0: {ratios}); "
                          "P1/P0 equals P1 with the one-point rule, so the tissue and the needles' bending are "
                          "too stiff (docs/needle_model.md, 'Order 1'). Use order=2 (P2/P0) for results.",
                          LockingWarning, stacklevel=2)

        if order == 1:
            region_cls, quad = fem.RegionTetra, fem.TetrahedronQuadrature(order=quadrature_order or 1)
        else:
            region_cls, quad = fem.RegionQuadraticTetra, fem.TetrahedronQuadrature(order=quadrature_order or 2)
        points = mesh.points
        cell_type = mesh.cell_type
        # Global field: dof bookkeeping only, so no shape-function gradients on all cells.
        gmesh = fem.Mesh(points, mesh.cells, cell_type)
        self.region = region_cls(gmesh, quadrature=quad, grad=False)
        self.field = fem.FieldContainer([fem.Field(self.region, dim=3)])
        _lean_indices(self.field)
        self.bodies = {}
        self.regions = {}
        for name, ids in mesh.regions.items():
            rmesh = fem.Mesh(points, mesh.cells[ids], cell_type)  # shares the global points
            region = region_cls(rmesh, quadrature=quad)
            field = fem.FieldContainer([fem.Field(region, dim=3)])
            _lean_indices(field)
            field.link(self.field)
            mat = self.materials[name]
            if formulation == "mixed" and mat.model != "elastic":
                body = fem.SolidBodyNearlyIncompressible(mat.isochoric(), field, bulk=self.bulk[name])
            else:
                body = fem.SolidBody(mat.umat(bulk=self.bulk[name]), field)
            self.regions[name] = region
            self.bodies[name] = body

    @property
    def ndof(self) -> int:
        return int(self.field.fieldsizes[0])

    def describe(self) -> dict:
        return {
            "order": self.order,
            "formulation": self.formulation,
            "materials": {r: m.name for r, m in self.materials.items()},
            "bulk_modulus_MPa": self.bulk,
            "dofs": self.ndof,
        }
