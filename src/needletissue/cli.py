"""The `needletissue` command. Thin: each concern registers its commands from needletissue.commands."""

from __future__ import annotations

import signal
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


def _one_line_summaries(*typers: typer.Typer) -> None:
    """Command lists show each docstring's first paragraph as one line: Typer's rich help kept the
    source's line breaks there, so the summaries broke mid-sentence."""
    import inspect

    for t in typers:
        for info in t.registered_commands:
            doc = info.help or inspect.getdoc(info.callback) or ""
            info.short_help = info.short_help or " ".join(doc.split("\n\n")[0].split())


_one_line_summaries(app, *vars(groups).values())


def _click_exceptions():
    """Typer >= 0.2x runs on its own copy of click; older ones on click itself."""
    try:
        from typer._click import exceptions
    except ImportError:  # pragma: no cover
        from click import exceptions
    return exceptions


def _error(message: str, code: int):
    err.print(f"[red]error:[/red] {escape(message)}", soft_wrap=True)  # one line, paths unbroken
    sys.exit(code)


def main() -> None:
    """Entry point: user errors (ours and the command-line parser's) -> one red line `error: ...` and
    exit code 2, never a traceback or a boxed panel."""
    import warnings

    def one_line(message, category, filename, lineno, file=None, line=None):  # not path:line + source
        err.print(f"[yellow]warning:[/yellow] {escape(str(message))}", soft_wrap=True)

    warnings.showwarning = one_line
    _stop_on_sigterm()
    exc = _click_exceptions()
    try:
        rv = app(standalone_mode=False)
    except _Stopped:
        _error("stopped (SIGTERM): child processes stopped, temporary files removed", 128 + signal.SIGTERM)
    except InputError as e:
        _error(str(e), 2)
    except NeedleTissueError as e:
        _error(str(e), 1)
    except exc.NoArgsIsHelpError as e:  # a bare group: its help, as before
        e.show()
        sys.exit(e.exit_code)
    except exc.UsageError as e:  # bad option value, unknown option or command, missing argument
        where = f" (see `{e.ctx.command_path} --help`)" if e.ctx is not None else ""
        _error(" ".join(e.format_message().split()) + where, 2)
    except exc.ClickException as e:
        _error(" ".join(e.format_message().split()), e.exit_code)
    except typer.Abort:
        _error("aborted", 130)
    if rv == 130:  # Typer's answer to Ctrl-C (KeyboardInterrupt), after the command has unwound
        _error("interrupted: child processes stopped, temporary files removed", 130)
    sys.exit(rv if isinstance(rv, int) else 0)


class _Stopped(SystemExit):
    """SIGTERM, raised in the main thread: the command unwinds (its `finally` blocks remove temporary
    folders, stop child processes) like Ctrl-C, instead of dying at once and leaving them behind."""


def _stop_on_sigterm() -> None:
    def stop(signum, frame):
        raise _Stopped(128 + signum)

    signal.signal(signal.SIGTERM, stop)


if __name__ == "__main__":  # python -m needletissue.cli
    main()
