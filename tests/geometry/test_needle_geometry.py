"""Needle-tissue-bone geometry: region volumes against closed forms, named groups, conformity, bad input."""

from __future__ import annotations

import math
import os
from collections import Counter

import meshio
import numpy as np
import pytest

from needletissue.errors import InputError
from needletissue.cache import MESH_CACHE_ENV, mesh_cache_dir
from needletissue.geometry.needle import REGIONS, SURFACES, MeshError, NeedleGeometry, mesh_needle_model

COARSE = dict(needle_mesh_size=1.5, mesh_size=4.0, far_mesh_size=20.0, half_width=40.0, free_length=80.0)


def _read(path):
    m = meshio.read(path)
    names = {tag: name for name, (tag, dim) in m.field_data.items()}
    pts = m.points
    tets, tet_region, tris = [], [], {}
    for block, phys in zip(m.cells, m.cell_data["gmsh:physical"]):
        for c, t in zip(block.data, phys):
            if block.type == "tetra":
                tets.append(c)
                tet_region.append(names[t])
            elif block.type == "triangle":
                tris.setdefault(names[t], []).append(c)
    return pts, np.array(tets), np.array(tet_region), {k: np.array(v) for k, v in tris.items()}


def _tet_volumes(pts, tets):
    a, b, c, d = (pts[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def _tri_areas(pts, tris):
    a, b, c = (pts[tris[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


@pytest.fixture(scope="module", params=[2, 1], ids=["two_needles", "one_needle"])
def built(request, tmp_path_factory):
    g = NeedleGeometry(needles=request.param, **COARSE)
    path = tmp_path_factory.mktemp("mesh") / "needle.msh"
    info = mesh_needle_model(g, path)
    return g, info, _read(path)


def test_tetrahedra_estimate_is_within_2x_of_gmsh(built):
    """The pre-meshing estimate (size field integrated over the solid, regular tetrahedra) against the
    count gmsh makes: within a factor 2 (measured 0.8-1.8 over five size sets, docs/needle_model.md)."""
    g, info, _ = built
    assert 0.5 < info.tetrahedra / g.estimate_tetrahedra() < 2.0


def test_a_mesh_that_would_run_for_ever_is_refused_with_its_estimate(monkeypatch):
    """`--mesh-size 0.02` used to mesh for ever: refused before gmsh starts, naming the field, the estimate
    and the limit; an explicit max_tetrahedra admits it. The estimate scales as 1/h^3 where h dominates."""
    import gmsh

    monkeypatch.setattr(gmsh, "initialize", lambda *a, **k: pytest.fail("gmsh started"))
    with pytest.raises(InputError, match=r"tetrahedra estimated.*limit of 3,000,000") as exc:
        NeedleGeometry(mesh_size=0.02)
    assert exc.value.field == "mesh_size"
    with pytest.raises(InputError) as exc:
        NeedleGeometry(needle_mesh_size=0.05)
    assert exc.value.field == "needle_mesh_size"
    big = NeedleGeometry(mesh_size=0.02, max_tetrahedra=10**12).estimate_tetrahedra()
    half = NeedleGeometry(mesh_size=0.04, max_tetrahedra=10**12).estimate_tetrahedra()
    assert big / half == pytest.approx(8.0, rel=0.05)  # the near zone dominates: n ~ 1/h^3


def test_named_groups_present(built):
    g, info, (pts, tets, reg, tris) = built
    expected = [r for r in REGIONS if g.needles == 2 or r != "needle_2"]
    assert sorted(set(reg)) == sorted(expected)
    assert set(SURFACES) <= set(tris)
    assert info.tetrahedra == len(tets) and info.min_quality > 0


def test_layer_volumes_exact(built):
    """Planar layers are meshed exactly: each layer's tets (any region) fill its box to round-off."""
    g, _, (pts, tets, reg, _) = built
    vol = _tet_volumes(pts, tets)
    assert (vol > 0).all(), "inverted tetrahedra"
    zc = pts[tets].mean(axis=1)[:, 2]
    x0, x1, y0, y1 = g.extent
    A = (x1 - x0) * (y1 - y0)
    tm, ta, T = g.muscle_thickness, g.adipose_thickness, g.bone_thickness
    for lo, hi, exact in ((-T, 0, A * T), (0, tm, A * tm), (tm, tm + ta, A * ta)):
        inside = (zc > lo) & (zc < hi) & ~np.isin(reg, ["clamp"])
        assert vol[inside].sum() == pytest.approx(exact, rel=1e-9)
    # Bone = cortical + cancellous + needle part in bone; the core box is cancellous + needle part in it.
    cx0, cx1, cy0, cy1, cz0, cz1 = g.clamp_box
    in_clamp = np.isin(reg, ["clamp"]) | ((zc > cz0) & np.char.startswith(reg.astype(str), "needle"))
    assert vol[in_clamp].sum() == pytest.approx((cx1 - cx0) * (cy1 - cy0) * (cz1 - cz0), rel=1e-9)


def test_region_volumes_vs_analytic(built):
    """Needles are inscribed polygonal cylinders: volume below pi r^2 L by at most the chord deficit
    (h/r)^2/6 of a polygon with edge h (h = 1.5x the needle mesh size bounds gmsh's longest edge);
    regions with a needle hole are above their analytic volume by the same absolute amount."""
    g, _, (pts, tets, reg, _) = built
    vol = _tet_volumes(pts, tets)
    exact = g.analytic_volumes()
    r = g.diameter / 2
    deficit = (1.5 * g.needle_mesh_size / r) ** 2 / 6
    needle_total = sum(v for k, v in exact.items() if k.startswith("needle"))
    for name, v_exact in exact.items():
        v = vol[reg == name].sum()
        if name.startswith("needle"):
            assert v_exact * (1 - deficit) < v <= v_exact * (1 + 1e-9), name
        else:
            assert v_exact - 1e-6 <= v < v_exact + deficit * needle_total, name


def test_conforming_interfaces(built):
    """Every triangle is shared by at most two tets; faces of only one tet lie on the outer boundary
    (far faces, bone bottom, skin, or needle/clamp above the skin): no duplicated interface nodes."""
    g, _, (pts, tets, reg, tris) = built
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 3]],
                                    tets[:, [1, 2, 3]]]), axis=1)
    count = Counter(map(tuple, faces))
    assert max(count.values()) == 2
    single = np.array([f for f, n in count.items() if n == 1])
    c = pts[single].mean(axis=1)
    x0, x1, y0, y1 = g.extent
    eps = 1e-6
    outer = ((np.abs(c[:, 0] - x0) < eps) | (np.abs(c[:, 0] - x1) < eps) | (np.abs(c[:, 1] - y0) < eps)
             | (np.abs(c[:, 1] - y1) < eps) | (np.abs(c[:, 2] + g.bone_thickness) < eps)
             | (c[:, 2] > g.tissue_thickness - eps))
    assert outer.all(), f"{(~outer).sum()} boundary faces inside the model"
    # Interface groups are faces of tets on both sides.
    for name in ("muscle_bone", "needle_muscle", "needle_bone", "muscle_adipose", "needle_clamp"):
        f = np.sort(tris[name], axis=1)
        assert all(count[tuple(t)] == 2 for t in f), name


def test_surface_areas_exact(built):
    g, _, (pts, _, _, tris) = built
    x0, x1, y0, y1 = g.extent
    T = g.bone_thickness
    assert _tri_areas(pts, tris["gripper"]).sum() == pytest.approx(g.gripper_area, rel=1e-9)
    bone = (x1 - x0) * (y1 - y0) + 2 * ((x1 - x0) + (y1 - y0)) * T
    assert _tri_areas(pts, tris["bone_fixed"]).sum() == pytest.approx(bone, rel=1e-9)
    far = 2 * ((x1 - x0) + (y1 - y0)) * g.tissue_thickness
    assert _tri_areas(pts, tris["tissue_far"]).sum() == pytest.approx(far, rel=1e-9)
    muscle_bone = (x1 - x0) * (y1 - y0) - g.needles * math.pi * (g.diameter / 2) ** 2
    a = _tri_areas(pts, tris["muscle_bone"]).sum()
    assert muscle_bone <= a < muscle_bone + g.needles * math.pi * (g.diameter / 2) ** 2 * 0.2


def test_needle_axis_nodes(built):
    """The needle axes are embedded: mesh nodes on x = x_i, y = 0 from the tip (-h) to the end (l)."""
    g, _, (pts, *_) = built
    for x in g.needle_x:
        on = np.abs(pts[:, 0] - x) + np.abs(pts[:, 1]) < 1e-9
        z = np.sort(pts[on, 2])
        assert z[0] == pytest.approx(-g.depth) and z[-1] == pytest.approx(g.free_length)
        assert np.diff(z).max() <= 2.0 * g.needle_mesh_size


def test_mesh_is_reproducible(tmp_path):
    g = NeedleGeometry(**{**COARSE, "needle_mesh_size": 2.5})
    a = mesh_needle_model(g, tmp_path / "a.msh")
    b = mesh_needle_model(g, tmp_path / "b.msh")
    assert (a.nodes, a.tetrahedra) == (b.nodes, b.tetrahedra)


@pytest.mark.parametrize("kwargs, field", [
    (dict(free_length=40.0), "free_length"),            # needle ends inside the tissue/clamp
    (dict(spacing=4.0, diameter=5.0), "spacing"),        # needles overlap
    (dict(muscle_thickness=0.0), "muscle_thickness"),
    (dict(cortical_thickness=0.0), "cortical_thickness"),
    (dict(depth=45.0, bone_thickness=40.0), "depth"),    # needle longer than the model
    (dict(needles=3), "needles"),
    (dict(diameter=float("nan")), "diameter"),
    (dict(needle_mesh_size=6.0), "needle_mesh_size"),
])
def test_bad_geometry_rejected_before_meshing(kwargs, field, monkeypatch):
    import gmsh

    monkeypatch.setattr(gmsh, "initialize", lambda *a, **k: pytest.fail("gmsh started"))
    with pytest.raises(InputError) as exc:
        mesh_needle_model(NeedleGeometry(**kwargs), "unused.msh")
    assert exc.value.field == field


def test_gmsh_failure_is_a_clear_error(tmp_path, monkeypatch):
    import gmsh

    def boom(dim=3):
        raise Exception("PLC Error: a segment and a facet intersect")

    monkeypatch.setattr(gmsh.model.mesh, "generate", boom)
    with pytest.raises(MeshError, match="gmsh failed"):
        mesh_needle_model(NeedleGeometry(**COARSE), tmp_path / "x.msh", isolate=False)


def test_isolated_mesh_equals_in_process_mesh(tmp_path):
    a = mesh_needle_model(NeedleGeometry(**COARSE), tmp_path / "a.msh")
    b = mesh_needle_model(NeedleGeometry(**COARSE), tmp_path / "b.msh", isolate=False)
    assert (a.nodes, a.tetrahedra, a.region_tetrahedra) == (b.nodes, b.tetrahedra, b.region_tetrahedra)
    assert a.min_quality == pytest.approx(b.min_quality, rel=1e-12)


def test_a_native_crash_in_the_mesher_is_an_error_not_a_dead_process(tmp_path, monkeypatch):
    # gmsh's high-order optimiser once aborted the whole process (SIGABRT) in CI; the child stands for it
    from needletissue.geometry.child import ChildCrash, call_in_child

    with pytest.raises(ChildCrash, match="SIGABRT"):
        call_in_child("os:abort", {}, what="gmsh (needle model)")
    (tmp_path / "fails_in_child.py").write_text(
        "from needletissue.geometry.needle import MeshError\n"
        "def run():\n    raise MeshError('3 inverted tetrahedra')\n")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    with pytest.raises(MeshError, match="3 inverted tetrahedra"):
        call_in_child("fails_in_child:run", {}, what="gmsh")


def test_a_mesher_child_whose_parent_is_gone_does_nothing(tmp_path):
    # SIGTERM to `fe needle` while the child interpreter was still starting: PR_SET_PDEATHSIG was set only
    # after the parent had died, so the orphan meshed on and wrote the mesh into --out after the command
    # had exited. The child now checks it still has the parent that started it before doing anything.
    import json
    import os
    import subprocess
    import sys

    (tmp_path / "touch_in_child.py").write_text(
        "from pathlib import Path\ndef run(path):\n    Path(path).write_text('meshed')\n    return {}\n")
    done, answer = tmp_path / "mesh.msh", tmp_path / "answer.json"
    request = json.dumps({"target": "touch_in_child:run", "kwargs": {"path": str(done)}, "answer": str(answer)})
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-c", "from needletissue.geometry.child import main; main()"]
    gone = subprocess.run(cmd, input=request, text=True, capture_output=True, timeout=60,
                          env={**env, "NEEDLETISSUE_CHILD_PARENT": "1"})  # not our parent: it has died
    assert gone.returncode != 0 and not done.exists() and not answer.exists()
    alive = subprocess.run(cmd, input=request, text=True, capture_output=True, timeout=60,
                           env={**env, "NEEDLETISSUE_CHILD_PARENT": str(os.getpid())})
    assert alive.returncode == 0 and done.read_text() == "meshed" and json.loads(answer.read_text()) == {"value": {}}


def test_sigterm_to_a_caller_without_a_handler_stops_the_mesher_and_removes_its_folders(tmp_path):
    # a `reproduce` stage worker (default SIGTERM action) stopped while gmsh ran in its child left the
    # child's needletissue-child-* folder in $TMPDIR
    import os
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "slow_in_child.py").write_text("import time\ndef run():\n    time.sleep(60)\n    return {}\n")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = dict(os.environ, TMPDIR=str(tmp),
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    p = subprocess.Popen([sys.executable, "-c", "from needletissue.geometry.child import call_in_child\n"
                          "call_in_child('slow_in_child:run', {}, what='gmsh')"], env=env, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True).stdout:
        assert p.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(0.5)  # the child is running
    kids = subprocess.run(["pgrep", "-P", str(p.pid)], capture_output=True, text=True).stdout.split()
    p.send_signal(signal.SIGTERM)
    p.communicate(timeout=30)
    assert p.returncode == 143
    time.sleep(0.5)
    assert not [k for k in kids if os.path.exists(f"/proc/{k}")] and list(tmp.iterdir()) == []


def test_mesh_cache_returns_the_same_mesh_without_gmsh_and_keys_every_input(tmp_path, monkeypatch):
    """A cached mesh is the stored file byte for byte with the same facts, gmsh not started; another
    geometry or order is a miss, so is a damaged entry (rewritten); NEEDLETISSUE_MESH_CACHE=0 turns the cache off."""
    import needletissue.geometry.needle as nd

    monkeypatch.setenv(MESH_CACHE_ENV, str(tmp_path / "cache"))
    g = NeedleGeometry(**COARSE)
    old = os.umask(0o027)
    try:
        a = mesh_needle_model(g, tmp_path / "a.msh", cache=True)
    finally:
        os.umask(old)
    assert not a.cached and len(list((tmp_path / "cache").glob("*.msh"))) == 1
    assert {f.stat().st_mode & 0o777 for f in (tmp_path / "cache").iterdir()} == {0o640}  # the umask's
    assert not list((tmp_path / "cache").glob(".*"))  # no temporary file left

    def no_gmsh(*args, **kwargs):
        raise RuntimeError("gmsh ran")

    real = nd._mesh
    monkeypatch.setattr(nd, "_mesh", no_gmsh)
    b = mesh_needle_model(g, tmp_path / "sub" / "b.msh", cache=True)
    assert b.cached and (tmp_path / "sub" / "b.msh").read_bytes() == (tmp_path / "a.msh").read_bytes()
    assert (b.nodes, b.tetrahedra, b.region_tetrahedra, b.min_quality) == \
        (a.nodes, a.tetrahedra, a.region_tetrahedra, a.min_quality)
    assert nd._cache_key(g, 1) != nd._cache_key(g, 2)
    assert nd._cache_key(g, 1) != nd._cache_key(NeedleGeometry(**{**COARSE, "mesh_size": 5.0}), 1)
    with pytest.raises(RuntimeError, match="gmsh ran"):
        mesh_needle_model(NeedleGeometry(**{**COARSE, "mesh_size": 5.0}), tmp_path / "c.msh", cache=True)
    monkeypatch.setattr(nd, "_mesh", real)
    # a damaged entry (a truncated .msh) is a miss: gmsh runs again and the entry is rewritten whole
    (entry,) = (tmp_path / "cache").glob("*.msh")
    entry.write_bytes(entry.read_bytes()[:3000])
    e = mesh_needle_model(g, tmp_path / "e.msh", cache=True)
    assert not e.cached and entry.read_bytes() == (tmp_path / "e.msh").read_bytes()
    assert mesh_needle_model(g, tmp_path / "f.msh", cache=True).cached
    monkeypatch.setenv(MESH_CACHE_ENV, "0")
    assert mesh_cache_dir() is None
    assert not mesh_needle_model(g, tmp_path / "d.msh", cache=True).cached
