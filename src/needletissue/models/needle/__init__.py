"""The needle-tissue-bone FE model (``needletissue fe needle``): ``model`` (config, run, results),
``plot`` (figures), ``convergence`` (mesh-convergence study, Richardson estimate)."""

from needletissue.models.needle.model import (
    MATERIALS,
    DeflectionCurve,
    NeedleLoadResult,
    NeedleModelConfig,
    NeedleModelResult,
    ritz_model,
    run_needle_model,
    with_geometry,
    write_outputs,
)

__all__ = ["MATERIALS", "DeflectionCurve", "NeedleLoadResult", "NeedleModelConfig", "NeedleModelResult",
           "ritz_model", "run_needle_model", "with_geometry", "write_outputs"]
