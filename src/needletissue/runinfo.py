"""Reproducibility: atomic writes, package versions and run metadata next to every result."""

from __future__ import annotations

import functools
import json
import math
import os
import platform
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import asdict, is_dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from needletissue.errors import InputError

# every package that shapes a number, mesh or file (pyproject's dependencies, plus MKL under
# pypardiso and llvmlite under numba); tests/test_runinfo.py checks the list covers pyproject.toml
_PACKAGES = (
    "numpy", "scipy", "felupe", "tensortrax", "gmsh", "meshio", "pyvista", "vtk", "SimpleITK", "nibabel",
    "pydicom", "scikit-image", "matplotlib", "dask", "distributed", "pydantic", "pandas", "pyarrow",
    "pyamg", "pypardiso", "mkl", "pymetis", "ipctk", "tetgen", "numba", "llvmlite", "threadpoolctl", "tomli_w",
    "typer", "rich",
)


def versions() -> dict[str, str]:
    """Installed versions of the packages that shape a result, and the BLAS/LAPACK libraries loaded."""
    from needletissue import __version__

    out = {"python": sys.version.split()[0], "platform": platform.platform(), "needletissue": __version__}
    for name in _PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    blas = _blas_libraries()
    if blas:
        out["blas"] = blas
    return out


def _blas_libraries() -> str:
    """e.g. "openblas 0.3.27 (openmp); mkl 2024.1": which libraries the solves ran on."""
    try:
        from threadpoolctl import threadpool_info

        seen = []
        for lib in threadpool_info():
            if lib.get("user_api") != "blas":
                continue
            item = f"{lib.get('internal_api')} {lib.get('version') or '?'}"
            if lib.get("threading_layer") not in (None, "unknown"):
                item += f" ({lib['threading_layer']})"
            if item not in seen:
                seen.append(item)
        return "; ".join(seen)
    except Exception:  # a record must never fail a run
        return ""


@functools.lru_cache(maxsize=1)
def _git_state() -> tuple[str | None, bool | None]:
    """(commit, dirty) of the checkout the package runs from, or (None, None) when it is installed."""
    import subprocess

    src = Path(__file__).resolve().parent
    try:
        top = subprocess.run(["git", "-C", str(src), "rev-parse", "--show-toplevel"], capture_output=True,
                             text=True, timeout=5)
        if top.returncode != 0 or (Path(top.stdout.strip()) / "src" / "needletissue").resolve() != src:
            return None, None
        head = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=5)
        dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5)
        return (head.stdout.strip() or None), (bool(dirty.stdout.strip()) if dirty.returncode == 0 else None)
    except (OSError, subprocess.SubprocessError):
        return None, None


def run_record() -> dict:
    """When, by which command and from which source a result was made."""
    import datetime
    import shlex

    commit, dirty = _git_state()
    argv = [Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python", *sys.argv[1:]]
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "command": shlex.join(argv), "git_commit": commit, "git_dirty": dirty}


def version_record() -> dict:
    """versions.json: the package versions (top level, as before) and the run record under "run"."""
    return {**versions(), "run": run_record()}


def to_jsonable(obj):
    """Dataclasses, NumPy arrays and scalars, Paths -> plain JSON types (NaN and +-inf -> null)."""
    if is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float) and not math.isfinite(obj):  # JSON has no NaN or Infinity
        return None
    return obj


def _unwritable(path, exc: OSError) -> InputError:
    where = f" ({exc.filename})" if exc.filename and str(exc.filename) != str(path) else ""
    return InputError(str(path), f"cannot write here: {exc.strerror or exc}{where}")


def make_dir(path: str | Path) -> Path:
    """mkdir -p; an output folder that cannot be made is the user's input error, not a traceback."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise InputError(str(path), "cannot write here: exists and is not a folder") from None
    except OSError as exc:
        raise _unwritable(path, exc) from None
    return path


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux /proc), else set+restore."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_output_dir(path: str | Path, field: str = "--out") -> Path:
    """Refuse, before anything is computed or written, an output folder that cannot be written: a file,
    or a folder (or, when absent, its nearest existing parent) in which no folder can be made (read-only
    permissions or file system). The check makes and removes an empty probe folder; it leaves nothing."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(field, f"{path} exists and is not a folder")
    probe = path
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise InputError(field, f"{path}: {probe} is not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".needletissue-probe-", dir=probe))
    except OSError as exc:
        raise InputError(field, f"{path}: cannot write in {probe}: {exc.strerror or exc}") from None
    return path


def write_atomic(path: str | Path, data: bytes | str) -> Path:
    """Write to a temporary file in the same folder, then rename: never a half-written file.

    The file gets the mode an ordinary ``open()`` would give (0666 minus the umask), not mkstemp's 0600,
    so colleagues and web servers can read the reports and figures when the umask lets them."""
    path = Path(path)
    make_dir(path.parent)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise _unwritable(path, exc) from None
    if isinstance(data, str):
        data = data.encode("utf-8")  # reports carry mu, minus signs: never the locale's codec
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


# zlib level of the VTU files: 1 writes a paper-scale result (1.35 M tets, whole mesh and blocks) in 7.0 s instead
# of meshio's level 6 at 12.0 s, 350 against 347 MB (float64 fields compress little at any level; docs/bench.md)
VTU_ZLIB_LEVEL = 1


def write_vtu(path: str | Path, points, cells, point_data: dict | None = None, cell_data: dict | None = None,
              field_data: dict | None = None) -> Path:
    """A tetrahedral mesh as VTU (binary inline base64 blocks, zlib at VTU_ZLIB_LEVEL) by VTK's own XML
    writer: `cells` (n, 4) or (n, 10) in VTK's node order, point and cell arrays by name, `field_data` one
    value per name (ParaView: Information panel). Written to a hidden partial file, synced and renamed
    (mode from the umask, never half a file). VTK releases the GIL while it compresses, so several files
    can be written on threads side by side; meshio reads the result as fast as its own."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkDoubleArray, vtkIntArray, vtkPoints
    from vtkmodules.vtkCommonDataModel import VTK_QUADRATIC_TETRA, VTK_TETRA, vtkCellArray, vtkUnstructuredGrid
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridWriter

    keep = []  # the NumPy arrays VTK reads without copying, alive until written

    def array(values, name=None):
        a = np.ascontiguousarray(values)
        if a.dtype == bool:  # VTK has no bool array NumPy can share: 0 / 1 bytes
            a = a.view(np.uint8)
        keep.append(a)
        out = numpy_to_vtk(a, deep=False)
        if name is not None:
            out.SetName(name)
        return out

    path = Path(path)
    grid = vtkUnstructuredGrid()
    pts = vtkPoints()
    pts.SetData(array(np.asarray(points, float)))
    grid.SetPoints(pts)
    cells = np.asarray(cells, np.int64)
    connectivity = vtkCellArray()
    connectivity.SetData(array(np.arange(0, cells.size + 1, cells.shape[1], dtype=np.int64)), array(cells.ravel()))
    grid.SetCells(VTK_TETRA if cells.shape[1] == 4 else VTK_QUADRATIC_TETRA, connectivity)
    for name, values in (point_data or {}).items():
        grid.GetPointData().AddArray(array(values, name))
    for name, values in (cell_data or {}).items():
        grid.GetCellData().AddArray(array(values, name))
    for name, value in (field_data or {}).items():
        a = vtkIntArray() if isinstance(value, (int, np.integer)) else vtkDoubleArray()
        a.SetName(name)
        a.InsertNextValue(value)
        grid.GetFieldData().AddArray(a)
    make_dir(path.parent)
    tmp = path.with_name(f".{path.stem}.partial.vtu")
    try:
        writer = vtkXMLUnstructuredGridWriter()
        writer.SetInputData(grid)
        writer.SetFileName(str(tmp))
        writer.SetDataModeToBinary()  # inline base64 blocks: meshio reads VTK's appended raw data 10x slower
        writer.SetCompressorTypeToZLib()
        writer.SetCompressionLevel(VTU_ZLIB_LEVEL)
        writer.SetHeaderTypeToUInt64()
        if not writer.Write() or writer.GetErrorCode():
            from vtkmodules.vtkCommonMisc import vtkErrorCode

            raise OSError(f"{path}: VTK could not write it "
                          f"({vtkErrorCode.GetStringFromErrorCode(writer.GetErrorCode())})")
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


@contextmanager
def staged_output(out_dir: str | Path, replaces: str | None = None):
    """A hidden folder inside out_dir to write a run's files into (yielded); when the block ends without
    an exception its entries are moved into out_dir (folders and VTUs first, results.json last). On any
    exception (SIGTERM, Ctrl-C, a failure) the folder is removed instead, with out_dir when this made it
    and nothing else is in it: a stopped run leaves out_dir as it was, not half a set of files.

    `replaces`: a regular expression of entry names the run owns (e.g. per-force VTUs); entries of
    out_dir matching it that this run did not write (an earlier run's other forces) are removed."""
    import re
    import shutil

    out_dir = Path(out_dir)
    made = not out_dir.exists()
    make_dir(out_dir)
    try:
        stage = Path(tempfile.mkdtemp(prefix=".partial-", dir=out_dir))
    except OSError as exc:
        raise _unwritable(out_dir, exc) from None
    try:
        os.chmod(stage, 0o777 & ~current_umask())
        yield stage
        new = {p.name for p in stage.iterdir()}
        if replaces:
            for old in out_dir.iterdir():
                if old.name not in new and re.fullmatch(replaces, old.name):
                    _remove(old)
        rank = {".vtu": 1, ".vtm": 2, ".pvd": 3, ".json": 5}
        for p in sorted(stage.iterdir(), key=lambda p: (0 if p.is_dir() else rank.get(p.suffix, 4),
                                                        p.name == "results.json", p.name)):
            dest = out_dir / p.name
            if p.is_dir() and dest.is_dir() and not dest.is_symlink():
                old = dest.with_name(f".{dest.name}.old-{os.getpid()}")
                os.replace(dest, old)
                os.replace(p, dest)
                _remove(old)
                continue
            if (dest.exists() or dest.is_symlink()) and (p.is_dir() or (dest.is_dir() and not dest.is_symlink())):
                _remove(dest)  # a folder over a file, or a file over a folder: os.replace cannot
            os.replace(p, dest)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        if made and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise
    shutil.rmtree(stage, ignore_errors=True)


def _remove(path: Path) -> None:
    import shutil

    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


def save_figure(fig, path: str | Path, dpi: int = 150) -> Path:
    """Save a Matplotlib figure atomically, format from the suffix (png when none)."""
    import io

    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lstrip(".") or "png", dpi=dpi)
    return write_atomic(path, buf.getvalue())


def relocate(obj, root: str | Path):
    """JSON data with every absolute path inside ``root`` made relative to it (POSIX form, "." for
    root itself), so a result folder can be copied, moved or shared: a path in a file is relative to
    the folder holding that file. Paths outside ``root`` (inputs such as a CT) stay as they were."""
    root = Path(os.path.realpath(root))

    def one(v):
        if isinstance(v, dict):
            return {k: one(x) for k, x in v.items()}
        if isinstance(v, list):
            return [one(x) for x in v]
        if isinstance(v, str) and v.startswith(os.sep) and len(v) < 4096:
            p = Path(os.path.realpath(v))
            if p == root or root in p.parents:
                return p.relative_to(root).as_posix() or "."
        return v

    return one(to_jsonable(obj))


def write_json(path: str | Path, obj) -> Path:
    """JSON, atomically; paths inside the file's folder written relative to it (relocatable)."""
    path = Path(path)
    return write_atomic(path, json.dumps(relocate(obj, path.parent), indent=2) + "\n")


def write_run_files(out_dir: str | Path, config, results) -> None:
    """The three files every run leaves: resolved config (TOML), versions and results (JSON).
    Paths inside out_dir are written relative to it (see `relocate`)."""
    import tomli_w

    out_dir = Path(out_dir)
    cfg = relocate(config, out_dir)
    write_atomic(out_dir / "config.toml", tomli_w.dumps(_drop_none(cfg)))
    write_json(out_dir / "versions.json", version_record())
    write_json(out_dir / "results.json", results)


def _drop_none(obj):
    if isinstance(obj, dict):
        return {k: _drop_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_drop_none(v) for v in obj]
    return obj


def read_toml(path: str | Path, field: str = "--config") -> dict:
    """A TOML file as a dict; a missing, unreadable or malformed file is an InputError naming it."""
    import tomllib

    path = Path(path)
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(field, f"no such file: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(str(path), f"cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(str(path), f"not valid TOML: {exc}") from None


def dataclass_from(cls, data: dict, where: str = "--config"):
    """Build dataclass `cls` from a TOML/JSON table (as config.toml holds it): nested dataclass fields
    from sub-tables, lists to tuples where the field's default is a tuple; an unknown key is an
    InputError naming it and the allowed ones (a typo must not silently fall back to a default)."""
    import dataclasses
    import typing

    if not isinstance(data, dict):
        raise InputError(where, f"expected a table, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise InputError(f"{where}: {unknown[0]}", f"unknown field; allowed: {', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    kw = {}
    for name, value in data.items():
        hint = hints.get(name)
        if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, dict):
            value = dataclass_from(hint, value, f"{where}: {name}")
        elif isinstance(value, list) and isinstance(fields[name].default, tuple):
            value = tuple(value)
        elif isinstance(value, list) and typing.get_origin(hint) is tuple:
            value = tuple(value)
        kw[name] = value
    try:
        return cls(**kw)
    except TypeError as exc:
        raise InputError(where, str(exc)) from None


def ignore_sigpipe() -> None:
    """Before talking to a child process through a pipe: native libraries (ITK, VTK) may reset SIGPIPE to
    its default, and a child that died (or was stopped before reading) then killed this process through
    the closed pipe instead of raising an error. Main thread only (where Python sets handlers)."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, signal.SIG_IGN)
