"""Patch test: an affine deformation imposed on the boundary is reproduced exactly inside a distorted
mesh, for linear and quadratic tetrahedra, displacement and mixed formulations, with the nonlinear
tissue law; the reaction equals the analytic nominal stress times the face area."""

import numpy as np
import pytest

from needletissue import materials
from needletissue.fem import FEModel, PrescribedDisplacement, TaggedMesh, solve

F = np.array([[1.10, 0.05, 0.00], [0.02, 0.95, 0.03], [0.00, 0.04, 1.05]])  # homogeneous, J != 1


def distorted_box():
    m = TaggedMesh.box((10, 10, 10), (4, 4, 4), region="muscle")
    rng = np.random.default_rng(1)
    inner = np.all((m.points > 1e-9) & (m.points < 10 - 1e-9), axis=1)
    m.points[inner] += rng.uniform(-1.2, 1.2, (inner.sum(), 3))  # +-36 % of the 3.33 mm spacing
    m.check(min_quality=0.1)
    # every boundary face as one surface, for the Dirichlet data
    m.surfaces["boundary"] = np.concatenate([m.surfaces[k] for k in ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax")])
    return m


@pytest.mark.parametrize("order,formulation", [(1, "displacement"), (2, "displacement"), (2, "mixed")])
def test_affine_deformation_reproduced(order, formulation):
    mesh = distorted_box()
    model = FEModel(mesh, {"muscle": "muscle"}, order=order, formulation=formulation)
    X = model.mesh.points
    u_exact = X @ (F - np.eye(3)).T
    bcs = [PrescribedDisplacement("boundary", lambda x: x @ (F - np.eye(3)).T)]
    bnodes = model.mesh.surface_nodes("boundary")
    res = solve(model, bcs, [1.0], progress=False)[-1]
    inner = np.setdiff1d(np.arange(len(X)), bnodes)
    assert inner.size > 0
    np.testing.assert_allclose(res.displacement[inner], u_exact[inner], atol=1e-10 * np.abs(u_exact).max())
    # the stress is the same in every cell
    vm = res.cell_data["von_mises_MPa"]
    assert np.ptp(vm) < 1e-8 * vm.max()
    # and equals the material's Cauchy stress at F (FElupe's constitutive evaluation, no FE)
    mat = materials.get("muscle")
    umat = mat.umat(bulk=mat.bulk)
    P = umat.gradient([F.reshape(3, 3, 1, 1), None])[0][..., 0, 0]
    sigma = P @ F.T / np.linalg.det(F)
    s = sigma - np.trace(sigma) / 3 * np.eye(3)
    np.testing.assert_allclose(vm.mean(), np.sqrt(1.5 * np.sum(s * s)), rtol=1e-8)  # deviatoric: no pressure
    np.testing.assert_allclose(res.cell_data["principal_stretches"][0],
                               np.sqrt(np.linalg.eigvalsh(F.T @ F)), rtol=1e-10)
