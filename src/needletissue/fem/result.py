"""Converged results at one load factor: displacement, reactions, stresses, stretches; VTU and JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.runinfo import to_jsonable, write_atomic, write_vtu


FRAME_DEFAULT = "the mesh's coordinates, mm"


@dataclass
class FEResult:
    """Converged state at one requested load factor (never an unconverged one).

    displacement              : (n, 3) mm at the mesh nodes (tetra10 meshes include midside nodes)
    max_displacement_by_region: {region: max |u| over the region's nodes, mm}
    reaction_forces           : {surface: (3,) N} force the support/prescribed surface exerts on the
                                body (sum over the surface's nodes), for Fixed and PrescribedDisplacement
    steps, newton_iterations  : converged sub-steps and Newton iterations since the start of the solve
    newton_substeps           : modified-Newton substeps (corrections with an iteration's factorisation,
                                no tangent assembly) since the start of the solve (solve(substeps=...))
    cutbacks                  : failed attempts that were halved
    wall_time_s               : since the start of the solve
    cell_data                 : per cell: von_mises_MPa (Cauchy), principal_stretches (3, ascending),
                                cauchy_stress_MPa and green_lagrange_strain (3x3 row-major, 9 columns),
                                drucker_stable (1/0), region (int tag, names in `region_tags`); cell
                                means over the quadrature points
    materials                 : {region: material name}
    drucker_unstable_fraction : {region: volume fraction of its cells whose principal stretches lie
                                outside the law's Drucker-stable range} (hyperelastic tissues only)
    """

    load_factor: float
    displacement: np.ndarray
    max_displacement_by_region: dict[str, float]
    reaction_forces: dict[str, np.ndarray]
    steps: int
    newton_iterations: int
    wall_time_s: float
    mesh_stats: dict
    cutbacks: int = 0
    linear_solver: str = ""
    timing_s: dict = field(default_factory=dict)
    residual_norms: list = field(default_factory=list)
    region_tags: dict[str, int] = field(default_factory=dict)
    points: np.ndarray | None = field(default=None, repr=False)
    cells: np.ndarray | None = field(default=None, repr=False)
    cell_data: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    materials: dict[str, str] = field(default_factory=dict)
    drucker_unstable_fraction: dict[str, float] = field(default_factory=dict)
    newton_substeps: int = 0  # modified-Newton substeps (same factorisation) since the start of the solve
    linear_factor: str = ""  # Pardiso's Cholesky: "single+cg" (linsolve.SINGLE) or "double"; "" for the others
    # Pardiso since the start of the solve: factorisations, and the tangents solved by GMRES on their symmetric
    # part's factor (linsolve.SYM_GMRES) with its back-substitutions; {} for the other backends
    linear_counts: dict[str, int] = field(default_factory=dict)

    def check_drucker(self, materials: dict[str, str]) -> "FEResult":
        """Flag cells beyond their material's Drucker-stable range (materials.stability: the law's
        incompressible log-strain Hessian at the cell's principal stretches); warn (UnstableMaterialWarning)
        for every region with such cells. Fills drucker_unstable_fraction and cell_data["drucker_stable"]."""
        import warnings

        from needletissue.materials import closed_form as cf
        from needletissue.materials import registry
        from needletissue.materials.stability import UnstableMaterialWarning, drucker_margin

        self.materials = dict(materials)
        lam = self.cell_data.get("principal_stretches")
        tag = self.cell_data.get("region")
        if lam is None or tag is None or self.cells is None:
            return self
        a, b, c, d = (self.points[self.cells[:, i]] for i in range(4))
        vol = np.abs(np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a)) / 6.0  # straight-sided
        stable = np.ones(len(tag), dtype=np.int8)
        for region, i in self.region_tags.items():
            mat = registry.get(materials[region]) if region in materials else None
            if mat is None or mat.model not in cf.PARAMETERS:  # elastic solids: no Drucker limit here
                continue
            ids = np.flatnonzero(tag == i)
            ok = drucker_margin(mat.model, mat.parameters, lam[ids].T) > 0
            stable[ids] = ok
            frac = float(vol[ids][~ok].sum() / vol[ids].sum()) if len(ids) else 0.0
            self.drucker_unstable_fraction[region] = frac
            if frac > 0:  # one text per region: Python shows it once, not at every load step
                warnings.warn(f"{region} ({mat.name}, {mat.model}) is stretched beyond its Drucker-stable range "
                              "in part of its volume: results there rest on the law outside its valid range "
                              "(fraction per load: drucker_unstable_volume_fraction)", UnstableMaterialWarning,
                              stacklevel=2)
        self.cell_data["drucker_stable"] = stable
        return self

    @property
    def max_displacement(self) -> float:
        return float(np.linalg.norm(self.displacement, axis=1).max())

    def to_dict(self) -> dict:
        """JSON-ready summary (no per-node arrays)."""
        out = {
            "load_factor": self.load_factor,
            "max_displacement_mm": self.max_displacement,
            "max_displacement_by_region_mm": self.max_displacement_by_region,
            "reaction_forces_N": {k: np.asarray(v).tolist() for k, v in self.reaction_forces.items()},
            "steps": self.steps,
            "newton_iterations": self.newton_iterations,
            "newton_substeps": self.newton_substeps,
            "cutbacks": self.cutbacks,
            "wall_time_s": self.wall_time_s,
            "linear_solver": self.linear_solver,
            "linear_factor": self.linear_factor,
            "linear_counts": self.linear_counts,
            "timing_s": self.timing_s,
            "mesh_stats": self.mesh_stats,
            "region_tags": self.region_tags,
            "materials": self.materials,
            "drucker_unstable_volume_fraction": self.drucker_unstable_fraction,
        }
        if "von_mises_MPa" in self.cell_data:
            vm, tag = self.cell_data["von_mises_MPa"], self.cell_data["region"]
            out["max_von_mises_by_region_MPa"] = {k: float(vm[tag == i].max()) for k, i in self.region_tags.items()}
            lam = self.cell_data["principal_stretches"]
            out["principal_stretch_range_by_region"] = {
                k: [float(lam[tag == i, 0].min()), float(lam[tag == i, 2].max())] for k, i in self.region_tags.items()}
        return to_jsonable(out)

    def write_vtu(self, path, frame: str = FRAME_DEFAULT, force_N: float | None = None,
                  blocks: bool = True) -> Path:
        """VTU for ParaView, written atomically: point displacement (mm); per cell von Mises and the Cauchy
        stress tensor (MPa), the Green-Lagrange strain tensor, principal stretches, drucker_stable and the
        region tag. Field data (ParaView: Information panel) name each region tag and its material, and the
        coordinate frame (`frame`), as arrays whose names carry the text (meshio and ParaView read them).
        With `blocks`, also the same result split by region beside it (write_blocks: path with .vtm)."""
        path = Path(path)
        field_data = {f"region {i} = {r}" + (f" (material {self.materials[r]})" if r in self.materials else ""): i
                      for r, i in self.region_tags.items()}
        with _writers() as pool:  # VTK releases the GIL while it compresses: the pieces are written side by side
            whole = pool.submit(write_vtu, path, self.points, self.cells, {"displacement": self.displacement},
                                self.cell_data, {**field_data, **self._load_field_data(frame, force_N)})
            if blocks:
                self.write_blocks(path.with_suffix(".vtm"), frame, force_N, pool=pool)
            whole.result()
        return path

    def _load_field_data(self, frame, force_N) -> dict:
        out = {f"coordinate frame: {frame}": 0}
        if force_N is not None:
            out["force_N"] = force_N
        out["load_factor"] = self.load_factor
        return out

    def write_blocks(self, path, frame: str = FRAME_DEFAULT, force_N: float | None = None, pool=None) -> Path:
        """ParaView multiblock file `path` (.vtm) with one block per region, the block named by the region,
        and a folder of the same stem holding one VTU per region (`<stem>/<region>.vtu`, referenced by a
        relative path: a copied result folder still opens). Each piece holds its region's cells and only
        their nodes, with the fields of write_vtu, plus `mesh_node_id` / `mesh_cell_id` (the node and cell
        numbers in the whole-mesh VTU) and field data naming its region, material, frame and force."""
        from xml.sax.saxutils import quoteattr

        path = Path(path)
        if pool is None:
            with _writers() as pool:
                return self.write_blocks(path, frame, force_N, pool)
        folder = path.with_suffix("")
        tag = np.asarray(self.cell_data["region"])
        rows, written, jobs = [], set(), []
        for region, i in sorted(self.region_tags.items(), key=lambda kv: kv[1]):
            ids = np.flatnonzero(tag == i)
            if not len(ids):
                continue
            nodes, local = np.unique(self.cells[ids], return_inverse=True)
            name = _file_name(region, written)
            written.add(name)
            label = f"region {i} = {region}" + (f" (material {self.materials[region]})"
                                                 if region in self.materials else "")
            jobs.append(pool.submit(
                write_vtu, folder / name, self.points[nodes], local.reshape(-1, self.cells.shape[1]),
                {"displacement": self.displacement[nodes], "mesh_node_id": nodes.astype(np.int64)},
                {**{k: np.asarray(v)[ids] for k, v in self.cell_data.items()}, "mesh_cell_id": ids.astype(np.int64)},
                {label: i, **self._load_field_data(frame, force_N)}))
            rows.append(f'    <DataSet index="{len(rows)}" name={quoteattr(region)} '
                        f'file={quoteattr(f"{folder.name}/{name}")}/>')
        for job in jobs:
            job.result()
        for stale in folder.glob("*.vtu"):  # regions of an earlier run into the same folder
            if stale.name not in written:
                stale.unlink()
        text = ('<?xml version="1.0"?>\n<!-- needletissue: one block per region, named by the region; '
                'pieces relative to this file -->\n<VTKFile type="vtkMultiBlockDataSet" version="1.0" '
                'byte_order="LittleEndian">\n  <vtkMultiBlockDataSet>\n' + "\n".join(rows)
                + "\n  </vtkMultiBlockDataSet>\n</VTKFile>\n")
        return write_atomic(path, text)


def _file_name(region: str, taken: set) -> str:
    """A portable file name for a region's piece (letters, digits, _ - . only), unique in its folder."""
    import re

    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", region).strip(".") or "region"
    name, k = f"{stem}.vtu", 1
    while name in taken:
        k += 1
        name = f"{stem}_{k}.vtu"
    return name


def _writers():
    """A thread pool for the VTU pieces, one thread per granted core: most of a piece's time is zlib in VTK's
    writer, which releases the GIL (two paper-scale VTUs on two threads: 5.3 s, one alone 5.4 s)."""
    from concurrent.futures import ThreadPoolExecutor

    from needletissue.fem.linsolve import granted_threads

    return ThreadPoolExecutor(granted_threads(), thread_name_prefix="needletissue-vtu")


def write_series(path, steps: list[tuple[float, str]]) -> Path:
    """ParaView .pvd collection: one file per load, the force (N) as ParaView's time (steps: (force, file
    relative to the .pvd's folder)). The models list the .vtm of each load (FEResult.write_blocks): in
    ParaView the regions are then named blocks, switched on and off in the Multiblock Inspector and
    extracted by name, at every force, instead of thresholds on an integer tag."""
    from xml.sax.saxutils import quoteattr

    rows = "\n".join(f'    <DataSet timestep="{t!r}" part="0" file={quoteattr(str(f))}/>' for t, f in steps)
    text = ('<?xml version="1.0"?>\n<!-- needletissue: time = reduction force in N -->\n'
            '<VTKFile type="Collection" version="0.1">\n  <Collection>\n' + rows + "\n  </Collection>\n</VTKFile>\n")
    return write_atomic(path, text)


def green_lagrange(F: np.ndarray) -> np.ndarray:
    """E = (F^T F - I) / 2 of deformation gradients with shape (3, 3, ...)."""
    C = np.einsum("ki...,kj...->ij...", F, F)
    return 0.5 * (C - np.eye(3).reshape((3, 3) + (1,) * (F.ndim - 2)))


def von_mises(sigma: np.ndarray) -> np.ndarray:
    """von Mises of stresses with shape (..., 3, 3)."""
    s = sigma - np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3
    return np.sqrt(1.5 * np.einsum("...ij,...ij->...", s, s))


def principal_stretches(F: np.ndarray) -> np.ndarray:
    """Ascending principal stretches of deformation gradients with shape (..., 3, 3); the eigenvalues of C by
    Jacobi rotations on all matrices at once (materials.laws.eigh3: 1.35 M matrices 1.5-1.7 -> 0.8-1.0 s against
    LAPACK's per-matrix eigvalsh, equal to 1e-15)."""
    from needletissue.materials.laws import eigh3

    C = np.einsum("...ki,...kj->...ij", F, F)
    lam = np.sort(eigh3(C.reshape(-1, 3, 3))[0], axis=1).reshape(C.shape[:-1])
    return np.sqrt(np.clip(lam, 0.0, None))


def write_results(out_dir, results: list[FEResult], config=None, vtu: bool = True, prefix: str = "fe") -> dict:
    """Write one VTU per load factor (`{prefix}_<k>.vtu`, with its per-region .vtm), the series
    `{prefix}.pvd` over the .vtm files, and config.toml + versions.json +
    results.json (`{"results": [FEResult.to_dict(), ...], "vtu": [...]}`) into out_dir. Atomic."""
    from needletissue.runinfo import write_run_files

    out_dir = Path(out_dir)
    files = []
    if vtu:
        for k, r in enumerate(results):
            files.append(r.write_vtu(out_dir / f"{prefix}_{k}.vtu").name)
        write_series(out_dir / f"{prefix}.pvd", [(r.load_factor, str(Path(f).with_suffix(".vtm")))
                                                for r, f in zip(results, files)])
    payload = {"results": [r.to_dict() for r in results], "vtu": files}
    write_run_files(out_dir, config if config is not None else {}, payload)
    return payload
