"""`needletissue reproduce` (the main job) and `needletissue config show`."""

from __future__ import annotations

from pathlib import Path

import typer

_CONFIG_HELP = "TOML file overriding any field of the built-in default (see `needletissue config show`)."


def register(app: typer.Typer, groups) -> None:
    config = typer.Typer(help="The built-in configuration of `reproduce` (TOML; units mm, N, MPa, s).",
                         no_args_is_help=True)
    app.add_typer(config, name="config")

    @config.command("show")
    def show(
        config_file: Path = typer.Option(None, "--config", help=_CONFIG_HELP),
        as_json: bool = typer.Option(False, "--json", help="Print JSON instead of annotated TOML."),
    ):
        """Print the resolved configuration (default, overridden by --config), each field with its unit."""
        from needletissue.report.config import annotated_toml, load_config

        cfg = load_config(config_file)
        if as_json:
            print(cfg.model_dump_json(indent=2))
        else:
            print(annotated_toml(cfg))

    @app.command("reproduce")
    def reproduce(
        out: Path = typer.Option(Path("results"), "--out", help="Output folder (replaced atomically when the run ends)."),
        config_file: Path = typer.Option(None, "--config", help=_CONFIG_HELP),
        ct: Path = typer.Option(None, "--ct", help="CT (NIfTI or DICOM folder) for the anatomical model; "
                                "default: the example CT in ../shared/data when present."),
        labels: Path = typer.Option(None, "--labels", help="Label map on the CT grid (with --ct)."),
        quiet: bool = typer.Option(False, "--quiet", help="No progress lines."),
    ):
        """Reproduce the paper: material curves, traction validation, Ritz at 100/200/300 N, needle FE,
        and the anatomical model when data is present. Writes results.json, config.toml, versions.json,
        figures, VTU files and a self-contained report.html into --out."""
        from needletissue.models.render import offscreen

        offscreen()
        from rich.console import Console

        from needletissue.errors import InputError
        from needletissue.report.config import load_config
        from needletissue.report.pipeline import run_reproduce
        from needletissue.report.stages import stage_list

        cfg = load_config(config_file)  # every config error before any computation
        for name, p in (("--ct", ct), ("--labels", labels)):
            if p is not None and not p.exists():
                raise InputError(name, f"no such file or folder: {p}")
        import sys

        try:
            res = run_reproduce(cfg, out, stage_list(), ct=ct, labels=labels, progress=not quiet)
        except (KeyboardInterrupt, SystemExit) as exc:  # SIGINT / SIGTERM (pipeline._StopOnSignals)
            code = exc.code if isinstance(exc, SystemExit) else 130
            Console(stderr=True).print(f"[red]error:[/red] reproduce interrupted: workers stopped, temporary "
                                       f"folder removed, {out} left as it was", soft_wrap=True)
            sys.exit(code if isinstance(code, int) else 1)
        con = Console()
        con.print(f"wrote {res.out_dir} ({res.wall_time_s:.1f} s): report.html, results.json, comparison.md, config.toml, "
                  "versions.json")
        failed = [o.name for o in res.outcomes if o.status == "failed"]
        if failed:
            con.print(f"[red]failed stages:[/red] {', '.join(failed)} (see results.json)")
            raise typer.Exit(1)
