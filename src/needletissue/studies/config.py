"""Study configuration (pydantic at the boundary): what to vary, how to sample it, which model to run.

Every error names the field (e.g. ``parameters.tissue_thickness_mm.std``) and is raised while the
file is read, before any case is computed.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from needletissue.errors import InputError
from needletissue.runinfo import read_toml

DISTRIBUTIONS = ("uniform", "normal", "truncnorm", "lognormal")


class _Strict(BaseModel):
    # allow_inf_nan=False: TOML has nan and inf; a NaN in a grid would run (and fail) case by case
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ParameterSpec(_Strict):
    """One varied parameter. Its unit is the unit in its name (``_mm``, ``_N``, ``_MPa``, ``_N_per_mm2``).

    Grid studies give ``values``; sampling studies give a ``distribution`` and its constants.
    """

    values: list[float] | None = Field(None, description="Grid values, in the parameter's unit.")
    distribution: Literal["uniform", "normal", "truncnorm", "lognormal"] | None = Field(
        None, description="uniform(low, high); normal(mean, std); truncnorm(mean, std, low, high); "
        "lognormal(median, sigma of log).")
    low: float | None = Field(None, description="Lower bound, in the parameter's unit.")
    high: float | None = Field(None, description="Upper bound, in the parameter's unit.")
    mean: float | None = Field(None, description="Mean (normal, truncnorm), in the parameter's unit.")
    std: float | None = Field(None, gt=0, description="Standard deviation (normal, truncnorm), in the parameter's unit.")
    median: float | None = Field(None, gt=0, description="Median (lognormal), in the parameter's unit.")
    sigma: float | None = Field(None, gt=0, description="Standard deviation of ln(value) (lognormal), dimensionless.")

    @model_validator(mode="after")
    def _complete(self):
        need = {
            "uniform": ("low", "high"), "normal": ("mean", "std"),
            "truncnorm": ("mean", "std", "low", "high"), "lognormal": ("median", "sigma"),
        }
        if self.values is not None:
            if self.distribution is not None:
                raise ValueError("give either values (grid) or a distribution, not both")
            if not self.values:
                raise ValueError("values must not be empty")
            return self
        if self.distribution is None:
            raise ValueError("give values (grid) or a distribution: " + ", ".join(DISTRIBUTIONS))
        missing = [n for n in need[self.distribution] if getattr(self, n) is None]
        if missing:
            raise ValueError(f"distribution {self.distribution} needs {', '.join(missing)}")
        extra = [n for n in ("low", "high", "mean", "std", "median", "sigma")
                 if getattr(self, n) is not None and n not in need[self.distribution]]
        if extra:
            raise ValueError(f"distribution {self.distribution} does not use {', '.join(extra)}")
        if self.low is not None and self.high is not None and not self.low < self.high:
            raise ValueError(f"low ({self.low}) must be < high ({self.high})")
        return self

    def support(self) -> tuple[float, float, bool]:
        """Smallest and largest value the distribution or grid can produce; True when the lower end is
        open (lognormal: values > 0 but never 0)."""
        if self.values is not None:
            return min(self.values), max(self.values), False
        match self.distribution:
            case "uniform" | "truncnorm":
                return self.low, self.high, False
            case "normal":
                return -math.inf, math.inf, False
            case "lognormal":
                return 0.0, math.inf, True
        raise AssertionError(self.distribution)


class StudySettings(_Strict):
    name: str = Field("study", min_length=1, description="Study name (used in figure titles).")
    model: Literal["ritz", "fe_needle"] = Field(
        "ritz", description="Case model: 'ritz' (Rayleigh-Ritz, vectorised batches) or 'fe_needle' "
        "(3D FE needle model, one task per case).")
    method: Literal["grid", "monte_carlo", "latin_hypercube", "sobol"] = Field(
        "latin_hypercube", description="grid (Cartesian product of values), monte_carlo, latin_hypercube "
        "(scipy.stats.qmc.LatinHypercube) or sobol (Saltelli design for Sobol indices: samples * (d + 2) cases).")
    samples: int = Field(1000, ge=2, le=50_000_000, description="Number of samples (monte_carlo, "
                         "latin_hypercube) or base samples N (sobol, a power of 2 is best); ignored by grid.")
    seed: int = Field(12345, ge=0, description="Random seed: the same seed gives the same cases.")
    chunk_size: int | None = Field(None, ge=1, le=10_000_000, description="Cases per Dask task; default "
                                   "20,000 for ritz (vectorised batch), 1 for fe_needle.")
    outputs: list[str] | None = Field(None, description="Outputs to summarise (default: all of the model's).")


class StudyConfig(_Strict):
    study: StudySettings = Field(default_factory=StudySettings)
    fixed: dict[str, float | int | bool | str] = Field(
        default_factory=dict, description="Model parameters held fixed for every case, in their units.")
    parameters: dict[str, ParameterSpec] = Field(description="Varied parameters, by name.")

    @model_validator(mode="after")
    def _consistent(self):
        if not self.parameters:
            raise ValueError("parameters: give at least one varied parameter")
        grid = self.study.method == "grid"
        for name, p in self.parameters.items():
            if grid and p.values is None:
                raise ValueError(f"parameters.{name}: method grid needs values = [...]")
            if not grid and p.values is not None:
                raise ValueError(f"parameters.{name}: method {self.study.method} needs a distribution, not values")
        if self.study.method == "sobol" and len(self.parameters) < 2:
            raise ValueError("study.method: sobol needs at least two varied parameters")
        both = set(self.fixed) & set(self.parameters)
        if both:
            raise ValueError(f"fixed: {', '.join(sorted(both))} also varied in parameters")
        return self


def _field_path(err: dict) -> str:
    return ".".join(str(p) for p in err["loc"] if not str(p).startswith("function-"))


def validation_to_input_error(exc: ValidationError, prefix: str = "") -> InputError:
    """First pydantic error -> InputError naming the field (dotted path) and the allowed range."""
    err = exc.errors()[0]
    path = _field_path(err)
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = "unknown field"
    elif err["type"] == "missing":
        msg = "required field is missing"
    field = ".".join(x for x in (prefix, path) if x) or "config"
    # Messages from model validators already start with the field they are about.
    if ":" in msg.split(" ")[0]:
        field, _, msg = msg.partition(": ")
        field = ".".join(x for x in (prefix, field) if x)
    return InputError(field, msg)


def load_study(path: str | Path) -> StudyConfig:
    """Read and validate a study TOML; the model's parameter names and ranges are checked too."""
    from needletissue.studies.models import get_model

    cfg = parse_study(read_toml(path))
    get_model(cfg.study.model).check_config(cfg)
    return cfg


def parse_study(data: dict) -> StudyConfig:
    try:
        return StudyConfig.model_validate(data)
    except ValidationError as exc:
        raise validation_to_input_error(exc) from None
