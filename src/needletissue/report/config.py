"""Configuration of `needletissue reproduce`: the TOML shipped with the package, validated by pydantic.

The shipped file (needletissue/configs/default.toml) holds every value; a user file given with
``--config`` overrides any subset of fields (deep merge). Unknown fields, values out of range and wrong
types are errors that name the field, raised before any stage runs. Units are in every description.
"""

from __future__ import annotations

import copy
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator

from needletissue.errors import FORCE_LIMIT_N, FORCE_RANGE_HELP
from needletissue.runinfo import read_toml
from needletissue.studies.config import validation_to_input_error

class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # TOML has nan, inf


def _forces(v: list[float]) -> list[float]:
    if not v:
        raise ValueError("give at least one force")
    bad = [f for f in v if not abs(f) <= FORCE_LIMIT_N]
    if bad:
        raise ValueError(f"forces must be within |F| <= {FORCE_LIMIT_N:g} N (the range shared by ritz, fe needle, "
                         f"fe pelvis and reproduce), got {bad[0]:g}")
    return v


def _positive_forces(v: list[float]) -> list[float]:
    if any(not f > 0 for f in _forces(v)):
        raise ValueError("the FE models take forces > 0 N (the direction is fixed by the model)")
    return v


Forces = Annotated[list[float], AfterValidator(_forces)]
PositiveForces = Annotated[list[float], AfterValidator(_positive_forces)]


class MaterialsStage(_Strict):
    enabled: bool = Field(description="Run the stage: stress-stretch curves (paper Fig. 3 style).")
    names: list[str] = Field(min_length=1, description="Hyperelastic materials to plot (registry names).")
    stretch_max: float = Field(gt=1.0, le=3.0, description="Largest stretch of the uniaxial curves, dimensionless.")
    points: int = Field(ge=2, le=10_000, description="Points per curve.")


class TractionStage(_Strict):
    enabled: bool = Field(description="Run the soft-tissue traction validation (FE block vs closed form, Eq. 16).")
    materials: list[Literal["muscle", "adipose"]] = Field(min_length=1, description="Tissues to pull.")


class Layer(_Strict):
    name: str = Field(min_length=1, description="Tissue layer name (next to bone first).")
    thickness_mm: float = Field(gt=0, le=500, description="Layer thickness along the needle, mm.")
    k_N_per_mm2: float = Field(gt=0, le=1e4, description="Spring stiffness per unit needle length, N/mm per mm (= MPa).")


class RitzStage(_Strict):
    enabled: bool = Field(description="Run the Rayleigh-Ritz needle model (paper Fig. 5).")
    forces_N: Forces = Field(description=f"Reduction forces, N ({FORCE_RANGE_HELP}).")
    diameter_mm: float = Field(gt=0, le=50, description="Needle diameter, mm.")
    free_length_mm: float = Field(gt=0, le=1000, description="Needle length from bone to gripper centre, mm.")
    youngs_modulus_MPa: float = Field(gt=0, le=1e7, description="Needle Young's modulus, MPa.")
    order: int | Literal["auto"] = Field(description="Trial polynomial order (3 = the paper's cubic) or 'auto'.")
    use_cos: bool = Field(description="Use v/cos(theta) in the spring energy (paper Eq. 11).")
    layers: list[Layer] = Field(min_length=1, description="Tissue layers from the bone outward.")

    @field_validator("order")
    @classmethod
    def _order(cls, v):
        if isinstance(v, int) and v < 3:
            raise ValueError("order must be >= 3 or 'auto'")
        return v


class NeedleFEStage(_Strict):
    enabled: bool = Field(description="Run the parametric needle-tissue-bone FE model at a demo mesh size.")
    forces_N: PositiveForces = Field(description=f"Reduction forces, N ({FORCE_RANGE_HELP}).")
    needles: Literal[1, 2] = Field(description="One needle (like-for-like with Ritz) or two joined by the clamp.")
    diameter_mm: float = Field(gt=0, le=50, description="Needle diameter, mm.")
    free_length_mm: float = Field(gt=0, le=1000, description="Needle length from the bone surface to its end, mm.")
    mesh_size_mm: float = Field(gt=0, le=50, description="Element size in tissue, bone and clamp near the needle, mm.")
    needle_mesh_size_mm: float = Field(gt=0, le=20, description="Element size on the needle, mm.")
    far_mesh_size_mm: float = Field(gt=0, le=100, description="Element size at the far boundary, mm.")


class PelvisStage(_Strict):
    enabled: Literal["auto", "on", "off"] = Field(
        description="Anatomical model: 'auto' runs it when ../shared/data (or $NEEDLETISSUE_DATA) is present "
        "or a CT is given, 'on' always, 'off' never.")
    source: Literal["ct", "ssm"] = Field(description="Geometry from the example CT or the mean-shape surfaces.")
    ct: str = Field(description="CT file (NIfTI or DICOM folder); empty = the example CT.")
    labels: str = Field(description="Label map on the CT grid; empty = the example label map.")
    forces_N: PositiveForces = Field(description=f"Reduction forces, N ({FORCE_RANGE_HELP}).")
    mesh_size_mm: float = Field(gt=0, le=50, description="Tissue element size at the needles, mm.")
    mesher: Literal["smooth", "box"] = Field(description="'smooth' (the reconstruction `segment` + `mesh` make, "
                                             "graded; fe pelvis's default) or 'box' (tissue by element centroid).")


class ReportSettings(_Strict):
    dpi: int = Field(ge=50, le=600, description="Figure resolution, dots per inch.")


class ReproduceConfig(_Strict):
    materials: MaterialsStage
    traction: TractionStage
    ritz: RitzStage
    needle_fe: NeedleFEStage
    pelvis: PelvisStage
    report: ReportSettings


DEFAULT_NAME = "default.toml"


def default_text() -> str:
    return resources.files("needletissue.configs").joinpath(DEFAULT_NAME).read_text(encoding="utf-8")


def default_dict() -> dict:
    return tomllib.loads(default_text())


def deep_merge(base: dict, override: dict, path: str = "") -> dict:
    """override on top of base; tables merge, everything else (lists included) replaces."""
    out = copy.deepcopy(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v, f"{path}{k}.")
        else:
            out[k] = v
    return out


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> ReproduceConfig:
    """Default config, overridden by the TOML file at ``path`` and then by ``overrides``."""
    data = default_dict()
    if path is not None:
        data = deep_merge(data, read_toml(path))
    if overrides:
        data = deep_merge(data, overrides)
    try:
        return ReproduceConfig.model_validate(data)
    except ValidationError as exc:
        raise validation_to_input_error(exc) from None


def annotated_toml(cfg: ReproduceConfig) -> str:
    """The resolved config as TOML with each field's description (and unit) as a comment."""
    import tomli_w

    lines = ["# needletissue reproduce: resolved configuration. Units: mm, N, MPa, s.", ""]
    for section, sub in cfg:
        sub_model = type(sub)
        lines.append(f"[{section}]")
        tables = []
        for name, value in sub:
            desc = sub_model.model_fields[name].description or ""
            if isinstance(value, list) and value and isinstance(value[0], BaseModel):
                tables.append((name, desc, value))
                continue
            lines.append(f"# {desc}")
            lines.append(tomli_w.dumps({name: value}).strip())
        for name, desc, items in tables:
            for item in items:
                lines.append("")
                lines.append(f"# {desc}")
                lines.append(f"[[{section}.{name}]]")
                for fname, fval in item:
                    lines.append(f"{tomli_w.dumps({fname: fval}).strip()}  # "
                                 f"{type(item).model_fields[fname].description}")
        lines.append("")
    return "\n".join(lines)
