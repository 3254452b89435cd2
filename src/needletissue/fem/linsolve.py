"""Linear solvers for the Newton iterations: SciPy direct, PyPardiso, PyAMG-preconditioned CG.

Each factory returns a callable solver(A, b) -> x as FElupe's newtonraphson expects, and keeps the
accumulated wall time of its calls in `.seconds` (for the benchmarks and results JSON).
"""

from __future__ import annotations

import time
from importlib.util import find_spec

import numpy as np

from needletissue.errors import InputError

SOLVERS = ("auto", "pardiso", "scipy", "amg")
# Pardiso: analyse (reorder, symbolic factorisation) once per sparsity pattern, not at every Newton
# iteration (a bonded model's pattern is fixed after its first iteration). False: the previous behaviour (phase 13
# every call), kept for the A/B benchmark (benchmarks/bench_fe_needle.py).
REUSE_ANALYSIS = True
# "auto": direct Pardiso up to this many free dofs with linear tets, PyAMG-CG above; SciPy only small and
# without Pardiso. With the tissue's K = 10 MPa (issue 16) AMG-CG needs 800-900 iterations: on the anatomical
# model's first tangent (order 1) Pardiso took 3.0 s against 35.9 s at 65k dofs and 16.6 s against 134 s at
# 198k (benchmarks/linear_solvers_pelvis.py; docs/fem.md "Linear solvers"), at 2.2x AMG's memory. The
# paper-scale model (752,010 dofs) peaks at 10.7 GiB with Pardiso (METIS 5's ordering), which this 24 GiB
# machine holds; the factor grows ~n^1.26, so twice that size would not fit.
AUTO_DIRECT_MAX_DOFS = 800_000
# Quadratic (tetra10) models: the anatomical model at 273,330 dofs (100/200/300 N): Pardiso 426 s CPU,
# 4.96 GiB peak; AMG-CG 2,679 s CPU, 3.28 GiB; same answer to 1e-5 (docs/pelvis_model.md, "Mesh
# convergence"). Pardiso's memory grows ~n^1 here: ~7 GiB at 400k then; with the single-precision factor
# the graded smooth mesh at 398,877 dofs peaks at 3.83 GiB (2026-12-05), so 600k fits with room.
AUTO_DIRECT_MAX_DOFS_QUADRATIC = 600_000
AUTO_SCIPY_MAX_DOFS = 20_000


def has_pardiso() -> bool:
    return find_spec("pypardiso") is not None


def choose(name: str, ndof: int, order: int = 1) -> str:
    """Resolve "auto" by the number of free dofs and the element order; validate explicit names."""
    if name not in SOLVERS:
        raise InputError("solver", f"must be one of {SOLVERS}, got {name!r}")
    if name == "pardiso" and not has_pardiso():
        raise InputError("solver", "pardiso requested but pypardiso is not installed (pip install pypardiso)")
    if name != "auto":
        return name
    if has_pardiso():
        limit = AUTO_DIRECT_MAX_DOFS_QUADRATIC if order == 2 else AUTO_DIRECT_MAX_DOFS
        return "pardiso" if ndof <= limit else "amg"
    return "scipy" if ndof <= AUTO_SCIPY_MAX_DOFS else "amg"


class TimedSolver:
    """solver(A, b) with accumulated time and call count."""

    def __init__(self, name: str, fun):
        self.name = name
        self._fun = fun
        self.seconds = 0.0
        self.calls = 0
        self.fun = fun

    def close(self):
        """Release the backend's memory (Pardiso's analysis); the solver stays usable."""
        close = getattr(self._fun, "close", None)
        if close is not None:
            close()

    @property
    def factor(self) -> str:
        """Pardiso's Cholesky precision: "single+cg" (refined by CG) or "double" (also after a fallback);
        "" for the other backends."""
        single = getattr(self._fun, "single", None)
        return "" if single is None else ("single+cg" if single else "double")

    @property
    def counts(self) -> dict[str, int]:
        """Pardiso's factorisations, and the tangents solved by GMRES on a cheaper factor (SYM_GMRES, SYM_GMRES_FACTOR)
        with the back-substitutions it took (substeps' included); {} for the other backends."""
        f = self._fun
        if not isinstance(f, _Pardiso):
            return {}
        return {"factorisations": f.factorisations, "gmres_solves": f.gmres_solves,
                "gmres_back_substitutions": f.gmres_back_substitutions}

    @property
    def can_resolve(self) -> bool:
        """Whether the backend can keep its last factorisation for `resolve` (Pardiso with reuse)."""
        return bool(getattr(self._fun, "can_keep", False))

    def keep_factor(self, keep: bool = True):
        """Keep the next factorisations until `release` (for `resolve`); no-op without support."""
        if self.can_resolve:
            self._fun.keep = keep

    def resolve(self, b):
        """x = A^-1 b with the factor of the last call's A (one back-substitution; GMRES after SYM_GMRES), or None
        when no factor is kept. The factor stays kept."""
        fun = getattr(self._fun, "resolve", None)
        if fun is None:
            return None
        t = time.perf_counter()
        try:
            return fun(np.asarray(b, float))
        finally:
            self.seconds += time.perf_counter() - t

    def release(self):
        """Free a kept factor (the analysis stays)."""
        release = getattr(self._fun, "release", None)
        if release is not None:
            release()

    def __call__(self, A, b, upper: bool = False):
        """x = A^-1 b. upper=True: A is the upper triangle (CSR, sorted) of a symmetric matrix."""
        if not np.all(np.isfinite(b)):  # e.g. a contact item's NaN residual after interpenetration
            raise np.linalg.LinAlgError(f"{self.name}: non-finite residual")
        t = time.perf_counter()
        try:
            if upper and isinstance(self._fun, _Pardiso):
                x = self._fun(A, b, upper=True)
            else:
                if upper:  # the other backends take the whole matrix
                    import scipy.sparse as sp

                    A = (A + sp.triu(A, 1, format="csr").T).tocsr()
                x = self._fun(A, b)
        except np.linalg.LinAlgError:
            raise
        except Exception as exc:  # backend errors (PyPardisoError, SuperLU 'singular matrix', ...)
            raise np.linalg.LinAlgError(f"{self.name}: {type(exc).__name__}: {exc}") from exc
        finally:
            self.seconds += time.perf_counter() - t
        self.calls += 1
        if not np.all(np.isfinite(x)):
            raise np.linalg.LinAlgError(f"{self.name}: non-finite solution (singular or indefinite tangent)")
        return x


def make(name: str, points: np.ndarray | None = None, dof1: np.ndarray | None = None,
         rtol: float = 1e-9, maxiter: int = 3000, single: bool | None = None) -> TimedSolver:
    """A timed linear solver. For "amg", `points` (n,3) and the free dofs `dof1` give the rigid-body
    modes (near-null space) that smoothed aggregation needs for elasticity. `single`: Pardiso's
    Cholesky in single precision, refined by CG (default SINGLE)."""
    if name == "pardiso":
        fun = _Pardiso(REUSE_ANALYSIS, SINGLE if single is None else single)
    elif name == "scipy":
        from scipy.sparse.linalg import spsolve

        def fun(A, b):
            return spsolve(A.tocsc(), b)

    elif name == "amg":
        import pyamg
        from scipy.sparse.linalg import cg, gmres

        if points is None or dof1 is None:
            raise InputError("solver", "amg needs the mesh points and free dofs for rigid-body modes")
        B = rigid_body_modes(points)[dof1]

        def fun(A, b):
            A = A.tocsr()
            # small coarsest level: its dense pseudo-inverse is applied every cycle
            ml = pyamg.smoothed_aggregation_solver(A, B=B, symmetry="symmetric",
                                                   strength=("symmetric", {"theta": 0.0}), max_coarse=50)
            it = [0]

            def count(_):
                it[0] += 1

            if abs(A - A.T).max() <= 1e-12 * abs(A).max():
                x, info = cg(A, b, rtol=rtol, atol=0.0, maxiter=maxiter, M=ml.aspreconditioner(), callback=count)
            else:  # e.g. frictional contact: non-symmetric tangent, CG does not apply
                x, info = gmres(A, b, rtol=rtol, atol=0.0, restart=50, maxiter=maxiter // 50 + 1,
                                M=ml.aspreconditioner(), callback=count, callback_type="pr_norm")
            if info != 0:
                raise np.linalg.LinAlgError(f"amg-cg did not converge in {maxiter} iterations (info={info})")
            fun.cg_iterations += it[0]
            return x

        fun.cg_iterations = 0
    else:
        raise InputError("solver", f"must be one of {SOLVERS[1:]} here, got {name!r}")
    return TimedSolver(name, fun)


# Pardiso's fill-reducing ordering: "metis" computes it with METIS 5 (pymetis: nested dissection of the
# matrix graph) and hands it to Pardiso's Cholesky (iparm 5 = 1); "mkl" leaves it to Pardiso's own METIS (iparm
# 2 = 2), as LDL^T always does; the LU (contact) gets METIS 5's too (LU_IPARM).
# On the default `fe needle` tangent (72,348 dofs) Pardiso's own gives 40.5 M factor nonzeros and 49.8 GFlop
# per Cholesky, METIS 5's 37.1 M and 39.3 GFlop: factorisation 1.9 -> 1.3 s on two threads, analysis
# 0.8 -> 0.3 s (plus ~1 s of ordering, once per pattern, kept in the mesh cache) (docs/bench.md, "Pardiso's ordering: METIS 5").
ORDERING = "metis"


def nested_dissection(M) -> np.ndarray | None:
    """METIS 5's nested-dissection ordering of the symmetric pattern of M (CSR; an upper triangle or the
    whole matrix): perm[k] = the row that goes to position k (int32), or None for a matrix without
    off-diagonal entries (nothing to order). An ordering of a pattern met before (the same mesh and supports)
    is read from the mesh cache (needletissue.cache; METIS is deterministic: the same ordering)."""
    import io
    from importlib.metadata import version

    import pymetis
    import scipy.sparse as sp

    from needletissue.cache import cache_key, mesh_cache_dir, read_entry, sha256, write_entry

    n = M.shape[0]
    folder = mesh_cache_dir()
    if folder is not None:  # keyed by M's own pattern: the graph below is a function of it
        key = cache_key({"pattern": sha256(M.indptr, M.indices), "dtypes": [str(M.indptr.dtype), str(M.indices.dtype)],
                         "shape": list(M.shape), "pymetis": version("pymetis")})
        entry = read_entry(folder, key, ".perm.npy")
        if entry is not None:
            try:
                perm = np.load(io.BytesIO(entry[0]), allow_pickle=False)
                if perm.shape == (n,) and perm.dtype == np.int32:
                    return perm
            except (OSError, ValueError):
                pass
    G = sp.csr_matrix((np.ones(M.nnz, np.int8), M.indices, M.indptr), shape=M.shape)
    G = (G + G.T).tocsr()
    G.setdiag(0)
    G.eliminate_zeros()
    if G.nnz == 0:
        return None
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(G.indptr, G.indices))
    perm = np.asarray(perm, np.int32)
    if perm.shape != (n,):
        raise RuntimeError(f"fem.linsolve: METIS returned an ordering of {perm.size} rows for {n}")
    if folder is not None:
        buf = io.BytesIO()
        np.save(buf, perm)
        write_entry(folder, key, ".perm.npy", buf.getvalue(), {"rows": n, "graph_nonzeros": int(G.nnz)})
    return perm


# Pardiso iparm (1-based as in MKL's manual) for mtype 2: user values (1), METIS ordering (2), no
# iterative refinement (8), report the factor's nonzeros (18); the rest 0 as MKL's defaults for it.
CHOLESKY_IPARM = {1: 1, 2: 2, 8: 0, 18: -1}
# ... and for the LU (mtype 11, frictional contact): MKL's own defaults for it made explicit (METIS, pivot
# perturbation 1e-13, scaling and matching; iparm 8 = 0: refinement only after a perturbed pivot) instead of
# iparm[0] = 0, which also refines every solve twice; with METIS 5's ordering as the Cholesky's. Captured contact
# tangent of the coarse anatomical model (47,374 rows): factor 38.3 -> 34.4 M nonzeros, back-substitution
# 0.108 -> 0.03 s, the same relative residual (6e-12) (docs/bench.md, "The contact LU").
LU_IPARM = {1: 1, 2: 2, 10: 13, 11: 1, 13: 1, 18: -1}


# The Cholesky factor in single precision (iparm 28 = 1: half the memory, ~0.6x the time) preconditions CG
# on the double-precision tangent, to a relative residual of SINGLE_RTOL (4-9 back-substitutions on the
# needle model); a tangent whose CG needs more than SINGLE_MAXITER iterations, or that is not positive
# definite in single precision, is factored in double, and so is every later one. Paper-scale history:
# linear solves 514 -> 255 s, peak 10.93 -> 8.19 GiB (docs/bench.md, "Single-precision Cholesky").
SINGLE = True
SINGLE_RTOL = 1e-8
SINGLE_MAXITER = 40


def _single(M, b):
    """M (CSR) and b in single precision, as Pardiso reads them with iparm 28 = 1."""
    import scipy.sparse as sp

    M32 = M if M.dtype == np.float32 else sp.csr_matrix((M.data.astype(np.float32), M.indices, M.indptr),
                                                       shape=M.shape)
    return M32, np.asfortranarray(b, np.float32)


# Frictional contact's non-symmetric tangent from SYM_GMRES_ROWS rows: GMRES, right-preconditioned by a cheaper factor
# than the double LU: the LU in single precision (SYM_GMRES_FACTOR = SINGLE_LU, the default since 2026-12-06) or the
# LDL^T of the symmetric part in double precision (SYM_PART). The single LU has the double LU's fill in half the
# bytes, and its one back-substitution is off only in a soft mode that GMRES restores in a few more: on the default
# anatomical model's captured tangents 9 / 17 back-substitutions to 1e-10 against the symmetric part's 22 / 38; the
# whole default contact run, back to back (docs/bench.md, "Frictional contact against bonded", 2026-12-06): the same
# 14 Newton iterations, 624 -> 227 back-substitutions, solve 681 -> 460 s wall, peak 5.69 -> 6.13 GB. Before it:
# the LDL^T of the symmetric part instead of the LU. The friction's non-symmetric part is small, and the
# symmetric part's factor has half the LU's fill and flops: on the default anatomical model's captured tangents
# (318,505 rows) LDL^T 18 s wall / 38 s CPU and 2.3 GB against the LU's 41 s / 78 s and 4.5 GB, then 25-58
# back-substitutions of ~0.3 s to 1e-10. The whole default contact run, back to back: solve 843 -> 790 s wall,
# 1,461 -> 1,067 s CPU, peak 9.44 -> 7.04 GiB, the same Newton iterations (docs/bench.md, "Frictional contact
# against bonded"). The symmetric part in single precision loses a soft mode and GMRES stalls; below ~100k rows the
# LU is cheap against the back-substitutions; on the needle models the friction part is not small and GMRES stalls.
# A tangent whose GMRES misses SYM_GMRES_MAXITER is solved by the LU, and so is every later one. GMRES runs as GCR
# that keeps its directions (_Recycled): a substep's resolve() on the kept tangent starts from the Newton solve's and
# the earlier substeps' directions and needs 1-10 back-substitutions to SYM_GMRES_RESOLVE_RTOL, where plain GMRES
# needed ~15 to 1e-2 (default contact run, back to back: 895 -> 633 back-substitutions, solve 903 -> 776 s wall,
# the same 16 Newton iterations; at 1e-2 the substeps then converge less and the 100 N increment takes one more).
SYM_GMRES = True
SYM_GMRES_ROWS = 100_000
SYM_GMRES_RTOL = 1e-10
SYM_GMRES_RESOLVE_RTOL = 1e-4
SYM_GMRES_MAXITER = 100
SYM_GMRES_RECYCLE = 100  # directions kept per tangent (_Recycled; 2 vectors each: 510 MB at 318,505 rows)
# ... or to the residual a direct solver leaves on an ill-conditioned tangent: a normwise backward error
# |r|_2 / (|A|_inf |x|_inf + |b|_inf) of SYM_GMRES_BACKWARD (the LU's is 3e-16 to 2e-15 on the captured
# tangents; a coarse anatomical tangent whose LU leaves 1.1e-9 of |b| stalls GMRES at 8e-10)
SYM_GMRES_BACKWARD = 1e-14
# LDL^T of the symmetric part: our METIS ordering (2, 5), Bunch-Kaufman pivots perturbed at 1e-8 (10: MKL's
# default for symmetric indefinite), no refinement (8), no scaling or matching (11, 13: slower to analyse,
# 5.5-7.8 s against 1.2 s, and the same GMRES counts)
SYM_PART_IPARM = {1: 1, 2: 2, 8: 0, 10: 8, 18: -1}
SYM_PART = "symmetric part"  # _Pardiso's solver (mtype -2) for it
SINGLE_LU = "single LU"  # _Pardiso's solver (mtype 11, iparm 28 = 1) for the tangent itself in single precision
SYM_GMRES_FACTOR = SINGLE_LU  # GMRES's preconditioner: the single-precision LU, or the symmetric part's LDL^T


class _Recycled:
    """Right-preconditioned GCR on one matrix A (`A`: CSR, `precondition`: r -> M^-1 r) that keeps its directions z
    and their images c = A z, the c orthonormal, for every later right-hand side (SYM_GMRES): a new b is first
    projected on the stored directions (no back-substitution), and only what they leave costs new ones. A
    modified-Newton substep's residual is mostly made of the hard modes the Newton solve's directions span already.
    On one right-hand side the iterates are GMRES's (the same Krylov space, minimal residual). Up to `capacity`
    directions (2 vectors each); a solve that fills the store starts a new one from its current iterate (a
    restart)."""

    def __init__(self, A, precondition, capacity: int):
        self.A, self.precondition = A, precondition
        self.norm_A = float(abs(A).sum(axis=1).max())  # |A|_inf, for the backward error
        self.Z = np.empty((A.shape[0], max(1, capacity)), order="F")
        self.C = np.empty_like(self.Z)
        self.k = 0

    def solve(self, b, rtol: float, maxiter: int, first=None):
        """(x, back-substitutions) with |b - A x| <= max(rtol |b|, the backward error bound at x); (None, ...) if
        maxiter back-substitutions do not reach it. `first`: precondition(b) if the caller has it (it counts as
        one)."""
        b = np.asarray(b, float)
        used, goal, b_max = 0, rtol * float(np.linalg.norm(b)), float(np.abs(b).max())

        def target(x):  # the residual's 2-norm at rtol |b| or at a normwise backward error of SYM_GMRES_BACKWARD
            return max(goal, SYM_GMRES_BACKWARD * (self.norm_A * float(np.abs(x).max()) + b_max))

        x, r = np.zeros_like(b), b.copy()
        if self.k:
            C, Z = self.C[:, :self.k], self.Z[:, :self.k]
            a = C.T @ r
            x += Z @ a
            r -= C @ a
        while True:
            rn = float(np.linalg.norm(r))
            if not np.isfinite(rn):
                return None, used
            if rn <= target(x):
                r = b - self.A @ x  # the true residual (the recurrence drifts with the store's orthogonality)
                if float(np.linalg.norm(r)) <= target(x):
                    return x, used
            if used >= maxiter:
                return None, used
            z = self.precondition(r) if first is None or used or self.k else first
            used += 1
            c = self.A @ z
            if self.k == self.Z.shape[1]:
                self.k = 0  # full: a restart from x
            C, Z = self.C[:, :self.k], self.Z[:, :self.k]
            for _ in range(2):  # classical Gram-Schmidt twice
                h = C.T @ c
                c -= C @ h
                z -= Z @ h
            nc = float(np.linalg.norm(c))
            if not nc > 0:
                return None, used
            self.C[:, self.k], self.Z[:, self.k] = c / nc, z / nc
            a = float(self.C[:, self.k] @ r)
            x += a * self.Z[:, self.k]
            r -= a * self.C[:, self.k]
            self.k += 1


def _symmetric(upper):
    """x -> A x for the symmetric A whose upper triangle (CSR) is `upper`."""
    d, lower = upper.diagonal(), upper.T.tocsr()
    return lambda x: upper @ x + lower @ x - d * x


def _pcg(A, precondition, b, rtol: float, maxiter: int):
    """Preconditioned CG on A x = b (A: a matvec), from precondition(b); None if the residual is not below
    rtol |b| within maxiter iterations."""
    nb = np.linalg.norm(b)
    x = precondition(b)
    if nb == 0:
        return x
    r = b - A(x)
    z = precondition(r)
    p, rz = z, r @ z
    for _ in range(maxiter + 1):
        if np.linalg.norm(r) <= rtol * nb:
            return x
        q = A(p)
        alpha = rz / (p @ q)
        if not np.isfinite(alpha) or alpha <= 0:
            return None
        x = x + alpha * p
        r = r - alpha * q
        z = precondition(r)
        rz, rz0 = r @ z, rz
        p = z + (rz / rz0) * p
    return None


class _Pardiso:
    """solver(A, b) on MKL Pardiso through pypardiso's ctypes wrapper, phase by phase.

    Symmetric tangents (hyperelastic bodies) -> Cholesky LL^T on the upper triangle (mtype 2), and
    LDL^T (mtype -2) from the first tangent that is not positive definite on (Pardiso error -4; e.g. a
    tissue law beyond its stable range); the general LU (mtype 11) for non-symmetric ones (frictional
    contact). On the needle model's tangent (37,677 dofs, one MKL thread) the numerical factorisation
    takes 0.61 s CPU as LL^T and 0.84 s as LDL^T (same fill, 19.2 M), LU ~1.5x LDL^T. Per call:
    analysis (phase 11) only when the sparsity pattern differs from the analysed one, numerical
    factorisation (22), solve (33), then the factor is released (phase 0: no stale factor, and no
    factor held during the next assembly) while the analysis stays. The needle model (37,677 dofs,
    tet10): analysis 0.36 s, factorisation 1.10 s (LDL^T), solve 0.08 s (0.036 s for Cholesky without
    iterative refinement, CHOLESKY_IPARM) of CPU per call; the solution
    equals a fresh phase 13's to round-off (docs/bench.md).

    With `keep` set (TimedSolver.keep_factor), the factor of the last call stays for `resolve(b)`
    (phase 33 only: modified-Newton substeps in fem.solve) until `release()` or the next call.

    With `single` the Cholesky is factored in single precision and refined by CG on the double tangent
    (SINGLE); LDL^T and LU stay double, but for GMRES's preconditioner from SYM_GMRES_ROWS rows (SYM_GMRES_FACTOR).
    """

    def __init__(self, reuse: bool = True, single: bool = False):
        import weakref

        _mkl_rt_path()
        from pypardiso import PyPardisoSolver

        self.reuse = reuse
        self.solvers = {m: PyPardisoSolver(mtype=m) for m in (2, -2, 11)}
        self.solvers[SYM_PART] = PyPardisoSolver(mtype=-2)  # a non-symmetric tangent's symmetric part (SYM_GMRES)
        self.solvers[SINGLE_LU] = PyPardisoSolver(mtype=11)
        # Cholesky: MKL's parameters (iparm[0] = 0) add two steps of iterative refinement to every
        # solve, each a residual and a back-substitution: 0.088 -> 0.036 s CPU per solve without,
        # same relative residual (2.8e-11) on the needle model's tangent. With no pivot perturbed
        # (positive definite) refinement has nothing to repair; the LU likewise (LU_IPARM); LDL^T keeps MKL's
        # defaults.
        for key, iparm in ((2, CHOLESKY_IPARM), (11, LU_IPARM), (SINGLE_LU, LU_IPARM), (SYM_PART, SYM_PART_IPARM)):
            for i, v in iparm.items():
                self.solvers[key].set_iparm(i, v)
        self.sym_gmres = True  # non-symmetric tangents by SYM_GMRES until one misses, then by the LU
        self.gmres_tangent = None  # the tangent whose SYM_GMRES factor is kept, for resolve()
        self.factorisations = 0
        self.gmres_solves = 0  # tangents solved by SYM_GMRES, and their back-substitutions (resolve()'s included)
        self.gmres_back_substitutions = 0
        self.definite = True  # try Cholesky first until a tangent is not positive definite
        self.symmetric = True  # False after a non-symmetric matrix: the LU for every later one, untested
        self.single = single  # Cholesky in single precision, refined by CG, until CG does not converge
        self.pattern = {}  # mtype -> (indptr, indices) of the analysed matrix
        self.analyses = 0
        self.keep = False  # keep the factor after a call, for resolve(), until release()
        # (PyPardisoSolver, matrix as Pardiso read it: float32 values for a single factor) whose factor is kept; the
        # matrix is our own object on the caller's arrays: a caller may drop its tangent's values after the solve
        # (fem.solve._Bodies.solve), and a double factor's back-substitution still reads them when it refines (LDL^T
        # on perturbed pivots)
        self.kept = None
        weakref.finalize(self, _Pardiso._release, self.solvers)

    can_keep = True

    @staticmethod
    def _release(solvers):
        for ps in solvers.values():
            ps.free_memory(everything=True)

    def close(self):
        self._release(self.solvers)
        self.pattern.clear()
        self.kept = self.gmres_tangent = None

    def _forget(self, mtype):
        """Free a solver's factor and analysis, and forget the pattern it analysed: it is not used again, or it
        analyses afresh."""
        self.solvers[mtype].free_memory(everything=True)
        self.pattern.pop(mtype, None)

    def release(self):
        """Free the kept factor (phase 0), keep the analysis."""
        self.gmres_tangent = None
        if self.kept is not None:
            import scipy.sparse as sp

            ps = self.kept[0]
            self.kept = None
            ps.set_phase(0)
            ps._call_pardiso(sp.csr_matrix((0, 0)), np.zeros(0))
            ps.set_phase(13)

    def resolve(self, b):
        """Back-substitution (phase 33) with the kept factor; None when none is kept. With a single-precision
        factor too (no CG: a substep corrects with a stale tangent anyway, and Anderson mixing absorbs the
        rounding; CG there cost more than the factorisations saved on the needle model). After SYM_GMRES: GMRES on
        the kept tangent to SYM_GMRES_RESOLVE_RTOL, from the directions the tangent's solves have built (_Recycled;
        None if it misses)."""
        if self.kept is None:
            return None
        ps, M = self.kept
        if self.gmres_tangent is not None:  # the kept factor is SYM_GMRES_FACTOR's of the tangent
            x, used = self.gmres_tangent.solve(b, SYM_GMRES_RESOLVE_RTOL, SYM_GMRES_MAXITER)
            self.gmres_back_substitutions += used
            return x
        return self._back(ps, M)(b)

    def __call__(self, A, b, upper: bool = False):
        """upper=True: A is the sorted upper triangle (CSR) of a symmetric matrix, taken as it is."""
        import scipy.sparse as sp

        from pypardiso.pardiso_wrapper import PyPardisoError

        if upper:
            sym, M = True, A
        else:
            A = A.tocsr()
            # after the first non-symmetric matrix (implicit friction) the LU without testing: the test costs
            # 40-70 ms on the coarse needle model's contact tangent (20,160 rows), and friction stays
            sym = self.symmetric and abs(A - A.T).max() <= 1e-12 * abs(A).max()
            self.symmetric = sym
            M = sp.triu(A, format="csr") if sym else A
        if sym and self.definite:
            try:
                return self._solve(2, M, b)
            except PyPardisoError as exc:
                if exc.value != -4:  # -4: a pivot <= 0, not positive definite
                    raise
                if self.single:  # perhaps only in single precision: the double Cholesky first
                    self.single = False
                    self._forget(2)
                    return self(A, b, upper=upper)
                self.definite = False
                self._forget(2)
        if not sym and self.sym_gmres and SYM_GMRES and M.shape[0] >= SYM_GMRES_ROWS:
            x = self._sym_gmres(M, b)
            if x is not None:
                return x
            self.sym_gmres = False  # missed: the LU for this tangent and every later one
            self._forget(SYM_GMRES_FACTOR)
        return self._solve(-2 if sym else 11, M, b)

    def _sym_gmres(self, M, b):
        """x = M^-1 b (M non-symmetric, CSR) by GMRES (GCR, _Recycled) preconditioned with M's LU in single precision
        or the LDL^T of M's symmetric part (SYM_GMRES_FACTOR); None, the factor freed, if it does not reach
        SYM_GMRES_RTOL in SYM_GMRES_MAXITER back-substitutions. With `keep` the factor, M and the directions stay for
        resolve()."""
        import scipy.sparse as sp
        from pypardiso.pardiso_wrapper import PyPardisoError

        if SYM_GMRES_FACTOR == SINGLE_LU:
            S = M
        else:
            S = sp.triu(M + M.T, format="csr")
            S.data *= 0.5
            S.sort_indices()
        keep, self.keep = self.keep, True
        try:
            first = self._solve(SYM_GMRES_FACTOR, S, b)
        except PyPardisoError:  # e.g. singular: the LU will say so
            return None
        finally:
            self.keep = keep
        del S
        ps, F = self.kept
        krylov = _Recycled(sp.csr_matrix(M), self._back(ps, F), SYM_GMRES_RECYCLE)  # our own M: the caller may drop it
        x, used = krylov.solve(b, SYM_GMRES_RTOL, SYM_GMRES_MAXITER, first)
        self.gmres_back_substitutions += used
        if x is None or not keep:
            self.release()
        else:
            self.gmres_tangent = krylov
        if x is not None:
            self.gmres_solves += 1
        return x

    def _solve(self, mtype, M, b):
        import scipy.sparse as sp

        ps = self.solvers[mtype]
        ps._check_A(M)  # sorts the indices, rejects empty rows, sets CSR input (iparm 12)
        b = ps._check_b(M, np.asarray(b, float))
        self.release()
        if not self.reuse:
            ok = False
            try:
                x = ps.solve(M, b)
                ok = True
                return x
            finally:
                if ok and self.keep:
                    self.kept = (ps, sp.csr_matrix(M))
                else:
                    ps.free_memory(everything=True)
        known = self.pattern.get(mtype)
        fit = None
        if known is not None:
            # on the analysed pattern, or on its union with M's: a contact pair that comes and goes costs one
            # analysis, not one per return
            M, pattern = _fit(M, known)
            if pattern is known:
                fit = M
            else:
                ps.free_memory(everything=True)
        if fit is None:
            self.pattern.pop(mtype, None)
            if mtype in (2, 11, SYM_PART, SINGLE_LU):  # these iparm are ours (iparm 1 = 1); LDL^T keeps MKL's
                perm = nested_dissection(M) if ORDERING == "metis" else None
                ps.perm = np.zeros(0, np.int32) if perm is None else perm + 1
                ps.set_iparm(5, 0 if perm is None else 1)  # 1: the fill-reducing ordering is ps.perm
            # the factor's precision (and a, b, x's): single for a Cholesky refined by CG and for GMRES's LU
            ps.set_iparm(28, int((mtype == 2 and self.single) or mtype == SINGLE_LU))
        single = bool(ps.iparm[27])
        F, Fb = _single(M, b) if single else (M, b)  # what Pardiso reads (float32 values if single)
        if fit is None:
            ps.set_phase(11)
            ps._call_pardiso(F, Fb)
            self.pattern[mtype] = (M.indptr.copy(), M.indices.copy())
            self.analyses += 1
        ok, x = False, None
        try:
            ps.set_phase(22)
            ps._call_pardiso(F, Fb)
            self.factorisations += 1
            if mtype == SINGLE_LU:  # GMRES's preconditioner (_sym_gmres): one back-substitution, in double
                x = self._back(ps, F)(b)
            elif single:
                x = _pcg(_symmetric(M), self._back(ps, F), b, SINGLE_RTOL, SINGLE_MAXITER)
            else:
                ps.set_phase(33)
                x = ps._call_pardiso(F, b)
            ok = x is not None
        except Exception:
            self.pattern.pop(mtype, None)  # analyse afresh after a failure
            raise
        finally:
            if ok and self.keep:  # the factor stays for resolve() until release()
                self.kept = (ps, sp.csr_matrix(F))
                ps.set_phase(13)
            else:
                ps.set_phase(0)  # release the factor, keep the analysis
                ps._call_pardiso(sp.csr_matrix((0, 0)), np.zeros(0))
                ps.set_phase(13)
        if x is None:  # CG did not converge: this tangent and every later one in double precision
            self.single = False
            self._forget(mtype)
            return self._solve(mtype, M, b)
        return x

    @staticmethod
    def _back(ps, F):
        """r -> F^-1 r by one back-substitution with the factor of F (single or double precision), in double."""
        single = F.dtype == np.float32

        def back(r):
            r = np.asfortranarray(r, np.float32) if single else ps._check_b(F, np.asarray(r, float))
            ps.set_phase(33)
            try:
                return np.asarray(ps._call_pardiso(F, r), float)
            finally:
                ps.set_phase(13)
        return back


def _keys(indptr, indices, n):
    return np.repeat(np.arange(len(indptr) - 1, dtype=np.int64) * n, np.diff(indptr)) + indices


def _fit(M, pattern):
    """(M on an analysed pattern, that pattern): M itself if its pattern is `pattern` (indptr, indices); M with
    explicit zeros where it has no entry if its entries are a subset of it; else M on the union of both patterns,
    and that union (to be analysed). Frictional contact changes the tangent's pattern at every iteration (pairs
    come and go): the analysis of a superset serves them all. One merge pass of the two sorted patterns for the
    three cases (a key search took 0.3 s per call on the one-needle contact model, docs/bench.md)."""
    indptr, indices = pattern
    if np.array_equal(indptr, M.indptr) and np.array_equal(indices, M.indices):
        return M, pattern
    import scipy.sparse as sp

    # here, not above: Numba costs 58 MB and 0.2 s, and a bonded run's tangents all have the analysed pattern
    from needletissue.fem._csr_merge import positions, union

    at = np.empty(M.nnz, np.int64)
    if not positions(indptr, indices, M.indptr, M.indices, at):
        indptr, indices = pattern = union(indptr, indices, M.indptr, M.indices)
        positions(indptr, indices, M.indptr, M.indices, at)
    data = np.zeros(len(indices))
    data[at] = M.data
    return sp.csr_matrix((data, indices, indptr), shape=M.shape), pattern


def request_reproducible_mkl():
    """MKL's conditional numerical reproducibility for this process (MKL_CBWR=AUTO unless the user set
    MKL_CBWR), if MKL is not loaded yet: Pardiso on two threads then gives the same bits in every run, which a
    contact run needs (docs/contact.md). Not for every run: it made the bonded one-needle model's solves
    10.2 -> 13.4 s (docs/bench.md). Once MKL is loaded the mode cannot change (mkl_cbwr_set fails)."""
    import os

    if not _mkl_loaded():
        os.environ.setdefault("MKL_CBWR", "AUTO")


def _mkl_loaded() -> bool:
    try:
        with open("/proc/self/maps") as maps:
            return "libmkl_rt" in maps.read()
    except OSError:
        return True


def _mkl_rt_path():
    """Point pypardiso at MKL's runtime library of the installed `mkl` wheel (PYPARDISO_MKL_RT): without it
    every PyPardisoSolver() globs the whole environment for it (0.6 s each, measured)."""
    import os

    if os.environ.get("PYPARDISO_MKL_RT"):
        return
    try:
        from importlib.metadata import PackageNotFoundError, files

        found = [f.locate() for f in files("mkl") or () if "mkl_rt" in f.name]
    except (PackageNotFoundError, OSError):
        return
    found = sorted((p for p in found if p.exists()), key=lambda p: len(str(p)))
    if found:
        os.environ["PYPARDISO_MKL_RT"] = str(found[0].resolve())


# Pardiso's MKL threads (unless MKL_NUM_THREADS is set): None = one per core (MKL's own default). On an idle
# 2-core machine two threads made the one-needle model 22.6 -> 16.9 s wall and the default `fe needle`
# 41.4 / 44.7 -> 34.0 / 39.2 s (docs/bench.md, "Threads"); on a machine shared with other jobs one thread is faster
# (MKL_NUM_THREADS=1). Processes that solve side by side take one each (report.pipeline).
PARDISO_THREADS: int | None = None


def mkl_reproducible() -> bool:
    """Whether MKL's conditional numerical reproducibility is on (loads MKL)."""
    import ctypes
    import os

    _mkl_rt_path()
    import pypardiso  # noqa: F401  (loads MKL's runtime library)

    return ctypes.CDLL(os.environ["PYPARDISO_MKL_RT"]).MKL_CBWR_Get(1) != 1  # MKL_CBWR_BRANCH, BRANCH_OFF


def granted_threads() -> int:
    """The threads this process may use: MKL_NUM_THREADS when set (report.pipeline gives each stage solving
    beside others its share there), else one per core it may run on."""
    import os

    share = os.environ.get("MKL_NUM_THREADS", "")
    return max(1, int(share)) if share.isdigit() else len(os.sched_getaffinity(0))


def thread_limits(name: str, reproducible: bool = False):
    """Context for a solve: OpenBLAS on one thread (single_threaded_openblas), and MKL's Pardiso on
    PARDISO_THREADS threads when MKL_NUM_THREADS is not set. `reproducible`: the same bits in every run,
    which a contact run needs (its Newton path near a barrier follows the round-off, docs/contact.md):
    Pardiso on two threads gives them with MKL's conditional numerical reproducibility (`request_reproducible_mkl`
    before MKL loads); without it such a run takes one thread."""
    import os
    from contextlib import ExitStack

    stack = ExitStack()
    stack.enter_context(single_threaded_openblas())
    threads = 1 if reproducible and name == "pardiso" and not mkl_reproducible() else PARDISO_THREADS
    # set even for MKL's default: gmsh run in the same process (the anatomical model's mesh) sets the shared
    # OpenMP runtime to its own thread count, and MKL follows it (measured: one thread after the mesh)
    threads = threads or granted_threads()
    if name == "pardiso" and "MKL_NUM_THREADS" not in os.environ:
        try:
            from threadpoolctl import ThreadpoolController
        except ImportError:
            return stack
        stack.enter_context(ThreadpoolController().select(internal_api="mkl").limit(limits=threads))
    return stack


def single_threaded_openblas():
    """Context: OpenBLAS (NumPy/SciPy) on one thread. Its threads spin on the many short vector
    operations of CG/AMG and assembly: on the shared 2-core machine a 13k-vector norm took 256 us
    threaded vs 2 us single-threaded, AMG-CG 33 s vs 2.8 s. MKL (Pardiso) is left alone."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # optional: without it nothing changes
        from contextlib import nullcontext

        return nullcontext()
    return ThreadpoolController().select(internal_api="openblas").limit(limits=1)


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """(3n, 6) translations and infinitesimal rotations about the centroid, dof order x0,y0,z0,x1,..."""
    x = points - points.mean(0)
    n = len(points)
    B = np.zeros((n, 3, 6))
    B[:, 0, 0] = B[:, 1, 1] = B[:, 2, 2] = 1.0
    # rotation about z: (-y, x, 0); about x: (0, -z, y); about y: (z, 0, -x)
    B[:, 0, 3], B[:, 1, 3] = -x[:, 1], x[:, 0]
    B[:, 1, 4], B[:, 2, 4] = -x[:, 2], x[:, 1]
    B[:, 0, 5], B[:, 2, 5] = x[:, 2], -x[:, 0]
    return B.reshape(3 * n, 6)
