"""Soft-tissue traction validation (paper Sec. 3.2, Figs. 8-9, Eq. 16).

A block of tissue (width x width x height, mm) is pulled from 0 to `max_displacement` mm at its top.
ends="free": the base slides (symmetry planes x=0, y=0, z=0), so the block is laterally free and the
state is homogeneous uniaxial tension. ends="clamped": base and top bonded (all components fixed), as
a gripped sample. FE nominal stress = top reaction / reference cross-section, against the closed-form
incompressible uniaxial nominal stress of the same strain energy; RMSE as Eq. 16.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from needletissue import materials
from needletissue.errors import InputError, check_number


@dataclass
class TractionConfig:
    """Inputs of the traction validation (mm, MPa)."""

    material: str = "muscle"
    width: float = 20.0  # mm, square cross-section side
    height: float = 20.0  # mm, gauge length (max stretch = 1 + max_displacement / height)
    max_displacement: float = 10.0  # mm
    points: int = 11  # load levels compared, including 0
    elements: int = 4  # elements per side (structured tetrahedra)
    order: int = 2
    formulation: str = "mixed"
    bulk_ratio: float = 1e4  # K / mu0 of the FE model (the theory is exactly incompressible)
    ends: str = "free"

    def __post_init__(self):
        if self.material not in ("muscle", "adipose") and self.material not in materials.names():
            raise InputError("material", f"unknown material {self.material!r}; known: muscle, adipose")
        check_number("width", self.width, gt=0)
        check_number("height", self.height, gt=0)
        check_number("max_displacement", self.max_displacement, gt=0)
        check_number("points", self.points, ge=2, le=1000)
        check_number("elements", self.elements, ge=1, le=64)
        check_number("bulk_ratio", self.bulk_ratio, ge=1, le=1e6)
        if self.ends not in ("free", "clamped"):
            raise InputError("ends", f"must be 'free' or 'clamped', got {self.ends!r}")
        if self.order not in (1, 2):
            raise InputError("order", f"must be 1 or 2, got {self.order!r}")


@dataclass
class TractionResult:
    material: str
    displacement_mm: list[float]
    stretch: list[float]
    fe_nominal_stress_MPa: list[float]
    theory_nominal_stress_MPa: list[float]
    rmse_MPa: float
    max_relative_error: float
    paper_rmse_MPa: float
    criterion_MPa: float = 0.05
    config: dict = field(default_factory=dict)
    newton_iterations: int = 0
    steps: int = 0
    wall_time_s: float = 0.0
    mesh_stats: dict = field(default_factory=dict)
    bulk_modulus_MPa: float = 0.0

    @property
    def passed(self) -> bool:
        return self.rmse_MPa < self.criterion_MPa

    def to_dict(self) -> dict:
        d = asdict(self)
        d["passed"] = self.passed
        return d


PAPER_RMSE = {"muscle": 0.0131, "adipose": 0.0105}  # MPa, paper Sec. 3.2


def theory_nominal_stress(material: str, stretch) -> np.ndarray:
    """Incompressible uniaxial nominal stress (MPa) of a tissue's isochoric strain energy.

    Uses the closed forms of needletissue.materials (Material.nominal_stress, written independently
    of FElupe) when present, else FElupe's ViewMaterialIncompressible on the same energy.
    """
    stretch = np.asarray(stretch, float)
    mat = materials.get(material)
    if mat.model == "elastic":
        raise InputError("material", f"{material} is not a hyperelastic tissue")
    if hasattr(mat, "nominal_stress"):
        return np.asarray(mat.nominal_stress("uniaxial", stretch), float).reshape(stretch.shape)
    import felupe as fem

    out = np.zeros_like(stretch)
    nz = ~np.isclose(stretch, 1.0)
    if nz.any():
        _, P, _ = fem.ViewMaterialIncompressible(mat.isochoric()).uniaxial(stretch[nz])
        out[nz] = P
    return out


def run(config: TractionConfig, progress: bool = False) -> TractionResult:
    from needletissue.fem import FEModel, Fixed, PrescribedDisplacement, TaggedMesh, solve

    c = config
    mat = materials.get(c.material)
    w, h, n = c.width, c.height, int(c.elements)
    nz = max(n, int(round(n * h / w)))
    mesh = TaggedMesh.box((w, w, h), (n + 1, n + 1, nz + 1), region=c.material)
    bulk = c.bulk_ratio * mat.initial_shear_modulus
    model = FEModel(mesh, {c.material: c.material}, order=c.order, formulation=c.formulation,
                    bulk={c.material: bulk})
    if c.ends == "free":
        bcs = [Fixed("xmin", (0,)), Fixed("ymin", (1,)), Fixed("zmin", (2,))]
    else:
        bcs = [Fixed("zmin")]
    top = (0.0, 0.0, c.max_displacement) if c.ends == "clamped" else (None, None, c.max_displacement)
    bcs.append(PrescribedDisplacement("zmax", top))
    factors = np.linspace(0, 1, int(c.points))
    results = solve(model, bcs, factors[1:], progress=progress)
    d = factors * c.max_displacement
    fe = np.concatenate([[0.0], [r.reaction_forces["zmax"][2] / (w * w) for r in results]])
    stretch = 1 + d / h
    theory = theory_nominal_stress(c.material, stretch)
    rmse = float(np.sqrt(np.mean((fe - theory) ** 2)))  # Eq. 16
    rel = float(np.max(np.abs(fe[1:] - theory[1:]) / np.abs(theory[1:])))
    last = results[-1]
    return TractionResult(
        material=c.material, displacement_mm=d.tolist(), stretch=stretch.tolist(),
        fe_nominal_stress_MPa=fe.tolist(), theory_nominal_stress_MPa=theory.tolist(), rmse_MPa=rmse,
        max_relative_error=rel, paper_rmse_MPa=PAPER_RMSE.get(c.material, float("nan")),
        config=asdict(c), newton_iterations=last.newton_iterations, steps=last.steps,
        wall_time_s=last.wall_time_s, mesh_stats=last.mesh_stats, bulk_modulus_MPa=bulk,
    )


def plot(result: TractionResult, path) -> None:
    """Nominal stress vs displacement: FE points and the closed-form curve (PNG, atomic)."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from needletissue.runinfo import write_atomic

    fig, ax = plt.subplots(figsize=(5, 3.6), dpi=150)
    cfg = result.config
    d = np.linspace(0, result.displacement_mm[-1], 200)
    ax.plot(d, theory_nominal_stress(result.material, 1 + d / cfg["height"]), "k-",
            label="closed form (incompressible)")
    ax.plot(result.displacement_mm, result.fe_nominal_stress_MPa, "o", mfc="none",
            label=f"FE ({cfg['ends']} ends), RMSE {result.rmse_MPa:.2e} MPa")
    ax.set_xlabel("top displacement (mm)")
    ax.set_ylabel("nominal stress (MPa)")
    ax.set_title(f"{result.material}: {cfg['width']:g}x{cfg['width']:g}x{cfg['height']:g} mm block")
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    write_atomic(path, buf.getvalue())
