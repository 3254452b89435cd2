"""The stages of `needletissue reproduce`. Each takes the resolved config and a StageContext and returns a
StageResult (its result dataclass, figures, files, and numbers to set beside the paper's).

Stages call the public functions of the engine packages; nothing here computes physics.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from needletissue.report.config import ReproduceConfig
from needletissue.report.paper import PAPER, PAPER_RANKING, fe_key
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
    from needletissue.report.render import describe

    describe(fig, f"Nominal stress (MPa) against stretch in uniaxial tension and compression of "
                  f"{', '.join(c.names)} (closed form); shaded: the Drucker-stable range (paper Fig. 3).")
    import matplotlib.pyplot as plt

    plt.close("all")
    notes = [f"{x['material']}: {x['model']}, Drucker-stable in uniaxial stretch "
             f"[{x['stable_range'][0]:.3g}, {x['stable_range'][1]:.3g}]" for x in data.curves]
    notes += [f"warning: {w.message}" for w in caught]
    return StageResult(data, figures=[fig], notes=notes)


# --- traction validation: FE tissue block vs closed form (paper Sec. 3.2, Eq. 16) -------------------


@dataclass
class TractionValidation:
    results: list[dict]  # models.traction.TractionResult.to_dict per tissue


def traction_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.models import traction

    d = ctx.stage_dir("traction")
    results, figs, comps = [], [], []
    for m in cfg.traction.materials:
        r = traction.run(traction.TractionConfig(material=m))
        fig = d / f"traction_{m}.png"
        traction.plot(r, fig)
        from needletissue.report.render import describe

        describe(fig, f"Traction validation, {m}: nominal stress against the pulled displacement, FE block "
                      "(points) and closed form (line) (paper Sec. 3.2).")
        results.append(r.to_dict())
        figs.append(fig)
        comps.append(Comparison(f"Traction validation RMSE, {m} (Eq. 16)", r.rmse_MPa, "MPa",
                                f"traction_rmse_{m}_MPa", "criterion < 0.05 MPa", limit=r.criterion_MPa))
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
    from needletissue.report.render import describe

    describe(d / "ritz_deflection_fig5.png", f"Rayleigh-Ritz needle deflection v(z) along the needle at "
             f"{', '.join(f'{r.force_N:g}' for r in res)} N (1 needle, free length {model.free_length_mm:g} mm; "
             "paper Fig. 5).")
    curves = {}
    for r in res:
        z, v = r.curve(101)
        curves[f"{r.force_N:g}"] = {"z_mm": z, "v_mm": v}
    data = RitzCurves(model.to_dict(), cfg.ritz.order, [r.to_json() for r in res], curves)
    by_force = {r.force_N: r for r in res}
    z3 = model.load_point_mm if model.load_point_mm is not None else model.free_length_mm
    setup = f"1 needle carrying the force, free length {model.free_length_mm:g} mm, load at {z3:g} mm"
    comps = [Comparison(f"Ritz tip deflection at {r.force_N:g} N ({setup})", r.tip_deflection_mm, "mm",
                        "ritz_tip_deflection_300N_mm" if r.force_N == 300.0 else None) for r in res]
    if 100.0 in by_force and 300.0 in by_force:
        inc = 100.0 * (by_force[300.0].tip_deflection_mm / by_force[100.0].tip_deflection_mm - 1.0)
        comps.append(Comparison("Ritz tip deflection increase, 300 N over 100 N", inc, "%",
                                "ritz_increase_300_vs_100N_percent",
                                "+200 % is the most any positive parameters give (w is sub-linear in F; docs/ritz.md)"))
    notes = [f"needle d = {model.diameter_mm:g} mm, free length l = {model.free_length_mm:g} mm, "
             f"E = {model.youngs_modulus_MPa:g} MPa, order {cfg.ritz.order}, "
             f"v/cos(theta) {'on' if model.cos_term else 'off'}"]
    return StageResult(data, figures=[d / "ritz_deflection_fig5.png"],
                       comparisons=comps, notes=notes)


# --- per-tissue deformation bar chart (results of an FE stage; plotting only) ----------------------


def drucker_notes(results: list[dict]) -> list[str]:
    """A warning note per force and region with tissue beyond its Drucker-stable range."""
    return [f"warning: {r['force_N']:g} N: {100 * f:.3g} % of {region} is beyond its Drucker-stable stretch range"
            for r in results for region, f in (r.get("drucker_unstable_volume_fraction") or {}).items() if f > 0]


def plot_region_deformation(results: list[dict], path, title: str, dpi: int = 110):
    """Grouped bars: maximum displacement (mm) of every region at every force."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from needletissue.runinfo import write_atomic

    regions = sorted({k for r in results for k in r["max_deformation_mm"]},
                     key=lambda k: -results[-1]["max_deformation_mm"].get(k, 0.0))
    x = np.arange(len(regions))
    w = 0.8 / max(1, len(results))
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(regions) + 2), 4))
    for i, r in enumerate(results):
        ax.bar(x + (i - (len(results) - 1) / 2) * w, [r["max_deformation_mm"].get(k, np.nan) for k in regions],
               w, label=f"{r['force_N']:g} N")
    ax.set_xticks(x, regions, rotation=30, ha="right")
    ax.set_ylabel("maximum deformation |u| (mm)")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    buf = io.BytesIO()
    forces = ", ".join(f"{r['force_N']:g}" for r in results)
    text = f"{title}, at {forces} N: maximum displacement |u| (mm) of each region."
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Description": text})
    plt.close(fig)
    return write_atomic(path, buf.getvalue())


# --- parametric needle-tissue-bone FE model (theory vs FE) ----------------------------------------


@dataclass
class NeedleFE:
    result: dict  # models.needle.NeedleModelResult.to_dict (the `fe needle --json` contract)


def needle_fe_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.models.needle import NeedleModelConfig, run_needle_model
    from needletissue.models.needle.plot import plot_deflection_curves
    from needletissue.geometry.needle import NeedleGeometry
    from needletissue.report.render import plot_theory_vs_fe, try_render

    c = cfg.needle_fe
    d = ctx.stage_dir("needle_fe")
    geom = NeedleGeometry(needles=c.needles, diameter=c.diameter_mm, free_length=c.free_length_mm,
                          mesh_size=c.mesh_size_mm, needle_mesh_size=c.needle_mesh_size_mm,
                          far_mesh_size=c.far_mesh_size_mm)
    # No out_dir: the model's own writer renders with VTK in this process; we write VTU and figures
    # here and render in a child process (a VTK crash then costs a picture, not the results).
    res = run_needle_model(NeedleModelConfig(geometry=geom, forces=tuple(c.forces_N)))
    data = res.to_dict()
    from needletissue.fem.result import write_series
    from needletissue.models.needle.model import FRAME

    files = []
    for r in res.results:
        files.append(d / f"needle_{r.force_N:g}N.vtu")
        r.fe.write_vtu(files[-1], frame=FRAME, force_N=r.force_N)
    files += [f.with_suffix(".vtm") for f in files]  # beside each VTU: its regions as named blocks
    files.append(write_series(d / "needle.pvd", [(r.force_N, f"needle_{r.force_N:g}N.vtm") for r in res.results]))
    notes = [f"mesh: {res.mesh['tetrahedra']:,} tetrahedra (order {res.mesh['order']}, {res.mesh['dofs']:,} dofs), "
             f"wall time {res.wall_time_s:.1f} s"]
    notes += drucker_notes(data["results"])
    figs = [plot_deflection_curves(res, d / "needle_deflection_theory_vs_fe.png"),
            plot_theory_vs_fe(data["results"], d / "needle_max_deformation_vs_force.png",
                              f"Needle FE model ({c.needles} needle(s)) vs Ritz and the paper", cfg.report.dpi),
            plot_region_deformation(data["results"], d / "needle_fe_region_deformation.png",
                                    "Needle FE model: maximum deformation per region", cfg.report.dpi)]
    from needletissue.models.render import RenderScene

    top = res.results[-1].force_N
    try_render(d / f"needle_{top:g}N.vtu", d / "needle_deformed.png",
               RenderScene(f"Needle FE model, {c.needles} needle{'s' if c.needles > 1 else ''}, {top:g} N",
                           res.config.direction,
                           load_point_mm=tuple(res.config.load_point)), notes, figs)
    # Not like for like with any FE number of the paper (its FE model is the anatomical one, two needles):
    # no paper column here, the paper's value in the note; the anatomical rows carry the comparison.
    comps = []
    n = c.needles
    for r in res.results:
        setup = (f"parametric model: {n} needle{'s' if n > 1 else ''}, {r.force_N / n:g} N per needle, free "
                 f"length {c.free_length_mm:g} mm")
        key = fe_key(r.force_N)
        comps.append(Comparison(f"FE max needle deformation at {r.force_N:g} N ({setup})",
                                r.max_needle_deformation_mm, "mm", None,
                                "not like for like" + (f": the paper's {PAPER[key].value:g} mm is its anatomical "
                                                       "two-needle model" if key else "")))
        if r.theory_fe_difference_mm is not None:
            comps.append(Comparison(f"FE - Ritz at {r.force_N:g} N ({setup}; Ritz with the same needle, layers "
                                    "and free length)", r.theory_fe_difference_mm, "mm", None,
                                    "FE maximum needle deformation minus Ritz tip deflection at the full force; "
                                    "the paper's 0.432 mm (18.062 - 17.63) sets its anatomical FE beside a Ritz "
                                    "model of another free length"))
    data["frame"] = _frame_beside_fe(c, res, comps)
    notes += [f"validity at {f['force_N']:g} N (frame model): " + "; ".join(f["frame_warnings"])
              for f in data["frame"] if f["frame_warnings"]]
    forces = [r.force_N for r in res.results]
    views = _view(d / "needle_3d.html", f"Needle FE model ({c.needles} needle(s)), deformed at each force",
                  notes, files, vtus=[d / f"needle_{f:g}N.vtu" for f in forces], forces=forces,
                  region_tags=res.results[-1].fe.region_tags, force_direction=res.config.direction,
                  needle_axis=(0.0, 0.0, 1.0), frame_of_reference="model (z along the needles)")
    return StageResult(NeedleFE(data), figures=figs, files=files, comparisons=comps, notes=notes, views=views)


def _view(path, title: str, notes: list, files: list, **scene) -> list:
    """The interactive 3D view of a model run (report.viewer), embedded in report.html and written
    standalone to path; if it cannot be built, a note instead: the numbers stand without it."""
    from needletissue.report.viewer import model_scene, write_viewer

    try:
        s = model_scene(scene.pop("vtus"), scene.pop("forces"), scene.pop("region_tags"),
                        scene.pop("force_direction"), scene.pop("needle_axis"), **scene)
        files.append(write_viewer(path, s, title))
    except Exception as exc:
        notes.append(f"3D view {Path(path).name} not written: {type(exc).__name__}: {exc}")
        return []
    return [(title, s)]


def frame_goal_mm(fe_mm: float) -> float:
    """The frame model's goal against an FE value: the paper's own theory-FE accuracy, max(0.432 mm, 2.4 %)."""
    return max(0.432, 0.024 * fe_mm)


def _frame_beside_fe(c, res, comps) -> list[dict]:
    """The needle-frame model (the robot's fast model) on the FE run's setup: same pins, free length,
    force and direction, with the factors calibrated on the FE sweep (frame.model.FE_CALIBRATION). The
    goal is the paper's own accuracy, max(0.432 mm, 2.4 %) of the FE value (docs/frame.md)."""
    import numpy as np

    from needletissue import frame
    from needletissue.frame.model import FE_CALIBRATION, FrameModel

    model = FrameModel(needles=c.needles, diameter_mm=c.diameter_mm, free_length_mm=c.free_length_mm,
                       **FE_CALIBRATION)
    out = []
    for r in res.results:
        fr = frame.solve(force=tuple(r.force_N * np.asarray(res.config.direction)), model=model)
        fe = r.max_needle_deformation_mm
        goal = frame_goal_mm(fe)
        setup = (f"{c.needles} needle{'s' if c.needles > 1 else ''}, {r.force_N / c.needles:g} N per needle, "
                 f"free length {c.free_length_mm:g} mm")
        comps.append(Comparison(
            f"|frame model - FE|, max needle deflection at {r.force_N:g} N ({setup}; frame factors fitted "
            f"to the FE sweep)", abs(fr.max_needle_deflection_mm - fe), "mm", None,
            f"frame {fr.max_needle_deflection_mm:.3f} mm, FE {fe:.3f} mm (demo mesh); the goal is the paper's "
            f"own theory-FE accuracy, max(0.432 mm, 2.4 %)", limit=goal))
        out.append({"force_N": r.force_N, "frame_max_needle_deflection_mm": fr.max_needle_deflection_mm,
                    "fe_max_needle_deformation_mm": fe, "goal_mm": goal,
                    "frame_clamp_displacement_mm": list(fr.clamp_displacement_mm),
                    "frame_error_estimate_mm": fr.error_estimate_mm, "frame_warnings": list(fr.warnings)})
    return out


def mesh_converged_limits(source: str, ct, labels, mesh_size_mm: float, mesher: str = "box") -> dict | None:
    """{force N: Richardson limit of the max needle deformation, mm} from the stored mesh-convergence study of
    the anatomical model (package data pelvis_convergence.json, benchmarks/pelvis_mesh_convergence.py, the box
    mesher), when this run is one of its levels: `fe pelvis --mesher box` on the bundled CT and labels at one
    of its sizes; else None."""
    import json
    from importlib.resources import files

    if source != "ct" or ct or labels or mesher != "box":
        return None
    study = json.loads(files("needletissue").joinpath("data/pelvis_convergence.json").read_text())
    if not any(abs(mesh_size_mm - h) < 1e-9 for h in study["sizes_mm"]):
        return None
    out = {}
    for key, fit in study["richardson"].items():
        name, force = key.split("@")
        if name == "max_needle_deformation_mm" and fit["extrapolated"] is not None:
            out[float(force.rstrip("N"))] = {"limit_mm": fit["extrapolated"], "order": fit["order"],
                                             "sizes_mm": study["sizes_mm"]}
    return out


def _frame_beside_pelvis(data: dict, comps, limits: dict | None = None) -> list[dict]:
    """The frame model fed with what the anatomical run measured along its pins: exposed length (bone
    entry to the needle end), pin spacing across the axis, insertion depth, clamp height, the two
    needles' mean tissue layers, and the force in the pins' frame (z out of the bone along the pins,
    x from pin 1 to pin 2; report.reconcile.anatomical_setup). The FE's needle maximum includes the
    (small) motion of the pelvis itself."""
    import numpy as np

    from needletissue import frame
    from needletissue.report.reconcile import anatomical_frame_model, anatomical_setup

    s = anatomical_setup(data)
    if s is None:
        return []
    model = anatomical_frame_model(s)
    spacing, free, layers = s.spacing_mm, s.free_length_mm, s.layers
    out = []
    for r in data["results"]:
        fr = frame.solve(force=tuple(r["force_N"] * np.asarray(s.force_unit)), model=model)
        fe = r["max_needle_deformation_mm"]
        goal = frame_goal_mm(fe)
        comps.append(Comparison(
            f"|frame model - FE|, max needle deflection at {r['force_N']:g} N (anatomical model: 2 needles, "
            f"{r['force_N'] / 2:g} N per needle, exposed length {free:.0f} mm, measured layers)",
            abs(fr.max_needle_deflection_mm - fe), "mm", None,
            f"frame {fr.max_needle_deflection_mm:.3f} mm, FE {fe:.3f} mm (demo mesh); frame fed with the "
            f"measured lengths and the two needles' mean layers", limit=goal))
        lim = (limits or {}).get(float(r["force_N"]))
        if lim is not None:
            fe0 = lim["limit_mm"]
            comps.append(Comparison(
                f"|frame model - mesh-converged FE|, max needle deflection at {r['force_N']:g} N (anatomical model, "
                f"as above; FE extrapolated to zero element size)", abs(fr.max_needle_deflection_mm - fe0), "mm", None,
                f"frame {fr.max_needle_deflection_mm:.3f} mm, FE limit {fe0:.3f} mm (Richardson from the same model "
                f"at {' / '.join(f'{h:g}' for h in lim['sizes_mm'])} mm, observed order {lim['order']:.2f}; "
                f"pelvis_convergence.json); the demo mesh's FE is {100 * (fe / fe0 - 1):+.1f} % from that limit",
                limit=frame_goal_mm(fe0)))
        out.append({"force_N": r["force_N"], "frame_max_needle_deflection_mm": fr.max_needle_deflection_mm,
                    "fe_max_needle_deformation_mm": fe, "goal_mm": goal, "force_in_pin_frame_N": list(fr.force_N),
                    "fe_mesh_converged_mm": None if lim is None else lim["limit_mm"],
                    "frame_model": {"spacing_mm": spacing, "free_length_mm": free,
                                    "layers_mm": [la.thickness_mm for la in layers]},
                    "frame_warnings": list(fr.warnings)})
    return out


# --- anatomical pelvis model (needs ../shared/data, $NEEDLETISSUE_DATA or --ct) --------------------


def _pelvis_enabled(cfg: ReproduceConfig, ctx: StageContext):
    mode = cfg.pelvis.enabled
    if mode == "off":
        return False, "disabled in config ([pelvis] enabled = \"off\")"
    if mode == "on" or ctx.ct is not None or cfg.pelvis.ct or cfg.pelvis.source == "ssm":
        return True, ""
    from needletissue.imaging.data import shared_data_dir

    shared = shared_data_dir()
    if shared is None or not shared.is_dir():
        return False, "no ../shared/data (or $NEEDLETISSUE_DATA) and no --ct: anatomical model skipped"
    return True, ""


@dataclass
class PelvisFE:
    result: dict  # models.pelvis.PelvisResult.to_dict (the `fe pelvis --json` contract)


def pelvis_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    from needletissue.models.pelvis import PelvisConfig, run_pelvis_model

    c = cfg.pelvis
    d = ctx.stage_dir("pelvis")
    ct = str(ctx.ct) if ctx.ct else (c.ct or None)
    labels = str(ctx.labels) if ctx.labels else (c.labels or None)
    from needletissue.report.render import plot_theory_vs_fe, try_render

    # figures=False: the model's VTK section render runs in this process (it crashed once on a 4 mm
    # mesh); we render the VTU it writes in a child process instead.
    res = run_pelvis_model(PelvisConfig(source=c.source, ct=ct, labels=labels, forces=list(c.forces_N),
                                        mesh_size=c.mesh_size_mm, mesher=c.mesher, out=str(d), figures=False))
    data = res.to_dict()
    files = sorted(d.glob("*.vtu")) + sorted(d.glob("*.vtm")) + sorted(d.glob("*.pvd"))
    notes = [f"mesh: {res.mesh.get('tetrahedra', 0):,} tetrahedra, wall time {res.wall_time_s:.1f} s", *res.notes]
    notes += drucker_notes(data["results"])
    figs = [plot_theory_vs_fe(data["results"], d / "pelvis_max_deformation_vs_force.png",
                              "Anatomical model vs Ritz and the paper", cfg.report.dpi),
            plot_region_deformation(data["results"], d / "pelvis_region_deformation.png",
                                    "Anatomical model: maximum deformation per tissue", cfg.report.dpi)]
    last = d / f"pelvis_{res.results[-1].force_N:g}N.vtu"
    if last.exists():
        from needletissue.models.pelvis.report import render_scene

        try_render(last, d / "pelvis_deformed.png", render_scene(data), notes, figs)
    comps = []
    exposed = [t.get("exposed_length_mm") for t in res.thickness if t.get("exposed_length_mm") is not None]
    length = f", exposed length {min(exposed):.0f}-{max(exposed):.0f} mm" if exposed else ""
    for r in res.results:
        setup = f"anatomical model: 2 needles and a clamp, {r.force_N / 2:g} N per needle{length}"
        comps.append(Comparison(f"FE max needle deformation at {r.force_N:g} N ({setup})",
                                r.max_needle_deformation_mm, "mm", fe_key(r.force_N)))
        if r.force_N == 300.0:
            if r.theory_fe_difference_mm is not None:
                comps.append(Comparison("|FE - theory| difference at 300 N (anatomical model)",
                                        r.theory_fe_difference_mm, "mm", "theory_fe_difference_300N_mm"))
            if "adipose" in r.max_deformation_mm:
                comps.append(Comparison("Adipose max deformation at 300 N (anatomical model)",
                                        r.max_deformation_mm["adipose"], "mm", "adipose_max_deformation_300N_mm"))
    paper_rank = " > ".join(PAPER_RANKING)
    ours = [t for t in res.ranking if t in ("adipose", "iliopsoas", "iliacus", "gluteus_medius", "gluteus_maximus")]
    comps.append(Comparison("Deformation ranking at the largest force", " > ".join(ours), "",
                            note=f"paper (Sec. 3.3): {paper_rank} (iliacus is part of our iliopsoas)"))
    for t in res.thickness:
        sd = PAPER["soft_tissue_thickness_std_mm"].value / PAPER["soft_tissue_thickness_mean_mm"].value
        comps.append(Comparison(f"Soft tissue along {t['needle']}", t["total_mm"], "mm",
                                "soft_tissue_thickness_mean_mm", "paper: mean of 10 patients (+- 5.43 mm); "
                                "agrees = within one patient SD", tolerance_percent=100 * sd))
    data["frame"] = _frame_beside_pelvis(data, comps, mesh_converged_limits(c.source, ct, labels, c.mesh_size_mm, c.mesher))
    base, top = data["site"]["needle_axes_mm"][0]
    forces = [r.force_N for r in res.results]
    views = _view(d / "pelvis_3d.html", "Anatomical model, deformed at each force (adipose and body wall "
                  "hidden at start)", notes, files, vtus=[d / f"pelvis_{f:g}N.vtu" for f in forces],
                  forces=forces, region_tags=data["mesh"]["region_tags"],
                  force_direction=data["force_vector_unit"], needle_axis=[t - b for b, t in zip(base, top)],
                  frame_of_reference="LPS", hidden=("adipose", "body_wall"))
    return StageResult(PelvisFE(data), figures=figs, files=files, comparisons=comps, notes=notes, views=views)


# --- reconciliation: which assumptions reproduce the paper's numbers (fast models only) ---------------


def reconciliation_stage(cfg: ReproduceConfig, ctx: StageContext) -> StageResult:
    """The chain from the anatomical FE to the paper's setup and the 300/100 N ratio cases, run with the
    frame and Ritz models (report.reconcile), and the measured reason of every row that differs."""
    from needletissue.report.reconcile import reconcile, row_reasons

    pelvis = ctx.previous.get("pelvis")
    data = pelvis.data.result if pelvis is not None else None
    rec = reconcile(ritz_model(cfg), data, order=cfg.ritz.order)
    rows = [c for r in ctx.previous.values() for c in r.comparisons]
    reasons = row_reasons(rows, rec, data)
    # the tables and conclusions are the report's "Reconciliation" section; here only what the stage did
    notes = [f"{len(rec.chain) + len(rec.checks)} chain steps and checks, {len(rec.ratio)} ratio cases (frame and "
             f"Ritz solves); a measured reason for {len(reasons)} of the "
             f"{sum(c.verdict.startswith('differs') for c in rows)} rows that differ from the paper. The tables and "
             "conclusions are in the Reconciliation section above."]
    return StageResult(rec, notes=notes, reasons=reasons)


def stage_list() -> list[Stage]:
    """The stages `reproduce` runs, in order. A stage joins this list when its engine is merged."""
    return [
        Stage("materials", "Material curves (Fig. 3)", materials_stage, _on("materials")),
        Stage("traction", "Traction validation (Sec. 3.2)", traction_stage,
              _on("traction")),
        Stage("ritz", "Ritz model, 100-300 N (Fig. 5)", ritz_stage, _on("ritz")),
        Stage("needle_fe", "Needle FE model, theory vs FE", needle_fe_stage, _on("needle_fe"), isolated=True),
        Stage("pelvis", "Anatomical pelvis model", pelvis_stage, _pelvis_enabled, isolated=True),
        # after every stage whose rows it explains; cheap (frame and Ritz solves, no FE)
        Stage("reconciliation", "Reconciliation with the paper", reconciliation_stage,
              lambda cfg, ctx: (True, "") if cfg.ritz.enabled else
              (False, "needs the Ritz model ([ritz] enabled = false)")),
    ]
