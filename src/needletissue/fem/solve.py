"""Load stepping with automatic cut-back around FElupe's newtonraphson."""

from __future__ import annotations

import copy
import threading
import time
from contextlib import closing, nullcontext

import numpy as np

from needletissue.errors import ConvergenceError, InputError, check_number
from needletissue.fem import linsolve
from needletissue.fem.model import Fixed, FEModel, PrescribedDisplacement, SurfaceForce
from needletissue.fem.result import FEResult, green_lagrange, principal_stretches, von_mises


# Modified-Newton substeps (solve(substeps=...), docs/bench.md "Newton"). The needle model's Newton
# iterations converge slowly, not quadratically, because stiff parts (clamp, needles) rotate: a
# linearised rotation stretches them, and their large spurious forces drive the soft modes. The tangent is
# consistent (tests/fem/test_newton.py), so further corrections with the same factorisation converge
# too, at a residual and a back-substitution each instead of a tangent assembly and a factorisation.
SUBSTEPS = 30               # at most this many substeps per Newton iteration
# an increment that converged in at most this many Newton iterations lets the next one grow 1.5x;
# contact runs (extra items) converge in 5-8 from their first increments on (docs/contact.md)
GROW_ITERATIONS = 5
GROW_ITERATIONS_ITEMS = 8
SUBSTEP_START = 1e-3        # first substep only if its correction is <= this x max |u| (1e-2 at the
                            # tissue's K = 10 MPa: substeps far from the solution mislead Newton, bench.md)
# Anderson mixing of the substeps (the last ANDERSON corrections; a secant update of the stale factor,
# like GMRES on a linear problem): the default `fe needle` 12 -> 8 Newton iterations (docs/bench.md)
ANDERSON = 8
SUBSTEP_CONTRACTION = 0.9   # a correction counts as progress if <= this x the smallest one so far;
SUBSTEP_TOL = 0.1           # they go on to |r| < this x tol: mixing stops just under tol, Newton overshoots
SUBSTEP_STALL = 3           # this many in a row without progress (or one 10x the smallest) end them
# Bonded runs assemble the bodies' residuals and tangents on this many threads (None: MKL_NUM_THREADS if set,
# else one per core): the bodies are independent and NumPy releases the GIL in their array work. Default
# `fe needle`: residual 0.060-0.074 -> 0.045-0.051 s, tangent 0.37-0.40 -> 0.24-0.25 s on two (docs/bench.md,
# "Threaded assembly").
# The sums keep the bodies' order, so the bits do not depend on the threads.
ASSEMBLY_THREADS: int | None = None


def assembly_threads() -> int:
    """ASSEMBLY_THREADS, else the threads granted to this process (linsolve.granted_threads)."""
    from needletissue.fem.linsolve import granted_threads

    return max(1, int(ASSEMBLY_THREADS)) if ASSEMBLY_THREADS is not None else granted_threads()


def _substep_plugin(fem, linear, dof1, nmax: int, tol: float):
    """A FElupe plugin: after the linear solve, update x1 = x + dx and add up to `nmax`
    modified-Newton corrections c = -K^-1 r with the factor `linear` kept, Anderson-mixed; counts
    them in `.taken`. Ends with the iterate of the smallest |r| (evaluated last)."""

    class _Substeps(fem.Plugin):
        taken = 0
        enabled = True

        def after_linear_solve(self, context, st):
            if not self.enabled:
                linear.release()
                return
            try:
                dx = st.dx
                if st.updated:  # another plugin has updated already
                    x, f = st.x, st.fun
                else:
                    x = context.update(st.x, dx)
                    f = context.fun(x)
                fnorm = context.check(dx, x, f)[1]
                best = (fnorm, x, f, dx)
                limit = SUBSTEP_START * float(np.linalg.norm(x[0].values, axis=1).max())
                dX, dF, last, smallest, stalled = [], [], None, np.inf, 0
                for _ in range(nmax):
                    if fnorm < SUBSTEP_TOL * tol or not np.isfinite(fnorm) or not np.all(np.isfinite(f)):
                        break
                    c = linear.resolve(-f[dof1])
                    if c is None or not np.all(np.isfinite(c)):
                        break
                    full = np.zeros_like(dx)
                    full[dof1] = c
                    cmax = float(np.linalg.norm(full.reshape(-1, 3), axis=1).max())
                    if not cmax <= limit:  # the first: near the solution; later ones: not diverging
                        break
                    stalled = stalled + 1 if cmax > SUBSTEP_CONTRACTION * smallest else 0
                    if stalled >= SUBSTEP_STALL:
                        break
                    smallest = min(smallest, cmax)
                    limit = 10 * smallest
                    if last is not None:
                        dF.append(c - last)
                        del dF[:-ANDERSON], dX[:len(dX) - len(dF)]
                    last = c
                    if dF:  # the combination of the last corrections with the least mixed residual
                        Fm = np.column_stack(dF)
                        gamma = np.linalg.lstsq(Fm, c, rcond=None)[0]
                        c = c - (np.column_stack(dX) + Fm) @ gamma
                        full[dof1] = c
                    x = context.update(x, full)
                    f = context.fun(x)
                    dx = dx + full
                    dX.append(c)
                    self.taken += 1
                    fnorm = context.check(dx, x, f)[1]
                    if fnorm < best[0]:
                        best = (fnorm, x, f, dx)
                if not fnorm <= best[0]:  # mixing is not monotone: back to the best iterate, evaluated last
                    _, x, f, dx = best
                    f = context.fun(x)
                st.x, st.fun, st.dx, st.updated = x, f, dx, True
            finally:
                linear.release()  # no factor held during the next tangent assembly

    return _Substeps()


def _items_plugin(fem, bodies):
    """A FElupe plugin: the bodies as the Newton context's items when fem.solve assembles them itself (_Bodies), for
    the plugins that read them (the line search's det F test); FElupe's own assembly does not see them."""

    class _Items(fem.Plugin):
        def before_newton(self, context, st):
            context.items = bodies

    return _Items()


def _pressure_plugin(fem, mixed):
    """A FElupe plugin: the first tangent of a predicted increment with the mixed bodies' cell pressure
    `p` (set per increment; None: FElupe's own). FElupe takes p = K (Jbar - 1) with Jbar the volume
    linearised from the last state; at an extrapolated state its error, second order in the increment
    (a linearly extrapolated rotation changes volume), times the tissue's K (8,571 mu0 for adipose) is a
    pressure ~20x the equilibrium one, whose geometric term p d2J/dF2 makes the tangent indefinite:
    Newton then inverts the tissue (docs/bench.md, "Predictor"). The residual does not depend on p
    (constant per cell, it cancels), so the equilibrium is the same."""

    class _Pressure(fem.Plugin):
        p = None

        def before_iteration(self, context, st):
            if st.iteration == 0 and self.p is not None:
                for b, p in zip(mixed, self.p):
                    b.results.state.p[:] = p
                    b.results.state.J[:] = 1 + p / b.bulk

    return _Pressure()


class _Values:
    """Stands in for FElupe's sparsity pattern of a body's field while _Bodies assembles it: keeps the
    integrated element matrices (a, i, b, k, c) instead of summing them into the body's own CSR matrix."""

    values = None

    def assemble(self, values):
        self.values = values
        return self

    def tocsr(self):
        return self


def _element_upper(a, ne: int) -> np.ndarray:
    """The values of each element's upper triangle (e1 <= e2) of `a`, element matrices (ne, ne, cells) in FElupe's
    value order, flat as (e1 <= e2, cells): one order for the integrated values and their slots (_Bodies)."""
    return np.reshape(a, (ne, ne, -1))[np.triu_indices(ne)].ravel()


_PATTERNS_LOCK = threading.Lock()  # FElupe's sparsity-pattern cache (module-level), swapped per body in _Bodies


class _Bodies:
    """Residual, tangent and linear solve for FElupe's newtonraphson when the items are the model's
    bodies, point loads and contact items (`extra`): each body's element matrices go straight into the upper
    triangle of the free-free block K11 (and into K10), whose CSR patterns are built once, through one
    int32 index per value of each element matrix's upper triangle into the body's own slots of K11,
    instead of FElupe's per-body CSR matrix (an int64 position per value, ~1.5 GB at paper scale), the
    sum of the bodies' global matrices, its partition, a symmetry test and a cut-out triangle at every
    iteration (docs/bench.md). The bodies' hyperelastic laws have symmetric tangents (second derivatives
    of an energy), so the element matrices' lower halves are not summed. Bodies are assembled on
    `threads` threads, at most one body's element matrices alive per thread (FElupe's copy in its
    results is dropped).

    `extra`: items among `items` whose matrices are not symmetric bodies' (frictional contact): their global
    matrices are added to the whole K11 (upper triangle mirrored) and K10 at the solve."""

    def __init__(self, items, bodies, dof1, dof0, ndof, threads: int = 1, extra=()):
        self.items, self.bodies, self.extra = items, bodies, list(extra)
        self.dof1, self.dof0, self.n = dof1, dof0, ndof
        self.slots = None    # per body: (the K11 upper-data slots it touches (0: none), each value's index among them)
        self.slots10 = None  # per body: (the values that go into K10, their slots there)
        # the bodies' own fields (FElupe's pattern cache is swapped per field in _values): else one thread
        own = len({id(b.field[0].indices) for b in bodies}) == len(bodies)
        self.threads = max(1, min(int(threads), len(bodies))) if own else 1
        self.pool = None
        # a body with more than half of the cells keeps the other threads idle: its material law is evaluated
        # in chunks of cells on FElupe's threads too (pointwise laws; the same bits; docs/bench.md, "Threaded
        # assembly")
        cells = [b.field.region.mesh.ncells for b in bodies]
        self.chunked = [b.umat for b, n in zip(bodies, cells) if 2 * n > sum(cells) and hasattr(b.umat, "parallel")
                        and not b.umat.parallel] if self.threads > 1 else []
        for umat in self.chunked:
            umat.parallel = True

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None
        for umat in self.chunked:
            umat.parallel = False
        self.chunked = []

    def _ordered(self, fun, items):
        """fun(item) for each item on the threads (one body's element matrices per thread: ~1 GB at paper
        scale), yielded in the items' order: the results of bodies done early wait for their turn, so they
        are kept small (a body's own slots, not the whole K11)."""
        if self.threads == 1:
            yield from map(fun, items)
            return
        import contextvars
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        if self.pool is None:
            self.pool = ThreadPoolExecutor(self.threads, thread_name_prefix="needletissue-assembly")
        # each job in a copy of the caller's context: NumPy's error state (np.errstate in solve) lives there
        pending = deque(self.pool.submit(contextvars.copy_context().run, fun, item) for item in items)
        try:
            while pending:
                yield pending.popleft().result()
        finally:
            for job in pending:  # the caller failed or stopped: no body left assembling behind it
                job.cancel()
            for job in pending:
                if not job.cancelled():
                    job.exception()

    @staticmethod
    def _vector(item, x) -> np.ndarray:
        import felupe as fem

        item.field.link(x)
        if type(item) is fem.SolidBody and len(item.field.fields) == 1 and item.apply is None:
            r = _Bodies._force(item)
        else:
            r = item.assemble.vector(field=item.field).toarray().ravel()
        if item.assemble.multiplier is not None:
            r = r * item.assemble.multiplier
        return r

    @staticmethod
    def _force(body) -> np.ndarray:
        """A displacement body's internal force vector, its element vectors summed by np.bincount in FElupe's
        order (the same bits) instead of FElupe's COO -> CSR matrix (int64 row and column per value): an adipose
        body of 981 k tets 3.0-3.15 -> 2.63-2.71 s per residual (docs/bench.md)."""
        from felupe.assembly import IntegralFormCartesian

        stress = body._gradient(body.field)[0]
        field = body.field[0]
        values = IntegralFormCartesian(stress, field, body.field.region.dV, grad_v=True).integrate()
        rows = field.indices.ai[0]
        return np.bincount(rows, weights=values.transpose(2, 0, 1).ravel(), minlength=field.indices.shape[0])

    def fun(self, x):
        f = np.zeros(self.n)
        for r in self._ordered(lambda item: self._vector(item, x), self.items):
            f[:r.shape[0]] += r
        return f

    @staticmethod
    def _values(body) -> np.ndarray:
        """The upper triangles of the body's integrated element matrices at the state of its last residual,
        flat, (e1 <= e2, cells) with e = node * dim + component (FElupe's value order restricted to them); the
        lower halves are their mirror images (symmetric tangents), so half the slots and sums (docs/bench.md).
        FElupe's own sparse assembly is skipped."""
        from weakref import WeakKeyDictionary

        from felupe.assembly._sparsity import _patterns

        key = body.field[0].indices
        with _PATTERNS_LOCK:
            patterns = _patterns.setdefault(key, WeakKeyDictionary())
            own, keep = patterns.get(key), _Values()
            patterns[key] = keep
        try:
            body.assemble.matrix()
        finally:
            with _PATTERNS_LOCK:
                if own is None:
                    del patterns[key]
                else:
                    patterns[key] = own
        # FElupe keeps its element matrices (900 values a tet10) and the material's tangent (81 values a
        # quadrature point: 0.9 GB at paper scale) for the next call; dropped, one body's are alive per
        # assembly thread, for ~20 ms of page faults per tangent
        r = body.results
        r.stiffness = r.stiffness_values = r.elasticity = None
        for name in ("_stiffness_values", "hessian"):
            if hasattr(r, name):
                setattr(r, name, None)
        values = keep.values  # (a, i, b, k, cells): the element matrices, symmetric in (a, i) <-> (b, k)
        upper = _element_upper(values, values.shape[0] * values.shape[1])  # a copy
        del values, keep
        if body.assemble.multiplier is not None:
            upper *= body.assemble.multiplier
        return upper

    def jac(self, x):
        """At the state of the last fun(x), as FElupe's own assembly: (upper triangle of K11, K10), and the
        `extra` items' global matrix summed when there are any."""
        import scipy.sparse as sp

        if self.slots is None:
            self._build()
        data = np.zeros(len(self.indices) + 1)
        data10 = np.zeros(self.k10.nnz)

        def summed(args):
            body, (used, local), (sel, slot) = args
            values = self._values(body)
            if values.size != local.size:
                raise RuntimeError(f"fem.solve: {values.size} element-matrix values, the pattern has {local.size}")
            return (used, np.bincount(local, weights=values, minlength=len(used)),
                    np.bincount(slot, weights=values[sel], minlength=len(data10)) if len(sel) else None)

        for used, d, d10 in self._ordered(summed, list(zip(self.bodies, self.slots, self.slots10))):
            data[used] += d  # the body's own slots (unique): the same sums, in the same order, as over all of K11
            if d10 is not None:
                data10 += d10
            del d, d10
        upper = sp.csr_matrix((data[1:], self.indices, self.indptr), shape=(len(self.dof1),) * 2)
        upper.has_sorted_indices = True
        k10 = sp.csr_matrix((data10, self.k10.indices, self.k10.indptr), shape=self.k10.shape)
        if not self.extra:
            return upper, k10
        extra = None
        for item in self.extra:  # at the state of their last residual, as FElupe's jac_items
            K = item.assemble.matrix()
            if item.assemble.multiplier is not None:
                K = K * item.assemble.multiplier
            extra = K if extra is None else extra + K
        return upper, k10, extra.tocsr()

    def _build(self):
        """The patterns of K11's upper triangle and of K10 from the bodies' sparsity patterns (FElupe's,
        built here and dropped), and the slot of each integrated value of each body in them."""
        import scipy.sparse as sp
        from felupe.assembly._sparsity import SparsityPattern

        pats = [SparsityPattern(b.field[0], b.field[0]) for b in self.bodies]
        n1, n0 = len(self.dof1), len(self.dof0)
        union = sum(sp.csr_matrix((np.ones(p.nnz), p.indices, p.indptr), shape=(self.n, self.n)) for p in pats)
        upper = sp.triu(union[self.dof1][:, self.dof1], format="csr")  # CSR order: sorted row * n1 + col
        upper.sort_indices()
        k10 = union[self.dof1][:, self.dof0].tocsr()
        k10.sort_indices()
        del union
        self.indptr, self.indices = upper.indptr.astype(np.int32), upper.indices.astype(np.int32)
        keys, keys10 = linsolve._keys(upper.indptr, upper.indices, n1), linsolve._keys(k10.indptr, k10.indices, n0)
        self.k10 = k10
        del upper
        free = np.full(self.n, -1, np.int64)
        free[self.dof1] = np.arange(n1)
        fixed = np.full(self.n, -1, np.int64)
        fixed[self.dof0] = np.arange(n0)
        self.slots, self.slots10 = [], []
        while pats:
            p = pats.pop(0)
            # per nonzero of the body's pattern: its slot in K11's upper triangle (a mirror image (col, row) where
            # row > col: the elements' lower halves are not summed, _values) and in K10 (free row, fixed column)
            rows = np.repeat(np.arange(self.n), np.diff(p.indptr))
            fr, fc = free[rows], free[p.indices]
            lo, hi = np.minimum(fr, fc), np.maximum(fr, fc)
            w = np.zeros(p.nnz, np.int32)  # slot 0 collects the values outside K11 (a fixed dof)
            keep = lo >= 0
            w[keep] = np.searchsorted(keys, lo[keep] * n1 + hi[keep]) + 1
            row10 = np.where(fr >= 0, fr, fc)
            col10 = np.where(fr >= 0, fixed[p.indices], fixed[rows])
            w10 = np.full(p.nnz, -1, np.int64)
            sel = (row10 >= 0) & (col10 >= 0)
            w10[sel] = np.searchsorted(keys10, row10[sel] * n0 + col10[sel])
            del rows, fr, fc, lo, hi, keep, row10, col10, sel
            # the same per value of the elements' upper triangles, in _values' order
            pos = _element_upper(p.position, int(round((p.position.size // p.ncells) ** 0.5)))
            w, v10 = w[pos], w10[pos]
            del pos, w10
            mark = np.zeros(len(keys) + 1, bool)
            mark[w] = True
            used = np.flatnonzero(mark)
            index = np.cumsum(mark, dtype=np.int32) - 1
            self.slots.append((used.astype(np.int32), index[w]))
            del mark, index, w
            sel = np.flatnonzero(v10 >= 0)
            self.slots10.append((sel, v10[sel]))
            del p, v10

    def solve(self, A, b, x, dof1, dof0, ext0, solver):
        """FElupe's partitioned solve, K11 du1 = b1 - K10 du0, with A = (upper triangle of K11, K10) or, with
        `extra` items, (upper triangle of the bodies' K11, their K10, the extra items' global matrix)."""
        import scipy.sparse as sp

        upper, k10, *extra = A
        if extra:  # the whole (non-symmetric) K11: the bodies' mirrored, the items' added
            rows = extra[0][dof1]
            whole = upper + sp.triu(upper, 1, format="csr").T + rows[:, dof1]  # CSR
            upper.data = np.empty(0)
            upper, k10 = whole, k10 + rows[:, dof0]
        du0 = ext0 - np.concatenate([f.values.ravel() for f in x.fields])[dof0]
        rhs = b[dof1] - k10 @ du0 if np.any(du0) else b[dof1]
        du = np.empty(self.n)
        du[dof1] = solver(upper, rhs, upper=not extra)
        du[dof0] = du0
        # the next iteration assembles a new tangent and the substeps use the kept factor: the values go now, not
        # after the substeps' residuals (a fresh empty array: a slice would keep them); a kept double factor holds
        # its own reference (linsolve._Pardiso.kept), a late reader here fails loudly
        upper.data = np.empty(0)
        return du


class _Loads:
    """FElupe boundaries and point loads for the BCs, updated to a load factor."""

    def __init__(self, model: FEModel, bcs):
        import felupe as fem

        mesh = model.mesh
        npts = len(mesh.points)
        u = model.field[0]
        self.boundaries = {}  # key -> (Boundary, full value)
        self.reaction_sets = {}  # surface -> (npts, 3) mask of the dofs whose reaction it reports
        self.taken = np.zeros((npts, 3), bool)
        self.loads = []  # (PointLoad, full nodal values)
        for i, bc in enumerate(bcs):
            if isinstance(bc, Fixed):
                comps = [(c, 0.0) for c in bc.components]
            elif isinstance(bc, PrescribedDisplacement) and callable(bc.value):
                nodes = mesh.surface_nodes(bc.surface)
                vals = np.asarray(bc.value(mesh.points[nodes]), float)
                if vals.shape != (len(nodes), 3) or not np.isfinite(vals).all():
                    raise InputError(f"PrescribedDisplacement({bc.surface!r}).value",
                                     f"the callable must return finite (k, 3) mm for the k={len(nodes)} surface nodes")
                comps = list(enumerate(vals.T))
            elif isinstance(bc, PrescribedDisplacement):
                if len(bc.value) != 3:
                    raise InputError(f"PrescribedDisplacement({bc.surface!r}).value", "needs 3 components (mm or None)")
                comps = [(c, check_number(f"PrescribedDisplacement({bc.surface!r}).value[{c}]", v))
                         for c, v in enumerate(bc.value) if v is not None]
            elif isinstance(bc, SurfaceForce):
                if len(bc.total) != 3:
                    raise InputError(f"SurfaceForce({bc.surface!r}).total", "needs 3 components (N)")
                total = np.array([check_number(f"SurfaceForce({bc.surface!r}).total[{c}]", v)
                                  for c, v in enumerate(bc.total)])
                mesh.surface_nodes(bc.surface)  # InputError naming the known surfaces
                nodes, w = mesh.nodal_area_weights(bc.surface)
                values = w[:, None] / w.sum() * total[None, :]
                values += _couple(mesh.points[nodes], w, bc)
                self.loads.append((fem.PointLoad(model.field, nodes, np.zeros_like(values)), values))
                continue
            else:
                raise InputError("bcs", f"unknown boundary condition {bc!r}")
            nodes = mesh.surface_nodes(bc.surface)
            for c, value in comps:
                if c not in (0, 1, 2):
                    raise InputError(f"{type(bc).__name__}({bc.surface!r}).components", f"must be in (0, 1, 2), got {c}")
                mask = np.zeros((npts, 3), bool)
                mask[nodes, c] = True
                self.boundaries[(i, c)] = (fem.Boundary(u, mask=mask), value)
            # each constrained dof's reaction counts once, for the first condition fixing it
            mask = np.zeros((npts, 3), bool)
            for c, _ in comps:
                mask[nodes, c] = True
            mask &= ~self.taken
            self.taken |= mask
            self.reaction_sets[bc.surface] = self.reaction_sets.get(bc.surface, False) | mask
        if not self.boundaries:
            raise InputError("bcs", "no Fixed or PrescribedDisplacement condition: the model can move as a rigid body")
        self.dof0, self.dof1 = fem.dof.partition(model.field, self.fboundaries)

    @property
    def fboundaries(self):
        return {str(k): b for k, (b, _) in self.boundaries.items()}

    def apply(self, model, lam: float):
        import felupe as fem

        for b, v in self.boundaries.values():
            b.update(lam * v)
        for load, v in self.loads:
            load.update(lam * v)
        return fem.dof.apply(model.field, self.fboundaries, self.dof0)


def _couple(x: np.ndarray, w: np.ndarray, bc: SurfaceForce) -> np.ndarray:
    """Nodal forces w_i (omega x r_i), r_i from the weighted centroid: they sum to zero and their
    moment sum w_i r_i x (omega x r_i) = J omega equals bc.moment (J: the surface's polar tensor)."""
    if len(bc.moment) != 3:
        raise InputError(f"SurfaceForce({bc.surface!r}).moment", "needs 3 components (N mm)")
    m = np.array([check_number(f"SurfaceForce({bc.surface!r}).moment[{c}]", v) for c, v in enumerate(bc.moment)])
    if not m.any():
        return np.zeros_like(x)
    r = x - (w @ x) / w.sum()
    rr = np.einsum("i,ij,ik->jk", w, r, r)
    omega = np.linalg.solve(np.trace(rr) * np.eye(3) - rr, m)
    return w[:, None] * np.cross(omega, r)


class _Progress:
    """Rich progress over the load factor; the description shows the Newton iteration and residual."""

    def __init__(self, enabled: bool, total: float):
        self.enabled = enabled
        self.total = total
        if enabled:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("load {task.completed:.4g}/{task.total:.4g}"), BarColumn(),
                                TextColumn("{task.description}"), TimeElapsedColumn(),
                                console=Console(stderr=True), transient=False)
            self.task = self.bar.add_task("", total=total)

    def __enter__(self):
        if self.enabled:
            self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self.bar.__exit__(*exc)

    def update(self, lam=None, text=None):
        if self.enabled:
            kw = {}
            if lam is not None:
                kw["completed"] = lam
            if text is not None:
                kw["description"] = text
            self.bar.update(self.task, **kw)


def solve(model: FEModel, bcs, load_factors=(1.0,), solver: str = "auto", items=(), progress: bool = True,
          initial_step: float | None = None, min_step: float = 1e-3, max_step: float | None = None,
          tol: float = 1e-8, maxiter: int | None = None, results: bool = True, predictor: bool | int = True,
          linesearch: bool | None = None, substeps: int | None = None, log=None,
          start: float = 0.0) -> list[FEResult]:
    """Solve the model quasi-statically, one FEResult per requested load factor.

    bcs          : Fixed / PrescribedDisplacement / SurfaceForce; values and forces scale with the
                   load factor (0 = unloaded).
    load_factors : increasing factors > 0 at which results are returned, e.g. [1/3, 2/3, 1] for
                   100/200/300 N of a 300 N force.
    solver       : "auto" (by free dofs), "pardiso", "scipy" or "amg" (PyAMG-preconditioned CG).
    items        : extra FElupe items (e.g. a contact item) assembled with the bodies.
    initial_step : first increment of the load factor (default: the first requested factor, with or
                   without contact items: each increment of smoothed friction slips anew where it
                   sticks, so the answer drifts with the number of increments, ~0.01 mm of needle per
                   increment at eps_v = 0.01 mm, and small ones cost 3-4x the iterations where large
                   ones converge; docs/contact.md, "Contact increments").
    min_step     : smallest increment after cut-backs (halving); below it ConvergenceError names the
                   load factor reached. max_step caps the increment (default: no cap).
    tol          : Newton tolerance on |residual of free dofs| / |reactions| (FElupe's norm).
    maxiter      : Newton iterations per increment before a cut-back (default 12; 25 with extra
                   `items`, whose line-searched iterations converge more slowly near contact changes).
    results      : False skips the stress/stretch evaluation (e.g. in benchmarks).
    predictor    : start each increment from the linear extrapolation of the last converged one
                   (fewer Newton iterations on smooth load paths; off after a cut-back); the mixed
                   bodies' cell pressure in the first tangent is extrapolated likewise. An int n:
                   from the n-th converged increment on (2 in contact runs from rest: the first
                   increment closes the gaps to the barrier's working distance, which is not
                   proportional to the load, so extrapolating it overshoots; docs/contact.md). With
                   contact items the extrapolation goes as far as a Newton step may
                   (CollisionFreeStep: 0.9 of its collision-free part), not all or nothing.
    linesearch   : backtracking line search in every Newton iteration (FElupe's LinesearchPlugin:
                   halve the step while det F <= 0 or the residual is non-finite, e.g. a contact
                   item's NaN for a step that passes a surface through another). Default: on when
                   extra `items` are given, off otherwise (bonded runs stay plain Newton).
    substeps     : modified-Newton substeps per Newton iteration (default SUBSTEPS, also with contact
                   items, whose steps CCD bounds; 0 with other extra `items` or a line search without
                   contact): after the update x + dx, further corrections
                   -K^-1 r(x) with the same factorisation of K (one residual and one back-substitution
                   each, no tangent assembly, no factorisation), Anderson-mixed over the last ANDERSON,
                   while the first is <= SUBSTEP_START max |u|, none is 10x the smallest so far and
                   fewer than SUBSTEP_STALL in a row fail to shrink below SUBSTEP_CONTRACTION of it,
                   until |r| < tol. Only with a solver that keeps its factor (Pardiso); the convergence
                   test is unchanged, so the answer is the same to the tolerance (docs/bench.md, "Newton").
                   An increment that fails after substeps is tried once more without them before
                   it is halved (not with contact items: contact increments fail at the barrier, and
                   the retry cost 25 more iterations, docs/contact.md).

    log          : a callable taking one dict per event as it happens (`SolveLog` writes them to a JSON-lines
                   file, so a long run says which load it reached while it runs and where it stopped):
                   "increment" (converged: load_factor, increment, iterations, cpu_s and wall_s since the
                   start, min_distance_mm per contact item, residuals: the relative residual of each Newton
                   iteration), "cutback" (the failed increment, why, and its residuals),
                   "failed" (ConvergenceError: the load factor reached).

    start        : load factor the model's fields (and bodies' states) already hold converged, e.g. a
                   restart from a saved state (benchmarks/contact_newton_log.py --restart); default 0.

    Reactions: a dof fixed by several conditions (e.g. on two fixed surfaces that share an edge)
    counts once, for the first condition in `bcs` that constrains it, so the reactions of all
    conditions sum to minus the applied load.

    The allowed increment grows 1.5x after an increment that converged in <= 5 iterations (<= 8 with
    extra `items`).
    """
    import felupe as fem

    lams = [check_number("load_factors[]", float(x), gt=0) for x in np.atleast_1d(load_factors)]
    if not lams or any(b <= a for a, b in zip(lams, lams[1:])):
        raise InputError("load_factors", f"must be a non-empty strictly increasing list of numbers > 0, got {lams}")
    check_number("min_step", min_step, gt=0)
    if initial_step is None:
        initial_step = lams[0]
    step = check_number("initial_step", initial_step, gt=0)
    max_step = np.inf if max_step is None else check_number("max_step", max_step, gt=0)
    step = min(step, max_step)
    maxiter = int(check_number("maxiter", (25 if items else 12) if maxiter is None else maxiter, ge=1))
    grow = GROW_ITERATIONS_ITEMS if items else GROW_ITERATIONS

    t0 = time.perf_counter()
    loads = _Loads(model, bcs)
    name = linsolve.choose(solver, len(loads.dof1), model.order)
    contact = any(hasattr(i, "step_bound") for i in items)
    if contact:  # the same bits in every run
        linsolve.request_reproducible_mkl()
    # contact runs: the double factor their measured paths were made with (a contact path follows the last digits)
    linear = linsolve.make(name, model.mesh.points, loads.dof1, single=False if contact else None)
    bodies = list(model.bodies.values())
    all_items = [*bodies, *(ld for ld, _ in loads.loads), *items]
    field = model.field

    state = {"fnorms": []}  # the increment's residuals, for the log
    bar = _Progress(progress, lams[-1])

    class _Report(fem.Plugin):
        def after_iteration(self, context, st):
            state["fnorms"].append(float(st.fnorm))
            bar.update(text=f"step {nsteps + 1} (dλ={dl:.3g}) Newton {st.iteration + 1}: |r| = {st.fnorm:.2e}")

    plugins = []
    searching = bool(items) if linesearch is None else bool(linesearch)
    # contact items bound every step by CCD (a substep through a surface gives a NaN residual and ends them)
    bounded = [i for i in items if hasattr(i, "step_bound")]
    # the direct assembly (_Bodies) for bonded runs and contact runs (their line search's det F test reads the
    # bodies, _items_plugin); FElupe's for other items and for the plain line search
    direct = len(bounded) == len(items) and (not searching or bool(bounded))
    assembly = _Bodies(all_items, bodies, loads.dof1, loads.dof0, model.ndof, threads=assembly_threads(),
                       extra=bounded) if direct else None
    newton = ({"items": all_items} if assembly is None
              else {"fun": assembly.fun, "jac": assembly.jac, "solve": assembly.solve})
    collision_free = None  # contact runs' CollisionFreeStep: also shortens the predictor
    if substeps is None:
        substeps = SUBSTEPS if bounded or not (items or searching) else 0
    substeps = int(check_number("substeps", substeps, ge=0))
    if substeps and searching and not bounded:
        raise InputError("substeps", "modified-Newton substeps and the line search exclude each other: "
                                     "give substeps=0 or linesearch=False")
    sub = None
    if substeps and linear.can_resolve:
        sub = _substep_plugin(fem, linear, loads.dof1, substeps, tol)
        linear.keep_factor(True)
        plugins.insert(0, sub)
    if searching:
        # no Armijo test on |r|: a barrier's residual is no merit function (measured: it stalled the
        # needle model at load factor 0.005); reject only inverted and non-finite trials
        if bounded:  # contact: a CCD-bounded step first; a slope line search once Newton stalls
            from needletissue.fem.contact.item import CollisionFreeStep, StallLinesearch

            collision_free = CollisionFreeStep(bounded)
            plugins[:0] = [collision_free, StallLinesearch(bounded)]
        else:
            plugins.insert(0, fem.LinesearchPlugin(admissible=True, residual=False, max_halvings=10,
                                                   criteria=[lambda trial: trial.finite]))
    mixed = [b for b in bodies if isinstance(b, fem.SolidBodyNearlyIncompressible)]
    pressure = _pressure_plugin(fem, mixed)
    plugins.insert(0, pressure)
    if searching and assembly is not None:  # the line search's admissibility test: det F per body
        plugins.insert(0, _items_plugin(fem, bodies))
    # the report first: it records an iteration's residual before a plugin may end the increment there
    plugins.insert(0, _Report())
    predict_from = 1 if isinstance(predictor, bool) else check_number("predictor", predictor, ge=1)
    if predict_from != int(predict_from):
        raise InputError("predictor", f"expected True, False or a whole number of increments >= 1, got {predictor!r}")
    lam, nsteps, nit, ncut = check_number("start", start, ge=0), 0, 0, 0
    if lams[0] <= lam:
        raise InputError("start", f"must be below the first load factor {lams[0]:g}, got {lam:g}")
    last_du, last_dl = None, 0.0  # last converged increment, for the predictor
    last_p = [b.results.state.p.copy() for b in mixed]  # the mixed bodies' pressure there
    last_dp = None
    newton_s = 0.0
    norms: list[list[float]] = []
    out = []
    # what no load changes, for every result: the mesh's statistics (once, not per load: 1 s at paper scale), and
    # each region's nodes (_result, at the first)
    facts: dict = {"stats": model.mesh.stats()}
    emit = _emitter(log, items, t0)
    # contact runs repeat bit for bit (MKL in its reproducible mode on two threads, else one: linsolve.thread_limits)
    with bar if progress else nullcontext(), linsolve.thread_limits(name, reproducible=bool(bounded)), closing(linear), \
            closing(assembly) if assembly is not None else nullcontext():
        for target in lams:
            while lam < target * (1 - 1e-12):
                # equal sub-steps no larger than the allowed increment (no tiny remainders)
                rest = target - lam
                dl = rest / np.ceil(rest / min(step, max_step) - 1e-9)
                saved = [f.values.copy() for f in field.fields]
                pressure.p = None
                if predictor and last_du is not None and nsteps >= predict_from:
                    scale = dl / last_dl
                    if collision_free is not None:  # contact: as far along it as no surface passes another
                        scale *= collision_free.step_fraction(saved[0], scale * last_du[0])
                    for f, d in zip(field.fields, last_du):
                        f.values = f.values + scale * d
                    pressure.p = [p + scale * d for p, d in zip(last_p, last_dp)]
                    if not all(i.admissible() for i in items if hasattr(i, "admissible")):
                        for f, v in zip(field.fields, saved):  # e.g. contact surfaces passed through
                            f.values = v.copy()
                        pressure.p = None
                stateful = [*bodies, *items]  # e.g. a frictional contact item's history
                checkpoints = [b.checkpoint() if hasattr(b, "checkpoint") else None for b in stateful]
                ext0 = loads.apply(model, lam + dl)
                taken0 = sub.taken if sub is not None else 0  # substeps count like iterations: converged ones
                ok, res, why = False, None, ""
                state["fnorms"] = []
                ts = time.perf_counter()
                try:
                    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # failures are handled
                        res = fem.newtonraphson(
                            x0=field, dof1=loads.dof1, dof0=loads.dof0, ext0=ext0,
                            solver=linear, tol=tol, maxiter=maxiter, verbose=0, plugins=plugins, **newton)
                    if assembly is not None and res.success:  # what FElupe does for items
                        for item in all_items:
                            item.results.update_statevars()
                    ok = bool(res.success) and np.all(np.isfinite(res.fun))
                    if ok:  # the energies are defined for det F < 0 too: reject inverted elements
                        jmin = min(_min_det_f(b) for b in bodies)
                        if not jmin > 0:
                            ok, why = False, f"inverted elements (min det F = {jmin:.3g})"
                except InputError:
                    raise
                except (ValueError, ArithmeticError, RuntimeError, np.linalg.LinAlgError) as exc:
                    why = f"{type(exc).__name__}: {exc}"
                newton_s += time.perf_counter() - ts
                if ok:
                    if sub is not None:
                        sub.enabled = True
                    field.link(res.x)
                    last_fun = res.fun  # residual at the converged state: reactions, no re-assembly
                    last_du = [f.values - v for f, v in zip(field.fields, saved)]
                    last_dl = dl
                    p = [b.results.state.p.copy() for b in mixed]
                    last_dp, last_p = [a - b for a, b in zip(p, last_p)], p
                    lam += dl
                    nsteps += 1
                    nit += int(res.iterations)
                    norms.append([float(x) for x in res.fnorms])
                    if res.iterations <= grow:  # grow the allowed increment (dl may be a split of it)
                        step = min(1.5 * max(step, dl), max_step)
                    else:
                        step = dl
                    bar.update(lam=lam)
                    emit("increment", load_factor=lam, increment=dl, iterations=int(res.iterations),
                         residuals=state["fnorms"])
                    continue
                # failed: restore the last converged state and halve the increment
                # (contact: halved at once; the failures there are the barrier's, not the substeps')
                retry = sub is not None and sub.enabled and sub.taken > taken0 and not bounded
                if sub is not None:
                    sub.taken = taken0
                for f, v in zip(field.fields, saved):
                    f.values = v
                for b, c in zip(stateful, checkpoints):
                    if c is not None:
                        b.restore(c)
                if retry:  # substeps can lead Newton astray: the same increment once more without them
                    sub.enabled = False
                    bar.update(text=f"retry dλ={dl:.3g} at λ={lam:.4g} without substeps")
                    continue
                ncut += 1
                last_du = None  # the path turned: no extrapolation from a failed direction
                step = dl / 2
                bar.update(text=f"cut-back to dλ={step:.3g} at λ={lam:.4g} ({why or 'no convergence in %d iterations' % maxiter})")
                emit("cutback", load_factor=lam, increment=dl, reason=why or f"no convergence in {maxiter} iterations",
                     residuals=state["fnorms"])
                if step < min_step:
                    loads.apply(model, lam)
                    emit("failed", load_factor=lam, steps=nsteps, iterations=nit, cutbacks=ncut)
                    raise ConvergenceError(
                        f"no convergence beyond load factor {lam:.6g} (target {target:.6g}): increment "
                        f"{dl:.3g} failed and halving it would go below min_step={min_step:g} "
                        f"({nsteps} steps, {nit} Newton iterations, {ncut} cut-backs; last: {why or 'max iterations'})")
            nsub = sub.taken if sub is not None else 0
            if results:
                out.append(_result(model, loads, last_fun, target, nsteps, nit, ncut, time.perf_counter() - t0,
                                   linear, newton_s, norms, nsub, facts))
            else:
                out.append(FEResult(target, field[0].values.copy(), {}, {}, nsteps, nit, time.perf_counter() - t0,
                                    copy.deepcopy(facts["stats"]), ncut, linear.name,
                                    {"newton": newton_s, "linear_solve": linear.seconds,
                                     "assembly_and_update": newton_s - linear.seconds}, norms,
                                    newton_substeps=nsub, linear_factor=linear.factor,
                                    linear_counts=linear.counts))
    return out


def _emitter(log, items, t0):
    """log(event, **fields) -> log({event, fields, cpu_s, wall_s, min_distance_mm}); a no-op without log."""
    if log is None:
        return lambda event, **kw: None
    c0 = time.process_time()
    contact = [i for i in items if hasattr(i, "contact_state")]

    def emit(event, **kw):
        rec = {"event": event, **kw, "cpu_s": round(time.process_time() - c0, 2),
               "wall_s": round(time.perf_counter() - t0, 2)}
        if contact:  # each item's last evaluation (for "increment": the converged state)
            rec["min_distance_mm"] = {"+".join(x.name for x in i.surface.interfaces): i.results.info.get("min_distance_mm")
                                      for i in contact}
        log(rec)

    return emit


def _min_det_f(body) -> float:
    """Smallest det F over the quadrature points of a body's last evaluation (the converged state)."""
    F = body.results.kinematics[0]
    return float(np.min(np.linalg.det(np.moveaxis(F, (0, 1), (-2, -1)))))


def _result(model, loads, fvec, lam, nsteps, nit, ncut, wall, linear, newton_s, norms, nsub, facts: dict) -> FEResult:
    """The converged state as an FEResult. `facts` holds what no load changes: the mesh's statistics, and each
    region's nodes from the first result on (1.4 s a load at paper scale together)."""
    mesh = model.mesh
    if "nodes" not in facts:
        facts["nodes"] = {r: np.unique(mesh.cells[ids]) for r, ids in mesh.regions.items()}
    u = model.field[0].values.copy()
    umag = np.linalg.norm(u, axis=1)
    fnod = fvec.reshape(-1, 3)
    reactions = {s: np.where(m, fnod, 0.0).sum(0) for s, m in loads.reaction_sets.items()}
    maxu = {r: float(umag[nodes].max()) for r, nodes in facts["nodes"].items()}
    ncell = len(mesh.cells)
    vm = np.zeros(ncell)
    stretch = np.zeros((ncell, 3))
    # for ParaView: row-major 3x3 tensors, cell means over the quadrature points; float32 halves their
    # memory (2 x 36 bytes a cell: 100 MB per load at the paper's 1.33 M elements)
    cauchy = np.zeros((ncell, 9), np.float32)
    strain = np.zeros((ncell, 9), np.float32)
    for r, ids in mesh.regions.items():
        body = model.bodies[r]
        sigma = np.asarray(body.evaluate.cauchy_stress(body.field))  # (3, 3, q, c)
        vm[ids] = von_mises(np.moveaxis(sigma, (0, 1), (-2, -1))).mean(0)
        cauchy[ids] = np.moveaxis(sigma.mean(2), -1, 0).reshape(-1, 9)
        F = body.field[0].extract()  # (3, 3, q, c)
        stretch[ids] = principal_stretches(np.moveaxis(F, (0, 1), (-2, -1))).mean(0)
        strain[ids] = np.moveaxis(green_lagrange(F).mean(2), -1, 0).reshape(-1, 9)
    tags = {r: i for i, r in enumerate(mesh.regions)}
    return FEResult(
        load_factor=lam, displacement=u, max_displacement_by_region=maxu, reaction_forces=reactions,
        steps=nsteps, newton_iterations=nit, wall_time_s=wall, mesh_stats=copy.deepcopy(facts["stats"]), cutbacks=ncut,
        linear_solver=linear.name,
        timing_s={"newton": newton_s, "linear_solve": linear.seconds, "assembly_and_update": newton_s - linear.seconds},
        residual_norms=[list(n) for n in norms], newton_substeps=nsub, linear_factor=linear.factor,
        linear_counts=linear.counts,
        region_tags=tags, points=mesh.points,
        cells=mesh.cells,
        cell_data={"von_mises_MPa": vm, "principal_stretches": stretch, "cauchy_stress_MPa": cauchy,
                   "green_lagrange_strain": strain, "region": mesh.region_of_cells().astype(np.int32)},
    ).check_drucker({r: m.name for r, m in model.materials.items()})
