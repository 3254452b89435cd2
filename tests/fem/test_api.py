"""The published FE-core API on a small mesh: BCs by surface name, results, VTU, errors."""

import json

import meshio
import numpy as np
import pytest

from needletissue.errors import InputError
from needletissue.fem import FEModel, Fixed, PrescribedDisplacement, SurfaceForce, TaggedMesh, solve, write_results


@pytest.fixture(scope="module")
def two_layers():
    return TaggedMesh.box((10, 10, 8), (3, 3, 5), layers={"muscle": (0, 4), "adipose": (4, 8)})


def test_force_equilibrium_and_outputs(two_layers, tmp_path):
    """Reaction at the fixed base balances the applied total force (Newton's third law)."""
    model = FEModel(two_layers, {"muscle": "muscle", "adipose": "adipose"})
    F = np.array([0.05, 0.0, 0.1])
    res = solve(model, [Fixed("zmin"), SurfaceForce("zmax", tuple(F))], [0.5, 1.0], progress=False)
    assert [r.load_factor for r in res] == [0.5, 1.0]
    np.testing.assert_allclose(res[-1].reaction_forces["zmin"], -F, atol=1e-6 * np.abs(F).max())
    np.testing.assert_allclose(res[0].reaction_forces["zmin"], -F / 2, atol=1e-6 * np.abs(F).max())
    # the softer, load-carrying top layer moves most; fixed nodes do not move
    assert res[-1].max_displacement_by_region["adipose"] > res[-1].max_displacement_by_region["muscle"] > 0
    assert np.abs(res[-1].displacement[two_layers.surface_nodes("zmin")]).max() == 0
    d = res[-1].to_dict()
    assert d["mesh_stats"]["cells_by_region"] == {"muscle": 2 * 2 * 2 * 6, "adipose": 2 * 2 * 2 * 6}  # 6 tets per hex
    assert d["steps"] >= 2 and d["newton_iterations"] >= d["steps"]
    path = res[-1].write_vtu(tmp_path / "out.vtu")
    m = meshio.read(path)
    assert set(m.cell_data) >= {"von_mises_MPa", "principal_stretches", "region"}
    np.testing.assert_allclose(m.point_data["displacement"], res[-1].displacement)
    payload = write_results(tmp_path / "run", res, {"load_N": 1.0})
    saved = json.loads((tmp_path / "run" / "results.json").read_text(encoding="utf-8"))
    assert saved == json.loads(json.dumps(payload)) and payload["vtu"] == ["fe_0.vtu", "fe_1.vtu"]
    assert (tmp_path / "run" / "versions.json").exists() and (tmp_path / "run" / "config.toml").exists()


def test_prescribed_displacement_is_reproduced(two_layers):
    model = FEModel(two_layers, {"muscle": "muscle", "adipose": "adipose"}, order=2, formulation="mixed")
    res = solve(model, [Fixed("zmin"), PrescribedDisplacement("zmax", (None, None, 2.0))], [1.0], progress=False)
    top = model.mesh.surface_nodes("zmax")
    np.testing.assert_allclose(res[0].displacement[top, 2], 2.0, rtol=1e-12)
    # pulling up needs an upward force at the top and a downward one at the base
    assert res[0].reaction_forces["zmax"][2] > 0
    np.testing.assert_allclose(res[0].reaction_forces["zmin"], -res[0].reaction_forces["zmax"], atol=1e-8)


def test_bad_input_names_the_field(two_layers):
    with pytest.raises(InputError, match="materials"):
        FEModel(two_layers, {"muscle": "muscle"})
    model = FEModel(two_layers, {"muscle": "muscle", "adipose": "adipose"})
    with pytest.raises(InputError, match="unknown surface 'gripper'"):
        solve(model, [Fixed("zmin"), SurfaceForce("gripper", (1, 0, 0))], progress=False)
    with pytest.raises(InputError, match="load_factors"):
        solve(model, [Fixed("zmin")], [1.0, 0.5], progress=False)
    with pytest.raises(InputError, match="solver"):
        solve(model, [Fixed("zmin")], solver="mumps", progress=False)


def test_progress_bar_goes_to_stderr(two_layers, capsys):
    """The Rich bar reports on stderr (stdout stays clean for --json) with Newton residuals."""
    model = FEModel(two_layers, {"muscle": "muscle", "adipose": "adipose"})
    solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.0, 0.0, 0.1))], [1.0], progress=True)
    out = capsys.readouterr()
    assert out.out == ""
    assert "Newton" in out.err and "|r|" in out.err


def test_reactions_of_supports_sharing_nodes_sum_to_minus_the_load(two_layers):
    """zmin and xmin share an edge of nodes: each constrained dof's reaction counts once (for the
    first condition fixing it), so the supports together balance the applied force (equilibrium)."""
    F = np.array([0.05, 0.02, 0.1])
    for bcs in ([Fixed("zmin"), Fixed("xmin")], [Fixed("xmin"), Fixed("zmin", components=(2,))]):
        model = FEModel(two_layers, {"muscle": "muscle", "adipose": "adipose"})
        r = solve(model, [*bcs, SurfaceForce("zmax", tuple(F))], [1.0], progress=False)[-1]
        total = r.reaction_forces["zmin"] + r.reaction_forces["xmin"]
        np.testing.assert_allclose(total, -F, atol=1e-6 * np.abs(F).max())
        assert np.abs(r.reaction_forces["zmin"]).max() > 0.1 * np.abs(F).max()  # both supports carry load
        assert np.abs(r.reaction_forces["xmin"]).max() > 0.1 * np.abs(F).max()


@pytest.mark.parametrize("quadratic", [False, True])
def test_surface_moment_is_an_exact_self_equilibrated_couple(quadratic):
    """SurfaceForce.moment: nodal forces linear in position whose sum is zero and whose moment about
    the area centroid is the given moment, on linear and quadratic faces, any direction."""
    from needletissue.fem.solve import _couple

    mesh = TaggedMesh.box((10, 6, 8), (3, 2, 4))
    if quadratic:
        mesh = mesh.to_quadratic()
    for surface in ("zmax", "xmin"):
        nodes, w = mesh.nodal_area_weights(surface)
        x = mesh.points[nodes]
        M = np.array([120.0, -45.0, 300.0])
        f = _couple(x, w, SurfaceForce(surface, moment=tuple(M)))
        c = (w @ x) / w.sum()
        np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-10)
        np.testing.assert_allclose(np.cross(x - c, f).sum(axis=0), M, rtol=1e-12)
    with pytest.raises(InputError, match="moment"):
        _couple(x, w, SurfaceForce("zmax", moment=(1.0, 2.0)))
