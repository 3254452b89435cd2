"""`needletissue frame`: the needle-frame model (solve when no subcommand; `compensate`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from needletissue.commands import numbers


def _triple(field: str, text: str | None):
    return numbers(field, text)


def _opts():
    """Model options shared by the solve and compensate commands (fresh OptionInfo objects each)."""
    from needletissue.frame import model as M

    return dict(
        needles=typer.Option(M.DEFAULT_NEEDLES, "--needles", help="Number of pins, 1-4, on the x axis."),
        spacing=typer.Option(M.DEFAULT_SPACING_MM, "--spacing", help="Pin axis spacing, mm (> diameter)."),
        diameter=typer.Option(M.DEFAULT_DIAMETER_MM, "--diameter", help="Pin diameter, mm (> 0)."),
        free_length=typer.Option(M.DEFAULT_FREE_LENGTH_MM, "--free-length",
                                 help="Pin length from the bone surface to its end, mm (> 0)."),
        depth=typer.Option(M.DEFAULT_DEPTH_MM, "--depth", help="Insertion depth in the bone, mm (> cortex)."),
        cortex=typer.Option(M.DEFAULT_CORTEX_MM, "--cortex", help="Cortical shell thickness, mm (> 0)."),
        clamp_length=typer.Option(M.DEFAULT_CLAMP_LENGTH_MM, "--clamp-length",
                                  help="Pin length held in the clamp below the pin end, mm (>= 0)."),
        layer=typer.Option(None, "--layer", help="Tissue layer NAME:THICKNESS_MM:K (K in N/mm per mm of pin = "
                           "N/mm^2, the paper's F = k (x + x^3)), repeat, stacked from the bone. Default "
                           "muscle:22:0.048 adipose:10:0.023."),
        no_tissue=typer.Option(False, "--no-tissue", help="No tissue springs."),
        root=typer.Option("bone", "--root", help="bone (elastic foundation: cortex + cancellous) or rigid "
                          "(pins built in at the bone surface)."),
        load_point=typer.Option(None, "--load-point", help="Where the wrench acts, X,Y,Z in mm, inside the clamp; "
                                "default the centre of the gripper faces."),
        foundation_factor=typer.Option(1.0, "--foundation-factor", help="Factor on the derived bone foundation "
                                       "(dimensionless, (0, 10])."),
        tissue_factor=typer.Option(1.0, "--tissue-factor", help="Factor on the layers' k (dimensionless, (0, 10])."),
        plastic=typer.Option(False, "--plastic", help="Elastic-plastic pin section (Ti-6Al-4V, yield 880 MPa, "
                             "linear hardening 530 MPa; monotonic loading)."),
        calibrated=typer.Option(False, "--calibrated", help="Use the factors fitted to the FE model "
                                "(frame.model.FE_CALIBRATION) instead of the physical ones (docs/frame.md)."),
        axial_factor=typer.Option(1.0, "--axial-factor", help="Factor on the bone's axial stiffness (shaft and "
                                  "tip; dimensionless, (0, 10])."),
        youngs_modulus=typer.Option(M.NEEDLE_E_MPA, "--youngs-modulus", help="Pin Young's modulus, MPa (> 0)."),
        bone_thickness=typer.Option(M.DEFAULT_BONE_THICKNESS_MM, "--bone-thickness",
                                    help="Bone thickness below its surface to its held far side, mm (> depth); "
                                    "the plate bone law's cancellous core lies between the cortex and it."),
        bone_law=typer.Option("plate", "--bone-law", help="plate (the cortex as a plate on a confined "
                              "cancellous core, default) or winkler (the earlier uniform foundation)."),
        clamp=typer.Option("rigid", "--clamp", help="rigid (a rigid body) or elastic (a Timoshenko bar along the "
                           "pins with its section and modulus; docs/frame.md)."),
        clamp_modulus=typer.Option(M.CLAMP_E_MPA, "--clamp-modulus", help="Young's modulus of the elastic clamp "
                                   "bar, MPa (> 0; default fe needle's steel, 200000)."),
        clamp_poisson=typer.Option(M.CLAMP_NU, "--clamp-poisson", help="Poisson's ratio of the elastic clamp bar "
                                   "(dimensionless, -1..0.5; default 0.30)."),
        clamp_section=typer.Option(None, "--clamp-section", help="Section of the elastic clamp bar W,H in mm: width "
                                   "along y, height along z (> 0); default fe needle's bar, 20 mm x the clamp "
                                   "length."),
        moment=typer.Option(None, "--moment", help="Moment MX,MY,MZ at the load point, N mm (with every force)."),
        json_out=typer.Option(False, "--json", help="Print JSON {model, results} instead of a table."),
    )


def _model(needles, spacing, diameter, free_length, depth, cortex, clamp_length, layer, no_tissue, root,
           load_point, foundation_factor, tissue_factor, youngs_modulus, axial_factor=1.0, calibrated=False,
           plastic=False, bone_thickness=None, bone_law="plate", clamp="rigid", clamp_modulus=None,
           clamp_poisson=None, clamp_section=None):
    from needletissue.frame.model import FE_CALIBRATION, FrameModel
    from needletissue.ritz.model import DEFAULT_LAYERS, Layer

    layers = tuple(Layer.parse(t) for t in layer) if layer else DEFAULT_LAYERS
    fitted = {}
    if calibrated:  # every fitted factor (the bone law's cortex_factor too), not only the ones with an option
        fitted = dict(FE_CALIBRATION)
        foundation_factor, axial_factor, tissue_factor = (fitted.pop(k) for k in
                                                          ("foundation_factor", "axial_factor", "tissue_factor"))
    return FrameModel(**fitted, needles=needles, spacing_mm=spacing, diameter_mm=diameter, free_length_mm=free_length,
                      depth_mm=depth, cortex_mm=cortex, clamp_length_mm=clamp_length, layers=layers,
                      tissue=not no_tissue, root=root, load_point_mm=_triple("--load-point", load_point),
                      foundation_factor=foundation_factor, tissue_factor=tissue_factor,
                      axial_factor=axial_factor, youngs_modulus_MPa=youngs_modulus, plastic=plastic,
                      bone_law=bone_law, clamp=clamp,
                      clamp_section_mm=None if clamp_section is None else numbers("--clamp-section", clamp_section, 2),
                      **({} if bone_thickness is None else {"bone_thickness_mm": bone_thickness}),
                      **({} if clamp_modulus is None else {"clamp_E_MPa": clamp_modulus}),
                      **({} if clamp_poisson is None else {"clamp_nu": clamp_poisson}))


def register(app: typer.Typer, groups) -> None:
    o, o2 = _opts(), _opts()
    frame_app = typer.Typer(help="Needle-frame model: n pins from the bone (elastic foundation) through the "
                            "tissue springs to a clamp (rigid or elastic), any wrench, large deflection "
                            "(docs/frame.md). Without a subcommand: solve for each --force.", invoke_without_command=True,
                            no_args_is_help=False)

    @frame_app.callback(invoke_without_command=True)
    def frame(
        ctx: typer.Context,
        force: Optional[List[str]] = typer.Option(None, "--force", help="Force FX,FY,FZ at the load point, N "
                                                  "(repeat; default 0,100,0 0,200,0 0,300,0 like fe needle)."),
        needles: int = o["needles"], spacing: float = o["spacing"], diameter: float = o["diameter"],
        free_length: float = o["free_length"], depth: float = o["depth"], cortex: float = o["cortex"],
        clamp_length: float = o["clamp_length"], layer: Optional[List[str]] = o["layer"],
        no_tissue: bool = o["no_tissue"], root: str = o["root"], load_point: Optional[str] = o["load_point"],
        foundation_factor: float = o["foundation_factor"], tissue_factor: float = o["tissue_factor"],
        youngs_modulus: float = o["youngs_modulus"], moment: Optional[str] = o["moment"],
        axial_factor: float = o["axial_factor"], calibrated: bool = o["calibrated"],
        plastic: bool = o["plastic"], bone_thickness: float = o["bone_thickness"],
        bone_law: str = o["bone_law"],
        clamp: str = o["clamp"], clamp_modulus: float = o["clamp_modulus"],
        clamp_poisson: float = o["clamp_poisson"], clamp_section: Optional[str] = o["clamp_section"],
        json_out: bool = o["json_out"],
        plot: Optional[Path] = typer.Option(None, "--plot", help="Draw each pin's deflection per force to "
                                            "FILE.png; config.toml, versions.json, results.json beside it."),
    ):
        """Clamp displacement and rotation, pin deflection curves, yield utilisation per wrench (mm, N, MPa)."""
        if ctx.invoked_subcommand is not None:
            return
        from needletissue.frame.solver import solve

        model = _model(needles, spacing, diameter, free_length, depth, cortex, clamp_length, layer, no_tissue,
                       root, load_point, foundation_factor, tissue_factor, youngs_modulus, axial_factor, calibrated,
                       plastic, bone_thickness, bone_law, clamp, clamp_modulus, clamp_poisson, clamp_section)
        M = _triple("--moment", moment)
        forces = [_triple("--force", f) for f in force] if force else [(0.0, F, 0.0) for F in (100.0, 200.0, 300.0)]
        results = [solve(f, M, model) for f in forces]
        out = {"model": model.to_dict(), "results": [r.to_json() for r in results]}
        if plot is not None:
            from needletissue.frame.plot import plot_frame
            from needletissue.runinfo import write_run_files

            plot = Path(plot)
            plot_frame(results, model, path=plot)
            write_run_files(plot.parent, out["model"], out)
        _warn(results)
        if json_out:
            print(json.dumps(out, indent=2))
            return
        _table(model, results)

    @frame_app.command("compensate")
    def compensate(
        target: str = typer.Option("0,0,0", "--target", help="Bone-fragment motion to achieve: translation "
                                   "X,Y,Z of the bone point under the clamp centre, mm."),
        target_rotation: str = typer.Option("0,0,0", "--target-rotation", help="Bone-fragment rotation vector "
                                            "RX,RY,RZ about that point, rad."),
        force: str = typer.Option("0,300,0", "--force", help="Expected or measured force FX,FY,FZ, N."),
        wrench_frame: str = typer.Option("world", "--wrench-frame", help="world (fixed axes) or clamp (a force "
                                         "sensor in the clamp: turns with it; iterated)."),
        needles: int = o2["needles"], spacing: float = o2["spacing"], diameter: float = o2["diameter"],
        free_length: float = o2["free_length"], depth: float = o2["depth"], cortex: float = o2["cortex"],
        clamp_length: float = o2["clamp_length"], layer: Optional[List[str]] = o2["layer"],
        no_tissue: bool = o2["no_tissue"], root: str = o2["root"], load_point: Optional[str] = o2["load_point"],
        foundation_factor: float = o2["foundation_factor"], tissue_factor: float = o2["tissue_factor"],
        youngs_modulus: float = o2["youngs_modulus"], moment: Optional[str] = o2["moment"],
        axial_factor: float = o2["axial_factor"], calibrated: bool = o2["calibrated"],
        plastic: bool = o2["plastic"], bone_thickness: float = o2["bone_thickness"],
        bone_law: str = o2["bone_law"],
        clamp: str = o2["clamp"], clamp_modulus: float = o2["clamp_modulus"],
        clamp_poisson: float = o2["clamp_poisson"], clamp_section: Optional[str] = o2["clamp_section"],
        json_out: bool = o2["json_out"],
    ):
        """Clamp pose to command so that the bone fragment reaches its target under the wrench."""
        from needletissue.frame.aim import compensate as comp

        model = _model(needles, spacing, diameter, free_length, depth, cortex, clamp_length, layer, no_tissue,
                       root, load_point, foundation_factor, tissue_factor, youngs_modulus, axial_factor, calibrated,
                       plastic, bone_thickness, bone_law, clamp, clamp_modulus, clamp_poisson, clamp_section)
        c = comp(_triple("--target", target), _triple("--target-rotation", target_rotation),
                 _triple("--force", force), _triple("--moment", moment), model, wrench_frame=wrench_frame,
                 detail=True)
        out = {"model": model.to_dict(), **c.to_json()}
        _warn([c.result])
        if json_out:
            print(json.dumps(out, indent=2))
            return
        from rich.console import Console

        f = lambda v: ", ".join(f"{x:.4f}" for x in v)  # noqa: E731
        Console().print(f"command clamp centre displacement [bold]{f(c.clamp_displacement_mm)}[/bold] mm, "
                        f"rotation [bold]{f(c.clamp_rotation_rad)}[/bold] rad; correction over a rigid "
                        f"construct {f(c.correction_mm)} mm; predicted residual {f(c.residual_mm)} mm "
                        f"({c.iterations} passes)")

    app.add_typer(frame_app, name="frame")


def _warn(results):
    from rich.console import Console

    err = Console(stderr=True, emoji=False)
    for r in results:
        for w in r.warnings:
            err.print(f"[yellow]warning[/yellow] ({', '.join(f'{x:g}' for x in r.force_N)} N): {w}",
                      soft_wrap=True, markup=True)


def _table(model, results):
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"Needle frame: {model.needles} pin(s) d={model.diameter_mm:g} mm, l={model.free_length_mm:g} mm, "
              f"depth {model.depth_mm:g} mm ({model.root} root), {model.clamp} clamp {model.clamp_length_mm:g} mm, "
              f"tissue {'on' if model.tissue else 'off'}")
    for col in ("F N", "clamp u mm", "|rot| rad", "max pin mm", "slope rad", "yield", "err mm"):
        t.add_column(col, justify="right")
    for r in results:
        import math

        t.add_row(",".join(f"{x:g}" for x in r.force_N), ",".join(f"{round(x, 3) + 0.0:.3f}" for x in r.clamp_displacement_mm),
                  f"{math.hypot(*r.clamp_rotation_rad):.4f}", f"{r.max_needle_deflection_mm:.3f}",
                  f"{max(n.root_slope_rad for n in r.needles):.4f}", f"{r.needle_yield_utilisation:.2f}",
                  f"{r.error_estimate_mm:.0e}")
    Console().print(t)
