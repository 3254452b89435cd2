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


def test_tensors_drucker_flag_and_paraview_files(tmp_path):
    """Under the homogeneous F: every cell's Cauchy tensor is the material's sigma(F) (FElupe's
    constitutive evaluation), its Green-Lagrange strain (F^T F - I) / 2, its Drucker flag the verdict of
    materials.stability at F; the VTU names regions, materials and frame in field data, the .pvd lists
    the loads with their load factor as time."""
    import meshio

    from needletissue.fem.result import write_results
    from needletissue.materials.stability import stable_at

    model = FEModel(distorted_box(), {"muscle": "muscle"}, order=1)
    bcs = [PrescribedDisplacement("boundary", lambda x: x @ (F - np.eye(3)).T)]
    results = solve(model, bcs, [0.5, 1.0], progress=False)
    res = results[-1]
    mat = materials.get("muscle")
    P = mat.umat(bulk=mat.bulk).gradient([F.reshape(3, 3, 1, 1), None])[0][..., 0, 0]
    sigma = P @ F.T / np.linalg.det(F)
    np.testing.assert_allclose(res.cell_data["cauchy_stress_MPa"], np.tile(sigma.ravel(), (len(model.mesh.cells), 1)),
                               rtol=1e-6, atol=1e-7 * np.abs(sigma).max())  # stored as float32
    np.testing.assert_allclose(res.cell_data["green_lagrange_strain"][0], (0.5 * (F.T @ F - np.eye(3))).ravel(),
                               atol=1e-7)
    assert set(res.cell_data["drucker_stable"]) == {int(stable_at("muscle", F.reshape(3, 3, 1))[0])}
    assert res.materials == {"muscle": "muscle"}
    assert res.drucker_unstable_fraction["muscle"] in (0.0, 1.0)
    payload = write_results(tmp_path, results, {})
    m = meshio.read(tmp_path / payload["vtu"][-1])
    assert "region 0 = muscle (material muscle)" in m.field_data and m.field_data["load_factor"][0] == 1.0
    assert any(k.startswith("coordinate frame: ") for k in m.field_data)
    assert m.cell_data["cauchy_stress_MPa"][0].shape == (len(model.mesh.cells), 9)
    pvd = (tmp_path / "fe.pvd").read_text(encoding="utf-8")
    assert 'timestep="0.5" part="0" file="fe_0.vtm"' in pvd and 'timestep="1.0" part="0" file="fe_1.vtm"' in pvd


def test_tissue_beyond_its_drucker_range_is_flagged_and_warned():
    """Muscle (MR5) stretched uniaxially 5 % beyond its Drucker-stable range (materials.stability): the
    whole block is flagged, with a warning; 5 % inside it, nothing is."""
    import warnings

    from needletissue.materials.stability import UnstableMaterialWarning, stable_range

    _, hi = stable_range("mooney_rivlin_5", materials.get("muscle").parameters, "uniaxial")
    for lam, expect in ((0.95 * hi, 0.0), (1.05 * hi, 1.0)):
        Fu = np.diag([lam ** -0.5, lam ** -0.5, lam])  # isochoric uniaxial stretch
        model = FEModel(distorted_box(), {"muscle": "muscle"}, order=1)
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            res = solve(model, [PrescribedDisplacement("boundary", lambda x: x @ (Fu - np.eye(3)).T)], [1.0],
                        progress=False)[-1]
        assert res.drucker_unstable_fraction["muscle"] == pytest.approx(expect)
        warned = [x for x in w if issubclass(x.category, UnstableMaterialWarning) and "muscle" in str(x.message)]
        assert bool(warned) == bool(expect)
