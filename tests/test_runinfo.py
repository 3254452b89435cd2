"""Run records: files a colleague can read (umask), relocatable, with the versions that shaped them."""

import json
import os
import stat

import numpy as np
import pytest

from needletissue.runinfo import current_umask, make_dir, to_jsonable, write_atomic, write_json


@pytest.fixture
def umask():
    old = os.umask(0o022)
    yield lambda m: os.umask(m)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077])
def test_atomic_files_and_dirs_follow_the_umask(tmp_path, umask, mask):
    umask(mask)
    assert current_umask() == mask
    f = write_atomic(tmp_path / "sub" / "a.txt", "x")
    j = write_json(tmp_path / "b.json", {"a": 1})
    d = make_dir(tmp_path / "d" / "e")
    # what open() and mkdir() give: 0666 / 0777 minus the umask (mkstemp alone gives 0600)
    assert stat.S_IMODE(f.stat().st_mode) == 0o666 & ~mask
    assert stat.S_IMODE(j.stat().st_mode) == 0o666 & ~mask
    assert stat.S_IMODE(d.stat().st_mode) == 0o777 & ~mask
    assert stat.S_IMODE(f.parent.stat().st_mode) == 0o777 & ~mask


def test_paths_inside_the_folder_are_written_relative(tmp_path):
    import json

    import tomllib

    from needletissue.runinfo import relocate, write_run_files

    out = tmp_path / "run"
    inside, outside = str(out / "a" / "x.vtu"), "/data/ct.nii.gz"
    assert relocate({"f": [inside, str(out)], "g": outside, "n": 1}, out) == {"f": ["a/x.vtu", "."], "g": outside,
                                                                              "n": 1}
    write_run_files(out, {"out": str(out), "ct": outside}, {"vtu": inside, "figures": {"files": [inside]}})
    text = (out / "results.json").read_text(encoding="utf-8") + (out / "config.toml").read_text(encoding="utf-8")
    assert str(tmp_path) not in text
    assert json.loads((out / "results.json").read_text(encoding="utf-8"))["vtu"] == "a/x.vtu"
    assert tomllib.loads((out / "config.toml").read_text(encoding="utf-8"))["ct"] == outside


def test_versions_cover_every_dependency_and_the_run_is_recorded(tmp_path):
    import json
    import re
    import subprocess
    import tomllib
    from pathlib import Path

    from needletissue.runinfo import _PACKAGES, write_run_files

    root = Path(__file__).resolve().parents[1]
    deps = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["project"]["dependencies"]
    norm = lambda n: re.sub(r"[-_.]+", "-", n).lower()  # noqa: E731  (PEP 503 names)
    listed = {norm(p) for p in _PACKAGES}
    missing = [d for d in deps if norm(re.split(r"[<>=;\[ ]", d)[0]) not in listed]
    assert not missing, f"add to runinfo._PACKAGES: {missing}"

    write_run_files(tmp_path, {}, {})
    v = json.loads((tmp_path / "versions.json").read_text(encoding="utf-8"))
    import needletissue
    import numpy

    assert v["needletissue"] == needletissue.__version__ and v["numpy"] == numpy.__version__
    run = v["run"]
    assert re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\+00:00$", run["date"]) and run["command"]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0 and Path(needletissue.__file__).resolve().is_relative_to(root):
        assert run["git_commit"] == head.stdout.strip()


def _tree(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_staged_output_stopped_leaves_the_folder_as_it_was(tmp_path):
    from needletissue.runinfo import staged_output

    out = tmp_path / "out"
    (out / "run_10N").mkdir(parents=True)
    (out / "run_10N" / "a.vtu").write_text("old")
    (out / "notes.txt").write_text("mine")
    before = _tree(out)
    for stop in (KeyboardInterrupt, SystemExit(143), RuntimeError("failed")):
        with pytest.raises(type(stop) if isinstance(stop, BaseException) else stop):
            with staged_output(out, replaces=r"run_[0-9]+N") as stage:
                (stage / "run_10N").mkdir()
                (stage / "run_10N" / "a.vtu").write_text("new")
                (stage / "results.json").write_text("{}")
                raise stop
        assert _tree(out) == before and (out / "run_10N" / "a.vtu").read_text() == "old"
    with pytest.raises(KeyboardInterrupt), staged_output(tmp_path / "fresh") as stage:
        (stage / "x").write_text("x")
        raise KeyboardInterrupt
    assert not (tmp_path / "fresh").exists()


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077])
def test_staged_output_moves_in_replaces_and_follows_the_umask(tmp_path, umask, mask):
    from needletissue.runinfo import staged_output

    umask(mask)
    out = tmp_path / "out"
    with staged_output(out, replaces=r"run_[0-9]+N(\.vtu)?") as stage:
        for f in (10, 20):
            (stage / f"run_{f}N").mkdir()
            write_atomic(stage / f"run_{f}N" / "piece.vtu", "first")
            write_atomic(stage / f"run_{f}N.vtu", "first")
    (out / "notes.txt").write_text("mine")
    with staged_output(out, replaces=r"run_[0-9]+N(\.vtu)?") as stage:
        (stage / "run_10N").mkdir()
        write_atomic(stage / "run_10N" / "piece.vtu", "second")
        write_atomic(stage / "run_10N.vtu", "second")
    assert _tree(out) == ["notes.txt", "run_10N", "run_10N.vtu", "run_10N/piece.vtu"]  # run_20N: gone
    assert (out / "run_10N" / "piece.vtu").read_text() == "second"
    assert stat.S_IMODE(out.stat().st_mode) == stat.S_IMODE((out / "run_10N").stat().st_mode) == 0o777 & ~mask
    assert stat.S_IMODE((out / "run_10N" / "piece.vtu").stat().st_mode) == 0o666 & ~mask


def test_staged_output_replaces_a_file_by_a_folder_and_back(tmp_path):
    from needletissue.runinfo import staged_output

    out = tmp_path / "out"
    out.mkdir()
    (out / "run_10N").write_text("a file where the run puts its pieces folder")
    (out / "run_10N.vtu").mkdir()  # and a folder where it puts a file
    with staged_output(out) as stage:
        (stage / "run_10N").mkdir()
        (stage / "run_10N" / "a.vtu").write_text("piece")
        (stage / "run_10N.vtu").write_text("whole")
    assert (out / "run_10N" / "a.vtu").read_text() == "piece" and (out / "run_10N.vtu").read_text() == "whole"


def test_non_finite_numbers_are_null_so_strict_parsers_read_the_file(tmp_path):
    """NaN and +-inf (Python's json writes them as NaN / Infinity, which JSON.parse rejects) become null,
    NumPy scalars included; finite numbers pass unchanged."""
    obj = {"a": float("inf"), "b": np.float64(-np.inf), "c": [np.nan, 1.5, np.float32(2.0)], "d": np.array([np.inf, 3])}
    out = to_jsonable(obj)
    assert out == {"a": None, "b": None, "c": [None, 1.5, 2.0], "d": [None, 3.0]}
    text = json.dumps(out, allow_nan=False)  # raises on any non-finite number left
    write_json(tmp_path / "r.json", obj)
    assert json.loads((tmp_path / "r.json").read_text()) == json.loads(text)
