"""Newton's method of fem.solve: the tangent is the derivative of the residual (checked by finite
differences, every material law of the needle model), and the modified-Newton substeps give the
same answer with fewer tangent assemblies and factorisations (docs/bench.md, "Newton")."""

import numpy as np
import pytest
from felupe.tools._newton import fun_items, jac_items, update

from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, linsolve, solve
from needletissue.errors import InputError
from needletissue.materials import TISSUE_BULK_RATIO, tissue_bulk

pardiso = pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")


def directional_error(body, x, v, h):
    """|(r(x + h v) - r(x - h v)) / 2h - K(x) v| / |K(x) v| for one body."""
    rp = fun_items([body], update(x, h * v))
    rm = fun_items([body], update(x, -h * v))
    fun_items([body], x)  # K at x: the body's matrix uses its last evaluated state
    Kv = jac_items([body], x) @ v
    return np.linalg.norm((rp - rm) / (2 * h) - Kv) / np.linalg.norm(Kv), Kv


@pytest.fixture(scope="module")
def loaded():
    """Bone / muscle (5-parameter Mooney-Rivlin) / adipose (Ogden) column, quadratic tets, sheared and
    pulled to finite strain (principal stretches beyond 1.2 in the tissue)."""
    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 7), layers={"cortical_bone": (0, 2), "muscle": (2, 8),
                                                         "adipose": (8, 12)})
    mats = {"cortical_bone": "cortical_bone", "muscle": "muscle", "adipose": "adipose"}
    # K = 100 mu0: displacement tetra10 locks and stalls at the default 10 MPa (8,571 mu0 for fat); the
    # check is of the laws' tangents, and the mixed body's internal state would make r(x) path-dependent
    model = FEModel(mesh, mats, order=2, formulation="displacement", bulk=tissue_bulk(mats, TISSUE_BULK_RATIO))
    r = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.2, 0.0, 0.4))], [1.0], progress=False)[-1]
    lam = r.cell_data["principal_stretches"]
    assert lam[:, 2].max() > 1.2  # finite strain: a wrong geometric or material tangent would show
    return model


@pytest.mark.parametrize("region", ["cortical_bone", "muscle", "adipose"])
def test_tangent_is_the_derivative_of_the_residual(loaded, region):
    """Central differences of each body's residual along a random direction match its assembled
    tangent to 1e-6 (the O(h^2) error is ~1e-9 here); a tangent off by 0.1 % fails the same test."""
    body = loaded.bodies[region]
    x = loaded.field
    v = np.random.default_rng(1).normal(size=x[0].values.size) * 1e-2
    err, Kv = directional_error(body, x, v, 1e-3)
    assert err < 1e-6
    # the check is not vacuous: the same comparison with a 0.1 % wrong tangent fails it
    rp = fun_items([body], update(x, 1e-3 * v))
    rm = fun_items([body], update(x, -1e-3 * v))
    fun_items([body], x)
    assert np.linalg.norm((rp - rm) / 2e-3 - 1.001 * Kv) / np.linalg.norm(Kv) > 1e-4


@pardiso
def test_pardiso_resolve_uses_the_kept_factor(monkeypatch):
    import scipy.sparse as sp

    monkeypatch.setattr(linsolve, "SINGLE", False)  # exact to round-off (the single factor: test_solvers)
    for reuse in (True, False):
        s = linsolve.TimedSolver("pardiso", linsolve._Pardiso(reuse))
        assert s.can_resolve
        A = (sp.diags([4.0] * 6) + sp.diags([1.0] * 5, 1) + sp.diags([1.0] * 5, -1)).tocsr()
        assert s.resolve(np.ones(6)) is None  # nothing kept yet
        s.keep_factor(True)
        s(A, np.ones(6))
        b = np.arange(6.0)
        np.testing.assert_allclose(A @ s.resolve(b), b, atol=1e-12)
        np.testing.assert_allclose(A @ s.resolve(2 * b), 2 * b, atol=1e-12)  # still kept
        s.release()
        assert s.resolve(b) is None
        s.close()


@pardiso
def test_substeps_same_answer_with_fewer_tangents():
    """A stiff cantilever (needle material) in large deflection: Newton with modified-Newton substeps
    reaches the field of plain Newton (same residual tolerance) with fewer tangent assemblies and
    factorisations; the substeps are counted."""
    mesh = TaggedMesh.box((30, 4, 4), (16, 3, 3), origin=(0, -2, -2), region="needle")
    out = {}
    for substeps in (0, None):
        model = FEModel(mesh, {"needle": "needle"}, order=2)
        out[substeps] = solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0, 0, 400.0))], [0.5, 1.0],
                              solver="pardiso", progress=False, results=False, substeps=substeps)
    assert np.abs(out[0][-1].displacement).max() > 1.0  # large deflection: several iterations per step
    for plain, sub in zip(out[0], out[None]):
        ref = plain.displacement
        np.testing.assert_allclose(sub.displacement, ref, rtol=0, atol=1e-7 * np.abs(ref).max())
        assert max(n[-1] for n in sub.residual_norms) < 1e-8
    assert out[0][-1].newton_substeps == 0
    assert out[None][-1].newton_substeps > 0
    assert out[None][-1].newton_iterations < out[0][-1].newton_iterations


def test_bodies_tangent_is_felupes_free_block():
    """fem.solve's direct assembly (the bodies' element matrices straight into the upper triangle of the
    free-free block, a fixed pattern, without FElupe's per-body sparsity patterns) gives FElupe's summed, partitioned tangent to round-off, in a
    deformed state of a mixed (P2/P0 tissue) three-region model, and its partitioned solve with a
    prescribed displacement (the K10 du0 term) gives FElupe's increment."""
    import felupe as fem
    import scipy.sparse as sp

    from needletissue.fem.model import PrescribedDisplacement
    from needletissue.fem.solve import _Bodies, _Loads

    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 6), layers={"cortical_bone": (0, 4), "muscle": (4, 8),
                                                         "adipose": (8, 12)})
    model = FEModel(mesh, {"cortical_bone": "cortical_bone", "muscle": "muscle", "adipose": "adipose"},
                    order=2, formulation="mixed")
    loads = _Loads(model, [Fixed("zmin"), PrescribedDisplacement("zmax", (0.3, None, 0.5))])
    x = model.field
    x[0].values[:] = np.random.default_rng(2).normal(size=x[0].values.shape) * 1e-2  # a deformed state
    items = list(model.bodies.values())
    ours = _Bodies(items, items, loads.dof1, loads.dof0, model.ndof)
    f = ours.fun(x)
    np.testing.assert_allclose(f, fun_items(items, x), rtol=0, atol=1e-12 * np.abs(f).max())
    upper, mats = ours.jac(x)
    from felupe.assembly._sparsity import _patterns
    assert not any(_patterns.get(b.field[0].indices) for b in items)  # FElupe's int64 positions not kept
    K = jac_items(items, x).tocsr()
    K11 = K[loads.dof1][:, loads.dof1]
    ref = sp.triu(K11).toarray()
    assert np.abs(ref).max() > 0 and upper.nnz >= sp.triu(K11).nnz
    np.testing.assert_allclose(upper.toarray(), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    ext0 = loads.apply(model, 1.0)
    assert np.any(ext0)

    def solver(A, b, upper=False):
        full = (A + sp.triu(A, 1).T) if upper else A
        return sp.linalg.spsolve(full.tocsc(), b)

    du = ours.solve((upper, mats), -f, x, loads.dof1, loads.dof0, ext0, solver)
    system = fem.solve.partition(x, K, loads.dof1, loads.dof0, f)
    ref = fem.solve.solve(*system, ext0, solver=solver)
    np.testing.assert_allclose(du, ref, rtol=0, atol=1e-9 * np.abs(ref).max())


def test_bodies_with_contact_items_give_felupes_whole_tangent_and_solve():
    """Contact runs assemble through _Bodies too (`extra`: the contact items): in a deformed state where the
    split interface's barrier and its friction are active (a non-symmetric tangent), the residual, the whole
    free-free block (the bodies' upper triangle mirrored, the item's matrix added) and K10 give FElupe's
    jac_items partition, and the partitioned solve with a prescribed displacement FElupe's increment."""
    import felupe as fem
    import scipy.sparse as sp

    from needletissue.fem.contact import ContactSettings, ContactSurface, FrictionalContact
    from needletissue.fem.contact.mesh import split_interfaces
    from needletissue.fem.model import PrescribedDisplacement
    from needletissue.fem.solve import _Bodies, _Loads

    mesh = TaggedMesh.box((6, 6, 8), (3, 3, 4), layers={"muscle": (0, 4), "adipose": (4, 8)})
    mesh, split = split_interfaces(mesh, ["muscle-adipose"])
    model = FEModel(mesh, {"muscle": "muscle", "adipose": "adipose"}, order=2)
    settings = ContactSettings(dhat=0.1, youngs_modulus=0.03, eps_v=1e-3)
    surface = ContactSurface.build(model.mesh.points, split, {"muscle-adipose": 0.3}, gap=settings.gap)
    item = FrictionalContact(model.field, surface, settings)
    # xmin held at x = 0 cuts through the interface: the item couples free and prescribed dofs (K10)
    loads = _Loads(model, [Fixed("zmin"), PrescribedDisplacement("zmax", (0.05, None, -0.02)),
                           PrescribedDisplacement("xmin", (0.0, None, None))])
    x = model.field
    X = model.mesh.points
    # the adipose slides 0.02 mm in x over the muscle and is pressed 0.01 mm into the barrier
    x[0].values[:] = np.where(X[:, 2:] > 4 - 1e-9, [0.02, 0.0, -0.01], 0.0)
    x[0].values[:] += np.random.default_rng(5).normal(size=X.shape) * 1e-4
    bodies = list(model.bodies.values())
    items = [*bodies, item]
    ours = _Bodies(items, bodies, loads.dof1, loads.dof0, model.ndof, extra=[item])
    f = ours.fun(x)
    assert item.results.info["active_contacts"] > 0
    ref = fun_items(items, x)
    np.testing.assert_allclose(f, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    A = ours.jac(x)
    K = jac_items(items, x).tocsr()
    K11 = K[loads.dof1][:, loads.dof1]
    assert abs(K11 - K11.T).max() > 1e-6 * abs(K11).max()  # friction: not symmetric
    ext0 = loads.apply(model, 1.0)
    seen = {}

    def solver(M, b, upper=False):
        assert not upper  # the whole matrix
        seen["K11"] = M.copy()
        return sp.linalg.spsolve(M.tocsc(), b)

    du = ours.solve(A, -f, x, loads.dof1, loads.dof0, ext0, solver)
    np.testing.assert_allclose(seen["K11"].toarray(), K11.toarray(), rtol=0, atol=1e-12 * abs(K11).max())
    assert abs(item.assemble.matrix().tocsr()[loads.dof1][:, loads.dof0]).max() > 0
    system = fem.solve.partition(x, K, loads.dof1, loads.dof0, f)
    expected = fem.solve.solve(*system, ext0, solver=lambda M, b: sp.linalg.spsolve(M.tocsc(), b))
    np.testing.assert_allclose(du, expected, rtol=0, atol=1e-9 * np.abs(expected).max())


def test_threaded_bodies_give_the_same_bits_and_stop_on_a_failing_body():
    """The bodies assembled on three threads give the residual and tangent of one thread bit for bit (the
    sums keep the bodies' order), FElupe's pattern cache is left as found, the threads end with close(); a
    body that fails raises its error from the threaded assembly as from the serial one."""
    import threading

    from felupe.assembly._sparsity import _patterns

    from needletissue.fem.solve import _Bodies, _Loads

    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 6), layers={"cortical_bone": (0, 3), "cancellous_bone": (3, 6),
                                                         "muscle": (6, 9), "adipose": (9, 12)})
    model = FEModel(mesh, {r: r for r in ("cortical_bone", "cancellous_bone", "muscle", "adipose")},
                    order=2, formulation="mixed")
    loads = _Loads(model, [Fixed("zmin"), SurfaceForce("zmax", (0.1, 0.0, 0.2))])
    x = model.field
    x[0].values[:] = np.random.default_rng(5).normal(size=x[0].values.shape) * 1e-2
    items = list(model.bodies.values())
    one = _Bodies(items, items, loads.dof1, loads.dof0, model.ndof, threads=1)
    three = _Bodies(items, items, loads.dof1, loads.dof0, model.ndof, threads=3)
    one.fun(x)  # the first residual of a mixed body also sets its state (FElupe): compare from the second
    f1, f3 = one.fun(x), three.fun(x)
    (u1, k1), (u3, k3) = one.jac(x), three.jac(x)
    assert np.abs(f1).max() > 0 and u1.nnz > 0 and three.pool is not None
    assert np.array_equal(f1, f3) and np.array_equal(u1.data, u3.data) and np.array_equal(k1.data, k3.data)
    assert not any(_patterns.get(b.field[0].indices) for b in items)
    with np.errstate(over="raise", invalid="ignore"):  # the caller's NumPy error state reaches the threads
        seen = list(three._ordered(lambda _: np.geterr(), range(4)))
    assert all(e["over"] == "raise" and e["invalid"] == "ignore" for e in seen)
    three.close()
    assert three.pool is None and not any(t.name.startswith("needletissue-assembly") for t in threading.enumerate())

    used, local = three.slots[2]
    three.slots[2] = (used, local[:-1])  # one body's values no longer fit its pattern
    with pytest.raises(RuntimeError, match="element-matrix values"):
        three.jac(x)
    three.close()


def test_a_dominant_body_evaluates_its_law_in_threaded_chunks_with_the_same_bits():
    """A body with more than half of the cells (adipose here) has its material law evaluated in chunks of
    cells on FElupe's threads while the bodies are assembled on threads: the residual and tangent of one
    thread bit for bit; the law's flag is restored by close()."""
    from needletissue.fem.solve import _Bodies, _Loads

    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 6), layers={"muscle": (0, 3), "adipose": (3, 12)})
    model = FEModel(mesh, {"muscle": "muscle", "adipose": "adipose"}, order=2, formulation="mixed")
    loads = _Loads(model, [Fixed("zmin"), SurfaceForce("zmax", (0.1, 0.0, 0.2))])
    x = model.field
    x[0].values[:] = np.random.default_rng(6).normal(size=x[0].values.shape) * 1e-2
    items = list(model.bodies.values())
    law = model.bodies["adipose"].umat
    law.chunksize = 64  # several chunks on this small mesh
    one = _Bodies(items, items, loads.dof1, loads.dof0, model.ndof, threads=1)
    one.fun(x)
    f1, (u1, k1) = one.fun(x), one.jac(x)
    two = _Bodies(items, items, loads.dof1, loads.dof0, model.ndof, threads=2)
    assert law.parallel and not model.bodies["muscle"].umat.parallel
    f2, (u2, k2) = two.fun(x), two.jac(x)
    assert np.array_equal(f1, f2) and np.array_equal(u1.data, u2.data) and np.array_equal(k1.data, k2.data)
    two.close()
    assert not law.parallel


def test_displacement_bodies_residual_by_bincount_equals_felupes_assembly_bit_for_bit():
    """_Bodies sums a displacement body's element force vectors with np.bincount instead of FElupe's COO -> CSR
    vector: the same bits, for tissue (Ogden, MR5) and elastic bodies; mixed bodies keep FElupe's assembly."""
    from needletissue.fem.solve import _Bodies

    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 6), layers={"cortical_bone": (0, 3), "muscle": (3, 6), "adipose": (6, 12)})
    for formulation in ("displacement", "mixed"):
        model = FEModel(mesh, {r: r for r in mesh.regions}, order=2, formulation=formulation)
        x = model.field
        x[0].values[:] = np.random.default_rng(7).normal(size=x[0].values.shape) * 5e-2
        for name, body in model.bodies.items():
            if formulation == "mixed" and name != "cortical_bone":
                continue  # FElupe's own assembly, and its condensed pressure moves with every call
            got = _Bodies._vector(body, x)
            ref = body.assemble.vector(field=body.field).toarray().ravel()
            assert np.abs(ref).max() > 0 and np.array_equal(got, ref), (formulation, name)


def test_predictor_with_nearly_incompressible_tissue():
    """Adipose column (P2/P0, K = 8,571 mu0) bent by a lateral tip load over three increments, 13 mm
    of 40: the increments started from the extrapolated displacement converge without a cut-back, in
    no more Newton iterations than from the last converged state, to the same field. With FElupe's own
    pressure at the extrapolated state (K x the linearised volume's second-order error, ~20x the
    equilibrium one here) the first tangent is indefinite and Newton diverges: 2 cut-backs."""
    mesh = TaggedMesh.box((10, 10, 40), (3, 3, 9), region="adipose")
    out = {}
    for predictor in (False, True):
        model = FEModel(mesh, {"adipose": "adipose"}, order=2, formulation="mixed")
        assert model.bulk["adipose"] / model.materials["adipose"].initial_shear_modulus > 8000
        out[predictor] = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.002, 0.0, 0.0))],
                               [1 / 3, 2 / 3, 1.0], progress=False, results=False, predictor=predictor)
    assert np.abs(out[True][-1].displacement).max() > 10.0  # large rotation of the column's top
    assert out[True][-1].cutbacks == 0
    assert out[True][-1].newton_iterations <= out[False][-1].newton_iterations
    for a, b in zip(out[True], out[False]):
        np.testing.assert_allclose(a.displacement, b.displacement, rtol=0, atol=1e-8 * np.abs(b.displacement).max())


def test_predictor_from_the_second_increment_starts_the_second_from_the_last_state():
    """predictor=2 (contact runs from rest, whose first increment closes the gaps): the first two increments
    as without a predictor, bit for bit, the third from the extrapolation, closer to equilibrium than from
    the last state. Anything but True, False or a whole number >= 1 is an InputError naming the field."""
    mesh = TaggedMesh.box((10, 10, 40), (3, 3, 9), region="adipose")
    out = {}
    for predictor in (False, 2):
        model = FEModel(mesh, {"adipose": "adipose"}, order=2, formulation="mixed")
        out[predictor] = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.002, 0.0, 0.0))],
                               [1 / 3, 2 / 3, 1.0], progress=False, results=False, predictor=predictor)[-1]
    plain, late = out[False].residual_norms, out[2].residual_norms
    assert late[:2] == plain[:2]
    assert late[2][0] < 0.5 * plain[2][0]
    for bad in (0, 1.5, -1, "2", float("nan")):
        with pytest.raises(InputError, match="predictor"):
            solve(model, [Fixed("zmin")], [1.0], progress=False, results=False, predictor=bad)
