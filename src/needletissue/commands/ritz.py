"""`needletissue ritz`: the Rayleigh-Ritz needle model (solve when no subcommand; `calibrate`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from needletissue.errors import FORCE_RANGE_HELP, InputError
from needletissue.ritz.model import MAX_DEFLECTION_RATIO


def _model(diameter, free_length, load_point, youngs_modulus, layer, no_cos):
    from needletissue.ritz import model as M

    layers = tuple(M.Layer.parse(t) for t in layer) if layer else M.DEFAULT_LAYERS
    return M.RitzModel(diameter_mm=diameter, free_length_mm=free_length, youngs_modulus_MPa=youngs_modulus,
                       layers=layers, load_point_mm=load_point, cos_term=not no_cos)


def _opts():
    """Model options shared by the solve and calibrate commands (fresh OptionInfo objects each)."""
    from needletissue.ritz.model import DEFAULT_DIAMETER_MM, DEFAULT_FREE_LENGTH_MM, NEEDLE_E_MPA

    return dict(
        diameter=typer.Option(DEFAULT_DIAMETER_MM, "--diameter", help="Needle diameter d, mm (> 0)."),
        free_length=typer.Option(DEFAULT_FREE_LENGTH_MM, "--free-length",
                                 help="Exposed needle length l from bone to gripper, mm (> 0)."),
        load_point=typer.Option(None, "--load-point",
                                help="Load point z3 from the bone, mm, in (0, l]; default l (free end)."),
        youngs_modulus=typer.Option(NEEDLE_E_MPA, "--youngs-modulus", help="Needle Young's modulus E, MPa (> 0)."),
        layer=typer.Option(None, "--layer", help="Tissue layer NAME:THICKNESS_MM:K (K in N/mm per mm of "
                           "needle = N/mm^2), repeat, stacked from the bone. Default muscle:22:0.048 "
                           "adipose:10:0.023."),
        order=typer.Option("3", "--order", help="Trial-function order: 3 (paper's cubic), N >= 3, or auto."),
        no_cos=typer.Option(False, "--no-cos", help="Drop the 1/cos(theta) factor in the spring term (Eq. 11)."),
        json_out=typer.Option(False, "--json", help="Print JSON {model, results} instead of a table."),
    )


_CONFIG_KEYS = ("diameter_mm", "free_length_mm", "load_point_mm", "youngs_modulus_MPa", "cos_term", "layers",
                "order", "tol_mm", "forces_N", "second_moment_mm4", "bending_stiffness_Nmm2")


def _read_config(path) -> dict:
    """The config.toml `ritz --plot` writes (derived second_moment/bending_stiffness are ignored)."""
    from needletissue.runinfo import read_toml

    c = read_toml(path)
    bad = sorted(set(c) - set(_CONFIG_KEYS))
    if bad:
        raise InputError(f"{path}: {bad[0]}", f"unknown field; allowed: {', '.join(_CONFIG_KEYS)}")
    if not all(isinstance(la, dict) and {"name", "thickness_mm", "k_N_per_mm2"} <= set(la)
               for la in c.get("layers", [])):
        raise InputError(f"{path}: layers", "each layer needs name, thickness_mm, k_N_per_mm2")
    return c


def _model_json(model, order, tol):
    d = model.to_dict()
    d["order"] = str(order)
    d["tol_mm"] = tol
    return d


def register(app: typer.Typer, groups) -> None:
    o, o2 = _opts(), _opts()
    ritz_app = typer.Typer(help="Rayleigh-Ritz needle-in-layered-springs model (paper Eqs. 8-15). "
                           "Without a subcommand: solve for each --force.", invoke_without_command=True,
                           no_args_is_help=False)

    @ritz_app.callback(invoke_without_command=True)
    def ritz(
        ctx: typer.Context,
        force: Optional[List[float]] = typer.Option(None, "--force", help="Reduction force F, N (repeat; "
                                                    f"negative = opposite direction; {FORCE_RANGE_HELP}). "
                                                    "The model is valid while |v|max / l <= "
                                                    f"{MAX_DEFLECTION_RATIO:g} (small rotations): beyond, "
                                                    "a warning."),
        diameter: float = o["diameter"],
        free_length: float = o["free_length"],
        load_point: Optional[float] = o["load_point"],
        youngs_modulus: float = o["youngs_modulus"],
        layer: Optional[List[str]] = o["layer"],
        order: str = o["order"],
        no_cos: bool = o["no_cos"],
        json_out: bool = o["json_out"],
        plot: Optional[Path] = typer.Option(None, "--plot", help="Draw v(z) per force (paper Fig. 5) to "
                                            "FILE.png; config.toml, versions.json, results.json beside it."),
        config_file: Optional[Path] = typer.Option(None, "--config", help="config.toml written by an earlier "
                                                   "`ritz --plot` (model, order, forces; mm, N, MPa): solves it "
                                                   "again; options given on the command line override it."),
    ):
        """Needle deflection v(z) for each --force (mm, N, MPa)."""
        if ctx.invoked_subcommand is not None:
            return
        if config_file is not None:
            from needletissue.commands import from_command_line

            c, given = _read_config(config_file), set(from_command_line(ctx))
            keep = lambda name, value, key: value if name in given or key not in c else c[key]  # noqa: E731
            force = keep("force", force, "forces_N")
            diameter = keep("diameter", diameter, "diameter_mm")
            free_length = keep("free_length", free_length, "free_length_mm")
            load_point = keep("load_point", load_point, "load_point_mm")
            youngs_modulus = keep("youngs_modulus", youngs_modulus, "youngs_modulus_MPa")
            order = str(keep("order", order, "order"))
            no_cos = no_cos if "no_cos" in given or "cos_term" not in c else not c["cos_term"]
            if "layer" not in given and "layers" in c:
                layer = [f"{la['name']}:{la['thickness_mm']}:{la['k_N_per_mm2']}" for la in c["layers"]]
        if not force:
            raise InputError("--force", "give at least one --force in N (e.g. --force 100 --force 300)")
        from needletissue.ritz import DEFAULT_TOL_MM, parse_order, solve_forces

        from needletissue.errors import check_force

        force = [check_force("--force", f, signed=True) for f in force]
        model = _model(diameter, free_length, load_point, youngs_modulus, layer, no_cos)
        parse_order(order)
        results = solve_forces(force, model, order=order)
        out = {"model": _model_json(model, order, DEFAULT_TOL_MM), "results": [r.to_json() for r in results]}
        beyond = [r for r in results if not r.within_validity]
        if beyond:
            import sys

            r = max(beyond, key=lambda r: r.deflection_ratio)
            print(f"warning: --force {', '.join(f'{b.force_N:g}' for b in beyond)} N: |v|max / l up to "
                  f"{r.deflection_ratio:.2f} > {MAX_DEFLECTION_RATIO:g}, beyond the Ritz model's small-rotation "
                  "range (docs/ritz.md); use the FE model (fe needle) there", file=sys.stderr)
        if plot is not None:
            from needletissue.ritz.plot import plot_deflection
            from needletissue.runinfo import write_run_files

            plot = Path(plot)
            plot_deflection(results, path=plot, model=model)
            write_run_files(plot.parent, {**out["model"], "forces_N": force}, out)  # `ritz --config` reads it
        if json_out:
            print(json.dumps(out, indent=2))
            return
        _table(out)

    @ritz_app.command("calibrate")
    def calibrate(
        parameter: str = typer.Option(..., "--parameter", help="What to solve for: force (N), free-length (mm), "
                                      "diameter (mm) or k:LAYER (N/mm^2)."),
        deflection: float = typer.Option(..., "--deflection", help="Measured deflection, mm (sign = direction)."),
        force: Optional[float] = typer.Option(None, "--force", help="Applied force, N (not with --parameter "
                                              "force)."),
        at: str = typer.Option("tip", "--at", help="Where the deflection was measured: tip or load-point."),
        diameter: float = o2["diameter"],
        free_length: float = o2["free_length"],
        load_point: Optional[float] = o2["load_point"],
        youngs_modulus: float = o2["youngs_modulus"],
        layer: Optional[List[str]] = o2["layer"],
        order: str = o2["order"],
        no_cos: bool = o2["no_cos"],
        json_out: bool = o2["json_out"],
    ):
        """Inverse use: the force for a deflection, or one parameter fitted to a (force, deflection) pair."""
        from needletissue.ritz import DEFAULT_TOL_MM, parse_order
        from needletissue.ritz.inverse import calibrate as cal

        model = _model(diameter, free_length, load_point, youngs_modulus, layer, no_cos)
        parse_order(order)
        param = parameter.replace("-", "_") if not parameter.startswith("k:") else parameter
        if param != "force" and force is None:
            raise InputError("--force", f"required to calibrate {parameter}")
        c = cal(param, force if force is not None else 0.0, deflection, model, at=at.replace("-", "_"),
                order=order)
        out = {"parameter": parameter, "value": c.value,
               "unit": {"force": "N", "free_length": "mm", "diameter": "mm"}.get(param, "N/mm^2"),
               "force_N": c.force_N, "deflection_mm": c.deflection_mm, "at": c.at,
               "model": _model_json(c.model, order, DEFAULT_TOL_MM), "result": c.result.to_json()}
        if json_out:
            print(json.dumps(out, indent=2))
            return
        from rich.console import Console

        Console().print(f"{parameter} = [bold]{c.value:.6g}[/bold] {out['unit']}  "
                        f"(F = {c.force_N:.6g} N gives {c.at} deflection {c.deflection_mm:.6g} mm, "
                        f"order {c.result.order}, error estimate {c.result.error_estimate_mm:.2g} mm)")

    app.add_typer(ritz_app, name="ritz")


def _table(out):
    from rich.console import Console
    from rich.table import Table

    m = out["model"]
    layers = ", ".join(f"{la['name']} {la['thickness_mm']:g} mm k={la['k_N_per_mm2']:g}" for la in m["layers"])
    t = Table(title=f"Ritz needle: d={m['diameter_mm']:g} mm, l={m['free_length_mm']:g} mm, "
              f"z3={m['load_point_mm']:g} mm, E={m['youngs_modulus_MPa']:g} MPa; {layers}; "
              f"cos term {'on' if m['cos_term'] else 'off'}")
    # "Newton" is the solve (always ok, with its iterations: it raises otherwise); "p ok" is the
    # trial-function order: does raising p change v(z) by less than the tolerance?
    for col in ("F N", "tip mm", "load mm", "max mm", "slope rad", "p", "Newton", "err mm", "p ok"):
        t.add_column(col, justify="right", no_wrap=True)
    for r in out["results"]:
        t.add_row(f"{r['force_N']:g}", f"{r['tip_deflection_mm']:.4f}", f"{r['load_point_deflection_mm']:.4f}",
                  f"{r['max_deflection_mm']:.4f}", f"{r['tip_slope_rad']:.4f}", str(r["order"]),
                  f"{'ok' if r['newton_converged'] else 'failed'} ({r['iterations']})",
                  f"{r['error_estimate_mm']:.1e}", "yes" if r["order_converged"] else "no")
    con = Console()
    con.print(t)
    if not all(r["order_converged"] for r in out["results"]):
        tol = m.get("tol_mm")
        con.print(f"p ok = no: the solve converged; raising the order p changes v(z) by err mm, more than "
                  f"the tolerance{f' {tol:g} mm' if tol else ''} (--order auto raises p until it does not).")
