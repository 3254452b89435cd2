"""The stages of `needletissue reproduce`. Each takes the resolved config and a StageContext and returns a
StageResult (its result dataclass, figures, files, and numbers to set beside the paper's).

Stages call the public functions of the engine packages; nothing here computes physics.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from needletissue.report.config import ReproduceConfig
from needletissue.report.pipeline import Comparison, Stage, StageContext, StageResult


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


# --- traction validation: FE tissue block vs closed form (paper Sec. 3.2, Eq. 16) -------------------


@dataclass
class TractionValidation:
    results: list[dict]  # fem.traction.TractionResult.to_dict per tissue


def traction_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.fem import traction

    d = ctx.stage_dir("traction")
    results, figs, comps = [], [], []
    for m in cfg.traction.materials:
        r = traction.run(traction.TractionConfig(material=m))
        fig = d / f"traction_{m}.png"
        traction.plot(r, fig)
        results.append(r.to_dict())
        figs.append(fig)
        comps.append(Comparison(f"Traction validation RMSE, {m} (Eq. 16)", r.rmse_MPa, "MPa",
                                f"traction_rmse_{m}_MPa", "criterion < 0.05 MPa"))
    notes = [f"{r['material']}: RMSE {r['rmse_MPa']:.3g} MPa over {len(r['displacement_mm'])} points, "
             f"max relative error {r['max_relative_error']:.2g}" for r in results]
    return StageResult(TractionValidation(results), figures=figs, comparisons=comps, notes=notes)


# --- Rayleigh-Ritz needle model at 100/200/300 N (paper Fig. 5) ------------------------------------


@dataclass
class RitzCurves:
    model: dict  # every parameter used (RitzModel.to_dict)
    order: int | str
    results: list[dict]  # the `ritz --json` contract per force
    curves: dict  # force -> {"z_mm": [...], "v_mm": [...]}


def ritz_model(cfg: ReproduceConfig):
    from needletissue.ritz import Layer, RitzModel

    r = cfg.ritz
    return RitzModel(diameter_mm=r.diameter_mm, free_length_mm=r.free_length_mm,
                     youngs_modulus_MPa=r.youngs_modulus_MPa, cos_term=r.use_cos,
                     layers=tuple(Layer(la.name, la.thickness_mm, la.k_N_per_mm2) for la in r.layers))


def ritz_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.ritz import plot_deflection, solve_forces

    model = ritz_model(cfg)
    res = solve_forces(cfg.ritz.forces_N, model, order=cfg.ritz.order)
    d = ctx.stage_dir("ritz")
    fig = plot_deflection(res, d / "ritz_deflection_fig5.png", model=model)
    import matplotlib.pyplot as plt

    plt.close(fig)
    curves = {}
    for r in res:
        z, v = r.curve(101)
        curves[f"{r.force_N:g}"] = {"z_mm": z, "v_mm": v}
    data = RitzCurves(model.to_dict(), cfg.ritz.order, [r.to_json() for r in res], curves)
    by_force = {r.force_N: r for r in res}
    comps = [Comparison(f"Ritz tip deflection at {r.force_N:g} N", r.tip_deflection_mm, "mm",
                        "ritz_tip_deflection_300N_mm" if r.force_N == 300.0 else None) for r in res]
    if 100.0 in by_force and 300.0 in by_force:
        inc = 100.0 * (by_force[300.0].tip_deflection_mm / by_force[100.0].tip_deflection_mm - 1.0)
        comps.append(Comparison("Ritz tip deflection increase, 300 N over 100 N", inc, "%",
                                "ritz_increase_300_vs_100N_percent",
                                "a stiffening model gives at most +200 % (3x the force); see docs/ritz.md"))
    notes = [f"needle d = {model.diameter_mm:g} mm, free length l = {model.free_length_mm:g} mm, "
             f"E = {model.youngs_modulus_MPa:g} MPa, order {cfg.ritz.order}, "
             f"v/cos(theta) {'on' if model.cos_term else 'off'}"]
    return StageResult(data, figures=[d / "ritz_deflection_fig5.png"],
                       comparisons=comps, notes=notes)


def stage_list() -> list[Stage]:
    """The stages `reproduce` runs, in order. A stage joins this list when its engine is merged."""
    return [
        Stage("materials", "Material curves (Fig. 3)", materials_stage, _on("materials")),
        Stage("traction", "Traction validation (Sec. 3.2)", traction_stage,
              _on("traction")),
        Stage("ritz", "Ritz model, 100-300 N (Fig. 5)", ritz_stage, _on("ritz")),
    ]
