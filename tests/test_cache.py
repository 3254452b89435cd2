"""needletissue.cache: entries read back as written, every defect a miss, a cache that cannot be written no error."""

from __future__ import annotations

import os

import pytest

from needletissue.cache import MESH_CACHE_ENV, cache_key, mesh_cache_dir, read_entry, write_entry


def test_an_entry_reads_back_and_every_damage_is_a_miss(tmp_path):
    assert write_entry(tmp_path, "k", ".bin", b"\x00mesh bytes", {"nodes": 3}) is True
    data, facts = read_entry(tmp_path, "k", ".bin")
    assert data == b"\x00mesh bytes" and facts["nodes"] == 3
    assert not list(tmp_path.glob(".*"))  # no temporary file left
    assert read_entry(tmp_path, "other", ".bin") is None                # absent
    (tmp_path / "k.bin").write_bytes(b"\x00mesh bytez")                  # torn or changed: checksum
    assert read_entry(tmp_path, "k", ".bin") is None
    write_entry(tmp_path, "k", ".bin", b"again", {})
    (tmp_path / "k.json").write_text("{not json")
    assert read_entry(tmp_path, "k", ".bin") is None


def test_a_cache_that_cannot_be_written_does_not_fail(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert write_entry(blocker / "cache", "k", ".bin", b"x", {}) is False   # a file where the folder should be
    assert read_entry(blocker / "cache", "k", ".bin") is None


def test_entries_follow_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        write_entry(tmp_path, "k", ".bin", b"x", {})
    finally:
        os.umask(old)
    assert {f.stat().st_mode & 0o777 for f in tmp_path.iterdir()} == {0o640}


def test_the_key_changes_with_every_input_and_the_code(tmp_path):
    code = tmp_path / "mesher.py"
    code.write_text("a = 1\n")
    k = cache_key({"size": 3.0, "gmsh": "4.15"}, (code,))
    assert k == cache_key({"gmsh": "4.15", "size": 3.0}, (code,))         # the order of the inputs does not count
    assert k != cache_key({"size": 3.5, "gmsh": "4.15"}, (code,))
    assert k != cache_key({"size": 3.0, "gmsh": "4.14"}, (code,))
    code.write_text("a = 2\n")
    assert k != cache_key({"size": 3.0, "gmsh": "4.15"}, (code,))


@pytest.mark.parametrize("value", ["0", "off", "No", "false"])
def test_the_cache_turns_off_and_moves(monkeypatch, tmp_path, value):
    monkeypatch.setenv(MESH_CACHE_ENV, value)
    assert mesh_cache_dir() is None
    monkeypatch.setenv(MESH_CACHE_ENV, str(tmp_path / "c"))
    assert mesh_cache_dir() == tmp_path / "c"
    monkeypatch.delenv(MESH_CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert mesh_cache_dir() == tmp_path / "xdg" / "needletissue" / "meshes"
