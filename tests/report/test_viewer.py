"""The report's interactive 3D view: surfaces and fields extracted right, data embedded losslessly, and
the page working in a real headless browser (Chromium via Playwright)."""

import base64
import json
import os
import re
import shutil
from contextlib import contextmanager

import meshio
import numpy as np
import pytest

from needletissue.report.viewer import Scene, boundary_triangles, scene_from_vtus, viewer_html, write_viewer

# two positive tetrahedra sharing the face (1, 2, 3)
POINTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
CELLS = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])


def _volume(p, c):
    return np.linalg.det(np.stack([p[c[1]] - p[c[0]], p[c[2]] - p[c[0]], p[c[3]] - p[c[0]]])) / 6


def test_boundary_triangles_are_outward_and_skip_shared_faces():
    assert all(_volume(POINTS, c) > 0 for c in CELLS)
    tri = boundary_triangles(CELLS)
    assert len(tri) == 6 and not any(set(t) == {1, 2, 3} for t in tri)
    centre = POINTS.mean(axis=0)
    for t in tri:  # the union is convex: every outward normal points away from its centre
        n = np.cross(POINTS[t[1]] - POINTS[t[0]], POINTS[t[2]] - POINTS[t[0]])
        assert n @ (POINTS[t].mean(axis=0) - centre) > 0


def _decode(s, dtype):
    return np.frombuffer(base64.b64decode(s), dtype=np.dtype(dtype).newbyteorder("<"))


def _write_frames(tmp_path):
    paths = []
    for k, f in enumerate((1.0, 2.0)):
        m = meshio.Mesh(POINTS, [("tetra", CELLS)], point_data={"displacement": f * POINTS * 0.1},
                        cell_data={"region": [np.array([0, 1])], "von_mises_MPa": [np.array([10.0, 30.0]) * f]})
        paths.append(tmp_path / f"f{k}.vtu")
        meshio.write(paths[-1], m)
    return paths


def test_scene_keeps_fields_per_region_and_embeds_them_losslessly(tmp_path):
    scene = scene_from_vtus(_write_frames(tmp_path), ["1 N", "2 N"], {0: "bone", 1: "muscle</script>"})
    bone, muscle = scene.regions
    assert (bone.name, len(bone.triangles), len(muscle.triangles)) == ("bone", 4, 4)
    # the shared vertices 1, 2, 3 carry each region's own stress, not a blend across the interface
    assert np.allclose(bone.von_mises[1], 20.0) and np.allclose(muscle.von_mises[1], 60.0)
    assert np.allclose(muscle.displacement[1], 0.2 * muscle.points)
    frag = viewer_html(scene, "t")
    assert "muscle</script>" not in frag  # a name cannot end the data script
    data = json.loads(re.search(r'<script type="application/json" id="ntv\d+-data">(.*?)</script>', frag,
                                re.S).group(1))
    r = data["regions"][1]
    assert np.array_equal(_decode(r["points"], "f4"), muscle.points.astype("f4").ravel())
    assert np.array_equal(_decode(r["triangles"], "u4"), muscle.triangles.astype("u4").ravel())
    assert data["ranges"]["vm"] == [0.0, 60.0]
    assert data["ranges"]["u"][1] == pytest.approx(0.2 * np.sqrt(3))


def _browser():
    """Chromium from the Debian packages, driven by Playwright; CI installs both (.ci/run)."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        exe = None
    if exe is None:
        if os.environ.get("NEEDLETISSUE_REQUIRE_BROWSER"):
            pytest.fail("NEEDLETISSUE_REQUIRE_BROWSER is set but Chromium or Playwright is missing")
        pytest.skip("needs Chromium (apt-get install chromium) and playwright (pip install playwright)")
    return exe


BROWSER_ARGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--no-first-run"]


@contextmanager
def open_in_browser(path, width=1100, height=800):
    """(page, errors) for a local HTML file in headless Chromium."""
    from playwright.sync_api import sync_playwright

    exe = _browser()
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=exe, args=BROWSER_ARGS)
        try:
            page = b.new_page(viewport={"width": width, "height": height})
            errors = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.goto(path.resolve().as_uri())
            yield page, errors
        finally:
            b.close()


@pytest.mark.browser
def test_viewer_draws_toggles_and_fits_a_phone_in_chromium(tmp_path):
    scene = scene_from_vtus(_write_frames(tmp_path), ["1 N", "2 N"], {0: "bone", 1: "muscle"})
    scene.arrow = {"origin": [0.5, 0.5, 0.5], "direction": [0, 1, 0], "label": "F"}
    page_path = write_viewer(tmp_path / "view.html", scene, "two tetrahedra")
    for width in (1100, 390):
        with open_in_browser(page_path, width=width) as (page, errors):
            page.wait_for_function("document.querySelector('.ntv').dataset.ready === '1'", timeout=30000)
            viewer = "document.querySelector('.ntv').viewer"
            assert page.evaluate(f"{viewer}.drawn") == 8
            pixels = page.evaluate("""() => { const c = document.querySelector('.ntv-gl');
                const g = c.getContext('webgl'); const px = new Uint8Array(c.width * c.height * 4);
                g.readPixels(0, 0, c.width, c.height, g.RGBA, g.UNSIGNED_BYTE, px);
                let lit = 0; for (let i = 0; i < px.length; i += 4) if (px[i] < 200) lit++; return lit; }""")
            assert pixels > 100, "nothing drawn"
            page.click("input[data-region='muscle']")
            assert page.evaluate(f"{viewer}.drawn") == 4
            page.select_option(".ntv-controls select >> nth=1", "vm")
            assert page.inner_text(".ntv-cbar-label") == "von Mises stress (MPa)"
            assert page.evaluate("document.documentElement.scrollWidth") <= width, "scrolls sideways"
            assert not errors, errors


def test_a_view_that_cannot_be_built_is_a_note_not_a_failed_stage(tmp_path):
    from needletissue.report.stages import _view

    notes, files = [], []
    common = dict(forces=[1.0, 2.0], region_tags={"bone": 0, "clamp": 1}, force_direction=(0, 1, 0),
                  needle_axis=(0, 0, 1), frame_of_reference="model")
    assert _view(tmp_path / "v.html", "t", notes, files, vtus=[tmp_path / "missing.vtu"] * 2, **common) == []
    assert files == [] and len(notes) == 1 and "v.html not written" in notes[0]
    (title, scene), = _view(tmp_path / "v.html", "t", notes, files, vtus=_write_frames(tmp_path), **common)
    assert files == [tmp_path / "v.html"] and (tmp_path / "v.html").is_file()
    # the force arrow starts at the clamp's centre; the view looks across the pin and the force
    clamp = next(r for r in scene.regions if r.name == "clamp")
    assert scene.arrow["origin"] == pytest.approx(clamp.points.mean(axis=0).tolist())
    assert np.cross((0, 0, 1), (0, 1, 0)) @ np.asarray(scene.view) > 0


@pytest.mark.browser
def test_report_figures_are_full_width_captioned_and_fit_a_phone(tmp_path):
    """report.html in Chromium: each figure spans the text column, its caption says what it shows (not only
    the file name), and at phone width (390 px) nothing makes the page scroll sideways."""
    from needletissue.report.config import load_config
    from needletissue.report.pipeline import run_reproduce
    from needletissue.report.stages import stage_list

    quick = {"traction": {"enabled": False}, "needle_fe": {"enabled": False}, "pelvis": {"enabled": "off"}}
    out = tmp_path / "res"
    assert run_reproduce(load_config(overrides=quick), out, stage_list(), progress=False).ok
    for width in (1100, 390):
        with open_in_browser(out / "report.html", width=width) as (page, errors):
            figs = page.evaluate("""() => [...document.querySelectorAll('figure')].map(f => ({
                img: f.querySelector('img').getBoundingClientRect().width,
                column: document.body.clientWidth - parseFloat(getComputedStyle(document.body).paddingLeft)
                        - parseFloat(getComputedStyle(document.body).paddingRight),
                caption: f.querySelector('figcaption').innerText}))""")
            assert len(figs) >= 2
            for f in figs:
                assert f["img"] == pytest.approx(f["column"], abs=2), f
                name = f["caption"].split()[-1]
                assert name.endswith(".png") and len(f["caption"]) > len(name) + 20, f
            assert page.evaluate("document.documentElement.scrollWidth") <= width, "scrolls sideways"
            assert not errors, errors
