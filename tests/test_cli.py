"""The root command: --version and --help work, for the root and for every materials command."""

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from needletissue import __version__
from needletissue.cli import app

runner = CliRunner()


def test_version():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0
    assert r.output.strip() == f"needletissue {__version__}"


@pytest.mark.parametrize("args", [[], ["materials"], ["materials", "list"], ["materials", "curve"],
                                  ["materials", "fit"]])
def test_help(args):
    r = runner.invoke(app, [*args, "--help"])
    assert r.exit_code == 0, r.output
    assert "Usage" in r.output


def test_console_entry_point_version():
    r = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "--version"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and __version__ in r.stdout
