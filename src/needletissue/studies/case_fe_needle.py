"""Study cases on the 3D needle-tissue-bone FE model (needletissue.models.needle): one case = one mesh and
one solve, one Dask task (chunk size 1 by default).

Parameters (units in the names): force_N (> 0; the direction is the model's default, lateral),
diameter_mm, free_length_mm, muscle_thickness_mm, adipose_thickness_mm, mesh_size_mm,
needle_mesh_size_mm, far_mesh_size_mm. Settings: needles (1 or 2). Tissue material parameters are the
registry's (paper values); vary the tissue through the Ritz model's spring stiffnesses instead.
"""

from __future__ import annotations

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
}
PARAMETERS = {
    "force_N": ParamInfo("Reduction force on the gripper, N (> 0, default lateral direction; the shared "
                         "force range).", gt=0, le=FORCE_LIMIT_N),
    "diameter_mm": ParamInfo("Needle diameter, mm.", gt=0),
    "free_length_mm": ParamInfo("Needle length from the bone surface to its end, mm.", gt=0),
    "muscle_thickness_mm": ParamInfo("Muscle layer thickness, mm.", gt=0),
    "adipose_thickness_mm": ParamInfo("Adipose layer thickness, mm.", gt=0),
    "mesh_size_mm": ParamInfo("Element size in tissue, bone and clamp near the needles, mm.", gt=0),
    "needle_mesh_size_mm": ParamInfo("Element size on the needles, mm.", gt=0),
    "far_mesh_size_mm": ParamInfo("Element size at the far boundary, mm.", gt=0),
}
SETTINGS = {"needles": "1 (like-for-like with Ritz) or 2 needles joined by the clamp."}
OUTPUTS = ("max_needle_deformation_mm", "clamp_displacement_mm", "ritz_tip_deflection_mm",
           "theory_fe_difference_mm", "max_deformation_muscle_mm", "max_deformation_adipose_mm",
           "tetrahedra", "case_wall_time_s")


def run_fe_needle_chunk(cases: pd.DataFrame, fixed: dict) -> pd.DataFrame:
    rows = []
    for _, case in cases.iterrows():
        t0 = time.perf_counter()
        values = {**fixed, **{k: case[k] for k in case.index if k != "case_id"}}
        geom = {GEOMETRY[k]: float(v) for k, v in values.items() if k in GEOMETRY}
        geom["needles"] = int(values.get("needles", 1))
        cfg = NeedleModelConfig(geometry=NeedleGeometry(**geom), forces=(float(values["force_N"]),))
        with tempfile.TemporaryDirectory() as tmp:  # the mesh file only; results come back in memory
            res = run_needle_model(cfg, mesh_path=f"{tmp}/needle_model.msh")
        r = res.results[0]
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
            "status": "ok", "error": "",
        })
    return pd.DataFrame(rows)


class _FECaseModel(CaseModel):
    def check_config(self, cfg) -> None:
        super().check_config(cfg)
        if cfg.fixed.get("needles", 1) not in (1, 2) or isinstance(cfg.fixed.get("needles", 1), bool):
            raise InputError("fixed.needles", f"must be 1 or 2, got {cfg.fixed['needles']!r}")
        if "force_N" not in set(cfg.parameters) | set(cfg.fixed):
            raise InputError("parameters.force_N", "the force must be varied or fixed (fixed.force_N = 300.0)")


register(_FECaseModel("fe_needle", PARAMETERS, OUTPUTS, 1, run_fe_needle_chunk, SETTINGS,
                      primary_outputs=("max_needle_deformation_mm", "theory_fe_difference_mm")))
