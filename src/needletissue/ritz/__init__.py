"""Rayleigh-Ritz model of a bone needle in layered nonlinear springs (paper Eqs. 8-15), any order.

    from needletissue import ritz
    r = ritz.solve(300.0)                       # default model, paper's cubic trial function
    r = ritz.solve(300.0, order="auto")         # raise the order until v(z) changes < tol_mm
    b = ritz.solve_batch(forces, diameter_mm=d, free_length_mm=l, ...)   # arrays, compiled loop
"""

from needletissue.ritz.model import DEFAULT_LAYERS, NEEDLE_E_MPA, Layer, RitzModel
from needletissue.ritz.solve import (
    DEFAULT_TOL_MM, BatchResult, RitzResult, parse_order, solve, solve_batch, solve_forces,
)

__all__ = [
    "DEFAULT_LAYERS", "DEFAULT_TOL_MM", "NEEDLE_E_MPA", "BatchResult", "Layer", "RitzModel",
    "RitzResult", "parse_order", "solve", "solve_batch", "solve_forces",
]
