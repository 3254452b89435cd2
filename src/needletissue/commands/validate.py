"""`needletissue validate traction`: FE tissue block vs closed-form uniaxial stress (paper Eq. 16)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app, groups) -> None:
    groups.validate.command("traction")(traction)


def traction(
    material: str = typer.Option(..., "--material", help="Tissue: muscle or adipose."),
    as_json: bool = typer.Option(False, "--json", help="Print the results as JSON on stdout."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Write the stress-displacement figure (PNG)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder for config.toml, versions.json, results.json "
                                       "(default with --plot: the figure's folder)."),
    width: float = typer.Option(20.0, help="Block cross-section side, mm."),
    height: float = typer.Option(20.0, help="Block height (gauge length), mm; max stretch = 1 + 10 mm / height."),
    max_displacement: float = typer.Option(10.0, help="Top displacement at the end of the pull, mm."),
    points: int = typer.Option(11, help="Load levels compared (including 0), >= 2."),
    elements: int = typer.Option(4, help="Tetrahedra edge divisions per block side."),
    order: int = typer.Option(2, help="Element order: 1 (tetra) or 2 (tetra10)."),
    formulation: str = typer.Option("mixed", help="mixed (u/p, P2/P0) or displacement."),
    bulk_ratio: float = typer.Option(1e4, help="Bulk modulus of the FE tissue / initial shear modulus (-)."),
    ends: str = typer.Option("free", help="free: laterally free (homogeneous uniaxial); clamped: bonded top and base."),
    progress: bool = typer.Option(False, help="Show a progress bar over load steps (stderr)."),
):
    """Pull a tissue block 0-10 mm and compare FE nominal stress with the incompressible closed form.

    Stress in MPa, displacement in mm; RMSE as the paper's Eq. 16 (criterion < 0.05 MPa). Exit code 1
    when the validation fails (results are still written and printed).
    """
    from rich.console import Console
    from rich.table import Table

    from needletissue.models import traction as tr
    from needletissue.runinfo import to_jsonable, write_run_files

    if material not in ("muscle", "adipose"):
        from needletissue.errors import InputError

        raise InputError("--material", f"must be muscle or adipose, got {material!r}")
    cfg = tr.TractionConfig(material=material, width=width, height=height, max_displacement=max_displacement,
                            points=points, elements=elements, order=order, formulation=formulation,
                            bulk_ratio=bulk_ratio, ends=ends)
    res = tr.run(cfg, progress=progress)
    if plot is not None:
        tr.plot(res, plot)
        out = out if out is not None else (plot.parent if str(plot.parent) else Path("."))  # run files next to the figure
    if out is not None:
        write_run_files(out, cfg, res.to_dict())
    if as_json:
        import json

        print(json.dumps(to_jsonable(res.to_dict()), indent=2))
        if not res.passed:
            raise typer.Exit(1)
        return
    t = Table(title=f"{material}: traction validation (paper Eq. 16)")
    for col in ("displacement (mm)", "stretch", "FE nominal (MPa)", "theory (MPa)"):
        t.add_column(col, justify="right")
    for d, s, f, th in zip(res.displacement_mm, res.stretch, res.fe_nominal_stress_MPa, res.theory_nominal_stress_MPa):
        t.add_row(f"{d:.2f}", f"{s:.3f}", f"{f:.5f}", f"{th:.5f}")
    c = Console()
    c.print(t)
    verdict = "[green]pass[/green]" if res.passed else "[red]fail[/red]"
    c.print(f"RMSE {res.rmse_MPa:.3e} MPa (paper {res.paper_rmse_MPa} MPa, criterion < {res.criterion_MPa}): {verdict}")
    if not res.passed:  # a failed validation is a failed command (scripts and CI must see it)
        raise typer.Exit(1)
