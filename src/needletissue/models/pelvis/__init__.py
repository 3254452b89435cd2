"""The paper's anatomical model (``needletissue fe pelvis``): ``model`` (config, boundary conditions,
solve, results) and ``report`` (figures, comparison table)."""

from needletissue.models.pelvis.model import (
    MATERIALS,
    PAPER,
    LoadResult,
    PelvisConfig,
    PelvisResult,
    build,
    comparison_table,
    force_unit,
    ritz_prediction,
    run_pelvis_model,
    thickness_crosscheck,
)

__all__ = ["MATERIALS", "PAPER", "LoadResult", "PelvisConfig", "PelvisResult", "build", "comparison_table",
           "force_unit", "ritz_prediction", "run_pelvis_model", "thickness_crosscheck"]
