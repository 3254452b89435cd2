"""Needle-in-layered-springs model: a cantilever needle clamped in bone, N tissue layers, a force.

Units: mm, N, MPa. Spring stiffness k per unit needle length in N/mm per mm = N/mm^2 (MPa).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property

import numpy as np

from needletissue.errors import InputError, check_number

# Paper Table 2: titanium-alloy bone needle.
NEEDLE_E_MPA = 110_000.0

# Validity of the model (docs/ritz.md): Euler-Bernoulli bending with the small-rotation curvature v''.
# At |v|max / l = 0.25 a cantilever's tip slope is ~1.5 * 0.25 = 0.375 rad and the true curvature
# v'' / (1 + v'^2)^1.5 is ~20 % below v'': beyond that the answer is outside what the model describes.
# (The paper's 300 N case: 17.63 / 84.18 = 0.21.)
MAX_DEFLECTION_RATIO = 0.25


@dataclass(frozen=True)
class Layer:
    """One tissue layer; layers are stacked outward from the bone in the order given."""

    name: str
    thickness_mm: float
    k_N_per_mm2: float  # spring force per unit needle length per mm of deflection, F = k (x + x^3)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError("layer.name", "must be a non-empty string")
        check_number(f"layer {self.name}: thickness_mm", self.thickness_mm, gt=0)
        check_number(f"layer {self.name}: k_N_per_mm2", self.k_N_per_mm2, gt=0)

    @classmethod
    def parse(cls, text: str) -> "Layer":
        """'NAME:THICKNESS_MM:K' (the CLI's --layer)."""
        parts = text.split(":")
        if len(parts) != 3:
            raise InputError("--layer", f"expected NAME:THICKNESS_MM:K, got {text!r}")
        name, t, k = parts
        try:
            t, k = float(t), float(k)
        except ValueError:
            raise InputError("--layer", f"THICKNESS_MM and K must be numbers, got {text!r}") from None
        return cls(name, t, k)


# Paper Table 1 (thickness and spring stiffness), muscle next to the bone.
DEFAULT_LAYERS = (Layer("muscle", 22.0, 0.048), Layer("adipose", 10.0, 0.023))

# Needle diameter and free length: the paper leaves them open (docs/ritz.md, "Paper consistency").
# A 5 mm Schanz pin with this free length gives the paper's 17.63 mm tip deflection at 300 N.
DEFAULT_DIAMETER_MM = 5.0
DEFAULT_FREE_LENGTH_MM = 84.18


@dataclass(frozen=True)
class RitzModel:
    """Model parameters. load_point_mm=None puts the force at the free end (z3 = l)."""

    diameter_mm: float = DEFAULT_DIAMETER_MM
    free_length_mm: float = DEFAULT_FREE_LENGTH_MM
    youngs_modulus_MPa: float = NEEDLE_E_MPA
    layers: tuple[Layer, ...] = field(default=DEFAULT_LAYERS)
    load_point_mm: float | None = None
    cos_term: bool = True

    def __post_init__(self):
        check_number("diameter_mm", self.diameter_mm, gt=0)
        check_number("free_length_mm", self.free_length_mm, gt=0)
        check_number("youngs_modulus_MPa", self.youngs_modulus_MPa, gt=0)
        layers = tuple(self.layers)
        for layer in layers:
            if not isinstance(layer, Layer):
                raise InputError("layers", f"expected Layer objects, got {layer!r}")
        object.__setattr__(self, "layers", layers)
        total = sum(layer.thickness_mm for layer in layers)
        if total > self.free_length_mm:
            raise InputError("layers", f"total thickness {total} mm must be <= free_length_mm "
                             f"{self.free_length_mm} mm (layers are stacked on the exposed needle)")
        if self.load_point_mm is not None:
            check_number("load_point_mm", self.load_point_mm, gt=0, le=self.free_length_mm)
        if not isinstance(self.cos_term, bool):
            raise InputError("cos_term", f"must be true or false, got {self.cos_term!r}")

    @property
    def second_moment_mm4(self) -> float:
        return math.pi * self.diameter_mm**4 / 64.0

    @property
    def bending_stiffness_Nmm2(self) -> float:
        return self.youngs_modulus_MPa * self.second_moment_mm4

    @property
    def z3_mm(self) -> float:
        return self.free_length_mm if self.load_point_mm is None else self.load_point_mm

    @property
    def tissue_thickness_mm(self) -> float:
        return sum(layer.thickness_mm for layer in self.layers)

    def replace(self, **changes) -> "RitzModel":
        return replace(self, **changes)

    def with_layer_k(self, name: str, k: float) -> "RitzModel":
        if name not in [layer.name for layer in self.layers]:
            raise InputError("layer", f"no layer named {name!r}; layers: {[la.name for la in self.layers]}")
        return replace(self, layers=tuple(replace(la, k_N_per_mm2=k) if la.name == name else la
                                          for la in self.layers))

    def to_dict(self) -> dict:
        """All parameters, with the derived I and EI, for JSON/TOML output."""
        d = asdict(self)
        d["load_point_mm"] = self.z3_mm
        d["second_moment_mm4"] = self.second_moment_mm4
        d["bending_stiffness_Nmm2"] = self.bending_stiffness_Nmm2
        return d

    @cached_property
    def _arrays(self):
        """Length-1 arrays for the compiled kernel (cached: the control loop re-uses the model)."""
        l = self.free_length_mm
        return (np.array([self.bending_stiffness_Nmm2 / l**3]), np.array([l]), np.array([self.z3_mm]),
                np.array([[la.thickness_mm for la in self.layers]], dtype=float).reshape(1, -1),
                np.array([[la.k_N_per_mm2 for la in self.layers]], dtype=float).reshape(1, -1))
