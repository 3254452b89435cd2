"""Graded smooth tissue interfaces: CGAL Mesh_3 on the label map with a size field.

The smooth route's surface nets (geometry.smooth) make every interface triangle one voxel wide, so a mesh
of the model's crop at 3 mm is ~630 k tetrahedra. CGAL's labelled-image mesher (Mesh_3,
`create_labeled_image_mesh_domain`) places the tissue interfaces on the label map's isosurfaces with
triangles as large as a size field allows: 3 mm at the needles' corridor growing to the far size, the
surface within a fraction of the local size of the labels' boundary. Its interface triangles replace the
surface nets in the PLC that TetGen meshes with the exact needles and clamp (smooth.smooth_tet_mesh), so
the rest of the route (optimisation, relocation, sliver removal, cortex) is unchanged.

CGAL's labelled-image domain with a size field has no Python binding on PyPI (the `cgal` wheels expose
polyhedral domains only; pygalmesh takes one size per label), so a 90-line C++ program
(`cgal_labels_mesh.cpp`, beside this file) is compiled on first use against the system's CGAL headers
(Debian / Ubuntu: `apt-get install libcgal-dev`; CGAL >= 5.5, header-only, links GMP and MPFR) and
kept in ~/.cache/needletissue/bin ($NEEDLETISSUE_BIN_CACHE), keyed by its source, the compiler and the CGAL
version.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, NeedleTissueError

SOURCE = Path(__file__).with_name("cgal_labels_mesh.cpp")
CXX_ENV = "CXX"
FACET_ANGLE = 25.0        # degrees: CGAL's lower bound on interface triangle angles
RADIUS_EDGE = 3.0         # CGAL's cell radius-edge bound (TetGen re-meshes the volume: only the surface is kept)
FACET_DISTANCE = 0.2      # x the local edge size: how far an interface triangle may lie from the label boundary
SEED = 0
INSTALL_HINT = ("the graded smooth mesher needs a C++ compiler and CGAL's headers (Debian / Ubuntu: "
                "`apt-get install g++ libcgal-dev`), or a uniform mesh: far_size equal to mesh_size "
                "(`--far-size` = `--mesh-size`), or `--mesher box`")


class MissingCGAL(NeedleTissueError, RuntimeError):
    """The graded mesher's helper cannot be built here (no compiler or no CGAL headers)."""


def _run(cmd, **kw):
    try:
        return subprocess.run(cmd, capture_output=True, text=True, **kw)
    except OSError as exc:
        raise MissingCGAL(f"{cmd[0]}: {exc.strerror}; {INSTALL_HINT}") from None


def cgal_version(cxx: str | None = None) -> str:
    """CGAL_VERSION of the headers the compiler finds; MissingCGAL when there are none."""
    cxx = cxx or os.environ.get(CXX_ENV, "g++")
    if shutil.which(cxx) is None:
        raise MissingCGAL(f"no C++ compiler {cxx!r} on PATH; {INSTALL_HINT}")
    r = _run([cxx, "-std=c++17", "-E", "-dM", "-include", "CGAL/version.h", "-x", "c++", os.devnull])
    for line in r.stdout.splitlines():
        if line.startswith("#define CGAL_VERSION "):
            return line.split(None, 2)[2].strip()
    raise MissingCGAL(f"no CGAL headers found by {cxx}; {INSTALL_HINT}")


BIN_CACHE_ENV = "NEEDLETISSUE_BIN_CACHE"   # folder of compiled helpers (default ~/.cache/needletissue/bin)
_HELPERS: dict[str, Path] = {}


def bin_cache_dir() -> Path:
    env = os.environ.get(BIN_CACHE_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "needletissue" / "bin"


def helper() -> Path:
    """The compiled helper: from the helper cache (bin_cache_dir, keyed by the source, the compiler and the
    CGAL version; an entry whose bytes fail their checksum is built again), else compiled now (~35 s) and
    stored there; where the cache cannot be written, this process's own copy in a temporary folder."""
    from needletissue.cache import cache_key, read_entry, write_entry
    from needletissue.runinfo import current_umask

    cxx = os.environ.get(CXX_ENV, "g++")
    version = cgal_version(cxx)
    compiler = _run([cxx, "--version"]).stdout.splitlines()[:1]
    key = cache_key({"cgal": version, "compiler": compiler, "cxx": cxx}, (SOURCE,))
    if key in _HELPERS and os.access(_HELPERS[key], os.X_OK):
        return _HELPERS[key]
    folder, name = bin_cache_dir(), f"cgal_labels_mesh-{key}"
    exe = folder / name
    if read_entry(folder, name, "") is None or not os.access(exe, os.X_OK):
        built = Path(tempfile.mkdtemp(prefix="needletissue-cgal-")) / "cgal_labels_mesh"
        r = _run([cxx, "-O2", "-DNDEBUG", "-std=c++17", str(SOURCE), "-o", str(built), "-lgmp", "-lmpfr", "-lpthread"])
        if r.returncode != 0:
            shutil.rmtree(built.parent, ignore_errors=True)
            raise MissingCGAL(f"compiling {SOURCE.name} against CGAL {version} failed:\n{r.stderr[-2000:]}\n"
                              f"{INSTALL_HINT}")
        ok = write_entry(folder, name, "", built.read_bytes(), {"cgal": version, "compiler": compiler})
        if ok:
            try:   # an executable, readable as the umask allows
                os.chmod(exe, 0o777 & ~current_umask())
            except OSError:   # a cache that cannot be written: this process's copy
                ok = False
        if ok:
            shutil.rmtree(built.parent, ignore_errors=True)
        else:
            os.chmod(built, 0o777 & ~current_umask())
            exe = built
    _HELPERS[key] = exe
    return exe


def size_field(arr: np.ndarray, spacing, focus: int, size: float, far_size: float, radius: float) -> np.ndarray:
    """Element size per voxel (mm): `size` on the voxels labelled `focus` (the needles' corridor), growing
    linearly with the distance from them to `far_size` at `radius` mm and beyond (the box mesher's law)."""
    from scipy import ndimage

    d = ndimage.distance_transform_edt(arr != focus, sampling=np.asarray(spacing, float)[::-1])
    return np.clip(size + (far_size - size) * d / radius, size, far_size).astype(np.float32)


def drop_small_components(arr: np.ndarray, spacing, size: np.ndarray, keep=(), factor: float = 1.0):
    """The label array with every connected piece (6-connected) smaller than `factor` x its local size cubed
    given to the nearest voxel outside such pieces; each label's largest piece, the labels in `keep` and
    the outside (0) that touches the array's border stay. A piece smaller than one element cannot be meshed
    at that size, and CGAL meshes every piece it is given. Returns (array, number of voxels changed)."""
    from scipy import ndimage

    vox = float(np.prod(spacing))
    small = np.zeros(arr.shape, bool)
    for lab in np.unique(arr):
        if lab in keep:
            continue
        comp, n = ndimage.label(arr == lab)
        if n <= 1 and lab != 0:
            continue
        idx = np.arange(1, n + 1)
        count = np.bincount(comp.ravel(), minlength=n + 1)[1:]
        h = np.asarray(ndimage.minimum(size, comp, idx), float)
        drop = count * vox < factor * h ** 3
        if lab == 0:   # the outside: every piece that reaches the border stays
            border = np.unique(np.concatenate([np.unique(f) for f in (comp[0], comp[-1], comp[:, 0], comp[:, -1],
                                                                        comp[:, :, 0], comp[:, :, -1])]))
            drop[border[border > 0] - 1] = False
        else:
            drop[np.argmax(count)] = False
        if drop.any():
            small |= np.isin(comp, idx[drop])
    if not small.any():
        return arr, 0
    near = ndimage.distance_transform_edt(small, return_distances=False, return_indices=True)
    out = arr[tuple(near)]
    return out, int(small.sum())


def mesh_labels(arr: np.ndarray, spacing, cell_size: np.ndarray, facet_size: np.ndarray | None = None,
                facet_distance: float = FACET_DISTANCE):
    """CGAL Mesh_3 of a label array (z, y, x; 0 outside, labels 1..255) in grid coordinates (index *
    spacing, x y z). Sizes are edge lengths (mm; CGAL bounds circumradii: a regular tetrahedron's is
    sqrt(6)/4 of its edge, an equilateral triangle's 1/sqrt(3)); facet_distance: how far an interface
    triangle may lie from the label boundary, x its edge size. Returns (points, cells, labels, info)."""
    if np.asarray(arr).size and (np.min(arr) < 0 or np.max(arr) > 255):
        raise InputError("labels", f"labels must be 0..255 (one byte), got {np.min(arr)}..{np.max(arr)}")
    arr = np.ascontiguousarray(arr, np.uint8)
    if arr.ndim != 3 or min(arr.shape) < 2 or not arr.any():
        raise InputError("labels", f"expected a 3D label array with a labelled voxel, got shape {arr.shape}")
    cell_size = np.ascontiguousarray(cell_size, np.float32)
    facet_size = cell_size if facet_size is None else np.ascontiguousarray(facet_size, np.float32)
    if cell_size.shape != arr.shape or facet_size.shape != arr.shape or not (cell_size > 0).all():
        raise InputError("cell_size", "size fields must be positive and of the label array's shape")
    exe = helper()
    with tempfile.TemporaryDirectory(prefix="needletissue-cgal-") as td:
        inp, out = Path(td, "in.bin"), Path(td, "out.bin")
        with open(inp, "wb") as f:
            np.asarray(arr.shape[::-1], np.int64).tofile(f)
            np.asarray([*np.asarray(spacing, float), FACET_ANGLE, facet_distance * np.sqrt(3), RADIUS_EDGE, SEED], float).tofile(f)
            arr.tofile(f)
            (cell_size * np.float32(np.sqrt(6) / 4)).tofile(f)
            (facet_size / np.float32(np.sqrt(3))).tofile(f)
        t0 = time.perf_counter()
        r = _run([str(exe), str(inp), str(out)])
        wall = time.perf_counter() - t0
        if r.returncode != 0:
            raise NeedleTissueError(f"CGAL Mesh_3 failed (exit {r.returncode}): {r.stderr[-2000:]}")
        raw = out.read_bytes()
    n_pts, n_cells = np.frombuffer(raw, np.int64, 2)
    o = 16
    points = np.frombuffer(raw, np.float64, 3 * n_pts, o).reshape(-1, 3).copy()
    o += 24 * n_pts
    cells = np.frombuffer(raw, np.int32, 4 * n_cells, o).reshape(-1, 4).astype(np.int64)
    labels = np.frombuffer(raw, np.int32, n_cells, o + 16 * n_cells).astype(np.int64)
    return points, cells, labels, {"cgal_tets": int(n_cells), "cgal_wall_s": wall, "cgal_version": cgal_version()}


def graded_interfaces(arr: np.ndarray, spacing, cell_size: np.ndarray, facet_size: np.ndarray | None = None,
                      facet_distance: float = FACET_DISTANCE, flat=None, volumes: np.ndarray | None = None,
                      fixed_labels=(), restore: bool = True):
    """Every tissue interface of a label array as one conforming triangle set (smooth.InterfaceSurfaces),
    graded by the size fields: the faces between CGAL's tetrahedra of different labels and those on the
    domain's boundary (label 0 beyond). The array is padded by one empty voxel so that its labels close.
    flat: (lo, hi) voxel index ranges (x, y, z) of the crop whose cut planes are put exactly on their plane
    (CGAL finds them to ~1e-4 mm; default the array's).
    restore: the interfaces are then offset along their normals until each label encloses `volumes[label]`
    (mm^3; default its voxels'; smooth.restore_volumes): triangles larger than the label map's folds cut
    them off, and a thin, folded tissue loses volume (the CT's body wall: -4.5 %, and -1.1 % more where
    pieces smaller than an element were merged). Vertices on the cut planes and on the faces of
    `fixed_labels` (the needles' corridor, whose volume is left as CGAL makes it) stay."""
    from needletissue.geometry.smooth import InterfaceSurfaces, label_volumes, restore_volumes
    from needletissue.geometry.tetmesh import face_pairs

    sp = np.asarray(spacing, float)
    pad = lambda a: np.pad(a, 1, mode="edge")   # noqa: E731  (sizes at the pad: the border's)
    points, cells, labels, info = mesh_labels(np.pad(arr, 1), sp, pad(cell_size),
                                              None if facet_size is None else pad(facet_size), facet_distance)
    points -= sp                                  # back to the unpadded grid
    lo, hi = (np.zeros(3), np.asarray(arr.shape[::-1], float)) if flat is None else np.asarray(flat, float)
    on_plane = np.zeros(len(points), bool)
    for plane in ((lo - 0.5) * sp, (hi - 0.5) * sp):   # the crop's cut faces: flat to the bit, as supports need
        near = np.abs(points - plane) < 0.01 * sp
        points[near] = np.broadcast_to(plane, points.shape)[near]
        on_plane |= near.any(1)
    inter, free, faces, two = face_pairs(cells, labels, pairs=True)
    nc = len(cells)
    partner = np.full(len(faces), -1)
    partner[two[:, 0]], partner[two[:, 1]] = two[:, 1], two[:, 0]
    bnd = np.concatenate([inter, free])
    side_a = labels[bnd % nc]
    side_b = np.where(partner[bnd] >= 0, labels[partner[bnd] % nc], 0)
    used, inv = np.unique(faces[bnd], return_inverse=True)
    tri = inv.reshape(-1, 3)
    pts = points[used]
    # orient each face out of side a (label_volumes' convention): its normal away from its cell's centroid
    c = points[cells[bnd % nc]].mean(1)
    t = pts[tri]
    flip = np.einsum("ij,ij->i", np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), t[:, 0] - c) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    bl = np.stack([side_a, side_b], 1)
    target = np.bincount(arr.ravel(), minlength=256) * float(np.prod(sp)) if volumes is None else np.asarray(volumes)
    present = np.flatnonzero(target[1:] > 0) + 1
    vol = label_volumes(pts, tri, bl)
    info["volume_change_cgal"] = {int(k): float(vol[k] / target[k] - 1) for k in present}
    if restore:
        fixed = on_plane[used]
        fixed[tri[np.isin(bl, fixed_labels).any(1)].ravel()] = True
        before, pts = pts, restore_volumes(pts, tri, bl, target, fixed, fixed_labels=fixed_labels)
        info["max_restore_move_mm"] = float(np.linalg.norm(pts - before, axis=1).max())
        vol = label_volumes(pts, tri, bl)
    info.update({"n_points": int(len(pts)), "n_triangles": int(len(tri)),
                 "volume_change_final": {int(k): float(vol[k] / target[k] - 1) for k in present}})
    return InterfaceSurfaces(points=pts, faces=tri, boundary_labels=bl, info=info)
