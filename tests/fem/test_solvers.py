"""The three linear solvers give the same Newton solution; "auto" picks by size."""

import numpy as np
import pytest

from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, linsolve, solve


def test_solvers_agree():
    mesh = TaggedMesh.box((30, 4, 4), (16, 3, 3), origin=(0, -2, -2), region="needle")
    out = {}
    for name in ("scipy", "pardiso", "amg"):
        model = FEModel(mesh, {"needle": "needle"}, order=2)
        r = solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0, 0, 50.0))], [1.0], solver=name, progress=False)
        out[name] = r[-1]
        assert r[-1].linear_solver == name
    ref = out["pardiso"].displacement
    assert np.abs(ref).max() > 0.1
    for name in ("scipy", "amg"):
        np.testing.assert_allclose(out[name].displacement, ref, atol=1e-6 * np.abs(ref).max())


def test_auto_choice():
    assert linsolve.choose("auto", 1_000) == ("pardiso" if linsolve.has_pardiso() else "scipy")
    assert linsolve.choose("auto", 10 * linsolve.AUTO_DIRECT_MAX_DOFS) == "amg"
    assert linsolve.choose("scipy", 10**7) == "scipy"


def test_rigid_body_modes_are_null_space():
    """K B = 0 for the unconstrained stiffness: the near-null space AMG needs."""
    mesh = TaggedMesh.box((3, 2, 1), (3, 3, 2), region="needle")
    model = FEModel(mesh, {"needle": "needle"})
    K = model.bodies["needle"].assemble.matrix()
    B = linsolve.rigid_body_modes(mesh.points)
    assert np.abs(K @ B).max() < 1e-9 * abs(K).max()
