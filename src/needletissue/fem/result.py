"""Converged results at one load factor: displacement, reactions, stresses, stretches; VTU and JSON."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.runinfo import to_jsonable, write_atomic


@dataclass
class FEResult:
    """Converged state at one requested load factor (never an unconverged one).

    displacement              : (n, 3) mm at the mesh nodes (tetra10 meshes include midside nodes)
    max_displacement_by_region: {region: max |u| over the region's nodes, mm}
    reaction_forces           : {surface: (3,) N} force the support/prescribed surface exerts on the
                                body (sum over the surface's nodes), for Fixed and PrescribedDisplacement
    steps, newton_iterations  : converged sub-steps and Newton iterations since the start of the solve
    cutbacks                  : failed attempts that were halved
    wall_time_s               : since the start of the solve
    cell_data                 : per cell: von_mises_MPa (Cauchy), principal_stretches (3, ascending),
                                region (int tag, names in `region_tags`)
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
            "cutbacks": self.cutbacks,
            "wall_time_s": self.wall_time_s,
            "linear_solver": self.linear_solver,
            "timing_s": self.timing_s,
            "mesh_stats": self.mesh_stats,
            "region_tags": self.region_tags,
        }
        if "von_mises_MPa" in self.cell_data:
            vm, tag = self.cell_data["von_mises_MPa"], self.cell_data["region"]
            out["max_von_mises_by_region_MPa"] = {k: float(vm[tag == i].max()) for k, i in self.region_tags.items()}
            lam = self.cell_data["principal_stretches"]
            out["principal_stretch_range_by_region"] = {
                k: [float(lam[tag == i, 0].min()), float(lam[tag == i, 2].max())] for k, i in self.region_tags.items()}
        return to_jsonable(out)

    def write_vtu(self, path) -> Path:
        """VTU for ParaView: point displacement (mm); cell von Mises Cauchy stress (MPa), principal
        stretches, region tag. Written atomically."""
        import meshio

        path = Path(path)
        cell_type = "tetra" if self.cells.shape[1] == 4 else "tetra10"
        m = meshio.Mesh(
            self.points, [(cell_type, self.cells)],
            point_data={"displacement": self.displacement},
            cell_data={k: [v] for k, v in self.cell_data.items()},
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.partial.vtu")
        meshio.write(tmp, m, binary=True)
        write_atomic(path, tmp.read_bytes())
        tmp.unlink()
        return path


def von_mises(sigma: np.ndarray) -> np.ndarray:
    """von Mises of stresses with shape (..., 3, 3)."""
    s = sigma - np.trace(sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) / 3
    return np.sqrt(1.5 * np.einsum("...ij,...ij->...", s, s))


def principal_stretches(F: np.ndarray) -> np.ndarray:
    """Ascending principal stretches of deformation gradients with shape (..., 3, 3)."""
    C = np.einsum("...ki,...kj->...ij", F, F)
    return np.sqrt(np.clip(np.linalg.eigvalsh(C), 0.0, None))


def write_results(out_dir, results: list[FEResult], config=None, vtu: bool = True, prefix: str = "fe") -> dict:
    """Write one VTU per load factor (`{prefix}_<k>.vtu`), and config.toml + versions.json +
    results.json (`{"results": [FEResult.to_dict(), ...], "vtu": [...]}`) into out_dir. Atomic."""
    from needletissue.runinfo import write_run_files

    out_dir = Path(out_dir)
    files = []
    if vtu:
        for k, r in enumerate(results):
            files.append(r.write_vtu(out_dir / f"{prefix}_{k}.vtu").name)
    payload = {"results": [r.to_dict() for r in results], "vtu": files}
    write_run_files(out_dir, config if config is not None else {}, payload)
    return payload
