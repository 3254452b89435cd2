"""Verification models for frictional contact: blocks on blocks, built and solved with FElupe.

Used by tests/fem/test_contact.py, tests/models/test_needle_contact.py and benchmarks/bench_contact.py. ``stacked_boxes`` returns a
TaggedMesh, so ``split_interfaces`` treats it like a model mesh.
``solve_steps`` is a small load-stepping Newton driver with line search and cut-back (the same
behaviour ``needletissue.fem.solve`` has), so the contact item is verified without the full FE core.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import felupe as fem
import numpy as np
from felupe.tools._newton import fun_items

from needletissue.errors import ConvergenceError
from needletissue.fem.contact import ContactSettings, ContactSurface, FrictionalContact
from needletissue.fem.contact.mesh import split_interfaces
from needletissue.fem.mesh import TaggedMesh


def stacked_boxes(boxes: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]], h: float) -> TaggedMesh:
    """A conforming tetrahedral mesh of axis-aligned boxes (mm), one region per box: tetrahedralize the
    bounding grid with spacing h and keep the cells inside the named boxes.

    Box corners must lie on the grid, so touching boxes share their interface nodes (conforming).
    """
    lo = np.min([b[0] for b in boxes.values()], axis=0)
    hi = np.max([b[1] for b in boxes.values()], axis=0)
    n = np.rint((hi - lo) / h).astype(int) + 1
    grid = fem.Cube(a=tuple(lo), b=tuple(hi), n=tuple(n)).triangulate()
    centroids = grid.points[grid.cells].mean(axis=1)
    keep, regions, start = [], {}, 0
    for name, (a, b) in boxes.items():
        inside = np.all((centroids > np.array(a)) & (centroids < np.array(b)), axis=1)
        ids = np.flatnonzero(inside)
        keep.append(ids)
        regions[name] = np.arange(start, start + len(ids))
        start += len(ids)
    cells = grid.cells[np.concatenate(keep)]
    used = np.unique(cells)
    renum = np.full(len(grid.points), -1)
    renum[used] = np.arange(len(used))
    return TaggedMesh(points=grid.points[used].copy(), cells=renum[cells], regions=regions)


@dataclass
class BlockModel:
    """FElupe bodies on one global field, plus the contact item (None when bonded)."""

    mesh: TaggedMesh
    field: fem.FieldContainer
    solids: list
    contact: FrictionalContact | None

    @property
    def items(self):
        return self.solids + ([self.contact] if self.contact is not None else [])


def build_model(mesh: TaggedMesh, materials: dict[str, object], friction: dict[str, float] | None,
                settings: ContactSettings = ContactSettings()) -> BlockModel:
    """One SolidBody per region (umat per region), split + contact item for ``friction`` interfaces."""
    interfaces = []
    if friction:
        mesh, interfaces = split_interfaces(mesh, list(friction))
    whole = fem.Mesh(mesh.points, mesh.cells, "tetra")
    field = fem.FieldContainer([fem.Field(fem.RegionTetra(whole), dim=3)])
    solids = []
    for name, cells in mesh.regions.items():
        sub = fem.Mesh(mesh.points, mesh.cells[cells], "tetra")
        f = fem.FieldContainer([fem.Field(fem.RegionTetra(sub), dim=3)])
        solids.append(fem.SolidBody(materials[name], f))
    contact = None
    if interfaces:
        surface = ContactSurface.build(mesh.points, interfaces, friction, gap=settings.gap)
        contact = FrictionalContact(field, surface, settings)
    return BlockModel(mesh, field, solids, contact)


# the residual-decrease criterion stalls at the stick-slip transition of the smoothed friction
# (the friction force saturates within eps_v); only admissible, finite trials are required
RESIDUAL_LS = False


def _finite(trial) -> bool:
    """Line-search criterion: reject trials the contact item marks inadmissible (NaN residual)."""
    return bool(np.all(np.isfinite(trial.fun)))


@dataclass
class StepResult:
    load_factor: float
    displacement: np.ndarray
    reaction: np.ndarray  # (n_dofs,) residual vector: reactions on prescribed dofs
    newton_iterations: int
    contact: dict


@dataclass
class Solution:
    steps: list[StepResult]
    wall_time_s: float
    newton_iterations: int
    substeps: int


def solve_steps(model: BlockModel, boundaries: dict, apply, factors, *, initial_step=None,
                min_step=1 / 256, maxiter=25, tol=1e-8, linesearch=True) -> Solution:
    """Ramp the load with apply(factor) through ``factors`` with Newton + cut-back.

    apply(factor) must update the boundary values / point loads for the load factor. Raises
    ConvergenceError naming the load factor reached when the step falls below min_step.
    """
    t0 = time.perf_counter()
    field = model.field
    dof1, dof0 = None, None
    loaded, results, total_iter, substeps = 0.0, [], 0, 0
    step = initial_step or (factors[0] if factors else 1.0)
    for target in factors:
        while loaded < target - 1e-12:
            trial = min(loaded + step, target)
            apply(trial)
            dof0, dof1 = fem.dof.partition(field, boundaries)
            ext0 = fem.dof.apply(field, boundaries, dof0)
            saved = [f.values.copy() for f in field.fields]
            saved_items = [i.checkpoint() for i in model.items if hasattr(i, "checkpoint")]
            plugins = [fem.LinesearchPlugin(admissible=True, residual=RESIDUAL_LS, max_halvings=8, criteria=[_finite])] if linesearch else None
            try:
                res = fem.newtonraphson(
                    x0=field, items=model.items, dof1=dof1, dof0=dof0, ext0=ext0,
                    maxiter=maxiter, tol=tol, verbose=0, plugins=plugins,
                )
                ok = bool(res.success)
            except (fem.NewtonConvergenceError, ArithmeticError, ValueError):
                ok, res = False, None
            if ok:
                for f, r in zip(field.fields, res.x.fields):
                    f.values[:] = r.values
                total_iter += res.iterations
                substeps += 1
                loaded = trial
                step = min(step * 1.5, 1.0)
                last_iter = res.iterations
            else:
                for f, v in zip(field.fields, saved):
                    f.values[:] = v
                for i, c in zip([i for i in model.items if hasattr(i, "checkpoint")], saved_items):
                    i.restore(c)
                step /= 2
                if step < min_step:
                    raise ConvergenceError(
                        f"contact solve did not converge: load factor {loaded:.4g} reached, "
                        f"step {step:.3g} below the minimum {min_step:.3g} towards {trial:.4g}"
                    )
        r = fun_items(model.items, field)
        info = model.contact.contact_state() if model.contact is not None else {}
        results.append(StepResult(target, field[0].values.copy(), r, last_iter, info))
    return Solution(results, time.perf_counter() - t0, total_iter, substeps)


def pressed_blocks(h: float, friction: dict[str, float] | None, settings: ContactSettings, push: float = 1.0,
                   factors=(1.0,)) -> tuple[BlockModel, Solution]:
    """Two 10 mm blocks (lower G = 10 MPa, upper G = 1 MPa, element size h mm) pressed together by a
    prescribed top displacement `push` (mm); x = 0 and y = 0 are symmetry planes, the bottom slides on
    z = -5. friction None: bonded; {"lower-upper": mu}: frictional contact."""
    mesh = stacked_boxes({"lower": ((0, 0, -5), (10, 10, 0)), "upper": ((0, 0, 0), (10, 10, 10))}, h)
    mats = {"lower": fem.NeoHooke(mu=10, bulk=50), "upper": fem.NeoHooke(mu=1, bulk=5)}
    m = build_model(mesh, mats, friction, settings)
    u = m.field[0]
    bnd = {
        "x0": fem.Boundary(u, fx=0, skip=(0, 1, 1)),
        "y0": fem.Boundary(u, fy=0, skip=(1, 0, 1)),
        "bottom": fem.Boundary(u, fz=-5, skip=(1, 1, 0)),
        "top": fem.Boundary(u, fz=10, skip=(1, 1, 0)),
    }
    return m, solve_steps(m, bnd, lambda t: bnd["top"].update(-push * t), list(factors), initial_step=0.5)
