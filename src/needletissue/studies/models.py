"""Case models a study can run: their parameters (name, unit, physical range), outputs and chunk runner.

A model's ``run_chunk(cases, fixed)`` takes a DataFrame of cases and returns one row per case with
the outputs, ``status`` ('ok' or 'failed') and ``error``. It never raises for one bad case: the case is
marked failed with its message and the others go on. Functions live at module level so Dask worker
processes can import them.
"""

from __future__ import annotations

import math
import os
import socket
import time
import traceback
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from needletissue.errors import InputError


@dataclass(frozen=True)
class ParamInfo:
    """A model parameter: description with unit, and its physical range (open or closed bounds)."""

    description: str
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None

    def range_text(self) -> str:
        parts = [f"{op} {v:g}" for op, v in ((">", self.gt), (">=", self.ge), ("<", self.lt), ("<=", self.le))
                 if v is not None]
        return " and ".join(parts) or "any finite value"

    def admits(self, lo: float, hi: float, lo_open: bool = False) -> bool:
        """True when every value in [lo, hi] ((lo, hi] when lo_open) is physical."""
        return ((self.gt is None or lo > self.gt or (lo_open and lo >= self.gt))
                and (self.ge is None or lo >= self.ge)
                and (self.lt is None or hi < self.lt) and (self.le is None or hi <= self.le))


@dataclass(frozen=True)
class CaseModel:
    name: str
    parameters: dict[str, ParamInfo]
    outputs: tuple[str, ...]
    default_chunk_size: int
    chunk_function: Callable[[pd.DataFrame, dict], pd.DataFrame]
    settings: dict[str, str] = field(default_factory=dict)  # non-numeric fixed options -> description
    primary_outputs: tuple[str, ...] = ()  # plotted when study.outputs is not given

    def check_config(self, cfg) -> None:
        """Names, fixed values and distributions: every value a case can receive must be physical."""
        for name, spec in cfg.parameters.items():
            info = self._info(f"parameters.{name}", name)
            lo, hi, lo_open = spec.support()
            if not info.admits(lo, hi, lo_open):
                hint = ""
                if spec.distribution in ("normal", "lognormal") or math.isinf(lo) or math.isinf(hi):
                    hint = "; use truncnorm with low/high inside the range, or uniform"
                raise InputError(
                    f"parameters.{name}", f"{spec.distribution or 'grid'} allows values in [{lo:g}, {hi:g}] "
                    f"but {name} must be {info.range_text()}{hint}")
        for name, value in cfg.fixed.items():
            if name in self.settings:
                continue
            info = self._info(f"fixed.{name}", name)
            if isinstance(value, (bool, str)) or not math.isfinite(value) or not info.admits(value, value):
                raise InputError(f"fixed.{name}", f"must be {info.range_text()}, got {value!r}")
        for out in cfg.study.outputs or ():
            if out not in self.outputs:
                raise InputError("study.outputs", f"unknown output {out!r}; {self.name} gives: {', '.join(self.outputs)}")

    def _info(self, field_name: str, name: str) -> ParamInfo:
        try:
            return self.parameters[name]
        except KeyError:
            known = ", ".join([*self.parameters, *self.settings])
            raise InputError(field_name, f"unknown parameter for model {self.name}; known: {known}") from None


_MODELS: dict[str, CaseModel] = {}


def register(model: CaseModel) -> CaseModel:
    _MODELS[model.name] = model
    return model


def get_model(name: str) -> CaseModel:
    _load_builtin()
    try:
        return _MODELS[name]
    except KeyError:
        raise InputError("study.model", f"unknown model {name!r}; known: {', '.join(_MODELS)}") from None


def names() -> list[str]:
    _load_builtin()
    return list(_MODELS)


def _load_builtin() -> None:
    # Each case module registers itself when its engine package is present on this branch.
    import importlib

    for mod in ("needletissue.studies.case_ritz", "needletissue.studies.case_fe_needle"):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if not (exc.name or "").startswith("needletissue"):
                raise


def run_chunk(model_name: str, cases: pd.DataFrame, fixed: dict) -> pd.DataFrame:
    """Dask task: run a chunk of cases. Failures become rows with status 'failed' and the error.

    Adds ``chunk_wall_time_s`` (compute time of the whole chunk, the same on each of its rows), from
    which the scheduling overhead of a study is measured."""
    model = get_model(model_name)  # imports the engine: worker start-up, counted outside compute
    start = time.time()
    t0 = time.perf_counter()
    out = _bisect(model, cases, fixed)
    out["chunk_wall_time_s"] = time.perf_counter() - t0
    # Wall-clock start/end and the process that ran it: the runner separates scheduling gaps from
    # compute and from workers idling at the end (same-host clocks; approximate on remote clusters).
    out["chunk_start_unix"] = start
    out["chunk_end_unix"] = time.time()
    out["chunk_worker"] = f"{socket.gethostname()}:{os.getpid()}"
    return out


def _bisect(model: CaseModel, cases: pd.DataFrame, fixed: dict) -> pd.DataFrame:
    """Run the chunk; if it raises, halve it until the failing cases stand alone (O(f log n) calls)."""
    try:
        return model.chunk_function(cases, fixed)
    except Exception as exc:
        if len(cases) == 1:
            return failed_rows(cases, model.outputs, exc)
    mid = len(cases) // 2
    return pd.concat([_bisect(model, cases.iloc[:mid], fixed), _bisect(model, cases.iloc[mid:], fixed)],
                     ignore_index=True)


def failed_rows(cases: pd.DataFrame, outputs, exc: BaseException) -> pd.DataFrame:
    msg = f"{type(exc).__name__}: {exc}" if str(exc) else "".join(traceback.format_exception_only(exc)).strip()
    df = pd.DataFrame({"case_id": cases["case_id"].to_numpy()})
    for o in outputs:
        df[o] = np.nan
    df["status"] = "failed"
    df["error"] = msg
    return df
