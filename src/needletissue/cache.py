"""Mesh cache: a mesh made before from the same inputs, read back instead of meshing again, and the
fill-reducing ordering of a sparsity pattern met before (fem.linsolve.nested_dissection).

One folder for everything that uses it (the needle model's gmsh mesh, the anatomical model's box mesh, METIS's
orderings):
$NEEDLETISSUE_MESH_CACHE, else $XDG_CACHE_HOME/needletissue/meshes (~/.cache/...); "0"/"off" turns it off.
An entry is `<key><suffix>` (the bytes) and `<key>.json` (facts, with the bytes' SHA-256), the key a hash of
every input, the versions of the libraries that make it and the code's own bytes. Delete the folder to
clear it. Best effort both ways: an unreadable or damaged entry is a miss, a cache that cannot be written
does not fail the run.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from needletissue.errors import InputError
from needletissue.runinfo import write_atomic

MESH_CACHE_ENV = "NEEDLETISSUE_MESH_CACHE"   # "0" / "off": no mesh cache; a folder: the cache there


def mesh_cache_dir() -> Path | None:
    """The cache folder: $NEEDLETISSUE_MESH_CACHE, else $XDG_CACHE_HOME/needletissue/meshes (~/.cache/...);
    None when that variable is 0/off/no/false."""
    env = os.environ.get(MESH_CACHE_ENV, "").strip()
    if env.lower() in ("0", "off", "no", "false"):
        return None
    if env:
        return Path(env).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "needletissue" / "meshes"


def cache_key(inputs: dict, code: tuple[Path, ...] = ()) -> str:
    """Hash of every input of what is cached (JSON-able: the versions of the libraries that make it included)
    and of the bytes of the code that makes it (a change to either makes new entries)."""
    h = hashlib.sha256(json.dumps(inputs, sort_keys=True).encode())
    for f in code:
        h.update(Path(f).read_bytes())
    return h.hexdigest()[:32]


def sha256(*chunks) -> str:
    """SHA-256 of bytes and NumPy arrays in turn (an array's memory as it is: no copy, its dtype not included)."""
    h = hashlib.sha256()
    for c in chunks:
        h.update(memoryview(np.ascontiguousarray(c)).cast("B") if isinstance(c, np.ndarray) else c)
    return h.hexdigest()


def read_entry(folder: Path, key: str, suffix: str) -> tuple[bytes, dict] | None:
    """(bytes, facts) of the entry `key`, or None: absent, unreadable, or bytes that do not match
    their checksum (the .json is written after the data, so a torn write is a miss)."""
    try:
        facts = json.loads((folder / f"{key}.json").read_text())
        data = (folder / f"{key}{suffix}").read_bytes()
        if sha256(data) != facts["sha256"]:
            return None
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return data, facts


def write_entry(folder: Path, key: str, suffix: str, data: bytes, facts: dict) -> bool:
    """Store an entry, each file by runinfo.write_atomic (never half a file, mode from the umask), the data
    first; a folder that cannot be written (read-only home, full disk) is ignored. Returns whether it stored."""
    try:
        write_atomic(folder / f"{key}{suffix}", data)
        write_atomic(folder / f"{key}.json", json.dumps({**facts, "sha256": sha256(data)}))
    except (OSError, InputError):
        return False
    return True
