"""Fixtures shared by the test packages."""

from __future__ import annotations

import os
import sys

import pytest

# The mesh cache (needletissue.cache: the needle and anatomical meshes, METIS's orderings) off for the tests, in this process and the
# CLI processes they start: each test meshes as before, whatever the user's cache holds (a test that
# stops `fe needle` while gmsh runs needs gmsh to run). The cache's own test turns it on in a tmp folder.
os.environ["NEEDLETISSUE_MESH_CACHE"] = "0"


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


@pytest.fixture(scope="session")
def cgal():
    """The graded mesher's CGAL helper (geometry.graded), compiled once per helper cache; skipped where CGAL's
    headers are missing unless NEEDLETISSUE_REQUIRE_CGAL is set (.ci/run installs them and sets it)."""
    from needletissue.geometry import graded

    try:
        return graded.helper()
    except graded.MissingCGAL as exc:
        if os.environ.get("NEEDLETISSUE_REQUIRE_CGAL"):
            pytest.fail(f"NEEDLETISSUE_REQUIRE_CGAL is set but the CGAL helper cannot be built: {exc}")
        pytest.skip(f"CGAL missing: {exc}")
