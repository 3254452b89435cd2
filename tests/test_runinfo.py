"""Run records: files a colleague can read (umask), relocatable, with the versions that shaped them."""

import os
import stat

import pytest

from needletissue.runinfo import current_umask, make_dir, write_atomic, write_json


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
