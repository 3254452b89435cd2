"""`needletissue study`: parameter studies and uncertainty on Dask (resumable)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer, groups) -> None:
    @app.command("study")
    def study(
        config: Path = typer.Option(..., "--config", help="Study TOML: [study], [fixed], [parameters.NAME] "
                                    "(units in each parameter's name: _mm, _N, _MPa, _N_per_mm2). See docs/studies.md."),
        out: Path = typer.Option(None, "--out", help="Output folder; default results/study-<name>/. "
                                 "Rerunning into the same folder resumes."),
        scheduler: str = typer.Option(None, "--scheduler", help="Address of an existing Dask scheduler "
                                      "(e.g. tcp://host:8786); default: a LocalCluster on this machine."),
        workers: int = typer.Option(2, "--workers", min=1, help="LocalCluster worker processes."),
        serial: bool = typer.Option(False, "--serial", help="Run in this process without Dask (debugging)."),
        quiet: bool = typer.Option(False, "--quiet", help="No progress bar."),
    ):
        """Grid, Monte Carlo, Latin hypercube or Sobol (Saltelli) study over force, tissue thickness,
        spring stiffnesses, material parameters, needle diameter and length. Writes results.parquet/.csv,
        failures.csv, summary (distributions, sensitivity indices), figures and results.json."""
        import os

        os.environ.setdefault("MPLBACKEND", "Agg")
        from rich.console import Console

        from needletissue.studies.config import load_study
        from needletissue.studies.runner import run_study

        cfg = load_study(config)  # every config error before any computation
        out = out or Path("results") / f"study-{cfg.study.name}"
        res = run_study(cfg, out, scheduler=scheduler, workers=workers, serial=serial, progress=not quiet)
        con = Console()
        con.print(f"{res.n_cases:,} cases: {res.n_ok:,} ok, {res.n_failed:,} failed "
                  f"({res.resumed:,} from an earlier run, {res.computed_this_run:,} computed now) "
                  f"in {res.wall_time_s:.1f} s -> {res.out_dir}")
        for f in res.failures[:10]:
            params = ", ".join(f"{k}={v:.6g}" for k, v in f["parameters"].items())
            con.print(f"[red]failed case {f['case_id']}[/red] ({params}): {f['error']}", soft_wrap=True)
        if len(res.failures) > 10:
            con.print(f"... {len(res.failures) - 10} more in {res.out_dir / 'failures.csv'}")
