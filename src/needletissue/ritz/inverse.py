"""Inverse use: the force for a measured deflection; one parameter calibrated to a (force, deflection).

The load-point deflection grows monotonically with the force (it is the derivative of the convex
function G(F) = max_v [F v(z3) - U(v)]), with the free length, and falls with the diameter and with
any layer's k, so each inverse problem is a bracketed scalar root (scipy.optimize.brentq).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy.optimize import brentq

from needletissue.errors import InputError, check_number
from needletissue.ritz.model import RitzModel
from needletissue.ritz.solver import DEFAULT_TOL_MM, RitzResult, solve

MAX_FORCE_N = 1e5
_XTOL = 1e-12


@dataclass(frozen=True)
class Calibration:
    """Result of an inverse solve: the parameter's value and the model/solution that match."""

    parameter: str  # "force", "free_length", "diameter" or "k:<layer>"
    value: float  # N, mm, mm or N/mm^2
    force_N: float
    deflection_mm: float  # the measured deflection matched
    at: str  # "tip" or "load_point"
    model: RitzModel
    result: RitzResult
    evaluations: int


def _measure(r: RitzResult, at: str) -> float:
    return r.tip_deflection_mm if at == "tip" else r.load_point_deflection_mm


def _check_at(at: str) -> str:
    if at not in ("tip", "load_point"):
        raise InputError("at", f"must be 'tip' or 'load_point', got {at!r}")
    return at


def force_for_deflection(deflection_mm: float, model: RitzModel | None = None, *, at: str = "tip",
                         order=3, tol_mm: float = DEFAULT_TOL_MM) -> Calibration:
    """The force (N) whose solution has the given deflection (mm; sign gives the direction)."""
    model = RitzModel() if model is None else model
    target = check_number("deflection_mm", deflection_mm)
    at = _check_at(at)
    if target == 0.0:
        r = solve(0.0, model, order, tol_mm)
        return Calibration("force", 0.0, 0.0, 0.0, at, model, r, 1)
    sign = math.copysign(1.0, target)
    calls = [0]

    def f(F):
        calls[0] += 1
        return _measure(solve(sign * F, model, order, tol_mm), at) * sign - abs(target)

    # Start from the bare cantilever's force (springs only stiffen: it is a lower bound of the answer).
    hi = 3.0 * model.bending_stiffness_Nmm2 * abs(target) / model.z3_mm**3
    while f(hi) < 0.0:
        hi *= 2.0
        if hi > MAX_FORCE_N:
            raise InputError("deflection_mm", f"needs a force above {MAX_FORCE_N:g} N, outside the model's range")
    F = brentq(f, 0.0, hi, xtol=_XTOL, rtol=1e-13)
    r = solve(sign * F, model, order, tol_mm)
    return Calibration("force", sign * F, sign * F, target, at, model, r, calls[0])


_BOUNDS = {"free_length": (None, 2000.0), "diameter": (0.05, 50.0)}


def calibrate(parameter: str, force_N: float, deflection_mm: float, model: RitzModel | None = None, *,
              at: str = "tip", order=3, tol_mm: float = DEFAULT_TOL_MM) -> Calibration:
    """Calibrate 'free_length', 'diameter' or 'k:<layer name>' so that force_N gives deflection_mm.

    parameter 'force' is force_for_deflection (force_N is then ignored).
    """
    model = RitzModel() if model is None else model
    if parameter == "force":
        return force_for_deflection(deflection_mm, model, at=at, order=order, tol_mm=tol_mm)
    F = check_number("force_N", force_N)
    target = check_number("deflection_mm", deflection_mm)
    at = _check_at(at)
    if F == 0.0 or target == 0.0 or math.copysign(1.0, F) != math.copysign(1.0, target):
        raise InputError("deflection_mm", "must be non-zero and have the sign of force_N")
    calls = [0]
    if parameter == "free_length":
        lo = max(model.tissue_thickness_mm, model.load_point_mm or 0.0)
        hi = _BOUNDS["free_length"][1]
        make = lambda x: model.replace(free_length_mm=x)  # noqa: E731
        lo = max(lo, 1e-6)
    elif parameter == "diameter":
        lo, hi = _BOUNDS["diameter"]
        make = lambda x: model.replace(diameter_mm=x)  # noqa: E731
    elif parameter.startswith("k:"):
        name = parameter[2:]
        model.with_layer_k(name, 1.0)  # validates the name
        lo, hi = 1e-9, 1e6
        make = lambda x: model.with_layer_k(name, x)  # noqa: E731
    else:
        raise InputError("parameter", f"must be force, free_length, diameter or k:<layer>, got {parameter!r}")

    def f(x):
        calls[0] += 1
        return abs(_measure(solve(F, make(x), order, tol_mm), at)) - abs(target)

    # deflection rises with free length, falls with diameter and k: search in log space
    try:
        flo, fhi = f(lo), f(hi)
    except Exception as exc:  # a bracket end outside the solver's range
        raise InputError(parameter, f"cannot bracket the calibration in [{lo:g}, {hi:g}]: {exc}") from None
    if flo * fhi > 0.0:
        reach = sorted((flo + abs(target), fhi + abs(target)))
        raise InputError("deflection_mm", f"{abs(target)} mm is not reachable by varying {parameter} in "
                         f"[{lo:g}, {hi:g}] (deflection range {reach[0]:.6g} .. {reach[1]:.6g} mm)")
    u = brentq(lambda t: f(math.exp(t)), math.log(lo), math.log(hi), xtol=1e-14, rtol=1e-14)
    x = math.exp(u)
    m = make(x)
    return Calibration(parameter, x, F, target, at, m, solve(F, m, order, tol_mm), calls[0])
