"""Needle-tissue-bone FE model on a coarse mesh: output contract, symmetry, equilibrium, and the shear
force in each needle's exposed segment from Euler-Bernoulli (EI v''' = -V), i.e. the force sharing."""

from __future__ import annotations

import json
import math

import meshio
import numpy as np
import pytest
from typer.testing import CliRunner

from needletissue.cli import app
from needletissue.fem.solvelog import SOLVE_LOG, read_log
from needletissue.models.needle import NeedleModelConfig, run_needle_model
from needletissue.geometry.needle import NeedleGeometry
from needletissue.cache import MESH_CACHE_ENV
from needletissue.materials import get

COARSE_CLI = ["--needle-mesh-size", "2.5", "--mesh-size", "8", "--far-mesh-size", "30"]
COARSE = dict(needle_mesh_size=2.5, mesh_size=8.0, far_mesh_size=30.0)
F_SMALL = 10.0   # N: small enough that the needle response is linear (deflection << length)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("needle_cli")
    res = CliRunner().invoke(app, ["fe", "needle", "--force", str(F_SMALL), "--force", str(2 * F_SMALL),
                                   *COARSE_CLI, "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout), out


HOOK_CALLS = []


@pytest.fixture(scope="module")
def one_needle():
    cfg = NeedleModelConfig(geometry=NeedleGeometry(needles=1, **COARSE), forces=(F_SMALL,), tissue_far="free")

    def mesh_hook(mesh):
        HOOK_CALLS.append(("mesh", set(mesh.surfaces)))
        return mesh

    def items(model):
        HOOK_CALLS.append(("items", model.ndof))
        return ()

    return run_needle_model(cfg, mesh_hook=mesh_hook, items=items)


def test_contact_hooks_see_the_named_interfaces(one_needle):
    (k1, surfaces), (k2, ndof) = HOOK_CALLS
    assert (k1, k2) == ("mesh", "items") and ndof > 0
    assert {"needle_muscle", "needle_bone", "muscle_bone"} <= surfaces


def _shear_from_curve(z, v, g):
    """-EI v''' from a cubic fit over the exposed needle, one diameter clear of the skin and clamp."""
    lo, hi = g.tissue_thickness + g.diameter, g.free_length - g.grip_length - g.diameter
    sel = (z > lo) & (z < hi)
    c3 = np.polyfit(z[sel], v[sel], 3)[0]
    EI = get("needle").parameters["E"] * math.pi * g.diameter ** 4 / 64
    return -6 * c3 * EI


def test_json_contract_and_files(cli_run):
    data, out = cli_run
    assert set(data["mesh"]) >= {"nodes", "tetrahedra"} and data["wall_time_s"] > 0
    assert [r["force_N"] for r in data["results"]] == [F_SMALL, 2 * F_SMALL]
    for r in data["results"]:
        assert {"force_N", "max_needle_deformation_mm", "clamp_displacement_mm", "max_deformation_mm",
                "ritz_tip_deflection_mm", "theory_fe_difference_mm"} <= set(r)
        assert set(r["max_deformation_mm"]) == {"cortical_bone", "cancellous_bone", "muscle", "adipose",
                                                "needle_1", "needle_2", "clamp"}
        assert r["theory_fe_difference_mm"] == pytest.approx(
            r["max_needle_deformation_mm"] - r["ritz_tip_deflection_mm"])
    for name in ("results.json", "config.toml", "versions.json", "needle_10N.vtu", "needle_20N.vtu",
                 "needle_deformed.png", "needle_deflection.png", "needle_model.msh"):
        assert (out / name).stat().st_size > 0, name
    vtu = meshio.read(out / "needle_20N.vtu")
    assert "region" in vtu.cell_data and "displacement" in vtu.point_data
    assert json.loads((out / "results.json").read_text(encoding="utf-8"))["results"][0]["force_N"] == F_SMALL
    # the progress log: its increments reach the last force, their Newton iterations are the results'
    log = read_log(out / SOLVE_LOG)
    assert log[0]["event"] == "start" and log[0]["interfaces"] == "bonded" and log[0]["dofs"] > 0
    assert log[-1]["event"] == "done" and log[-1]["force_N"] == pytest.approx(2 * F_SMALL)
    inc = [e for e in log if e["event"] == "increment"]
    assert sum(e["iterations"] for e in inc) == data["results"][-1]["newton_iterations"]


def test_two_needles_mirror_symmetric_and_share_the_force(cli_run):
    """The model is mirror-symmetric about x = 0 and the force (y) too: both needles deflect alike and
    each carries exactly F/2 as shear in its exposed segment."""
    data, _ = cli_run
    g = NeedleGeometry(**COARSE)
    for r in data["results"]:
        c = r["deflection_curves"]
        e1, e2 = r["needle_end_deflection_mm"]["needle_1"], r["needle_end_deflection_mm"]["needle_2"]
        assert e1 == pytest.approx(e2, rel=2e-2)
        for name in ("needle_1", "needle_2"):
            V = _shear_from_curve(np.array(c[name]["z_mm"]), np.array(c[name]["deflection_mm"]), g)
            assert V == pytest.approx(r["force_N"] / 2, rel=0.01), name


def test_small_load_response_is_linear(cli_run):
    data, _ = cli_run
    a, b = data["results"]
    assert b["max_needle_deformation_mm"] == pytest.approx(2 * a["max_needle_deformation_mm"], rel=0.02)


def test_equilibrium_of_supports(one_needle):
    """With free tissue far faces the bone far faces hold the whole applied force: reaction = -F.
    (With both supports fixed, shared edge nodes count once: see test_api's shared-support test.)"""
    r = one_needle.results[0]
    np.testing.assert_allclose(r.fe.reaction_forces["bone_fixed"], [0, -F_SMALL, 0], atol=1e-6 * F_SMALL)


def test_one_needle_carries_the_whole_force(one_needle):
    g = one_needle.config.geometry
    r = one_needle.results[0]
    c = r.curves["needle_1"]
    assert _shear_from_curve(c.z_mm, c.deflection_mm, g) == pytest.approx(F_SMALL, rel=0.01)
    assert set(r.max_deformation_mm) == {"cortical_bone", "cancellous_bone", "muscle", "adipose", "needle_1", "clamp"}
    # The clamp is held by the needle: its displacement is the needle's at the grip, below the needle max.
    assert 0 < r.clamp_displacement_mm <= r.max_needle_deformation_mm * 1.001


def test_bad_cli_input_is_one_line_exit_2():
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "fe", "needle",
                        "--diameter", "5", "--spacing", "4"], capture_output=True, text=True)
    assert p.returncode == 2
    assert "spacing" in p.stderr and "Traceback" not in p.stderr
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "fe", "needle",
                        "--force", "-100"], capture_output=True, text=True)
    assert p.returncode == 2 and "forces" in p.stderr
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "fe", "needle",
                        "--load-offset", "1,2"], capture_output=True, text=True)
    assert p.returncode == 2 and "--load-offset" in p.stderr


def test_written_config_is_accepted_back(cli_run, monkeypatch):
    """The config.toml `fe needle --out` writes is what `fe needle --config` runs again (round trip);
    options typed on the command line override the file, defaults do not."""
    import needletissue.models.needle as needle_pkg
    from needletissue.commands.fe_needle import load_config

    _, out = cli_run
    cfg, contact = load_config(out / "config.toml")
    assert cfg == NeedleModelConfig(geometry=NeedleGeometry(**COARSE), forces=(F_SMALL, 2 * F_SMALL))
    assert contact == {}
    seen = []

    class Stop(Exception):
        pass

    def fake_run(config, out_dir=None, **hooks):
        seen.append(config)
        raise Stop

    monkeypatch.setattr(needle_pkg, "run_needle_model", fake_run)
    res = CliRunner().invoke(app, ["fe", "needle", "--config", str(out / "config.toml"), "--json"])
    assert isinstance(res.exception, Stop) and seen[-1] == cfg
    res = CliRunner().invoke(app, ["fe", "needle", "--config", str(out / "config.toml"), "--mesh-size", "9",
                                   "--force", "5"])
    assert isinstance(res.exception, Stop)
    assert seen[-1].geometry.mesh_size == 9.0 and seen[-1].forces == (5.0,)
    assert seen[-1].geometry.needle_mesh_size == COARSE["needle_mesh_size"]  # from the file, not the default


def test_json_reports_clamp_motion_and_strength(cli_run):
    """Fields for reduced-order models and the elastic-validity check (issue 14): the clamp vector's
    norm is the existing clamp_displacement_mm, the utilisation is max von Mises / the registry's
    strength and scales linearly with the small force, the symmetric needles have equal root slopes."""
    data, _ = cli_run
    a, b = data["results"]
    for r in (a, b):
        assert np.linalg.norm(r["clamp_displacement_vector_mm"]) == pytest.approx(r["clamp_displacement_mm"])
        assert r["force_vector_N"] == pytest.approx([0.0, r["force_N"], 0.0])
        assert r["moment_Nmm"] == pytest.approx([0.0, 0.0, 0.0])
        assert r["clamp_fit"]["rms_residual_mm"] < 1e-2 * r["clamp_displacement_mm"]  # the steel clamp is rigid
        s1, s2 = (np.array(r["root_slope"][k]) for k in ("needle_1", "needle_2"))
        assert s1[1] > 0 and s1[1] == pytest.approx(s2[1], rel=2e-2)   # y load: y slopes, alike
        assert abs(s1[0]) < 1e-2 * s1[1] and abs(s2[0]) < 1e-2 * s2[1]
        vm = r["max_von_mises_MPa"]
        assert r["needle_yield_utilisation"] == pytest.approx(
            max(vm["needle_1"], vm["needle_2"]) / get("needle").strength)
        assert r["bone_strength_utilisation"] == pytest.approx(max(
            vm["cortical_bone"] / get("cortical_bone").strength, vm["cancellous_bone"] / get("cancellous_bone").strength))
        assert r["validity_warnings"] == []  # 10-20 N: far below yield
    assert b["needle_yield_utilisation"] == pytest.approx(2 * a["needle_yield_utilisation"], rel=0.02)


def _render_raising(monkeypatch, exc):
    """The deformed-model render (a child process, VTK) replaced by one that raises `exc` when waited for."""
    import needletissue.models.render as render

    class Raising:
        def __init__(self, *args):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc_info):
            return False

        def result(self):
            raise exc

    monkeypatch.setattr(render, "Isolated", Raising)


def _no_render(monkeypatch):
    """write_outputs without the (slow, VTK) deformed-model picture: the render fails, a warning says so."""
    _render_raising(monkeypatch, RuntimeError("no picture in this test"))


def test_outputs_stopped_midway_leave_the_folder_as_it_was(one_needle, tmp_path, monkeypatch):
    # SIGTERM/Ctrl-C while the picture rendered (the last step) left the VTUs, the .vtm pieces and the
    # .pvd of the run in --out without results.json: half a result folder
    from needletissue.models.needle import write_outputs

    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    _render_raising(monkeypatch, KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        write_outputs(one_needle, out)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    with pytest.raises(KeyboardInterrupt):
        write_outputs(one_needle, tmp_path / "new")
    assert not (tmp_path / "new").exists()  # nor an empty folder


def test_rerun_with_fewer_forces_and_a_moved_folder(one_needle, tmp_path, monkeypatch):
    # a second run into the same folder with fewer forces left the first run's needle_<F>N.vtu/.vtm and
    # pieces folders beside the new ones, listed nowhere but easily taken for this run's
    import dataclasses
    import re
    import shutil

    import pyvista as pv

    from needletissue.models.needle import write_outputs

    _no_render(monkeypatch)
    r10 = one_needle.results[0]
    two = dataclasses.replace(one_needle, results=[r10, dataclasses.replace(r10, force_N=30.0)])
    out = tmp_path / "out"
    with pytest.warns(UserWarning, match="needle_deformed.png not written"):
        write_outputs(two, out)
    assert {"needle_10N.vtm", "needle_30N.vtm", "needle_30N", "needle_30N.vtu"} <= {p.name for p in out.iterdir()}
    (out / "needle_model.msh").write_text("a mesh of some other run")
    with pytest.warns(UserWarning):
        write_outputs(two, out)  # no mesh given: none listed, and none of another run left to pass for it
    assert not (out / "needle_model.msh").exists()
    assert "mesh" not in json.loads((out / "results.json").read_text())["files"]
    with pytest.warns(UserWarning):
        write_outputs(one_needle, out, mesh=b"$MeshFormat\n")
    names = sorted(p.name for p in out.iterdir())
    assert names == ["config.toml", "needle.pvd", "needle_10N", "needle_10N.vtm", "needle_10N.vtu",
                     "needle_deflection.png", "needle_model.msh", "results.json", "versions.json"], names
    assert re.findall(r'file="([^"]+)"', (out / "needle.pvd").read_text()) == ["needle_10N.vtm"]
    for f in out.rglob("*"):  # nothing names the folder it was written in
        assert not f.is_file() or str(tmp_path).encode() not in f.read_bytes(), f
    moved = tmp_path / "elsewhere" / "copy"
    shutil.copytree(out, moved)
    shutil.rmtree(out)
    series = pv.read(moved / "needle.pvd")
    blocks = pv.read(moved / "needle_10N.vtm")
    n = len(r10.fe.region_tags)
    assert series.n_blocks == 1 and series[0].n_blocks == n == blocks.n_blocks  # the load's .vtm, by region
    assert list(blocks.keys()) == list(r10.fe.region_tags)
    assert sum(b.n_cells for b in blocks) == len(r10.fe.cells)


def test_a_cached_mesh_gives_the_same_model(one_needle, tmp_path, monkeypatch):
    """run_needle_model takes its mesh from the mesh cache when it holds one for the geometry (gmsh not
    run, results' mesh.cached) and the answer is the uncached run's."""
    import needletissue.geometry.needle as nd

    monkeypatch.setenv(MESH_CACHE_ENV, str(tmp_path / "cache"))
    cfg = one_needle.config
    nd.mesh_needle_model(cfg.geometry, tmp_path / "fill.msh", order=cfg.order, cache=True)
    monkeypatch.setattr(nd, "_mesh", lambda *a, **k: pytest.fail("gmsh ran for a cached mesh"))
    res = run_needle_model(cfg)
    assert res.mesh["cached"] and not one_needle.mesh["cached"]
    assert res.mesh["dofs"] == one_needle.mesh["dofs"]
    a, b = one_needle.results[0], res.results[0]
    assert b.max_needle_deformation_mm == pytest.approx(a.max_needle_deformation_mm, rel=1e-9)
    assert np.abs(b.fe.displacement - a.fe.displacement).max() <= 1e-9 * np.abs(a.fe.displacement).max()
