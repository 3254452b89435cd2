"""Fit the frame model's effective parameters (bone foundation factor, tissue spring factor, and
optionally the bone's axial factor) to FE runs or measurements by least squares, with Jacobian-based confidence intervals.

Each point: a model (geometry), a wrench and what was measured there (clamp-centre displacement vector
and/or the max needle deflection, mm). Residuals in mm; the factors are fitted in log space (they stay
positive); covariance s^2 (J^T J)^-1 with s^2 = SSR / (m - p), intervals +- t(0.975, m - p) sigma,
mapped back through exp (so they are asymmetric in the factor).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from needletissue.errors import InputError
from needletissue.frame.model import MAX_FACTOR, FrameModel

PARAMS = ("foundation_factor", "axial_factor", "tissue_factor", "cortex_factor", "confinement_factor")


@dataclass(frozen=True)
class CalibrationPoint:
    model: FrameModel
    force_N: tuple
    moment_Nmm: tuple = (0.0, 0.0, 0.0)
    clamp_displacement_mm: tuple | None = None   # measured (3), compared component-wise
    max_needle_deflection_mm: float | None = None


@dataclass(frozen=True)
class Calibration:
    params: dict          # name -> fitted value
    intervals: dict       # name -> (low, high) 95 % confidence
    rms_mm: float
    max_abs_mm: float
    residuals_mm: np.ndarray
    points: int
    cost_evaluations: int


def _predict(p: CalibrationPoint, values: dict, tolerance=None):
    from needletissue.frame.solver import solve

    r = solve(p.force_N, p.moment_Nmm, p.model.replace(**values), error_estimate=False)
    out = []
    if p.clamp_displacement_mm is not None:
        u = np.asarray(p.clamp_displacement_mm, float)
        s = 1.0 if tolerance is None else max(tolerance[0], tolerance[1] * float(np.linalg.norm(u)))
        out.extend((np.array(r.clamp_displacement_mm) - u) / s)
    if p.max_needle_deflection_mm is not None:
        d = float(p.max_needle_deflection_mm)
        s = 1.0 if tolerance is None else max(tolerance[0], tolerance[1] * abs(d))
        out.append((r.max_needle_deflection_mm - d) / s)
    return out


def calibrate(points, params=("foundation_factor", "tissue_factor"), x0=None, tolerance=None) -> tuple[dict, dict]:
    """(fitted params, 95 % confidence intervals); `calibration(...)` returns the full record."""
    c = calibration(points, params, x0, tolerance)
    return c.params, c.intervals


def calibration(points, params=("foundation_factor", "tissue_factor"), x0=None, tolerance=None) -> Calibration:
    """Least squares of the model against the points. tolerance=(mm, fraction): each residual is divided by
    max(mm, fraction x |measured|) (the clamp vector by its norm), so that every point counts in units of the
    accuracy asked of it (issue #14: max(0.432 mm, 2.4 %)) instead of the largest deflections dominating;
    None: residuals in mm. rms_mm and max_abs_mm are then in those units."""
    from scipy.optimize import least_squares
    from scipy.stats import t as student

    points = list(points)
    params = tuple(params)
    for name in params:
        if name not in PARAMS:
            raise InputError("params", f"can fit {PARAMS}, got {name!r}")
    if not points:
        raise InputError("points", "give at least one calibration point")
    for i, p in enumerate(points):
        if not isinstance(p, CalibrationPoint):
            raise InputError(f"points[{i}]", "expected a CalibrationPoint")
        if p.clamp_displacement_mm is None and p.max_needle_deflection_mm is None:
            raise InputError(f"points[{i}]", "needs a measured clamp_displacement_mm or max_needle_deflection_mm")
    x0 = np.zeros(len(params)) if x0 is None else np.log(np.asarray(x0, float))
    calls = [0]

    def fun(x):
        calls[0] += 1
        vals = dict(zip(params, np.exp(x)))
        return np.concatenate([_predict(p, vals, tolerance) for p in points])

    lim = np.log(MAX_FACTOR)
    sol = least_squares(fun, x0, bounds=(-lim, lim), x_scale=1.0, diff_step=1e-6)
    r = sol.fun
    m, k = r.size, len(params)
    J = sol.jac
    dof = max(m - k, 1)
    s2 = float(r @ r) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        sd = np.full(k, np.inf)
    q = student.ppf(0.975, dof)
    values = np.exp(sol.x)
    return Calibration(dict(zip(params, values.tolist())),
                       {n: (float(np.exp(x - q * s)), float(np.exp(x + q * s))) for n, x, s in zip(params, sol.x, sd)},
                       float(np.sqrt(np.mean(r**2))), float(np.abs(r).max()), r, len(points), calls[0])
