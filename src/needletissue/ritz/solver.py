"""Solve the Ritz model: one force (control loop), many forces, or arrays of parameter sets.

Every answer carries `error_estimate_mm` (sup over z of the change of v(z) when the order is raised by
one) and `order_converged` (error estimate <= tol_mm: about the trial-function order p, not the solve;
`converged` is its old name, kept for parsers). `solve_batch(..., error_estimate=False)` skips the
order p + 1 solve: the estimate is then NaN, `error_estimated` is False and so is `order_converged`
(not shown). A Newton solve that does not converge raises ConvergenceError; no unconverged answer is
ever returned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from needletissue.errors import ConvergenceError, InputError, check_number
from needletissue.ritz import basis, kernel
from needletissue.ritz.model import MAX_DEFLECTION_RATIO, RitzModel

DEFAULT_TOL_MM = 1e-4
_PARALLEL_MIN = 2_000  # below this a thread pool costs more than it saves
# Unrolled kernels for orders 3 and 4 (kernel._energy2/3). False selects the generic reference loops,
# which the tests and benchmarks/bench_ritz.py compare against.
_FAST = True
# With _FAST, order 3 through its closed-form energy (kernel.cubic_table; issue 18). False keeps the
# unrolled Gauss-point path for order 3 (the previous version, for the tests and the benchmark).
_CLOSED = True
# With _CLOSED, the order-4 solve behind the order-3 error estimate with the basis in monomial form
# (kernel._newton4). False: that solve on the unrolled Gauss path (the previous version).
_MONOMIAL4 = True
# With _MONOMIAL4, that solve replaced by one order-4 Newton step from the order-3 answer, in closed
# form (kernel._step4c; not with order='auto'). False: the full order-4 Newton (the previous version).
_STEP4 = True


@dataclass(frozen=True)
class RitzResult:
    """One solved force. Deflections in mm (sign of the force), slope in rad, energies in N mm."""

    force_N: float
    tip_deflection_mm: float
    load_point_deflection_mm: float
    max_deflection_mm: float  # v at the z where |v| is largest
    z_max_mm: float
    tip_slope_rad: float  # theta(l) = atan(v'(l))
    spring_reaction_N: dict  # layer name -> int k (x + x^3) dz over the layer
    energy_Nmm: float  # total potential energy at the solution
    bending_energy_Nmm: float
    spring_energy_Nmm: float
    work_Nmm: float
    coefficients: tuple  # paper's monomial form v = sum_j a_j z^j, (a_2, ..., a_p), units mm^(1-j)
    basis_coefficients_mm: tuple  # c_i of the integrated-Legendre trial functions (basis.py)
    order: int
    iterations: int  # Newton iterations of the order-p solve
    error_estimate_mm: float
    converged: bool  # error_estimate_mm <= tol_mm (the order, not Newton); alias order_converged
    free_length_mm: float
    error_estimated: bool = True  # False: solved without the order p + 1 solve, error_estimate_mm NaN

    @property
    def order_converged(self) -> bool:
        """error_estimate_mm <= tol_mm: raising the order p changes v(z) by less than tol (False when no
        estimate was computed). Newton itself always converged (it raises ConvergenceError otherwise)."""
        return self.converged

    @property
    def deflection_ratio(self) -> float:
        """|v|max / l: the model is valid up to MAX_DEFLECTION_RATIO (small rotations)."""
        return abs(self.max_deflection_mm) / self.free_length_mm

    @property
    def within_validity(self) -> bool:
        return self.deflection_ratio <= MAX_DEFLECTION_RATIO

    def deflection(self, z_mm) -> np.ndarray:
        """v(z) in mm at z in [0, l] mm."""
        z = np.asarray(z_mm, dtype=float)
        return basis.evaluate(z / self.free_length_mm, self.order) @ np.asarray(self.basis_coefficients_mm)

    def curve(self, n: int = 101) -> tuple[np.ndarray, np.ndarray]:
        """(z, v(z)) at n equally spaced points from the bone (z = 0) to the free end."""
        z = np.linspace(0.0, self.free_length_mm, n)
        return z, self.deflection(z)

    @cached_property
    def z_mm(self) -> np.ndarray:
        return self.curve()[0]

    @cached_property
    def v_mm(self) -> np.ndarray:
        return self.curve()[1]

    def to_json(self) -> dict:
        """The CLI's output contract for one force."""
        return {
            "force_N": self.force_N,
            "tip_deflection_mm": self.tip_deflection_mm,
            "load_point_deflection_mm": self.load_point_deflection_mm,
            "max_deflection_mm": self.max_deflection_mm,
            "tip_slope_rad": self.tip_slope_rad,
            "coefficients": list(self.coefficients),
            "order": self.order,
            "iterations": self.iterations,
            "order_converged": self.converged,  # error_estimate_mm <= tol_mm: the order p is enough
            "newton_converged": True,  # always: an unconverged Newton solve raises, never returns
            "converged": self.converged,  # old name of order_converged, kept for parsers
            "error_estimate_mm": self.error_estimate_mm,
            "deflection_to_free_length": self.deflection_ratio,
            "within_validity_range": self.within_validity,  # deflection_to_free_length <= 0.25
        }


@dataclass(frozen=True)
class BatchResult:
    """Solutions of N samples as arrays of length N (per-layer and coefficient arrays are (N, m))."""

    force_N: np.ndarray
    tip_deflection_mm: np.ndarray
    load_point_deflection_mm: np.ndarray
    max_deflection_mm: np.ndarray
    z_max_mm: np.ndarray
    tip_slope_rad: np.ndarray
    spring_reaction_N: np.ndarray  # (N, layers)
    energy_Nmm: np.ndarray
    bending_energy_Nmm: np.ndarray
    spring_energy_Nmm: np.ndarray
    work_Nmm: np.ndarray
    basis_coefficients_mm: np.ndarray  # (N, max_order - 1), zero beyond each sample's order
    order: np.ndarray
    iterations: np.ndarray
    error_estimate_mm: np.ndarray
    converged: np.ndarray  # error_estimate_mm <= tol_mm per sample (the order); alias order_converged
    free_length_mm: np.ndarray
    layer_names: tuple
    error_estimated: bool = True  # False: error_estimate=False, estimates NaN, order_converged False

    @property
    def order_converged(self) -> np.ndarray:
        return self.converged

    def __len__(self) -> int:
        return self.force_N.shape[0]

    @property
    def coefficients(self) -> np.ndarray:
        """Monomial coefficients a_j (columns j = 0 .. max_order; a_0 = a_1 = 0), units mm^(1-j)."""
        n = self.basis_coefficients_mm.shape[1]
        M = basis.monomial_matrix(n + 1)
        j = np.arange(n + 2)
        return (self.basis_coefficients_mm @ M) / self.free_length_mm[:, None] ** j

    def deflection(self, z_mm) -> np.ndarray:
        """v in mm: z scalar -> (N,); z (M,) -> (N, M) same z for all; z (N, M) -> per sample."""
        z = np.asarray(z_mm, dtype=float)
        zz = z if z.ndim == 2 else np.broadcast_to(np.atleast_1d(z), (len(self), z.size))
        n = self.basis_coefficients_mm.shape[1]
        phi = basis.evaluate(zz / self.free_length_mm[:, None], n + 1)
        v = np.einsum("nzi,ni->nz", phi, self.basis_coefficients_mm)
        return v[:, 0] if z.ndim == 0 else v

    def __getitem__(self, m: int) -> RitzResult:
        p = int(self.order[m])
        c = self.basis_coefficients_mm[m, : p - 1]
        a = (c @ basis.monomial_matrix(p)) / self.free_length_mm[m] ** np.arange(p + 1)
        return RitzResult(
            force_N=float(self.force_N[m]),
            tip_deflection_mm=float(self.tip_deflection_mm[m]),
            load_point_deflection_mm=float(self.load_point_deflection_mm[m]),
            max_deflection_mm=float(self.max_deflection_mm[m]),
            z_max_mm=float(self.z_max_mm[m]),
            tip_slope_rad=float(self.tip_slope_rad[m]),
            spring_reaction_N={name: float(r) for name, r in zip(self.layer_names, self.spring_reaction_N[m])},
            energy_Nmm=float(self.energy_Nmm[m]),
            bending_energy_Nmm=float(self.bending_energy_Nmm[m]),
            spring_energy_Nmm=float(self.spring_energy_Nmm[m]),
            work_Nmm=float(self.work_Nmm[m]),
            coefficients=tuple(float(x) for x in a[2:]),
            basis_coefficients_mm=tuple(float(x) for x in c),
            order=p,
            iterations=int(self.iterations[m]),
            error_estimate_mm=float(self.error_estimate_mm[m]),
            converged=bool(self.converged[m]),
            free_length_mm=float(self.free_length_mm[m]),
            error_estimated=self.error_estimated,
        )

    def results(self) -> list[RitzResult]:
        return [self[m] for m in range(len(self))]


def parse_order(order) -> tuple[int, bool]:
    """3, N >= 3, '5' or 'auto' -> (starting order, auto)."""
    if isinstance(order, str):
        if order.strip().lower() == "auto":
            return 3, True
        try:
            order = int(order)
        except ValueError:
            raise InputError("order", f"must be an integer >= 3 or 'auto', got {order!r}") from None
    if isinstance(order, bool) or not isinstance(order, (int, np.integer)):
        raise InputError("order", f"must be an integer >= 3 or 'auto', got {order!r}")
    if not 3 <= order <= basis.P_MAX:
        raise InputError("order", f"must be >= 3 and <= {basis.P_MAX} (or 'auto'), got {order}")
    return int(order), False


def _tables():
    A, Ad = basis.legendre_tables()
    GX, GW = basis.gauss_tables()
    gphi = np.ascontiguousarray(basis.evaluate(basis.GRID, basis.P_MAX + 1))
    return A, Ad, GX, GW, basis.GRID, gphi


_TABLES = None


def _run(F, KB, L, Z3, T, K, cos_term, order, auto, max_order, tol, parallel, estimate=True):
    """F has one entry per sample; KB, L, Z3, T, K one row per sample or one shared row."""
    global _TABLES
    if _TABLES is None:
        _TABLES = _tables()
    N = F.shape[0]
    pmax = max_order if auto else order
    C = np.empty((N, pmax - 1))  # the kernel writes pmax - 1 coefficients
    S = np.empty((kernel.NCOLS, N))  # one row per output column
    R = np.empty((N, T.shape[1]))
    if parallel is None:
        parallel = N >= _PARALLEL_MIN
    if parallel:
        from numba import get_num_threads
        fn, chunks = kernel.solve_parallel, min(N, 8 * get_num_threads())
    else:
        fn, chunks = kernel.solve_serial, 1
    fn(F, KB, L, Z3, T, K, cos_term, order, auto, pmax, tol, *_TABLES, C, S, R, chunks, _FAST,
       _FAST and _CLOSED, estimate, _MONOMIAL4, _STEP4)
    status = S[kernel.STATUS]
    if status.any():
        bad = np.flatnonzero(status != kernel.OK)
        m = bad[0]
        g = 0 if L.shape[0] == 1 else m
        why = {kernel.MAX_ITER: "iteration limit", kernel.LINE_SEARCH: "line search failed",
               kernel.NOT_FINITE: "non-finite energy"}[int(status[m])]
        raise ConvergenceError(
            f"Ritz Newton did not converge for {bad.size} of {N} samples ({why}); first: sample {m}, "
            f"force {F[m]} N, free length {L[g]} mm, EI/l^3 {KB[g]} N/mm")
    return C, S, R


def solve(force: float, model: RitzModel | None = None, order=3, tol_mm: float = DEFAULT_TOL_MM,
          max_order: int = 16) -> RitzResult:
    """Deflection of the needle under one force (N; negative = opposite direction)."""
    model = RitzModel() if model is None else model
    F = np.array([check_number("force_N", force)])
    p, auto = parse_order(order) if order != 3 else (3, False)
    if auto:
        max_order = int(check_number("max_order", max_order, ge=3, le=basis.P_MAX))
    tol = check_number("tol_mm", tol_mm, gt=0)
    KB, L, Z3, T, K = model._arrays
    C, S, R = _run(F, KB, L, Z3, T, K, model.cos_term, p, auto, max_order, tol, False)
    return _result(F, C, S, R, model, 0, tol)


def _result(F, C, S, R, model, m, tol) -> RitzResult:
    s = S[:, m]
    p = int(s[kernel.ORDER])
    c = C[m, : p - 1]
    a = (c @ basis.monomial_matrix(p)) / model.free_length_mm ** np.arange(p + 1)
    return RitzResult(
        force_N=float(F[m]),
        tip_deflection_mm=float(s[kernel.TIP]),
        load_point_deflection_mm=float(s[kernel.LOAD]),
        max_deflection_mm=float(s[kernel.VMAX]),
        z_max_mm=float(s[kernel.ZMAX]),
        tip_slope_rad=math.atan(s[kernel.TIP_DVDZ]),
        spring_reaction_N={la.name: float(r) for la, r in zip(model.layers, R[m])},
        energy_Nmm=float(s[kernel.U_BEND] + s[kernel.U_SPRING] - s[kernel.WORK]),
        bending_energy_Nmm=float(s[kernel.U_BEND]),
        spring_energy_Nmm=float(s[kernel.U_SPRING]),
        work_Nmm=float(s[kernel.WORK]),
        coefficients=tuple(a[2:].tolist()),
        basis_coefficients_mm=tuple(c.tolist()),
        order=p,
        iterations=int(s[kernel.ITER]),
        error_estimate_mm=float(s[kernel.ERR]),
        converged=bool(s[kernel.ERR] <= tol),
        free_length_mm=model.free_length_mm,
    )


def solve_forces(forces, model: RitzModel | None = None, order=3, tol_mm: float = DEFAULT_TOL_MM,
                 max_order: int = 16) -> list[RitzResult]:
    """One result per force, same model (one compiled call)."""
    model = RitzModel() if model is None else model
    forces = [check_number(f"force_N[{i}]", f) for i, f in enumerate(forces)]
    p, auto = parse_order(order)
    max_order = int(check_number("max_order", max_order, ge=3, le=basis.P_MAX))
    tol = check_number("tol_mm", tol_mm, gt=0)
    F = np.array(forces, dtype=float)
    N = F.size
    KB, L, Z3, T, K = model._arrays  # one row, shared by every force
    C, S, R = _run(F, KB, L, Z3, T, K, model.cos_term, p, auto, max_order, tol, None)
    return [_result(F, C, S, R, model, m, tol) for m in range(N)]


def _index(i, shape) -> tuple:
    return tuple(int(j) for j in np.unravel_index(i, shape))


def _array(field: str, value, *, gt=None):
    a = np.asarray(value, dtype=float)
    bad = ~np.isfinite(a)
    if bad.any():
        raise InputError(field, f"must be finite, got {a[bad].flat[0]} at index "
                         f"{_index(np.flatnonzero(bad)[0], a.shape)}")
    if gt is not None and not (a > gt).all():
        i = np.flatnonzero(~(a > gt))[0]
        raise InputError(field, f"must be > {gt}, got {a.flat[i]} at index {_index(i, a.shape)}")
    return a


def _rows(a, ng, nl):
    """(ng, nl) C-contiguous float64 from (nl,), (1, nl) or (ng, nl) (a filled copy when broadcast:
    ascontiguousarray of a broadcast view is ~10x slower)."""
    if a.shape == (ng, nl):
        return np.ascontiguousarray(a, dtype=float)
    out = np.empty((ng, nl))
    out[...] = a
    return out


def solve_batch(force, *, diameter_mm=None, free_length_mm=None, youngs_modulus_MPa=None,
                thickness_mm=None, k_N_per_mm2=None, load_point_mm=None, model: RitzModel | None = None,
                order=3, tol_mm: float = DEFAULT_TOL_MM, max_order: int = 16,
                parallel: bool | None = None, error_estimate: bool = True) -> BatchResult:
    """Solve N samples in one compiled call; every argument broadcasts to N.

    force: (N,) N. diameter_mm, free_length_mm, youngs_modulus_MPa, load_point_mm: scalars or (N,)
    (load_point_mm None = the model's, whose None is the free end). thickness_mm, k_N_per_mm2: (layers,) or (N, layers), layers
    stacked from the bone. Parameters not given come from `model` (default RitzModel()). When only the
    force varies, the model's order-3 energy forms are computed once for the batch.
    error_estimate=False skips the order p + 1 solve behind error_estimate_mm (about half the cost at
    p = 3): the estimates are then NaN, `error_estimated` False and `order_converged` False.
    Runs on all Numba threads for N >= 2000 (set NUMBA_NUM_THREADS to limit).
    """
    model = RitzModel() if model is None else model
    p, auto = parse_order(order)
    max_order = int(check_number("max_order", max_order, ge=3, le=basis.P_MAX))
    tol = check_number("tol_mm", tol_mm, gt=0)
    if not isinstance(error_estimate, (bool, np.bool_)):
        raise InputError("error_estimate", f"must be true or false, got {error_estimate!r}")
    if auto and not error_estimate:
        raise InputError("error_estimate", "order='auto' raises the order by the error estimate: it "
                         "cannot be switched off")
    F = _array("force_N", force)
    d = _array("diameter_mm", model.diameter_mm if diameter_mm is None else diameter_mm, gt=0)
    l = _array("free_length_mm", model.free_length_mm if free_length_mm is None else free_length_mm, gt=0)
    E = _array("youngs_modulus_MPa", model.youngs_modulus_MPa if youngs_modulus_MPa is None
               else youngs_modulus_MPa, gt=0)
    t = _array("thickness_mm", [la.thickness_mm for la in model.layers] if thickness_mm is None
               else thickness_mm, gt=0)
    k = _array("k_N_per_mm2", [la.k_N_per_mm2 for la in model.layers] if k_N_per_mm2 is None
               else k_N_per_mm2, gt=0)
    if t.ndim == 0 or k.ndim == 0 or t.shape[-1] != k.shape[-1]:
        raise InputError("thickness_mm/k_N_per_mm2", f"need matching trailing layer axes, got "
                         f"{t.shape} and {k.shape}")
    if load_point_mm is None:
        load_point_mm = model.load_point_mm  # the model's own (None: the free end)
    z3 = None if load_point_mm is None else _array("load_point_mm", load_point_mm, gt=0)
    try:
        shape_model = np.broadcast_shapes(d.shape, l.shape, E.shape, t.shape[:-1], k.shape[:-1],
                                          () if z3 is None else z3.shape)
        N = np.broadcast_shapes(F.shape, shape_model)
    except ValueError as exc:
        raise InputError("solve_batch", f"arguments do not broadcast to one sample axis: {exc}") from None
    if len(N) > 1:
        raise InputError("solve_batch", f"samples must be one axis, got shape {N}")
    n = N[0] if N else 1
    # one model row for all samples when only the force varies, else one row per sample
    ng = 1 if math.prod(shape_model) == 1 else n
    nl = t.shape[-1]
    F = np.ascontiguousarray(np.broadcast_to(F, (n,)), dtype=float)
    d, l, E = (np.ascontiguousarray(np.broadcast_to(a.reshape(-1) if a.size == 1 else a, (ng,)),
                                    dtype=float) for a in (d, l, E))
    T, K = _rows(t, ng, nl), _rows(k, ng, nl)
    total = T[:, 0].copy()  # column by column: a sum over a short last axis is ~20x slower in NumPy
    for j in range(1, nl):
        total += T[:, j]
    too_thick = total > l * (1 + 1e-12)  # round-off of thickness fractions of l
    if too_thick.any():
        m = np.flatnonzero(too_thick)[0]
        raise InputError("thickness_mm", f"total layer thickness must be <= free_length_mm, got "
                         f"{T[m].sum()} > {l[m]} at index {m}")
    if z3 is None:
        Z3 = l.copy()
    else:
        Z3 = np.ascontiguousarray(np.broadcast_to(z3.reshape(-1) if z3.size == 1 else z3, (ng,)),
                                  dtype=float)
        over = Z3 > l
        if over.any():
            m = np.flatnonzero(over)[0]
            raise InputError("load_point_mm", f"must be in (0, free_length_mm], got {Z3[m]} > {l[m]} "
                             f"at index {m}")
    d2 = d * d  # products, not np.power (a libm pow per element for exponents other than 2)
    KB = E * (np.pi * (d2 * d2) / 64.0) / (l * l * l)
    # one compiled signature only: C-contiguous, writeable float64 (broadcast views are read-only)
    F, KB, l, Z3, T, K = (np.require(a, np.float64, ["C", "W"]) for a in (F, KB, l, Z3, T, K))
    C, S, R = _run(F, KB, l, Z3, T, K, model.cos_term, p, auto, max_order, tol, parallel,
                   bool(error_estimate))
    return BatchResult(
        force_N=F,
        tip_deflection_mm=S[kernel.TIP],
        load_point_deflection_mm=S[kernel.LOAD],
        max_deflection_mm=S[kernel.VMAX],
        z_max_mm=S[kernel.ZMAX],
        tip_slope_rad=np.arctan(S[kernel.TIP_DVDZ]),
        spring_reaction_N=R,
        energy_Nmm=S[kernel.U_BEND] + S[kernel.U_SPRING] - S[kernel.WORK],
        bending_energy_Nmm=S[kernel.U_BEND],
        spring_energy_Nmm=S[kernel.U_SPRING],
        work_Nmm=S[kernel.WORK],
        basis_coefficients_mm=C,
        order=S[kernel.ORDER].astype(int),
        iterations=S[kernel.ITER].astype(int),
        error_estimate_mm=S[kernel.ERR],
        converged=S[kernel.ERR] <= tol,
        free_length_mm=l if ng == n else np.full(n, l[0]),
        layer_names=tuple(la.name for la in model.layers) if nl == len(model.layers)
        else tuple(f"layer{j}" for j in range(nl)),
        error_estimated=bool(error_estimate),
    )
