"""Study cases on the Rayleigh-Ritz model: one Dask task solves a whole chunk through
needletissue.ritz.solve_batch (vectorised, compiled).

Parameters (units in the names): force_N, diameter_mm, free_length_mm, youngs_modulus_MPa,
load_point_mm, per layer ``<layer>_thickness_mm`` and ``k_<layer>_N_per_mm2`` (layers of the Ritz
default model, paper Table 1: muscle next to bone, then adipose), or ``tissue_thickness_mm``: the total
soft-tissue thickness, split between the layers in their default proportion (22 : 10), which is how the
paper's 31.82 +- 5.43 mm (all soft tissue, 10 patients) maps onto the two-layer model.
Fixed settings: ``order`` (3, N or 'auto') and ``cos_term`` (true/false).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from needletissue.errors import FORCE_LIMIT_N, InputError
from needletissue.ritz import RitzModel, solve_batch
from needletissue.studies.models import CaseModel, ParamInfo, register

_DEFAULT = RitzModel()
LAYERS = tuple(la.name for la in _DEFAULT.layers)

PARAMETERS = {
    "force_N": ParamInfo("Reduction force at the load point, N (sign = direction; the shared force range).",
                         ge=-FORCE_LIMIT_N, le=FORCE_LIMIT_N),
    "diameter_mm": ParamInfo("Needle diameter, mm.", gt=0),
    "free_length_mm": ParamInfo("Needle length from bone to the load point region, mm.", gt=0),
    "youngs_modulus_MPa": ParamInfo("Needle Young's modulus, MPa.", gt=0),
    "load_point_mm": ParamInfo("Distance of the load point from the bone, mm (default: free end).", gt=0),
    "tissue_thickness_mm": ParamInfo("Total soft-tissue thickness, mm, split in the default layer proportion.", gt=0),
    **{f"{n}_thickness_mm": ParamInfo(f"Thickness of the {n} layer, mm.", gt=0) for n in LAYERS},
    **{f"k_{n}_N_per_mm2": ParamInfo(f"Spring stiffness of the {n} layer, N/mm per mm of needle (MPa).", gt=0)
       for n in LAYERS},
}
SETTINGS = {"order": "Trial polynomial order: 3 (paper), N >= 3 or 'auto'.",
            "cos_term": "v / cos(theta) in the spring energy (paper Eq. 11): true or false."}
OUTPUTS = ("tip_deflection_mm", "load_point_deflection_mm", "max_deflection_mm", "tip_slope_rad",
           "error_estimate_mm", *(f"spring_reaction_{n}_N" for n in LAYERS))


def _column(cases: pd.DataFrame, fixed: dict, name: str):
    # A fresh writable array: columns unpickled on a Dask worker are read-only, and Numba compiles a
    # separate (slow, ~10 s) specialisation of the Ritz kernel for read-only arrays.
    if name in cases:
        return np.array(cases[name].to_numpy(dtype=float), copy=True)
    return fixed.get(name)


def run_ritz_chunk(cases: pd.DataFrame, fixed: dict) -> pd.DataFrame:
    n = len(cases)
    model = RitzModel(cos_term=bool(fixed.get("cos_term", True)))
    defaults = np.array([la.thickness_mm for la in _DEFAULT.layers])
    total = _column(cases, fixed, "tissue_thickness_mm")
    if total is not None:
        thickness = np.outer(np.broadcast_to(total, (n,)), defaults / defaults.sum())
    else:
        thickness = np.column_stack([np.broadcast_to(
            v if (v := _column(cases, fixed, f"{la}_thickness_mm")) is not None else d, (n,))
            for la, d in zip(LAYERS, defaults)])
    k = np.column_stack([np.broadcast_to(
        v if (v := _column(cases, fixed, f"k_{la.name}_N_per_mm2")) is not None else la.k_N_per_mm2, (n,))
        for la in _DEFAULT.layers])
    force = _column(cases, fixed, "force_N")
    if force is None:
        raise InputError("force_N", "give force_N as a varied or fixed parameter")
    b = solve_batch(
        np.array(np.broadcast_to(force, (n,)), dtype=float), diameter_mm=_column(cases, fixed, "diameter_mm"),
        free_length_mm=_column(cases, fixed, "free_length_mm"),
        youngs_modulus_MPa=_column(cases, fixed, "youngs_modulus_MPa"),
        load_point_mm=_column(cases, fixed, "load_point_mm"), thickness_mm=thickness, k_N_per_mm2=k,
        model=model, order=fixed.get("order", 3), parallel=False,  # Dask gives the parallelism
    )
    out = pd.DataFrame({"case_id": cases["case_id"].to_numpy()})
    for o in OUTPUTS[:5]:
        out[o] = getattr(b, o)
    for j, name in enumerate(LAYERS):
        out[f"spring_reaction_{name}_N"] = b.spring_reaction_N[:, j]
    out["status"] = "ok"
    out["error"] = ""
    return out


class _RitzCaseModel(CaseModel):
    def check_config(self, cfg) -> None:
        super().check_config(cfg)
        given = set(cfg.parameters) | set(cfg.fixed)
        per_layer = sorted(given & {f"{n}_thickness_mm" for n in LAYERS})
        if "tissue_thickness_mm" in given and per_layer:
            raise InputError("parameters.tissue_thickness_mm",
                             f"give either the total thickness or per-layer thicknesses ({', '.join(per_layer)})")
        from needletissue.ritz import parse_order

        if "order" in cfg.fixed:
            parse_order(cfg.fixed["order"])
        if "cos_term" in cfg.fixed and not isinstance(cfg.fixed["cos_term"], bool):
            raise InputError("fixed.cos_term", f"must be true or false, got {cfg.fixed['cos_term']!r}")
        if "force_N" not in given:
            raise InputError("parameters.force_N", "the force must be varied or fixed (fixed.force_N = 300.0)")


register(_RitzCaseModel("ritz", PARAMETERS, OUTPUTS, 20_000, run_ritz_chunk, SETTINGS,
                        primary_outputs=("tip_deflection_mm", "max_deflection_mm")))
