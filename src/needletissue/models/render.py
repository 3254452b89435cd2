"""Static (PNG) renders of a model result that a reader can read: bone opaque, soft tissue translucent,
needles and clamp coloured by |u|, the undeformed needle axes and clamp outline, the force arrow with its
magnitude, an axes triad with the coordinate frame, and the colour bar in its own column beside the model
(never over it). Off-screen PyVista; callers run it in a child process (a VTK crash costs a picture).

The scene comes from a result VTU (fem.result.FEResult.write_vtu: region tags in cell data, region and
material names, frame and force in field-data array names) or from the same arrays in memory."""

from __future__ import annotations

import io
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from needletissue.runinfo import ignore_sigpipe, write_atomic

BONE_COLOUR = "#e8dcc0"  # ivory: reads as bone and stays distinct from the viridis map
OUTLINE_COLOUR = "#555555"
ARROW_COLOUR = "#d62728"
TISSUE_OPACITY = 0.18  # enough to see the tissue's shape and colour, little enough to see the bone through it
SIDE = 0.24  # width of the side column (colour bar, legend, axes) as a fraction of the window


def offscreen(env=os.environ):
    """Set `env` (a mapping: os.environ or a child's) for off-screen PyVista. Without a display VTK 9.4+
    tries X first and prints "bad X server connection" before it falls back to EGL: ask for EGL
    directly when the library is there (forcing a window class VTK cannot load would fail instead)."""
    import ctypes.util

    env.setdefault("PYVISTA_OFF_SCREEN", "true")
    env.setdefault("MPLBACKEND", "Agg")
    if not env.get("DISPLAY") and not env.get("WAYLAND_DISPLAY") and ctypes.util.find_library("EGL"):
        env.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    return env


@dataclass
class RenderScene:
    """What a static render shows besides the mesh. Vectors in the mesh's frame (mm).

    title          : first line of the picture (model and force)
    force_direction: the applied reduction force's direction (normalised here)
    needle_axis    : along the needles, out of the bone; the view looks across the needles and the force
    load_point_mm  : where the force acts (undeformed); None: the clamp's centre
    scale          : deformation scale factor (1 = true scale)
    frame          : the coordinate frame's name; None: the VTU's "coordinate frame: ..." field data
    axis_labels    : labels of the triad's x, y, z arrows; None: from the frame ("x (R)" ... in RAS, LPS)
    focus_steel    : frame the view on the needles and clamp (with context around them) instead of the
                     whole model (the anatomy is large beside the needle site)
    cut            : tissue cut in the plane of the needles and the force, the far half drawn opaque (its cut
                     face shows the tissue's |u| around the needles), instead of a translucent skin
    """

    title: str
    force_direction: tuple[float, float, float]
    needle_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    load_point_mm: tuple[float, float, float] | None = None
    scale: float = 1.0
    frame: str | None = None
    axis_labels: tuple[str, str, str] | None = None
    focus_steel: bool = False
    cut: bool = False


@dataclass
class Regions:
    """Cell groups of the mesh by how they are drawn: names -> region tags."""

    names: dict[int, str]
    materials: dict[int, str]

    def kind(self, tag: int) -> str:
        """'steel' (needles, clamp), 'bone' (a bone material) or 'tissue'."""
        name, mat = self.names.get(tag, str(tag)), self.materials.get(tag, "")
        if name.startswith(("needle", "clamp")) or mat in ("needle", "clamp"):
            return "steel"
        if "bone" in mat or "bone" in name:
            return "bone"
        return "tissue"


_REGION = re.compile(r"^region (-?\d+) = (.+?)(?: \(material (.+)\))?$")


def regions_from_field_data(names) -> Regions:
    """Region and material names from the field-data array names FEResult.write_vtu writes."""
    reg, mat = {}, {}
    for n in names:
        m = _REGION.match(n)
        if m:
            reg[int(m[1])] = m[2]
            if m[3]:
                mat[int(m[1])] = m[3]
    return Regions(reg, mat)


def frame_from_field_data(names) -> str:
    return next((n.removeprefix("coordinate frame: ") for n in names if n.startswith("coordinate frame: ")), "")


def read_vtu(vtu):
    """(linear grid with point 'displacement' and cell 'region', Regions, frame, force_N or None)."""
    import pyvista as pv

    grid = pv.read(str(vtu))
    keys = list(grid.field_data.keys())
    force = float(np.asarray(grid.field_data["force_N"]).ravel()[0]) if "force_N" in keys else None
    return _linear(grid), regions_from_field_data(keys), frame_from_field_data(keys), force


def grid_from_arrays(points, cells, displacement, region):
    """A PyVista grid of the mesh (tet4 or tet10 cells) with 'displacement' and 'region'."""
    import pyvista as pv

    cells = np.asarray(cells)
    ctype = pv.CellType.QUADRATIC_TETRA if cells.shape[1] == 10 else pv.CellType.TETRA
    conn = np.hstack([np.full((len(cells), 1), cells.shape[1]), cells]).ravel()
    grid = pv.UnstructuredGrid(conn, np.full(len(cells), ctype, np.uint8), np.asarray(points, float))
    grid.point_data["displacement"] = np.asarray(displacement, float)
    grid.cell_data["region"] = np.asarray(region)
    return _linear(grid)


def _linear(grid):
    """Linear tetrahedra on the corner nodes (VTK orders them first), with the same data. Built anew:
    PyVista's linear_copy keeps ten ids per cell, and VTK filters on such cells crashed here; the midside
    nodes add nothing a picture can show at this size."""
    import pyvista as pv

    if grid.celltypes.max() <= pv.CellType.TETRA:
        return grid
    corners = np.asarray(grid.cells_dict[pv.CellType.QUADRATIC_TETRA])[:, :4]
    out = pv.UnstructuredGrid({pv.CellType.TETRA: corners}, np.asarray(grid.points))
    for k in grid.point_data.keys():
        out.point_data[k] = grid.point_data[k]
    for k in grid.cell_data.keys():
        out.cell_data[k] = grid.cell_data[k]
    return out


@dataclass
class Built:
    """An off-screen plotter holding the scene (not rendered yet) and the caption that describes it."""

    plotter: object
    caption: str


def build(grid, regions: Regions, scene: RenderScene, force_N: float, frame: str = "",
          window_size=(1400, 1000)) -> Built:
    """The scene on an off-screen plotter: tests inspect it, render() saves it."""
    offscreen()
    import pyvista as pv

    grid = grid.copy()
    u = np.asarray(grid.point_data["displacement"], float)
    grid.point_data["|u| (mm)"] = np.linalg.norm(u, axis=1)
    tag = np.asarray(grid.cell_data["region"]).astype(int)
    kinds = {t: regions.kind(t) for t in np.unique(tag)}
    ids = {k: np.flatnonzero(np.isin(tag, [t for t, kk in kinds.items() if kk == k]))
           for k in ("steel", "bone", "tissue")}

    def surface(cell_ids, warp=True):
        s = grid.extract_cells(cell_ids).extract_surface(algorithm="dataset_surface")
        return s.warp_by_vector("displacement", factor=scene.scale) if warp else s

    clim = (0.0, float(grid.point_data["|u| (mm)"].max()) or 1.0)
    pl = pv.Plotter(off_screen=True, window_size=window_size, shape=(1, 2), col_weights=[1 - SIDE, SIDE],
                    border=False)
    pl.subplot(0, 0)
    colour = dict(scalars="|u| (mm)", cmap="viridis", clim=clim, show_scalar_bar=False)
    mapper = None
    f = np.asarray(scene.force_direction, float)
    f /= np.linalg.norm(f)
    axis = np.asarray(scene.needle_axis, float)
    axis /= np.linalg.norm(axis)
    across = np.cross(axis, f)
    across = across / np.linalg.norm(across) if np.linalg.norm(across) > 1e-9 else _any_normal(axis)
    if len(ids["tissue"]):
        if scene.cut:
            # Cut in the plane of the needle and the force: the far half, opaque, shows on its cut face how
            # the tissue moves around the needles; the near half is left out so the bone is seen.
            # Whole cells by their centroid's side (VTK's clip filters segfaulted on these meshes here).
            origin = _steel_centre(grid, tag, regions)
            centres = np.asarray(grid.points)[_tets(grid)].mean(axis=1)
            far = ids["tissue"][(centres[ids["tissue"]] - origin) @ across < 0]
            a = pl.add_mesh(surface(far), opacity=0.85, name="tissue", **colour)
        else:
            skin = _outer_surface(grid, ids["tissue"]).warp_by_vector("displacement", factor=scene.scale)
            # unlit: on a jagged (voxel-derived) skin, shading every facet differently reads as shards
            a = pl.add_mesh(skin, opacity=TISSUE_OPACITY, lighting=False, name="tissue", **colour)
        mapper = a.mapper
    if len(ids["bone"]):
        pl.add_mesh(surface(ids["bone"]), color=BONE_COLOUR, name="bone", smooth_shading=False)
    steel_ref = None
    if len(ids["steel"]):
        a = pl.add_mesh(surface(ids["steel"]), name="needles_and_clamp", **colour)
        mapper = a.mapper
        steel_ref = surface(ids["steel"], warp=False)
    outline = _undeformed_outline(grid, tag, regions)
    if outline is not None:
        pl.add_mesh(outline, color=OUTLINE_COLOUR, line_width=2.5, name="undeformed_outline")

    focus = steel_ref.bounds if (scene.focus_steel and steel_ref is not None) else grid.bounds
    lo, hi = np.array(focus[::2]), np.array(focus[1::2])
    if scene.focus_steel:  # context around the needle site, within the model
        pad = 0.6 * (hi - lo).max()
        lo, hi = np.maximum(lo - pad, grid.bounds[::2]), np.minimum(hi + pad, grid.bounds[1::2])
    size = float(np.linalg.norm(hi - lo))
    load = _load_point(grid, tag, regions, scene)
    if load is not None:
        start = _moved_with_clamp(load, grid, tag, regions, scene.scale)
        length = 0.3 * size
        arrow = pv.Arrow(start=start, direction=f, scale=length, tip_length=0.2, tip_radius=0.06, shaft_radius=0.02)
        pl.add_mesh(arrow, color=ARROW_COLOUR, name="force_arrow")
        pl.add_point_labels(np.atleast_2d(start + 1.05 * length * f), [f"F = {force_N:g} N"], font_size=22,
                            text_color=ARROW_COLOUR, shape_color="white", shape_opacity=0.8,
                            always_visible=True, show_points=False, name="force_label")

    centre = 0.5 * (lo + hi)
    # Across the needles and the force (the bending shows in the picture's plane), turned 30 degrees
    # towards the force and tilted down the needles a little so that two needles do not hide each other.
    view = np.cos(np.radians(30)) * across - np.sin(np.radians(30)) * f + 0.35 * axis
    view /= np.linalg.norm(view)
    pl.camera_position = [tuple(centre + 3 * size * view), tuple(centre), tuple(axis)]
    pl.reset_camera(bounds=(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2]))
    frame = scene.frame if scene.frame is not None else frame
    labels = scene.axis_labels or _axis_labels(frame)
    pl.add_axes(viewport=(0.0, 0.0, 0.22, 0.26), xlabel=labels[0], ylabel=labels[1], zlabel=labels[2],
                line_width=3)

    pl.subplot(0, 1)
    pl.add_text(_wrap(scene.title, 26), position="upper_left", font_size=13, color="black", name="title")
    if mapper is not None:
        pl.add_scalar_bar("|u| (mm)", mapper=mapper, vertical=True, position_x=0.12, position_y=0.34,
                          width=0.22, height=0.38, title_font_size=18, label_font_size=15, n_labels=5,
                          fmt="%.3g", color="black")
    legend = [f"deformed x{scene.scale:g}" + (" (true scale)" if scene.scale == 1 else "")]
    said = []  # the same items in the caption, as sentences
    if len(ids["bone"]):
        legend.append("bone: opaque, ivory")
        said.append("bone opaque (ivory)")
    if len(ids["tissue"]):
        if scene.cut:
            legend.append("soft tissue: |u|, cut through the needles along the force (far half)")
            said.append("soft tissue coloured by |u| (mm), cut in the plane of the needles and the force "
                        "(the far half shown)")
        else:
            legend.append("soft tissue: translucent, |u|")
            said.append("soft tissue translucent, coloured by |u| (mm)")
    if len(ids["steel"]):
        legend.append("needles, clamp: |u|")
        said.append("needles and clamp coloured by |u| (mm)")
    if outline is not None:
        legend.append("grey lines: undeformed needle axes and clamp")
        said.append("grey lines: the undeformed needle axes and clamp")
    if load is not None:
        legend.append(f"red arrow: force {force_N:g} N")
        said.append(f"red arrow: the {force_N:g} N reduction force at its load point, along "
                    f"({f[0]:.2f}, {f[1]:.2f}, {f[2]:.2f})")
    legend.append("frame: " + frame)
    pl.add_text(_wrap("\n".join(legend), 30), position=(8, 12), font_size=10, color="black", name="legend")
    scale = "true scale" if scene.scale == 1 else f"displacements scaled x{scene.scale:g}"
    caption = (f"{scene.title}: deformed shape ({scale}); " + "; ".join(said)
               + (f". Frame: {frame}." if frame else "."))
    return Built(pl, caption)


def render(built: Built, png) -> Path:
    """Screenshot of a built scene, written atomically as a PNG with its caption in the PNG's
    "Description" text (report.html shows it under the figure; it travels with a shared PNG)."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo

    with freetype_text():
        img = built.plotter.screenshot(None, return_img=True)
    built.plotter.close()
    info = PngInfo()
    info.add_itxt("Description", built.caption)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="png", pnginfo=info)
    return write_atomic(png, buf.getvalue())


def render_vtu(vtu, png, scene: RenderScene) -> Path:
    """Render a result VTU (see module doc) to png."""
    grid, regions, frame, force = read_vtu(vtu)
    return render(build(grid, regions, scene, force if force is not None else float("nan"), frame), png)


def isolated(fn, *args):
    """Run fn(*args) in a fresh process: a crash in VTK's native code cannot take the caller down."""
    with Isolated(fn, *args) as job:
        return job.result()


class Isolated:
    """fn(*args) started now in a fresh process, so the caller works on meanwhile; `result()` waits for
    it. As a context: leaving it by an exception (or SIGTERM / Ctrl-C) stops the child at once."""

    def __init__(self, fn, *args):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        ignore_sigpipe()   # a dead worker: BrokenProcessPool, not a dead caller
        self.name = getattr(fn, "__name__", str(fn))
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"), initializer=_worker_start)
        self.future = self.pool.submit(fn, *args)

    def result(self):
        from concurrent.futures.process import BrokenProcessPool

        try:
            return self.future.result()
        except BrokenProcessPool:
            raise RuntimeError(f"{self.name} crashed (native code)") from None

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if (kind is not None and not issubclass(kind, Exception)) or not self.future.done():
            # SIGTERM / Ctrl-C, or the caller failed before waiting: stop the child now (waiting let it
            # finish and write its PNG into the output folder after the command had exited)
            stop_workers(self.pool)
        self.pool.shutdown(wait=True, cancel_futures=True)


def _worker_start():
    """In isolated()'s child: Ctrl-C, which reaches the whole process group, is the caller's to handle (it
    stops the child); the child printed a KeyboardInterrupt traceback of its own."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # and it dies with the process that started it, however that one ends (a `reproduce` stage worker
    # stopped with SIGTERM left it rendering on)
    import multiprocessing as mp

    parent = mp.parent_process()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # not Linux
        return
    if parent is not None and os.getppid() != parent.pid:  # the parent died before the line above
        os._exit(1)


def stop_workers(pool) -> None:
    """Terminate a ProcessPoolExecutor's processes (Python 3.14 has pool.terminate_workers())."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        p.terminate()
    for p in procs:
        p.join(5)
        if p.is_alive():
            p.kill()
            p.join(5)


def _axis_labels(frame: str) -> tuple[str, str, str]:
    """Anatomical directions on the triad's arrows when the frame is RAS or LPS."""
    if "RAS" in frame:
        return ("x (R)", "y (A)", "z (S)")
    if "LPS" in frame:
        return ("x (L)", "y (P)", "z (S)")
    return ("x", "y", "z")


class freetype_text:
    """VTK >= 9.3 sends any text with '|' to its MathText backend, which reads the bar as a column
    separator and drops it ("|u| (mm)" showed as "u (mm)"); FreeType draws the text as written."""

    def __enter__(self):
        import vtkmodules.vtkRenderingFreeType  # noqa: F401  (registers the text renderer)
        from vtkmodules.vtkRenderingCore import vtkTextRenderer

        self.tr = vtkTextRenderer.GetInstance()
        self.old = self.tr.GetDefaultBackend()
        self.tr.SetDefaultBackend(vtkTextRenderer.FreeType)
        return self

    def __exit__(self, *exc):
        self.tr.SetDefaultBackend(self.old)


def _wrap(text: str, width: int) -> str:
    import textwrap

    return "\n".join(textwrap.fill(line, width, subsequent_indent="  ") for line in text.splitlines())


def _any_normal(v):
    n = np.cross(v, (1.0, 0.0, 0.0))
    if np.linalg.norm(n) < 1e-6:
        n = np.cross(v, (0.0, 1.0, 0.0))
    return n / np.linalg.norm(n)


def _steel_cells(tag, regions, which):
    return np.flatnonzero(np.isin(tag, [t for t, n in regions.names.items() if n.startswith(which)]))


def _tets(grid) -> np.ndarray:
    """(n, 4) corner nodes of the linear grid's tetrahedra, in cell order."""
    return np.asarray(grid.cells).reshape(grid.n_cells, 5)[:, 1:]


def _steel_centre(grid, tag, regions):
    cells = _steel_cells(tag, regions, ("needle", "clamp"))
    return np.asarray((grid.extract_cells(cells) if len(cells) else grid).points).mean(axis=0)


def _load_point(grid, tag, regions, scene):
    if scene.load_point_mm is not None:
        return np.asarray(scene.load_point_mm, float)
    cells = _steel_cells(tag, regions, "clamp")
    if not len(cells):
        return None
    return np.asarray(grid.extract_cells(cells).points).mean(axis=0)


def _moved_with_clamp(point, grid, tag, regions, scale):
    """Where `point` goes when the clamp moves as a rigid body (the best-fit rotation and translation of
    its nodes, Kabsch): the load point rides on the steel clamp, which turns as the needles bend."""
    cells = _steel_cells(tag, regions, "clamp")
    if not len(cells):
        return np.asarray(point, float)
    clamp = grid.extract_cells(cells)
    p = np.asarray(clamp.points, float)
    q = p + scale * np.asarray(clamp.point_data["displacement"], float)
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - cp).T @ (q - cq))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return cq + rot @ (np.asarray(point, float) - cp)


def _outer_surface(grid, cell_ids):
    """The model's outer surface where it bounds the given cells (the skin and the model's cut faces):
    one translucent layer in front of the bone instead of every tissue interface stacked up (VTK draws
    translucent faces in mesh order off-screen, so stacked layers show as shards)."""
    surf = grid.extract_surface(algorithm="dataset_surface", pass_cellid=True)
    keep = np.isin(np.asarray(surf.cell_data["vtkOriginalCellIds"]), cell_ids)
    return surf.extract_cells(np.flatnonzero(keep)).extract_surface(algorithm="dataset_surface")


def _undeformed_outline(grid, tag, regions):
    """Lines of the undeformed steel: each needle's axis (principal axis of its nodes, end to end) and the
    clamp's feature edges."""
    import pyvista as pv

    parts = []
    for t, name in regions.names.items():
        cells = np.flatnonzero(tag == t)
        if not len(cells):
            continue
        sub = grid.extract_cells(cells)
        if name.startswith("needle"):
            p = np.asarray(sub.points)
            c = p.mean(axis=0)
            d = np.linalg.svd(p - c, full_matrices=False)[2][0]
            s = (p - c) @ d
            parts.append(pv.Line(c + s.min() * d, c + s.max() * d))
        elif name.startswith("clamp"):
            edges = sub.extract_surface(algorithm="dataset_surface").extract_feature_edges(
                feature_angle=30, boundary_edges=False, non_manifold_edges=False, manifold_edges=False)
            # the outer box (its edges are one connected piece, the widest), not the loops of the needle
            # holes through it
            pieces = list(edges.connectivity().split_bodies())
            if pieces:
                widest = max(pieces, key=lambda q: float(np.linalg.norm(np.ptp(np.asarray(q.points), axis=0))))
                parts.append(widest.extract_surface(algorithm=None))
    if not parts:
        return None
    return pv.merge(parts) if len(parts) > 1 else parts[0]
