"""The stages of `needletissue reproduce`. Each takes the resolved config and a StageContext and returns a
StageResult (its result dataclass, figures, files, and numbers to set beside the paper's).

Stages call the public functions of the engine packages; nothing here computes physics.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from needletissue.report.config import ReproduceConfig
from needletissue.report.pipeline import Stage, StageContext, StageResult


def _on(section):
    def enabled(cfg: ReproduceConfig, ctx: StageContext):
        return (True, "") if getattr(cfg, section).enabled else (False, f"disabled in config ([{section}] enabled = false)")
    return enabled


# --- materials: closed-form stress-stretch curves (paper Fig. 3 style) -----------------------------


@dataclass
class MaterialCurves:
    curves: list[dict]  # the `materials curve --json` contract, one per material


def materials_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.materials import curves, plot

    c = cfg.materials
    d = ctx.stage_dir("materials")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        data = MaterialCurves([curves.curve(n, "uniaxial", c.stretch_max, c.points).to_json() for n in c.names])
    fig = d / "stress_stretch_uniaxial.png"
    plot.plot_curves(tuple(c.names), "uniaxial", stretch_max=c.stretch_max, out=fig)
    import matplotlib.pyplot as plt

    plt.close("all")
    notes = [f"{x['material']}: {x['model']}, Drucker-stable in uniaxial stretch "
             f"[{x['stable_range'][0]:.3g}, {x['stable_range'][1]:.3g}]" for x in data.curves]
    notes += [f"warning: {w.message}" for w in caught]
    return StageResult(data, figures=[fig], notes=notes)


def stage_list() -> list[Stage]:
    """The stages `reproduce` runs, in order. A stage joins this list when its engine is merged."""
    return [
        Stage("materials", "Material curves (paper Fig. 3 style)", materials_stage, _on("materials")),
    ]
