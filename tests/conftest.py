"""Fixtures shared by the test packages."""

from __future__ import annotations

import sys

import pytest


@pytest.fixture
def run_cli(monkeypatch, capsys):
    """run_cli(*args) -> (exit code, stdout, stderr) of `needletissue *args`, in this process."""
    from needletissue.cli import main

    def run(*args):
        monkeypatch.setattr(sys, "argv", ["needletissue", *map(str, args)])
        code = 0
        try:
            main()
        except SystemExit as exc:
            code = exc.code or 0
        out = capsys.readouterr()
        return code, out.out, out.err

    return run
