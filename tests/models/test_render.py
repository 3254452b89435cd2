"""The static renders (models.render): the scene holds what a reader needs (opaque bone, tissue, needles
and clamp by |u|, the undeformed outline, the force arrow along the force at the load point, axes), the
colour bar reads "|u| (mm)" and sits clear of the model, and the PNG carries its caption."""

import os

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")

from needletissue.models.render import Regions, RenderScene, build, freetype_text, render  # noqa: E402

FORCE = np.array([0.0, 1.0, 0.0])


def _model():
    """A 20 x 20 x 40 mm block: bone below z = 8, muscle above, one needle column and a clamp slab on top;
    the needle bends along +y (u_y grows with z^2), the bone stays put."""
    from needletissue.fem import TaggedMesh

    m = TaggedMesh.box((20, 20, 40), (6, 6, 11))
    c = m.points[m.cells].mean(axis=1)
    tag = np.where(c[:, 2] < 8, 0, 1)  # bone, muscle
    tag[(np.abs(c[:, 0] - 10) < 4) & (np.abs(c[:, 1] - 10) < 4) & (c[:, 2] >= 8)] = 2  # needle_1
    tag[c[:, 2] >= 32] = 3  # clamp
    u = np.zeros_like(m.points)
    u[:, 1] = 5.0 * np.clip(m.points[:, 2] - 8, 0, None) ** 2 / 32**2
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: m.cells}, m.points)
    grid.point_data["displacement"] = u
    grid.cell_data["region"] = tag
    regions = Regions({0: "cortical_bone", 1: "muscle", 2: "needle_1", 3: "clamp"},
                      {0: "cortical_bone", 1: "muscle", 2: "needle", 3: "clamp"})
    return grid, regions


@pytest.fixture(scope="module")
def built():
    grid, regions = _model()
    b = build(grid, regions, RenderScene("Test block, 300 N", tuple(FORCE), (0, 0, 1)), 300.0, "test frame, mm")
    with freetype_text():
        b.plotter.screenshot(None, return_img=True)  # lays the scene out in the window
    yield grid, b
    b.plotter.close()


def test_scene_has_the_elements_a_reader_needs(built):
    grid, b = built
    model = b.plotter.renderers[0]
    assert {"bone", "tissue", "needles_and_clamp", "undeformed_outline", "force_arrow"} <= set(model.actors)
    assert model.actors["bone"].prop.opacity == 1.0 and model.actors["tissue"].prop.opacity < 0.5
    assert list(b.plotter.scalar_bars.keys()) == ["|u| (mm)"]
    assert b.plotter.scalar_bars["|u| (mm)"].GetTitle() == "|u| (mm)"
    assert "300 N" in b.caption and "true scale" in b.caption and "test frame" in b.caption


def test_force_arrow_points_along_the_force_from_the_displaced_clamp(built):
    grid, b = built
    arrow = b.plotter.renderers[0].actors["force_arrow"].mapper.dataset
    p = np.asarray(arrow.points)
    d = np.linalg.svd(p - p.mean(axis=0))[2][0]
    assert abs(d @ FORCE) > 0.999  # the arrow's long axis is the force's direction
    tip = p[np.argmax(p @ FORCE)]
    clamp = grid.extract_cells(np.flatnonzero(grid.cell_data["region"] == 3))
    start = np.asarray(clamp.points).mean(axis=0) + np.asarray(clamp.point_data["displacement"]).mean(axis=0)
    assert (tip - start) @ FORCE > 0
    assert np.linalg.norm(np.cross(tip - start, FORCE)) < 1e-6 * np.linalg.norm(tip - start) + 1e-6


def test_outline_is_the_undeformed_needle_axis_and_clamp(built):
    grid, b = built
    lines = np.asarray(b.plotter.renderers[0].actors["undeformed_outline"].mapper.dataset.points)
    clamp_lo = np.asarray(grid.extract_cells(np.flatnonzero(grid.cell_data["region"] == 3)).bounds)[::2]
    needle = np.asarray(grid.extract_cells(np.flatnonzero(grid.cell_data["region"] == 2)).points)
    axis = lines[lines[:, 2] < clamp_lo[2] - 1e-9]  # below the clamp: the needle's axis
    # where the needle stood (inside its undeformed cross-section), not where it went (up to 5 mm along +y)
    assert len(axis) and np.all((axis[:, :2] >= needle[:, :2].min(axis=0) - 1e-6)
                                & (axis[:, :2] <= needle[:, :2].max(axis=0) + 1e-6))
    assert lines[:, 1].max() <= 20 + 1e-6  # the clamp's outline is not moved along +y either


def _display_rect(points, renderer):
    from vtkmodules.vtkRenderingCore import vtkCoordinate

    c = vtkCoordinate()
    c.SetCoordinateSystemToWorld()
    xy = []
    for p in points:
        c.SetValue(*p)
        xy.append(c.GetComputedDisplayValue(renderer))
    xy = np.asarray(xy, float)
    return xy.min(axis=0), xy.max(axis=0)


def test_colour_bar_is_clear_of_the_model(built):
    grid, b = built
    model, side = b.plotter.renderers[0], b.plotter.renderers[1]
    bounds = np.asarray(model.ComputeVisiblePropBounds())
    corners = np.array([[x, y, z] for x in bounds[0:2] for y in bounds[2:4] for z in bounds[4:6]])
    lo, hi = _display_rect(corners, model)
    w, h = b.plotter.window_size
    vp = np.asarray(model.GetViewport()) * [w, h, w, h]
    lo, hi = np.maximum(lo, vp[:2]), np.minimum(hi, vp[2:])  # what of the model can show at all
    assert np.all(hi > lo)
    bar = b.plotter.scalar_bars["|u| (mm)"]
    b0 = np.asarray(bar.GetPositionCoordinate().GetComputedDisplayValue(side), float)
    b1 = np.asarray(bar.GetPosition2Coordinate().GetComputedDisplayValue(side), float)
    assert np.all(b1 > b0)
    overlap = np.all(np.minimum(hi, b1) > np.maximum(lo, b0))
    assert not overlap, (lo, hi, b0, b1)


def test_bars_in_the_title_are_drawn():
    """VTK's MathText backend reads '|' as a column separator and drops it ("u|" as wide as "u"); under
    freetype_text both bars take their room."""
    import vtkmodules.vtkRenderingFreeType  # noqa: F401
    from vtkmodules.vtkRenderingCore import vtkTextProperty, vtkTextRenderer

    prop = vtkTextProperty()
    prop.SetFontSize(24)

    def width(s):
        box = [0, 0, 0, 0]
        assert vtkTextRenderer.GetInstance().GetBoundingBox(prop, s, box, 72)
        return box[1] - box[0]

    with freetype_text():
        assert width("u|") > width("u")
        assert width("|u| (mm)") - width("u (mm)") >= 1.5 * width("|")


def test_png_has_its_caption_and_follows_the_umask(tmp_path):
    from PIL import Image

    grid, regions = _model()
    old = os.umask(0o027)
    try:
        png = render(build(grid, regions, RenderScene("Test block, 300 N", tuple(FORCE), scale=2.0), 300.0, "f"),
                     tmp_path / "r.png")
    finally:
        os.umask(old)
    assert png.stat().st_mode & 0o777 == 0o640
    img = Image.open(png)
    assert img.size == (1400, 1000)
    assert img.text["Description"].startswith("Test block, 300 N: deformed shape (displacements scaled x2)")
    assert not [p for p in tmp_path.iterdir() if p.name != "r.png"]


def test_an_off_centre_load_point_rides_on_the_turning_clamp():
    """Clamp turned 10 degrees about x (and shifted): the arrow starts where that rigid motion takes the
    load point, not where the clamp's mean displacement would."""
    grid, regions = _model()
    tag = np.asarray(grid.cell_data["region"])
    clamp_nodes = np.unique(grid.cells.reshape(-1, 5)[tag == 3, 1:])
    x = np.asarray(grid.points)
    centre = np.array([10.0, 10.0, 36.0])
    a = np.radians(10.0)
    rot = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    shift = np.array([0.0, 4.0, 1.0])
    u = np.zeros_like(x)
    u[clamp_nodes] = (x[clamp_nodes] - centre) @ rot.T + centre + shift - x[clamp_nodes]
    grid.point_data["displacement"] = u
    load = centre + [0.0, 0.0, 15.0]
    b = build(grid, regions, RenderScene("t", tuple(FORCE), load_point_mm=tuple(load)), 300.0)
    p = np.asarray(b.plotter.renderers[0].actors["force_arrow"].mapper.dataset.points)
    tail = p[np.isclose(p @ FORCE, (p @ FORCE).min(), atol=1e-6)].mean(axis=0)
    np.testing.assert_allclose(tail, rot @ (load - centre) + centre + shift, atol=1e-4)  # float32 mesh
    b.plotter.close()


def test_isolated_stops_its_child_when_the_caller_is_interrupted(tmp_path):
    # SIGTERM/Ctrl-C to `fe needle` while it rendered: the executor waited for the child, which went on
    # and wrote needle_deformed.png after the command had stopped (or outlived it, with SIGTERM).
    import signal
    import time

    from needletissue.models.render import isolated

    late = tmp_path / "late.png"

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGALRM, interrupt)
    signal.setitimer(signal.ITIMER_REAL, 1.5)  # the child is started (spawn) and sleeping by then
    t0 = time.perf_counter()
    try:
        with pytest.raises(KeyboardInterrupt):
            isolated(exec, f"import time, pathlib; time.sleep(4); pathlib.Path({str(late)!r}).write_text('x')")
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert time.perf_counter() - t0 < 3.5  # did not wait for the child
    time.sleep(4)
    assert not late.exists()  # the child was stopped, not left to finish


def test_isolated_job_runs_beside_the_caller_and_is_stopped_when_the_caller_fails(tmp_path):
    # `fe needle` renders its picture while it writes the other files: the child works meanwhile, and a
    # failure of the caller before it waits stops the child (no PNG appears after the command failed)
    import time

    from needletissue.models.render import Isolated

    go, done, late = tmp_path / "go.txt", tmp_path / "done.txt", tmp_path / "late.txt"
    wait_for_go = (f"import time, pathlib\nt = time.monotonic() + 60\nwhile not pathlib.Path({str(go)!r}).exists():\n"
                   f"    assert time.monotonic() < t, 'never ran beside the caller'\n    time.sleep(0.02)\n"
                   f"pathlib.Path({str(done)!r}).write_text('x')")
    with Isolated(exec, wait_for_go) as job:
        go.write_text("x")  # the caller's own work while the child runs; the child finishes only after it
        job.result()
    assert done.exists()
    with pytest.raises(ValueError):
        with Isolated(exec, f"import time, pathlib; time.sleep(3); pathlib.Path({str(late)!r}).write_text('x')"):
            time.sleep(1)  # the child is started (spawn)
            raise ValueError("the caller failed")
    time.sleep(4)
    assert not late.exists()


def test_isolated_child_dies_with_a_killed_caller(tmp_path):
    # a `reproduce` stage worker killed while it rendered left its render child running on (an orphan)
    import signal
    import subprocess
    import sys
    import time

    late = tmp_path / "late.png"
    work = f"import time, pathlib; time.sleep(4); pathlib.Path({str(late)!r}).write_text('x')"
    p = subprocess.Popen([sys.executable, "-c", f"from needletissue.models.render import isolated\nisolated(exec, {work!r})"])
    deadline = time.monotonic() + 60
    while b"spawn_main" not in subprocess.run(["pgrep", "-a", "-P", str(p.pid)], capture_output=True).stdout:
        assert p.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(1.0)  # the child is past its start
    p.send_signal(signal.SIGKILL)
    p.wait(10)
    time.sleep(5)
    assert not late.exists()


def test_render_without_a_display_prints_no_x_server_warning(tmp_path):
    # `reproduce` printed VTK's "bad X server connection" once per figure: VTK 9.4+ tries X first without a
    # display. offscreen() asks for EGL directly where it is installed; the picture must still be made.
    import ctypes.util
    import subprocess
    import sys

    from needletissue.models.render import offscreen

    if not ctypes.util.find_library("EGL"):
        pytest.skip("no libEGL here: VTK's own fallback order applies")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY",
                                                            "VTK_DEFAULT_OPENGL_WINDOW")}
    env = offscreen(env)
    assert env["VTK_DEFAULT_OPENGL_WINDOW"] == "vtkEGLRenderWindow"
    png = tmp_path / "s.png"
    code = ("import pyvista as pv; p = pv.Plotter(off_screen=True); p.add_mesh(pv.Sphere()); "
            f"p.screenshot({str(png)!r})")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "X server" not in r.stderr
    assert png.stat().st_size > 1000
    with_display = offscreen({"DISPLAY": ":0"})
    assert "VTK_DEFAULT_OPENGL_WINDOW" not in with_display  # a desktop user's display is left alone
