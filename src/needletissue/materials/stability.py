"""Drucker stability of incompressible isotropic hyperelastic laws (as ANSYS and Abaqus check it).

Drucker: d(tau) : d(e) > 0 for every incompressible increment of log strain d(e) (tr d(e) = 0),
tau the Kirchhoff stress. With tau_i = dW/de_i - p the pressure drops out and the condition is that
the Hessian of W in log strains, restricted to the plane de_1 + de_2 + de_3 = 0, is positive definite:
H2 = V^T H V with V = [[1, 0], [0, 1], [-1, -1]].

`stable_range` walks from stretch 1 outwards along a load case and returns the interval in which
the condition holds, inside the checked window STRETCH_WINDOW (an end equal to the window's end means
"stable at least up to there").
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from needletissue.materials import closed_form as cf

STRETCH_WINDOW = (0.2, 5.0)
_V = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])


class UnstableMaterialWarning(UserWarning):
    """A hyperelastic law is used at stretches where it is not Drucker-stable."""


def drucker_margin(model: str, parameters: dict, lam: np.ndarray) -> np.ndarray:
    """Smallest eigenvalue (MPa) of the incompressible log-strain Hessian at principal stretches lam.

    lam: (3, n) principal stretches; they are made isochoric (divided by J^(1/3)) first.
    Positive means Drucker-stable. det(V^T H V) = 1^T adj(H) 1 (exact for this V), which avoids the
    cancellation of the direct 2x2 determinant when one principal stiffness dwarfs the others
    (Ogden alpha = 16 in compression: 1e8 vs 1e-8 MPa); smallest eigenvalue = det / largest.
    """
    lam = np.asarray(lam, dtype=float).reshape(3, -1)
    lam = lam / np.prod(lam, axis=0) ** (1 / 3)
    H = cf.log_hessian(model, parameters, lam)
    M = np.einsum("ia,ijn,jb->abn", _V, H, _V)
    tr = M[0, 0] + M[1, 1]
    h = lambda i, j: H[i, j]  # noqa: E731
    det = (h(1, 1) * h(2, 2) - h(1, 2) ** 2 + h(0, 0) * h(2, 2) - h(0, 2) ** 2 + h(0, 0) * h(1, 1) - h(0, 1) ** 2
           + 2 * (h(0, 2) * h(1, 2) - h(0, 1) * h(2, 2) + h(0, 1) * h(1, 2) - h(0, 2) * h(1, 1)
                  + h(0, 1) * h(0, 2) - h(0, 0) * h(1, 2)))
    disc = np.sqrt(np.maximum(tr**2 - 4 * det, 0.0))
    big = 0.5 * (tr + disc)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(big > 0, det / big, 0.5 * (tr - disc))


def is_stable(model: str, parameters: dict, mode: str, stretch) -> np.ndarray:
    """Boolean mask: Drucker-stable at each stretch of the load case."""
    return drucker_margin(model, parameters, cf.principal_stretches(mode, stretch)) > 0


def stable_range(model: str, parameters: dict, mode: str,
                 window: tuple[float, float] = STRETCH_WINDOW, tol: float = 1e-10) -> tuple[float, float]:
    """(lo, hi): the stretch interval around 1 in which the law is Drucker-stable for this load case.

    Scans a fine log-spaced grid, then bisects each boundary to `tol`.
    """
    cf.check_mode(mode)
    margin = lambda s: drucker_margin(model, parameters, cf.principal_stretches(mode, s))  # noqa: E731
    if margin(1.0)[0] <= 0:
        return (1.0, 1.0)
    ends = []
    for end in window:
        grid = np.exp(np.linspace(0.0, np.log(end), 2001))
        bad = np.flatnonzero(margin(grid) <= 0)
        if bad.size == 0:
            ends.append(float(end))
            continue
        a, b = grid[bad[0] - 1], grid[bad[0]]  # stable at a, unstable at b
        while abs(b - a) > tol:
            m = 0.5 * (a + b)
            a, b = (m, b) if margin(m)[0] > 0 else (a, m)
        ends.append(float(a))
    return ends[0], ends[1]


@dataclass(frozen=True)
class StabilityReport:
    """Stable stretch range per load case of one law."""

    model: str
    parameters: dict
    ranges: dict  # mode -> (lo, hi)
    window: tuple[float, float] = STRETCH_WINDOW

    def to_json(self) -> dict:
        return {"model": self.model, "parameters": self.parameters,
                "stable_range": {k: list(v) for k, v in self.ranges.items()}, "window": list(self.window)}


def stability_report(model: str, parameters: dict) -> StabilityReport:
    return StabilityReport(model, parameters, {m: stable_range(model, parameters, m) for m in cf.MODES})


def warn_if_unstable(name: str, model: str, parameters: dict, mode: str, stretch,
                     rng: tuple[float, float] | None = None) -> str | None:
    """Warn (UnstableMaterialWarning) and return the message when a stretch lies outside the stable range."""
    s = np.atleast_1d(np.asarray(stretch, dtype=float))
    lo, hi = stable_range(model, parameters, mode) if rng is None else rng
    outside = (s < lo) | (s > hi)
    if not outside.any():
        return None
    msg = (f"{name} ({model}) is not Drucker-stable in {mode} beyond its stable stretch range "
           f"[{lo:.4g}, {hi:.4g}]; {int(outside.sum())} of {s.size} stretches "
           f"(from {s[outside].min():.4g} to {s[outside].max():.4g}) lie outside it")
    warnings.warn(msg, UnstableMaterialWarning, stacklevel=2)
    return msg


def stable_at(material, F) -> np.ndarray:
    """Drucker verdict of a named tissue material at deformation gradients F (3, 3, ...), e.g. FE
    quadrature points: True where the isochoric part of F is stable. Elastic materials: all True."""
    from needletissue.materials import registry

    mat = registry.get(material)
    F = np.asarray(F, dtype=float)
    if mat.model not in cf.PARAMETERS:
        return np.ones(F.shape[2:], dtype=bool)
    Fm = np.moveaxis(F.reshape(3, 3, -1), -1, 0)
    C = np.einsum("nki,nkj->nij", Fm, Fm)
    lam = np.sqrt(np.linalg.eigvalsh(C)).T  # (3, n)
    return (drucker_margin(mat.model, mat.parameters, lam) > 0).reshape(F.shape[2:])
