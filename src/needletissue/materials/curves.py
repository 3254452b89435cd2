"""Stretch-stress curves of named materials for the homogeneous incompressible load cases."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from needletissue.errors import InputError, check_number
from needletissue.materials import closed_form as cf
from needletissue.materials import registry, stability


@dataclass(frozen=True)
class Curve:
    """Nominal stress (MPa) vs stretch of one material in one load case, with its stable range."""

    material: str
    model: str
    parameters: dict
    mode: str
    stretch: np.ndarray
    nominal_stress_MPa: np.ndarray
    stable_range: tuple[float, float]
    warning: str | None = None

    def to_json(self) -> dict:
        """The CLI contract: material, model, parameters, mode, stretch, nominal_stress_MPa, stable_range."""
        return {
            "material": self.material,
            "model": self.model,
            "parameters": self.parameters,
            "mode": self.mode,
            "stretch": [float(x) for x in self.stretch],
            "nominal_stress_MPa": [float(x) for x in self.nominal_stress_MPa],
            "stable_range": [float(x) for x in self.stable_range],
        }


def hyperelastic(name) -> registry.Material:
    mat = registry.get(name)
    if mat.model not in cf.PARAMETERS:
        known = [n for n in registry.names() if registry.get(n).model in cf.PARAMETERS]
        raise InputError("material", f"{mat.name} is linear elastic ({mat.model}); curves need a hyperelastic "
                         f"material, one of: {', '.join(known)}")
    return mat


def curve(name, mode: str = "uniaxial", stretch_max: float = 1.5, points: int = 51) -> Curve:
    """Closed-form curve from stretch 1 to stretch_max (down to it when < 1); warns outside the stable range."""
    mat = hyperelastic(name)
    cf.check_mode(mode)
    stretch_max = check_number("stretch_max", stretch_max, gt=0)
    if stretch_max == 1.0:
        raise InputError("stretch_max", "must differ from 1 (1 is the undeformed state)")
    if isinstance(points, bool) or not isinstance(points, (int, np.integer)) or points < 2:
        raise InputError("points", f"must be an integer >= 2, got {points!r}")
    stretch = np.linspace(1.0, stretch_max, int(points))
    stress = cf.nominal_stress(mat.model, mat.parameters, mode, stretch)
    rng = stability.stable_range(mat.model, mat.parameters, mode)
    msg = stability.warn_if_unstable(mat.name, mat.model, mat.parameters, mode, stretch, rng)
    return Curve(mat.name, mat.model, dict(mat.parameters), mode, stretch, stress, rng, msg)


@dataclass(frozen=True)
class Compressibility:
    """FElupe uniaxial tension of the nearly incompressible umat (lateral faces traction-free)."""

    material: str
    bulk_MPa: float
    stretch: np.ndarray
    volume_ratio: np.ndarray  # J
    stress_ratio: np.ndarray  # P(umat with K) / P(incompressible closed form)


def compressibility(name, stretch, bulk: float | None = None) -> Compressibility:
    """How far the FE material (isochoric law & Volumetric(K)) is from incompressible in uniaxial tension."""
    import felupe as fem

    mat = hyperelastic(name)
    K = mat.bulk if bulk is None else check_number("bulk", bulk, gt=0)
    lam = np.atleast_1d(np.asarray(stretch, dtype=float))
    if np.any(lam == 1.0):
        raise InputError("stretch", "exclude stretch 1 (zero stress, ratio undefined)")
    view = fem.ViewMaterial(mat.umat(bulk=K), ux=lam, ps=None, bx=None)
    (l1, l2, l3), P, _ = view.uniaxial()
    ratio = P / cf.nominal_stress(mat.model, mat.parameters, "uniaxial", lam)
    return Compressibility(mat.name, K, lam, l1 * l2 * l3, ratio)
