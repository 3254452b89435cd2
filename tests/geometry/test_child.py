"""Meshers run in child processes (geometry.child): errors come back, and a stopped caller stops them."""

import time

import pytest

from needletissue.geometry.child import ChildCrash, call_in_child, start_in_child

WRITER = '''
import time
from pathlib import Path

def write_slowly(out, n):
    for i in range(n):
        Path(out, f"{i:04d}").write_text("")
        time.sleep(0.02)
    return {"written": n}
'''


@pytest.fixture
def writer(tmp_path, monkeypatch):
    mod = tmp_path / "mod"
    mod.mkdir()
    (mod / "slowwriter.py").write_text(WRITER)
    monkeypatch.setenv("PYTHONPATH", str(mod))
    out = tmp_path / "out"
    out.mkdir()
    return out


def test_value_comes_back(writer):
    assert call_in_child("slowwriter:write_slowly", {"out": str(writer), "n": 3}, what="w") == {"written": 3}
    assert len(list(writer.iterdir())) == 3


def test_stop_kills_the_child_before_returning(writer):
    # `mesh` stopped by SIGTERM removed its staging folder while the surfaces child still wrote into
    # it: a hidden .partial-* folder stayed in --out. stop() must leave nothing writing.
    job = start_in_child("slowwriter:write_slowly", {"out": str(writer), "n": 5000}, what="the writer")
    deadline = time.monotonic() + 30
    while not any(writer.iterdir()):
        assert time.monotonic() < deadline, "the child never started writing"
        time.sleep(0.02)
    job.stop()
    n = len(list(writer.iterdir()))
    time.sleep(0.5)
    assert len(list(writer.iterdir())) == n < 5000
    with pytest.raises(ChildCrash, match="the writer"):
        job()


def test_stop_before_the_child_starts(writer):
    job = start_in_child("slowwriter:write_slowly", {"out": str(writer), "n": 5000}, what="the writer")
    job.stop()   # at once: the child may not even exist yet
    time.sleep(0.5)
    assert len(list(writer.iterdir())) < 5000
    with pytest.raises(ChildCrash):
        job()


def test_stopped_child_with_sigpipe_at_its_default(writer):
    # VTK/ITK reset SIGPIPE to its default: writing the request to a child killed before it read it
    # then killed the caller (pytest died with exit 141 in CI)
    import signal

    old = signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    try:
        for _ in range(20):
            job = start_in_child("slowwriter:write_slowly", {"out": str(writer), "n": 5000}, what="w")
            job.stop()
            with pytest.raises(ChildCrash):
                job()
    finally:
        signal.signal(signal.SIGPIPE, old)
