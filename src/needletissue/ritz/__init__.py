"""Rayleigh-Ritz model of a bone needle in layered nonlinear springs (paper Eqs. 8-15), any order.

    from needletissue import ritz
    r = ritz.solve(300.0)                       # default model, paper's cubic trial function
    r = ritz.solve(300.0, order="auto")         # raise the order until v(z) changes < tol_mm
    b = ritz.solve_batch(forces, diameter_mm=d, free_length_mm=l, ...)   # arrays, compiled loop

The solver (Numba) is imported on first use so that `needletissue --help` stays fast.
"""

from needletissue.ritz.model import DEFAULT_LAYERS, NEEDLE_E_MPA, Layer, RitzModel

_LAZY = {
    "DEFAULT_TOL_MM": "solver", "BatchResult": "solver", "RitzResult": "solver", "parse_order": "solver",
    "solve": "solver", "solve_batch": "solver", "solve_forces": "solver",
    "Calibration": "inverse", "calibrate": "inverse", "force_for_deflection": "inverse",
    "vesic_k": "foundation", "plot_deflection": "plot",
}

__all__ = ["DEFAULT_LAYERS", "NEEDLE_E_MPA", "Layer", "RitzModel", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"needletissue.ritz.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'needletissue.ritz' has no attribute {name!r}")
