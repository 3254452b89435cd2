"""`needletissue materials list|curve|fit`: named materials, closed-form curves, stability, fitting."""

from __future__ import annotations

import json
import warnings
from enum import Enum
from pathlib import Path

import numpy as np
import typer


class Mode(str, Enum):
    uniaxial = "uniaxial"
    biaxial = "biaxial"
    planar = "planar"


_MATERIALS_HELP = ("TOML file of extra materials (tables with model, parameters in MPa, density in g/cm^3, "
                   "source); also read from $NEEDLETISSUE_MATERIALS.")


def _load_user(path: Path | None):
    from needletissue import materials

    if path is not None:
        materials.load_toml(path)


def _report(caught):
    from rich.console import Console

    err = Console(stderr=True)
    for w in caught:
        err.print(f"[yellow]warning:[/yellow] {w.message}", soft_wrap=True)


def _fmt(v):
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(f"{x:.5g}" for x in v) + "]"
    return f"{v:.5g}"


def _print_json(obj):
    from needletissue.runinfo import to_jsonable

    print(json.dumps(to_jsonable(obj), indent=2))


def register(app: typer.Typer, groups) -> None:
    mat = typer.Typer(help="Hyperelastic tissue laws of the study: curves, Drucker stability, fitting. "
                      "Stresses in MPa.", no_args_is_help=True)
    app.add_typer(mat, name="materials")

    @mat.command("list")
    def list_(
        as_json: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
        materials_file: Path = typer.Option(None, "--materials", envvar="NEEDLETISSUE_MATERIALS",
                                            help=_MATERIALS_HELP),
    ):
        """List the named materials: law, parameters (MPa), density (g/cm^3), mu0 and K (MPa), stable ranges."""
        from needletissue import materials
        from needletissue.materials import closed_form as cf
        from needletissue.materials import stability

        _load_user(materials_file)
        rows = []
        for name in materials.names():
            m = materials.get(name)
            row = {
                "name": m.name, "model": m.model, "parameters": m.parameters, "density_g_cm3": m.density,
                "initial_shear_modulus_MPa": m.initial_shear_modulus, "bulk_modulus_MPa": m.bulk,
                "source": m.source,
            }
            if m.model in cf.PARAMETERS:
                row["stable_range"] = stability.stability_report(m.model, m.parameters).to_json()["stable_range"]
            rows.append(row)
        if as_json:
            _print_json(rows)
            return
        from rich.console import Console
        from rich.table import Table

        t = Table(title="needletissue materials (MPa, g/cm^3)")
        for c in ("name", "model", "parameters (MPa)", "mu0", "K", "rho", "Drucker-stable stretch u / b / p"):
            t.add_column(c)
        for r in rows:
            sr = r.get("stable_range")
            srs = " / ".join(f"{lo:.3g}-{hi:.3g}" for lo, hi in sr.values()) if sr else "-"
            par = ", ".join(f"{k}={_fmt(v)}" for k, v in r["parameters"].items())
            t.add_row(r["name"], r["model"], par, f"{r['initial_shear_modulus_MPa']:.4g}",
                      f"{r['bulk_modulus_MPa']:.4g}", f"{r['density_g_cm3']:g}", srs)
        import sys

        Console(width=None if sys.stdout.isatty() else 160).print(t)
        print(f"Stable ranges checked in stretch window {stability.STRETCH_WINDOW} "
              "(u = uniaxial, b = equibiaxial, p = planar).")

    @mat.command("curve")
    def curve(
        name: str = typer.Argument(..., help="Material name (see `materials list`)."),
        mode: Mode = typer.Option(Mode.uniaxial, "--mode", help="Incompressible load case."),
        stretch_max: float = typer.Option(1.5, "--stretch-max", help="Last stretch (-); < 1 for compression."),
        points: int = typer.Option(51, "--points", help="Number of stretches from 1 to --stretch-max."),
        as_json: bool = typer.Option(False, "--json", help="Print the curve as JSON."),
        plot: Path = typer.Option(None, "--plot", help="Write a PNG of the curve with the stable range shaded."),
        materials_file: Path = typer.Option(None, "--materials", envvar="NEEDLETISSUE_MATERIALS",
                                            help=_MATERIALS_HELP),
    ):
        """Closed-form nominal stress (MPa) vs stretch of a named material; warns outside its stable range."""
        from needletissue.materials import curves, stability

        _load_user(materials_file)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", stability.UnstableMaterialWarning)
            c = curves.curve(name, mode.value, stretch_max, points)
            if plot is not None:
                from needletissue.materials.plot import plot_curves

                lo, hi = sorted((1.0, stretch_max))
                plot_curves([name], mode.value, stretch_min=lo, stretch_max=hi, out=plot)
        if as_json:
            _print_json(c.to_json())
        else:
            print(f"{c.material}: {c.model} {c.parameters}, {c.mode}; Drucker-stable stretch range "
                  f"[{c.stable_range[0]:.4g}, {c.stable_range[1]:.4g}]")
            print(f"{'stretch':>10} {'P (MPa)':>14}")
            for s, p in zip(c.stretch, c.nominal_stress_MPa):
                print(f"{s:10.4f} {p:14.6e}")
        if plot is not None:
            print(f"wrote {plot}", file=__import__("sys").stderr)
        _report(caught)

    @mat.command("fit")
    def fit(
        data: Path = typer.Argument(..., help="CSV with header 'stretch,nominal_stress_MPa' (stress in MPa)."),
        model: str = typer.Option(..., "--model", help="neo_hooke, mooney_rivlin, mooney_rivlin_5, yeoh, "
                                  "ogden, ogden2, ogden3."),
        mode: Mode = typer.Option(Mode.uniaxial, "--mode", help="Load case of the data."),
        as_json: bool = typer.Option(False, "--json", help="Print the fit as JSON."),
        plot: Path = typer.Option(None, "--plot", help="Write a PNG of data and fit."),
    ):
        """Least-squares fit of a law to stretch / nominal-stress data: parameters (MPa), RMSE, R^2, stable range."""
        from needletissue.materials import fitting, stability

        fitting.fit_model(model)  # unknown model: error before reading the file
        d = fitting.read_csv(data)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", stability.UnstableMaterialWarning)
            r = fitting.fit(d, model, mode.value)
        if plot is not None:
            from needletissue.materials.plot import plot_fit

            plot_fit(r, d, plot)
        if as_json:
            _print_json(r.to_json())
        else:
            print(f"{r.model} ({r.law}) fitted to {r.n_points} {r.mode} points of {data}")
            for k, v in r.parameters.items():
                # 8 digits: the optimum's last digits differ between BLAS builds (--json keeps all of them)
                shown = ", ".join(f"{x:.8g}" for x in np.atleast_1d(v))
                print(f"  {k:6s} = {f'[{shown}]' if np.ndim(v) else shown}")
            print(f"  RMSE = {r.rmse_MPa:.6g} MPa, R^2 = {r.r2:.8f}")
            print(f"  Drucker-stable {r.mode} stretch range [{r.stable_range[0]:.4g}, {r.stable_range[1]:.4g}]"
                  f" (data {r.data_stretch_range[0]:.4g}-{r.data_stretch_range[1]:.4g})")
        _report(caught)
