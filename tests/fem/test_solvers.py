"""The three linear solvers give the same Newton solution; "auto" picks by size."""

import importlib

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
    if linsolve.has_pardiso():  # tetra10's factor is denser: AMG from fewer dofs than with linear tets
        lo, hi = linsolve.AUTO_DIRECT_MAX_DOFS_QUADRATIC, linsolve.AUTO_DIRECT_MAX_DOFS
        assert lo < hi
        assert linsolve.choose("auto", (lo + hi) // 2, order=1) == "pardiso"
        assert linsolve.choose("auto", (lo + hi) // 2, order=2) == "amg"
        assert linsolve.choose("auto", lo, order=2) == linsolve.choose("auto", hi, order=1) == "pardiso"
    assert linsolve.choose("scipy", 10**7) == "scipy"


def test_rigid_body_modes_are_null_space():
    """K B = 0 for the unconstrained stiffness: the near-null space AMG needs."""
    mesh = TaggedMesh.box((3, 2, 1), (3, 3, 2), region="needle")
    model = FEModel(mesh, {"needle": "needle"})
    K = model.bodies["needle"].assemble.matrix()
    B = linsolve.rigid_body_modes(mesh.points)
    assert np.abs(K @ B).max() < 1e-9 * abs(K).max()


@pytest.mark.parametrize("name", ["scipy", "pardiso", "amg"])
def test_bad_systems_raise_linalgerror(name):
    """NaN residuals and singular matrices become LinAlgError, which solve() turns into a cut-back."""
    import scipy.sparse as sp

    s = linsolve.make(name, np.zeros((2, 3)), np.arange(6))
    A = sp.identity(6, format="csr")
    with pytest.raises(np.linalg.LinAlgError):
        s(A, np.full(6, np.nan))
    with pytest.raises(np.linalg.LinAlgError):
        s(sp.csr_matrix((6, 6)), np.ones(6))


def test_amg_handles_nonsymmetric_tangent():
    """A frictional contact makes the tangent non-symmetric: AMG switches from CG to GMRES."""
    import scipy.sparse as sp

    mesh = TaggedMesh.box((10, 4, 4), (8, 3, 3), region="needle")
    model = FEModel(mesh, {"needle": "needle"})
    K = model.bodies["needle"].assemble.matrix().tocsr()
    free = np.arange(9, K.shape[0])  # drop the first 3 nodes: no rigid-body modes left
    A = K[free][:, free]
    A = (A + 1e-3 * abs(A).max() * sp.random(*A.shape, density=1e-3, random_state=0, format="csr")).tocsr()
    assert abs(A - A.T).max() > 0  # non-symmetric
    b = np.random.default_rng(0).normal(size=A.shape[0])
    x = linsolve.make("amg", mesh.points, free)(A, b)
    assert np.linalg.norm(A @ x - b) < 1e-6 * np.linalg.norm(b)


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_pardiso_analysis_reused_same_field(monkeypatch):
    """The sparsity of a bonded model does not change: Pardiso analyses once for all Newton iterations
    and load steps, and the field is the one of a fresh analysis per iteration (to 1e-6 of max |u|)."""
    mesh = TaggedMesh.box((30, 4, 4), (16, 3, 3), origin=(0, -2, -2), region="needle")
    made = []
    make = linsolve.make

    def spy(*a, **k):
        made.append(make(*a, **k))
        return made[-1]

    monkeypatch.setattr(linsolve, "make", spy)
    out = {}
    for reuse in (False, True):
        monkeypatch.setattr(linsolve, "REUSE_ANALYSIS", reuse)
        model = FEModel(mesh, {"needle": "needle"}, order=2)
        # plain Newton (no substeps): a factorisation per iteration, all on one analysis
        r = solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0, 0, 400.0))], [0.5, 1.0], solver="pardiso",
                  progress=False, substeps=0)
        out[reuse] = r[-1]
    s = made[-1]._fun
    # one pattern: fem.solve assembles into a fixed one (the undeformed tangent's exact zeros kept)
    assert out[True].newton_iterations == out[False].newton_iterations >= 4 and s.analyses == 1
    assert s.pattern == {}  # released when the solve ended
    ref = out[False].displacement
    assert np.abs(ref).max() > 1.0  # large deflection: several iterations per step
    np.testing.assert_allclose(out[True].displacement, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_pardiso_reanalyses_when_the_pattern_changes():
    import scipy.sparse as sp

    s = linsolve.make("pardiso")
    A = sp.diags([4.0] * 6).tocsr() + sp.diags([1.0] * 5, 1) + sp.diags([1.0] * 5, -1)
    x = s(A.tocsr(), np.ones(6))
    np.testing.assert_allclose(A @ x, 1.0)
    x = s((2 * A).tocsr(), np.ones(6))  # same pattern: no new analysis
    np.testing.assert_allclose(2 * A @ x, 1.0)
    B = (A + sp.diags([0.5] * 4, 2) + sp.diags([0.5] * 4, -2)).tocsr()
    x = s(B, np.ones(6))
    np.testing.assert_allclose(B @ x, 1.0)
    assert s._fun.analyses == 2
    # a pattern within the analysed one (contact pairs gone again): no new analysis, the same solution
    x = s((3 * A).tocsr(), np.ones(6))
    np.testing.assert_allclose(3 * A @ x, 1.0)
    C = (A + sp.diags([0.5] * 3, 3) + sp.diags([0.5] * 3, -3)).tocsr()  # outside: analyse the union of B and C
    x = s(C, np.ones(6))
    np.testing.assert_allclose(C @ x, 1.0)
    x = s(B, np.ones(6))  # within the union
    np.testing.assert_allclose(B @ x, 1.0)
    assert s._fun.analyses == 3 and len(s._fun.pattern) == 1
    s.close()


def test_a_matrix_fits_the_analysed_pattern_or_their_union():
    """linsolve._fit puts M on the analysed pattern (the same matrix, zeros where M has none) or, when M has an
    entry outside it, on the union of both patterns, which then holds each of them: against dense arithmetic."""
    import scipy.sparse as sp

    rng = np.random.default_rng(3)

    def random_csr(density):
        M = sp.random(40, 40, density=density, random_state=rng, format="csr") + sp.eye(40)
        M.sort_indices()
        return M.tocsr()

    A = random_csr(0.2)
    same, pattern = linsolve._fit(A, (A.indptr, A.indices))
    assert same is A and pattern[1] is A.indices
    sub = sp.csr_matrix(A.multiply(rng.random(A.shape) < 0.5))
    sub.eliminate_zeros()
    on, pattern = linsolve._fit(sub, (A.indptr, A.indices))
    assert pattern[1] is A.indices and on.nnz == A.nnz
    np.testing.assert_array_equal(on.toarray(), sub.toarray())
    B = random_csr(0.1)
    on, (indptr, indices) = linsolve._fit(B, (A.indptr, A.indices))
    union = (A != 0).toarray() | (B != 0).toarray()
    assert on.nnz == union.sum()
    np.testing.assert_array_equal(sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=A.shape).toarray(),
                                  union.astype(float))
    np.testing.assert_array_equal(on.toarray(), B.toarray())
    # the merge's edge cases: rows empty in either pattern, entries in the first and last columns
    for density in (0.02, 0.05, 0.5):
        A = sp.random(40, 40, density=density, random_state=rng, format="csr")
        B = sp.random(40, 40, density=density, random_state=rng, format="lil")
        B[0, 0], B[39, 39], B[5, 39] = 1.0, 2.0, 3.0
        B = B.tocsr()
        for M in (A, B):
            M.sort_indices()
        on, (indptr, indices) = linsolve._fit(B, (A.indptr, A.indices))
        union = (A != 0).toarray() | (B != 0).toarray()
        np.testing.assert_array_equal(
            sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=A.shape).toarray(), union.astype(float))
        np.testing.assert_array_equal(on.toarray(), B.toarray())


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_metis_ordering_is_a_permutation_that_pardiso_uses_for_the_same_solution(monkeypatch):
    """METIS 5's nested dissection (linsolve.ORDERING = "metis") reorders the Cholesky: a permutation of
    the rows, handed to Pardiso (iparm 5 = 1), which then solves the tetra10 stiffness to the same x as
    with its own METIS to round-off and fills no more of the factor."""
    import scipy.sparse as sp

    upper, A = _clamped_needle_tangent()  # the x = 0 face clamped: positive definite
    perm = linsolve.nested_dissection(upper)
    assert perm.dtype == np.int32 and np.array_equal(np.sort(perm), np.arange(upper.shape[0]))
    assert linsolve.nested_dissection(sp.identity(5, format="csr")) is None  # nothing to order
    b = np.random.default_rng(1).normal(size=upper.shape[0])
    x, fill = {}, {}
    monkeypatch.setattr(linsolve, "SINGLE", False)  # the double factor's round-off
    for ordering in ("mkl", "metis"):
        monkeypatch.setattr(linsolve, "ORDERING", ordering)
        s = linsolve.make("pardiso")
        x[ordering] = s(upper, b, upper=True)
        ps = s._fun.solvers[2]
        assert ps.iparm[4] == (1 if ordering == "metis" else 0)
        fill[ordering] = ps.iparm[17]
        s.close()
    assert np.linalg.norm(A @ x["metis"] - b) < 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(x["metis"], x["mkl"], rtol=0, atol=1e-9 * np.abs(x["mkl"]).max())
    assert 0 < fill["metis"] <= fill["mkl"]


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_lu_of_a_nonsymmetric_tangent_is_ordered_by_metis_without_refinement_steps(monkeypatch):
    """The LU (frictional contact's non-symmetric tangents) runs on LU_IPARM: METIS 5's ordering handed to Pardiso
    and no iterative refinement unless a pivot was perturbed (MKL's iparm[0] = 0 refined every solve twice); the same
    solution to round-off as with Pardiso's own ordering, the residual at the double factor's accuracy."""
    # the assembled block itself (not _clamped_needle_tangent's symmetrised copy): the fill comparison below is of
    # this matrix's orderings
    mesh = TaggedMesh.box((30, 4, 4), (12, 3, 3), origin=(0, -2, -2), region="needle")
    K = FEModel(mesh, {"needle": "needle"}, order=2).bodies["needle"].assemble.matrix().tocsr()
    fixed = np.flatnonzero(np.isclose(mesh.points[:, 0], 0.0))
    free = np.setdiff1d(np.arange(K.shape[0]), (3 * fixed[:, None] + np.arange(3)).ravel())
    A = _nonsymmetric(K[free][:, free])
    assert abs(A - A.T).max() > 0
    b = np.random.default_rng(2).normal(size=A.shape[0])
    x, fill = {}, {}
    for ordering in ("mkl", "metis"):
        monkeypatch.setattr(linsolve, "ORDERING", ordering)
        s = linsolve.make("pardiso")
        x[ordering] = s(A, b)
        ps = s._fun.solvers[11]
        assert (ps.iparm[0], ps.iparm[4], ps.iparm[6], ps.iparm[13]) == (1, 1 if ordering == "metis" else 0, 0, 0)
        fill[ordering] = ps.iparm[17]
        s.close()
    assert np.linalg.norm(A @ x["metis"] - b) < 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(x["metis"], x["mkl"], rtol=0, atol=1e-9 * np.abs(x["mkl"]).max())
    assert 0 < fill["metis"] <= fill["mkl"]


def test_after_a_nonsymmetric_matrix_the_lu_solves_the_next_ones_without_testing_them(monkeypatch):
    """A symmetric matrix is tested and factored by Cholesky; after the first non-symmetric one (implicit friction)
    Pardiso goes to its LU at once (no A - A^T, 40-70 ms per call on the coarse needle model), also for a symmetric
    one, with the solution to round-off."""
    S = _clamped_needle_tangent()[1]
    A = _nonsymmetric(S)
    b = np.random.default_rng(2).normal(size=A.shape[0])
    solver = linsolve.make("pardiso")
    x_sym = solver(S, b)
    assert list(solver._fun.pattern) == [2]  # Cholesky
    x = solver(A, b)
    assert 11 in solver._fun.pattern
    tests = []
    real_abs = abs

    def counting_abs(m):
        tests.append(1)
        return real_abs(m)

    monkeypatch.setattr("builtins.abs", counting_abs)
    y, y_sym = solver(A, b), solver(S, b)
    monkeypatch.undo()
    assert not tests
    np.testing.assert_allclose(y, x, rtol=0, atol=1e-10 * np.abs(x).max())
    # the first solve was the single-precision Cholesky refined by CG to SINGLE_RTOL (1e-8 of |b|: on this tangent
    # 1e-10 to 2.4e-10 of max |x| from the exact solution, with the CPU's MKL code path); the LU's to round-off
    assert np.linalg.norm(S @ y_sym - b) <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(y_sym, x_sym, rtol=0, atol=1e-8 * np.abs(x_sym).max())
    solver.close()


def test_metis_ordering_of_a_pattern_met_before_comes_from_the_cache(tmp_path, monkeypatch):
    """The ordering of a sparsity pattern met before is read from the mesh cache, the same permutation
    METIS computes (pymetis not called); another pattern is a miss; a damaged entry is a miss, rewritten."""
    import pymetis
    import scipy.sparse as sp

    from needletissue.cache import MESH_CACHE_ENV

    monkeypatch.setenv(MESH_CACHE_ENV, str(tmp_path))
    mesh = TaggedMesh.box((30, 4, 4), (12, 3, 3), origin=(0, -2, -2), region="needle")
    upper = sp.triu(FEModel(mesh, {"needle": "needle"}).bodies["needle"].assemble.matrix(), format="csr")
    monkeypatch.setenv(MESH_CACHE_ENV, "0")
    fresh = linsolve.nested_dissection(upper)
    monkeypatch.setenv(MESH_CACHE_ENV, str(tmp_path))
    assert np.array_equal(linsolve.nested_dissection(upper), fresh)   # a miss: computed and stored
    real = pymetis.nested_dissection
    monkeypatch.setattr(pymetis, "nested_dissection", lambda *a, **k: pytest.fail("METIS ran"))
    hit = linsolve.nested_dissection(upper.copy())                     # the same pattern, another matrix
    assert np.array_equal(hit, fresh) and hit.dtype == np.int32
    with pytest.raises(pytest.fail.Exception, match="METIS ran"):
        linsolve.nested_dissection(upper[:-3, :-3].tocsr())
    monkeypatch.setattr(pymetis, "nested_dissection", real)
    (entry,) = tmp_path.glob("*.perm.npy")
    entry.write_bytes(entry.read_bytes()[:100])
    assert np.array_equal(linsolve.nested_dissection(upper), fresh)
    assert np.array_equal(np.load(entry), fresh)                         # rewritten whole


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_mkl_reproducibility_only_on_request_before_mkl_loads():
    """MKL_CBWR=AUTO when a contact run asks before MKL is loaded (Pardiso on two threads: the same bits in
    every run); not by default (it slows the bonded solves), and not once MKL is loaded."""
    import os
    import subprocess
    import sys

    def run(code):
        env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
        return subprocess.run([sys.executable, "-c", "from needletissue.fem import linsolve; " + code], env=env,
                              capture_output=True, text=True, check=True).stdout.split()[-1]

    assert run("print(linsolve.mkl_reproducible())") == "False"
    assert run("linsolve.request_reproducible_mkl(); print(linsolve.mkl_reproducible())") == "True"
    assert run("linsolve.make('pardiso'); linsolve.request_reproducible_mkl(); print(linsolve.mkl_reproducible())") == "False"


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_contact_solves_keep_two_pardiso_threads_only_when_mkl_is_reproducible(monkeypatch):
    """Contact solves (reproducible=True) run on PARDISO_THREADS with MKL's reproducibility on, on one MKL
    thread without it; MKL_NUM_THREADS set by the user wins."""
    from threadpoolctl import threadpool_info

    linsolve.make("pardiso")  # loads MKL
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)

    def mkl_threads():
        return [i["num_threads"] for i in threadpool_info() if i.get("internal_api") == "mkl"]

    if not mkl_threads():
        pytest.skip("MKL not visible to threadpoolctl")
    monkeypatch.setattr(linsolve, "PARDISO_THREADS", 2)
    monkeypatch.setattr(linsolve, "mkl_reproducible", lambda: True)
    with linsolve.thread_limits("pardiso", reproducible=True):
        assert mkl_threads() == [2] * len(mkl_threads())
    monkeypatch.setattr(linsolve, "mkl_reproducible", lambda: False)
    with linsolve.thread_limits("pardiso", reproducible=True):
        assert mkl_threads() == [1] * len(mkl_threads())
    with linsolve.thread_limits("pardiso"):
        assert mkl_threads() == [2] * len(mkl_threads())


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_pardiso_gets_one_thread_per_core_whatever_set_mkl_before(monkeypatch):
    """The anatomical model's in-process gmsh mesh left MKL on one thread (its OpenMP runtime set to gmsh's
    thread count): a solve sets MKL's threads itself, one per core by default."""
    import os

    from threadpoolctl import ThreadpoolController, threadpool_info

    linsolve.make("pardiso")  # loads MKL
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    monkeypatch.setattr(linsolve, "PARDISO_THREADS", None)

    def mkl_threads():
        return [i["num_threads"] for i in threadpool_info() if i.get("internal_api") == "mkl"]

    if not mkl_threads():
        pytest.skip("MKL not visible to threadpoolctl")
    limiter = ThreadpoolController().select(internal_api="mkl").limit(limits=1)  # what the mesher left
    try:
        with linsolve.thread_limits("pardiso"):
            assert mkl_threads() == [len(os.sched_getaffinity(0))] * len(mkl_threads())
    finally:
        limiter.restore_original_limits()


def _clamped_needle_tangent(n=(30, 4, 4), cells=(12, 3, 3)):
    """The tetra10 stiffness of a steel bar clamped at x = 0 (positive definite): upper triangle, full matrix."""
    import scipy.sparse as sp

    mesh = TaggedMesh.box(n, cells, origin=(0, -2, -2), region="needle")
    K = FEModel(mesh, {"needle": "needle"}, order=2).bodies["needle"].assemble.matrix().tocsr()
    fixed = np.flatnonzero(np.isclose(mesh.points[:, 0], 0.0))
    free = np.setdiff1d(np.arange(K.shape[0]), (3 * fixed[:, None] + np.arange(3)).ravel())
    upper = sp.triu(K[free][:, free], format="csr")
    upper.sort_indices()
    return upper, (upper + sp.triu(upper, 1).T).tocsr()


def _nonsymmetric(S):
    """S plus a sparse random non-symmetric part of 1e-3 of its largest entry (a friction-like tangent), CSR."""
    import scipy.sparse as sp

    return (S + 1e-3 * abs(S).max() * sp.random(*S.shape, density=1e-3, random_state=0, format="csr")).tocsr()


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_single_precision_cholesky_is_refined_by_cg_to_the_double_solution(monkeypatch):
    """linsolve.SINGLE: Pardiso factors the tangent in single precision (iparm 28 = 1, half the factor's
    memory) and CG on the double matrix, preconditioned by that factor, brings the solution to SINGLE_RTOL;
    a substep's resolve is one single-precision back-substitution; a tangent whose CG does not converge is
    factored in double, and so is every later one."""
    upper, A = _clamped_needle_tangent()
    b = np.random.default_rng(2).normal(size=A.shape[0])
    monkeypatch.setattr(linsolve, "SINGLE", False)
    d = linsolve.make("pardiso")
    ref = d(upper, b, upper=True)
    d.close()
    monkeypatch.setattr(linsolve, "SINGLE", True)
    s = linsolve.make("pardiso")
    s.keep_factor(True)
    x = s(upper, b, upper=True)
    assert s._fun.solvers[2].iparm[27] == 1 and s.factor == "single+cg"  # the factor is single precision
    assert np.linalg.norm(A @ x - b) <= linsolve.SINGLE_RTOL * np.linalg.norm(b)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    y = s.resolve(b)  # one back-substitution with the single factor: close, not exact
    err = np.abs(y - ref).max() / np.abs(ref).max()
    kappa, eps32 = np.linalg.cond(A.toarray()), np.finfo(np.float32).eps  # kappa 1.3e6 here
    assert kappa * np.finfo(float).eps < eps32 < err < kappa * eps32  # single, not double; within its bound
    s.release()
    monkeypatch.setattr(linsolve, "SINGLE_MAXITER", 0)  # CG may not iterate: it cannot reach SINGLE_RTOL
    x = s(upper, b, upper=True)
    assert s.factor == "double" and s._fun.solvers[2].iparm[27] == 0  # double from now on
    assert np.linalg.norm(A @ x - b) < 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(s.resolve(b), x, rtol=0, atol=1e-12 * np.abs(x).max())  # a double factor kept
    s.close()


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_single_precision_newton_reaches_the_double_field(monkeypatch):
    """The Newton solution does not depend on the factor's precision (same tolerance on the residual):
    a large-deflection cantilever with substeps, single against double, to 1e-7 of max |u|."""
    mesh = TaggedMesh.box((30, 4, 4), (16, 3, 3), origin=(0, -2, -2), region="needle")
    out = {}
    for single in (False, True):
        monkeypatch.setattr(linsolve, "SINGLE", single)
        model = FEModel(mesh, {"needle": "needle"}, order=2)
        out[single] = solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0, 0, 400.0))], [0.5, 1.0],
                            solver="pardiso", progress=False, results=False)
    ref = out[False][-1].displacement
    assert np.abs(ref).max() > 1.0
    np.testing.assert_allclose(out[True][-1].displacement, ref, rtol=0, atol=1e-7 * np.abs(ref).max())
    assert max(n[-1] for n in out[True][-1].residual_norms) < 1e-8
    assert (out[True][-1].linear_factor, out[False][-1].linear_factor) == ("single+cg", "double")


def test_assembly_and_vtu_threads_follow_the_share_granted_in_mkl_num_threads(monkeypatch):
    """One rule for the threads a process may use: a stage given MKL_NUM_THREADS=1 beside another (report.pipeline)
    assembles and writes VTU on one thread; without it, one per core; ASSEMBLY_THREADS overrides assembly only."""
    import os

    from needletissue.fem import result
    solver = importlib.import_module("needletissue.fem.solve")  # the package exports the function

    monkeypatch.setattr(solver, "ASSEMBLY_THREADS", None)
    monkeypatch.setenv("MKL_NUM_THREADS", "1")
    with result._writers() as pool:
        assert (linsolve.granted_threads(), solver.assembly_threads(), pool._max_workers) == (1, 1, 1)
    monkeypatch.delenv("MKL_NUM_THREADS")
    cores = len(os.sched_getaffinity(0))
    with result._writers() as pool:
        assert (linsolve.granted_threads(), solver.assembly_threads(), pool._max_workers) == (cores, cores, cores)
    monkeypatch.setattr(solver, "ASSEMBLY_THREADS", 3)
    assert solver.assembly_threads() == 3 and linsolve.granted_threads() == cores


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_a_kept_double_factor_keeps_its_matrix_when_the_caller_drops_the_values(monkeypatch):
    """fem.solve._Bodies.solve drops the tangent's values after its solve (the substeps need only the factor). A kept
    double factor whose back-substitution reads A (two steps of iterative refinement, as Pardiso's LDL^T does on
    perturbed pivots) must still see them: resolve equals the solve."""
    from types import SimpleNamespace

    from needletissue.fem.solve import _Bodies

    upper, A = _clamped_needle_tangent()
    n = A.shape[0]
    b = np.random.default_rng(3).normal(size=n)
    monkeypatch.setattr(linsolve, "SINGLE", False)
    monkeypatch.setitem(linsolve.CHOLESKY_IPARM, 8, 2)  # phase 33 refines against A's values
    s = linsolve.make("pardiso")
    s.keep_factor(True)
    x = _Bodies.solve(SimpleNamespace(n=n), (upper, None), b, SimpleNamespace(fields=[SimpleNamespace(values=np.zeros(0))]),
                      np.arange(n), np.zeros(0, int), np.zeros(0), s)  # all dofs free
    assert upper.data.size == 0  # the caller's values are gone
    np.testing.assert_allclose(A @ x, b, rtol=0, atol=1e-8 * np.abs(b).max())
    np.testing.assert_allclose(s.resolve(b), x, rtol=0, atol=1e-12 * np.abs(x).max())
    s.close()


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc's malloc arenas")
@pytest.mark.parametrize("arena_max", [None, "8"])
def test_the_assembly_threads_allocate_from_the_main_heap(arena_max):
    """needletissue sets glibc's M_ARENA_MAX to 1 on import (docs/bench.md, "One heap for the assembly threads"):
    after a solve assembled on two threads, malloc_stats() lists only the main heap; a MALLOC_ARENA_MAX the user
    set is left alone, and then the threads get heaps of their own (what the setting removes)."""
    import os
    import re
    import subprocess
    import sys

    code = """
import ctypes, importlib
from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve
importlib.import_module("needletissue.fem.solve").ASSEMBLY_THREADS = 2
mesh = TaggedMesh.box((30, 4, 4), (16, 3, 3), layers={"a": (-9, 0), "b": (0, 9)}, origin=(0, -2, -2))
model = FEModel(mesh, {"a": "needle", "b": "cortical_bone"}, order=2)
solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0, 0, 100.0))], [1.0], progress=False, results=False)
ctypes.CDLL(None).malloc_stats()
"""
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}
    if arena_max:
        env["MALLOC_ARENA_MAX"] = arena_max
    run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    heaps = re.findall(r"^Arena \d+:", run.stderr, re.M)
    assert len(heaps) >= 2 if arena_max else heaps == ["Arena 0:"]


def _nonsymmetric_system(n=60, seed=0):
    rng = np.random.default_rng(seed)
    A = np.eye(n) * 4 + rng.normal(size=(n, n)) / np.sqrt(n)  # non-symmetric, well conditioned
    rough = np.linalg.inv(A + 0.3 * rng.normal(size=(n, n)) / np.sqrt(n))
    return A, rough, rng.normal(size=n)


def test_recycled_gcr_solves_a_nonsymmetric_system_and_says_when_it_cannot():
    """linsolve._Recycled (right-preconditioned GCR): to rtol with an exact, a rough and no preconditioner, also when
    a small store makes it restart; None when maxiter back-substitutions do not reach rtol; the count it reports is
    the preconditionings."""
    import scipy.sparse as sp

    A, rough, b = _nonsymmetric_system()
    exact = np.linalg.solve(A, b)
    count = [0]

    def counted(P):
        def apply(r):
            count[0] += 1
            return P @ r
        return apply

    used = {}
    for name, P, capacity in (("exact", np.linalg.inv(A), 30), ("rough", rough, 30), ("none", np.eye(len(b)), 5)):
        count[0] = 0
        x, used[name] = linsolve._Recycled(sp.csr_matrix(A), counted(P), capacity).solve(b, 1e-12, 200)
        assert used[name] == count[0]
        assert np.linalg.norm(A @ x - b) <= 1e-12 * np.linalg.norm(b)
        np.testing.assert_allclose(x, exact, rtol=0, atol=1e-10 * np.abs(exact).max())
    assert used["exact"] == 1 < used["rough"] < used["none"]
    x, n_used = linsolve._Recycled(sp.csr_matrix(A), counted(np.eye(len(b))), 30).solve(b, 1e-12, 3)
    assert x is None and n_used == 3


def test_recycled_gcr_is_minimal_residual_and_reuses_its_directions():
    """After m back-substitutions the store spans GMRES's space, P^-1 K_m(A P^-1, b): the residual left is the
    least-squares minimum over it, the images C = A Z orthonormal. A later right-hand side is projected on the
    store first: b scaled costs no back-substitution, b slightly perturbed fewer than from scratch."""
    import scipy.sparse as sp

    A, P, b = _nonsymmetric_system(seed=1)
    P = P + 0.5 * np.random.default_rng(2).normal(size=P.shape) / np.sqrt(len(b))  # a poor preconditioner
    for m in (1, 3, 6):
        s = linsolve._Recycled(sp.csr_matrix(A), P.__matmul__, 30)
        assert s.solve(b, 0.0, m) == (None, m)
        C, Z = s.C[:, :s.k], s.Z[:, :s.k]
        np.testing.assert_allclose(C.T @ C, np.eye(m), atol=1e-12)
        np.testing.assert_allclose(A @ Z, C, atol=1e-12)
        K = [b]
        for _ in range(m - 1):
            K.append(A @ (P @ K[-1]))
        AZ = A @ P @ np.column_stack(K)
        best = np.linalg.norm(b - AZ @ np.linalg.lstsq(AZ, b, rcond=None)[0])
        assert np.linalg.norm(b - C @ (C.T @ b)) == pytest.approx(best, rel=1e-8)
    s = linsolve._Recycled(sp.csr_matrix(A), P.__matmul__, 60)
    fresh = s.solve(b, 1e-10, 100)[1]
    x, again = s.solve(3 * b, 1e-10, 100)
    assert again == 0 and np.linalg.norm(A @ x - 3 * b) <= 1e-10 * 3 * np.linalg.norm(b)
    c = b + 1e-3 * np.random.default_rng(3).normal(size=len(b))
    x, near = s.solve(c, 1e-10, 100)
    assert near < fresh and np.linalg.norm(A @ x - c) <= 1e-10 * np.linalg.norm(c)


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
def test_a_bonded_solve_does_not_load_numba():
    """_fit's merge kernels (Numba: ~58 MB and 0.2 s) load only for a tangent whose pattern differs from the
    analysed one, which frictional contact has and a bonded run never: checked in a fresh interpreter."""
    import subprocess
    import sys

    code = """
import sys
from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve
mesh = TaggedMesh.box((4, 4, 8), (2, 2, 4), region="adipose")
model = FEModel(mesh, {"adipose": "adipose"}, order=2, formulation="mixed")
r = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.002, 0.0, 0.0))], [0.5, 1.0], progress=False,
          results=False, solver="pardiso")
assert r[-1].newton_iterations >= 2  # more than one tangent: _fit ran
print("numba" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[-1] == "False"


@pytest.mark.skipif(not linsolve.has_pardiso(), reason="pypardiso not installed")
@pytest.mark.parametrize("factor", [linsolve.SINGLE_LU, linsolve.SYM_PART])
def test_nonsymmetric_tangents_by_gmres_on_a_cheaper_factor(monkeypatch, factor):
    """linsolve.SYM_GMRES: from SYM_GMRES_ROWS rows a non-symmetric (friction) tangent is solved by GMRES
    preconditioned with its LU in single precision (or the LDL^T of its symmetric part), to SYM_GMRES_RTOL, as the
    double LU solves it; a substep's resolve() is GMRES on the kept tangent; a tangent whose GMRES misses
    SYM_GMRES_MAXITER is solved by the double LU, and so is every later one; below SYM_GMRES_ROWS rows the LU."""
    import scipy.sparse as sp

    monkeypatch.setattr(linsolve, "SYM_GMRES_FACTOR", factor)

    S = _clamped_needle_tangent()[1]
    A = _nonsymmetric(S)
    b = np.random.default_rng(3).normal(size=A.shape[0])
    ref = sp.linalg.spsolve(A.tocsc(), b)
    plain = linsolve.make("pardiso")
    assert A.shape[0] < linsolve.SYM_GMRES_ROWS
    x = plain(A, b)
    assert plain.counts == {"factorisations": 1, "gmres_solves": 0, "gmres_back_substitutions": 0}
    plain.close()

    monkeypatch.setattr(linsolve, "SYM_GMRES_ROWS", 0)
    s = linsolve.make("pardiso")
    s.keep_factor(True)
    x = s(A, b)
    counts = s.counts
    assert counts["factorisations"] == 1 and counts["gmres_solves"] == 1
    assert 1 < counts["gmres_back_substitutions"] <= linsolve.SYM_GMRES_MAXITER
    assert np.linalg.norm(A @ x - b) <= linsolve.SYM_GMRES_RTOL * np.linalg.norm(b)
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-8 * np.abs(ref).max())
    y = s.resolve(2 * b)  # in the span of the directions kept: no back-substitution
    assert s.counts == counts and np.linalg.norm(A @ y - 2 * b) <= linsolve.SYM_GMRES_RTOL * 2 * np.linalg.norm(b)
    c = np.random.default_rng(4).normal(size=A.shape[0])
    y = s.resolve(c)  # GMRES (GCR) on A again, to the substeps' tolerance, no factorisation
    assert s.counts["factorisations"] == 1 and s.counts["gmres_back_substitutions"] > counts["gmres_back_substitutions"]
    assert np.linalg.norm(A @ y - c) <= linsolve.SYM_GMRES_RESOLVE_RTOL * np.linalg.norm(c)
    assert (s._fun.kept[1].dtype == np.float32) == (factor == linsolve.SINGLE_LU)  # the factor GMRES runs on
    s.release()
    assert s.resolve(c) is None

    far = (S + 0.3 * abs(S).max() * sp.random(*S.shape, density=1e-2, random_state=5, format="csr")).tocsr()
    # far from symmetric (its symmetric part's factor) or one back-substitution (a float32 factor): GMRES misses
    monkeypatch.setattr(linsolve, "SYM_GMRES_MAXITER", 3 if factor == linsolve.SYM_PART else 1)
    x = s(far, b)
    assert s.counts["factorisations"] == 3 and s.counts["gmres_solves"] == 1  # GMRES's factor, then the double LU
    assert np.linalg.norm(far @ x - b) < 1e-10 * np.linalg.norm(b)
    assert not s._fun.sym_gmres
    s(A, b)  # and the LU from now on
    assert s.counts["factorisations"] == 4 and s.counts["gmres_solves"] == 1
    s.close()
