"""Mesh convergence of the needle model: one size factor scales all three element sizes; Richardson
extrapolation of the needle deformation from three levels."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from needletissue.errors import InputError


@dataclass
class Richardson:
    """f(h) = f0 + C h^p fitted through three levels with a constant refinement ratio r."""

    values: tuple[float, float, float]   # coarse, medium, fine
    ratio: float                         # h_coarse / h_medium = h_medium / h_fine
    order: float                         # observed p
    extrapolated: float                  # f0
    fine_error_estimate: float           # |f_fine - f0|


def richardson(coarse: float, medium: float, fine: float, ratio: float) -> Richardson:
    """Observed order and extrapolated value from three levels refined by a constant ratio."""
    if not ratio > 1:
        raise InputError("ratio", f"refinement ratio must be > 1, got {ratio}")
    d1, d2 = coarse - medium, medium - fine
    if d1 == 0 or d2 == 0 or d1 / d2 <= 0:
        raise InputError("values", f"levels {coarse}, {medium}, {fine} do not converge monotonically: "
                                   "no Richardson extrapolation")
    if abs(d2) >= abs(d1):  # order <= 0: the change grows with refinement, not in the asymptotic range
        raise InputError("values", f"levels {coarse}, {medium}, {fine} change more from medium to fine than from "
                                   "coarse to medium (observed order <= 0): no Richardson extrapolation")
    p = math.log(d1 / d2) / math.log(ratio)
    f0 = fine - d2 / (ratio**p - 1)
    return Richardson((coarse, medium, fine), ratio, p, f0, abs(fine - f0))


def run_convergence(config, ratio: float = 1.4, levels: tuple[float, ...] = (1.0, 0.0, -1.0), progress=False):
    """Run `config` with all element sizes scaled by ratio**level (level 1 = coarser); returns the
    per-level summaries and the Richardson fit of the max needle deformation at the largest force."""
    from needletissue.models.needle import run_needle_model

    rows = []
    for lev in levels:
        s = ratio**lev
        g = config.geometry
        geo = replace(g, needle_mesh_size=g.needle_mesh_size * s, mesh_size=g.mesh_size * s,
                      far_mesh_size=g.far_mesh_size * s)
        res = run_needle_model(replace(config, geometry=geo, progress=progress))
        r = res.results[-1]
        rows.append({"size_factor": s, "needle_mesh_size_mm": geo.needle_mesh_size, "mesh_size_mm": geo.mesh_size,
                     "tetrahedra": res.mesh["tetrahedra"], "dofs": res.mesh["dofs"], "wall_time_s": res.wall_time_s,
                     "force_N": r.force_N, "max_needle_deformation_mm": r.max_needle_deformation_mm,
                     "clamp_displacement_mm": r.clamp_displacement_mm})
    fit = None
    if len(rows) == 3:
        v = [row["max_needle_deformation_mm"] for row in rows]
        try:
            fit = richardson(*v, ratio=ratio)
        except InputError:
            fit = None
    return rows, fit
