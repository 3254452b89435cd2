"""Study cases on the 3D needle-tissue-bone FE model (needletissue.models.needle): one case = one mesh and
one solve, one Dask task (chunk size 1 by default).

Parameters (units in the names): force_N (> 0), diameter_mm, free_length_mm, spacing_mm, depth_mm,
cortical_thickness_mm, muscle_thickness_mm, adipose_thickness_mm, direction_angle_deg (force direction
in the x-y plane, from +y towards +x: 0 = across the needles' plane, the default; 90 = in it, the
portal frame), load_offset_{x,y,z}_mm (load point - gripper centre: a moment r x F), mesh_size_mm,
needle_mesh_size_mm or needle_mesh_size_per_diameter, far_mesh_size_mm, tissue_bulk_ratio (K/mu0). Settings: needles (1 or 2),
forces_N ("50,100,200": one load path per case instead of force_N; the scalar outputs are those at
the largest force, `per_force_json` holds every force's results). Tissue material parameters are the
registry's (paper values); vary the tissue through the Ritz model's spring stiffnesses instead.
"""

from __future__ import annotations

import json
import math
import tempfile
import time

import numpy as np
import pandas as pd

from needletissue.errors import FORCE_LIMIT_N, InputError
from needletissue.models.needle import NeedleModelConfig, run_needle_model
from needletissue.geometry.needle import NeedleGeometry
from needletissue.studies.models import CaseModel, ParamInfo, register

# study parameter -> NeedleGeometry field
GEOMETRY = {
    "diameter_mm": "diameter", "free_length_mm": "free_length", "muscle_thickness_mm": "muscle_thickness",
    "adipose_thickness_mm": "adipose_thickness", "mesh_size_mm": "mesh_size",
    "needle_mesh_size_mm": "needle_mesh_size", "far_mesh_size_mm": "far_mesh_size",
    "spacing_mm": "spacing", "depth_mm": "depth", "cortical_thickness_mm": "cortical_thickness",
}
PARAMETERS = {
    "force_N": ParamInfo("Reduction force on the gripper, N (> 0, default lateral direction; the shared "
                         "force range).", gt=0, le=FORCE_LIMIT_N),
    "diameter_mm": ParamInfo("Needle diameter, mm.", gt=0),
    "free_length_mm": ParamInfo("Needle length from the bone surface to its end, mm.", gt=0),
    "spacing_mm": ParamInfo("Needle axis spacing (two needles), mm.", gt=0),
    "depth_mm": ParamInfo("Insertion depth of the needles in bone, mm.", gt=0),
    "cortical_thickness_mm": ParamInfo("Cortical shell thickness, mm.", gt=0),
    "muscle_thickness_mm": ParamInfo("Muscle layer thickness, mm.", gt=0),
    "adipose_thickness_mm": ParamInfo("Adipose layer thickness, mm.", gt=0),
    "direction_angle_deg": ParamInfo("Force direction in the x-y plane, degrees from +y towards +x "
                                     "(0: across the needles' plane; 90: in it).", ge=-360, le=360),
    "load_offset_x_mm": ParamInfo("Load point minus gripper centre, x, mm (moment r x F).", ge=-1000, le=1000),
    "load_offset_y_mm": ParamInfo("Load point minus gripper centre, y, mm.", ge=-1000, le=1000),
    "load_offset_z_mm": ParamInfo("Load point minus gripper centre, z (along the needles), mm.", ge=-1000, le=1000),
    "mesh_size_mm": ParamInfo("Element size in tissue, bone and clamp near the needles, mm.", gt=0),
    "needle_mesh_size_mm": ParamInfo("Element size on the needles, mm.", gt=0),
    "needle_mesh_size_per_diameter": ParamInfo("Element size on the needles / needle diameter (dimensionless; "
                                               "instead of needle_mesh_size_mm).", gt=0, le=1),
    "far_mesh_size_mm": ParamInfo("Element size at the far boundary, mm.", gt=0),
    "tissue_bulk_ratio": ParamInfo("Tissue bulk modulus / initial shear modulus K/mu0 (dimensionless; default: "
                                   "the materials' K, 10 MPa; 100 = the K before issue 16).", ge=1, le=1e6),
}
SETTINGS = {"needles": "1 (like-for-like with Ritz) or 2 needles joined by the clamp.",
            "forces_N": "Forces of one load path per case, N, comma-separated (e.g. \"50,100,200,300\"); "
                        "instead of force_N."}
OUTPUTS = ("max_needle_deformation_mm", "clamp_displacement_mm", "ritz_tip_deflection_mm",
           "theory_fe_difference_mm", "max_deformation_muscle_mm", "max_deformation_adipose_mm",
           "tetrahedra", "case_wall_time_s", "clamp_rotation_rad", "needle_yield_utilisation",
           "bone_strength_utilisation", "newton_iterations")


def parse_forces(text) -> tuple[float, ...]:
    try:
        f = tuple(float(x) for x in str(text).split(",") if x.strip())
    except ValueError:
        raise InputError("fixed.forces_N", f"expected comma-separated forces in N, got {text!r}") from None
    if not f or any(not (math.isfinite(x) and x > 0) for x in f):
        raise InputError("fixed.forces_N", f"every force must be a finite number > 0 N, got {text!r}")
    return f


def case_config(values: dict) -> NeedleModelConfig:
    """The needle-model config of one case (fixed values and the case's parameters merged)."""
    geom = {GEOMETRY[k]: float(v) for k, v in values.items() if k in GEOMETRY}
    geom["needles"] = int(values.get("needles", 1))
    if "needle_mesh_size_per_diameter" in values:
        d = geom.get("diameter", NeedleGeometry.diameter)
        geom["needle_mesh_size"] = float(values["needle_mesh_size_per_diameter"]) * d
    forces = parse_forces(values["forces_N"]) if "forces_N" in values else (float(values["force_N"]),)
    a = math.radians(float(values.get("direction_angle_deg", 0.0)))
    offset = tuple(float(values.get(f"load_offset_{c}_mm", 0.0)) for c in "xyz")
    ratio = float(values["tissue_bulk_ratio"]) if "tissue_bulk_ratio" in values else None
    return NeedleModelConfig(geometry=NeedleGeometry(**geom), forces=forces,
                             direction=(math.sin(a), math.cos(a), 0.0), load_offset=offset, tissue_bulk_ratio=ratio)


def _per_force(r, res) -> dict:
    """Everything a reduced-order model compares with, for one force (JSON-ready)."""
    d = r.to_dict()
    keep = ("force_N", "force_vector_N", "moment_Nmm", "load_point_mm", "max_needle_deformation_mm",
            "clamp_displacement_mm", "clamp_displacement_vector_mm", "clamp_rotation_rad", "clamp_fit",
            "root_slope", "root_displacement_mm", "max_deformation_mm", "needle_end_deflection_mm",
            "ritz_tip_deflection_mm", "ritz_force_per_needle_tip_deflection_mm", "newton_iterations", "steps",
            "max_von_mises_MPa", "strength_utilisation", "needle_yield_utilisation",
            "bone_strength_utilisation", "validity_warnings")
    out = {k: d[k] for k in keep if k in d}
    out["solve_wall_time_s"] = float(r.fe.wall_time_s)   # since the start of the load path
    out["curves"] = {k: {"z_mm": np.round(c.z_mm, 6).tolist(),
                         "displacement_mm": np.round(c.displacement_mm, 6).tolist()} for k, c in r.curves.items()}
    return out


def run_fe_needle_chunk(cases: pd.DataFrame, fixed: dict) -> pd.DataFrame:
    rows = []
    for _, case in cases.iterrows():
        t0 = time.perf_counter()
        values = {**fixed, **{k: case[k] for k in case.index if k != "case_id"}}
        cfg = case_config(values)
        with tempfile.TemporaryDirectory() as tmp:  # the mesh file only; results come back in memory
            res = run_needle_model(cfg, mesh_path=f"{tmp}/needle_model.msh")
        r = res.results[-1]
        g = cfg.geometry
        case_info = {"geometry": g.to_dict(), "direction": list(cfg.direction), "load_offset_mm": list(cfg.load_offset),
                     "mesh": {k: res.mesh[k] for k in ("tetrahedra", "quadratic_nodes", "dofs", "min_quality_sicn")},
                     "wall_time_s": res.wall_time_s, "timing_s": res.timing_s,
                     "per_force": [_per_force(x, res) for x in res.results]}
        rows.append({
            "case_id": int(case["case_id"]),
            "max_needle_deformation_mm": r.max_needle_deformation_mm,
            "clamp_displacement_mm": r.clamp_displacement_mm,
            "ritz_tip_deflection_mm": np.nan if r.ritz_tip_deflection_mm is None else r.ritz_tip_deflection_mm,
            "theory_fe_difference_mm": np.nan if r.theory_fe_difference_mm is None else r.theory_fe_difference_mm,
            "max_deformation_muscle_mm": r.max_deformation_mm.get("muscle", np.nan),
            "max_deformation_adipose_mm": r.max_deformation_mm.get("adipose", np.nan),
            "tetrahedra": float(res.mesh["tetrahedra"]),
            "case_wall_time_s": time.perf_counter() - t0,
            "clamp_rotation_rad": float(np.linalg.norm(r.clamp_rotation_rad)),
            "needle_yield_utilisation": r.strength.get("needle_yield_utilisation", np.nan),
            "bone_strength_utilisation": r.strength.get("bone_strength_utilisation", np.nan),
            "newton_iterations": float(r.newton_iterations),
            "per_force_json": json.dumps(case_info),
            "status": "ok", "error": "",
        })
    return pd.DataFrame(rows)


class _FECaseModel(CaseModel):
    def check_config(self, cfg) -> None:
        super().check_config(cfg)
        if cfg.fixed.get("needles", 1) not in (1, 2) or isinstance(cfg.fixed.get("needles", 1), bool):
            raise InputError("fixed.needles", f"must be 1 or 2, got {cfg.fixed['needles']!r}")
        given = set(cfg.parameters) | set(cfg.fixed)
        if "forces_N" in cfg.fixed:
            parse_forces(cfg.fixed["forces_N"])
            if "force_N" in given:
                raise InputError("fixed.forces_N", "give force_N or forces_N, not both")
        elif "force_N" not in given:
            raise InputError("parameters.force_N", "the force must be varied or fixed (fixed.force_N = 300.0 "
                                                   "or fixed.forces_N = \"100,200,300\")")
        if {"needle_mesh_size_mm", "needle_mesh_size_per_diameter"} <= given:
            raise InputError("fixed.needle_mesh_size_per_diameter", "give needle_mesh_size_mm or "
                                                                     "needle_mesh_size_per_diameter, not both")


register(_FECaseModel("fe_needle", PARAMETERS, OUTPUTS, 1, run_fe_needle_chunk, SETTINGS,
                      primary_outputs=("max_needle_deformation_mm", "theory_fe_difference_mm")))
