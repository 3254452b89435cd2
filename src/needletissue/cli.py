"""The `needletissue` command. Thin: each concern registers its commands from needletissue.commands."""

from __future__ import annotations

import sys
from types import SimpleNamespace

import typer
from rich.console import Console
from rich.markup import escape

from needletissue import __version__
from needletissue.commands import (
    fe_needle, fe_pelvis, frame, imaging, materials, reproduce, ritz, study, validate,
)
from needletissue.errors import InputError, NeedleTissueError

# One module per concern; each defines register(app, groups) and keeps heavy imports inside commands.
_COMMAND_MODULES = (materials, ritz, frame, validate, fe_needle, fe_pelvis, imaging, reproduce, study)

app = typer.Typer(
    name="needletissue",
    help="Needle (Schanz pin) and pelvic soft-tissue deformation under a reduction force. "
    "Units: mm, N, MPa, s.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
groups = SimpleNamespace(
    fe=typer.Typer(help="3D finite-element models (FElupe).", no_args_is_help=True),
    validate=typer.Typer(help="Validation against closed forms.", no_args_is_help=True),
)
app.add_typer(groups.fe, name="fe")
app.add_typer(groups.validate, name="validate")
err = Console(stderr=True, emoji=False)  # "a:b:c" in a message must not become an emoji


def _version(value: bool):
    if value:
        print(f"needletissue {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
):
    """Needle-tissue interactive deformation toolkit."""


for _module in _COMMAND_MODULES:
    _module.register(app, groups)


def main() -> None:
    """Entry point: user errors -> one red line and exit code 2, never a traceback."""
    try:
        app()
    except InputError as exc:
        err.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)  # one line, paths unbroken
        sys.exit(2)
    except NeedleTissueError as exc:
        err.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)  # one line, paths unbroken
        sys.exit(1)
