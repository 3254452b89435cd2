"""The fast kernel paths against the generic reference loops: the unrolled, vectorised orders 3 and 4,
and order 3 through its closed-form energy (kernel.cubic_table: moments of the layers, once per model).

All paths run the same Newton iteration; the fast ones only evaluate the same exact integrals in
another order (Gauss points summed differently, or moments of s), so every result must agree to
round-off (1e-12 of the field's scale), iteration counts and failure reports included.
"""

import numpy as np
import pytest

from needletissue import ritz
from needletissue.errors import ConvergenceError, InputError
from needletissue.ritz import RitzModel, basis, kernel, solver

FIELDS = ("tip_deflection_mm", "load_point_deflection_mm", "max_deflection_mm", "z_max_mm", "tip_slope_rad",
          "spring_reaction_N", "energy_Nmm", "bending_energy_Nmm", "spring_energy_Nmm", "work_Nmm",
          "basis_coefficients_mm")


def _both(monkeypatch, fn, closed=True):
    """fn() on the reference loops, then on the fast path (closed: with the closed-form order 3)."""
    monkeypatch.setattr(solver, "_CLOSED", closed)
    out = []
    for fast in (False, True):
        monkeypatch.setattr(solver, "_FAST", fast)
        out.append(fn())
    return out


def _assert_same(ref, fast):
    assert np.array_equal(ref.order, fast.order)
    assert np.array_equal(ref.iterations, fast.iterations)
    assert np.array_equal(ref.converged, fast.converged)
    for f in FIELDS:
        a, b = getattr(ref, f), getattr(fast, f)
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max(), err_msg=f)


def _random_batch(rng, n):
    return dict(force=rng.uniform(-2000, 2000, n), diameter_mm=rng.uniform(3, 6, n),
                free_length_mm=rng.uniform(35, 150, n),
                thickness_mm=np.stack([rng.uniform(5, 25, n), rng.uniform(2, 10, n)], 1),
                k_N_per_mm2=np.array([0.048, 0.023]) * np.exp(rng.uniform(np.log(0.1), np.log(100), (n, 2))),
                load_point_mm=None)


@pytest.mark.parametrize("closed", [True, False], ids=["closed_p3", "unrolled"])
@pytest.mark.parametrize("order", [3, 4, "auto"])
@pytest.mark.parametrize("cos", [True, False])
def test_fast_path_equals_reference(monkeypatch, order, cos, closed):
    monkeypatch.setattr(solver, "_STEP4", False)  # the full order-4 estimate (the one-step: below)
    rng = np.random.default_rng(7)
    kw = _random_batch(rng, 400)
    kw["load_point_mm"] = kw["free_length_mm"] * rng.uniform(0.5, 1.0, 400)
    ref, fast = _both(monkeypatch, lambda: ritz.solve_batch(**kw, model=RitzModel(cos_term=cos), order=order,
                                                            parallel=False), closed)
    _assert_same(ref, fast)
    # the estimate is a difference of two deflections: round-off relative to the deflection
    np.testing.assert_allclose(fast.error_estimate_mm, ref.error_estimate_mm, rtol=1e-12,
                               atol=1e-12 * np.abs(ref.max_deflection_mm).max())


def test_fast_path_single_solve_and_failure_report(monkeypatch):
    ref, fast = _both(monkeypatch, lambda: ritz.solve(300.0))
    assert fast.iterations == ref.iterations and fast.converged == ref.converged
    assert fast.tip_deflection_mm == pytest.approx(ref.tip_deflection_mm, rel=1e-12)
    # a batch with one sample that cannot converge: the same error, naming the same sample
    msgs = []
    for fast_path in (False, True):
        monkeypatch.setattr(solver, "_FAST", fast_path)
        with pytest.raises(ConvergenceError) as exc:
            ritz.solve_batch(np.array([100.0, 1e200, 300.0, 1e250]), parallel=False)
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1] and "2 of 4 samples" in msgs[1] and "sample 1" in msgs[1]


@pytest.mark.parametrize("runs", [False, True], ids=["thickness_per_row", "thickness_in_runs"])
@pytest.mark.parametrize("cos", [True, False])
def test_closed_form_order3_on_random_models_and_stiff_tissue(monkeypatch, cos, runs):
    """Every parameter random, tissue up to 10^4 x Table 1 and loads near the bone: the closed form
    gives the reference's answers and iteration counts, also where |v| peaks inside the span; with
    the thicknesses in runs of 10 rows, through the per-row tables of kernel.cubic_table_rows."""
    rng = np.random.default_rng(11)
    n = 3000
    kw = _random_batch(rng, n)
    if runs:
        kw["thickness_mm"] = np.repeat(kw["thickness_mm"][::10], 10, axis=0)
    kw["youngs_modulus_MPa"] = rng.uniform(50e3, 210e3, n)
    kw["k_N_per_mm2"] = np.array([0.048, 0.023]) * np.exp(rng.uniform(np.log(0.1), np.log(1e4), (n, 2)))
    kw["load_point_mm"] = kw["free_length_mm"] * np.exp(rng.uniform(np.log(0.01), 0.0, n))
    ref, fast = _both(monkeypatch, lambda: ritz.solve_batch(**kw, model=RitzModel(cos_term=cos),
                                                            parallel=False, error_estimate=False))
    _assert_same(ref, fast)
    # where the maximum is inside the span it is the stationary point of v = a2 z^2 + a3 z^3
    a = fast.coefficients
    inner = fast.z_max_mm < fast.free_length_mm * (1 - 1e-9)
    assert inner.sum() >= 5
    np.testing.assert_allclose(fast.z_max_mm[inner], -2 * a[inner, 2] / (3 * a[inner, 3]), rtol=1e-12)


def test_force_only_batch_shares_one_model_row(monkeypatch):
    """Scalars for every model parameter: one table for the batch; the same numbers as one row each
    (kernel.cubic_table_rows: round-off apart, the same iterations)."""
    F = np.random.default_rng(3).uniform(-2000, 2000, 500)
    model = RitzModel(load_point_mm=70.0)  # solve_batch takes the load point as an argument only
    shared = ritz.solve_batch(F, model=model, load_point_mm=70.0, parallel=False, error_estimate=False)
    d = np.full(F.size, model.diameter_mm)  # an array: one model row per sample
    rows = ritz.solve_batch(F, model=model, load_point_mm=70.0, diameter_mm=d, parallel=False,
                            error_estimate=False)
    _assert_same(shared, rows)
    one = [ritz.solve(f, model) for f in F[:5]]  # the control-loop path, one force at a time
    np.testing.assert_allclose(shared.tip_deflection_mm[:5], [r.tip_deflection_mm for r in one], rtol=1e-13)


@pytest.mark.parametrize("cos", [True, False])
def test_model_rows_sharing_thicknesses_equal_one_model_each(cos):
    """Rows with every parameter random but the thicknesses in runs (the per-row table from the
    thickness columns, reused within a run and rebuilt between runs; a row alone gets its own
    cubic_table) against each row alone (one cubic_table): the same iterations, answers and
    estimates to round-off."""
    rng = np.random.default_rng(11)
    kw = _random_batch(rng, 60)
    T = np.repeat(kw["thickness_mm"][:4], 15, axis=0)
    T[20] *= 0.9  # a single row inside a run, and the last row alone
    T[59] *= 1.1
    kw["thickness_mm"] = T
    model = RitzModel(cos_term=cos)
    rows = ritz.solve_batch(**kw, model=model, parallel=False)
    one = [ritz.solve_batch(**{a: v[i:i + 1] for a, v in kw.items() if v is not None}, model=model,
                            parallel=False) for i in range(60)]
    assert np.array_equal(rows.iterations, [b.iterations[0] for b in one])
    for f in FIELDS + ("error_estimate_mm",):
        a = np.concatenate([getattr(b, f) for b in one])
        np.testing.assert_allclose(getattr(rows, f), a, rtol=1e-12,
                                   atol=1e-12 * np.abs(rows.max_deflection_mm).max(), err_msg=f)


def _rows_table(l, T, K, z3, cos):
    """The per-row table of one model (kernel.cubic_table_rows on thickness_table's columns)."""
    GX, _ = basis.gauss_tables()
    nl = T.size
    G, ZQ, tab = np.empty((nl, kernel._PHI3)), np.empty((nl, 12)), np.empty(kernel._NTAB)
    h = kernel.thickness_table(T, cos, G, ZQ, np.empty(kernel._NMU), GX)
    kernel.cubic_table_rows(l, K.reshape(1, nl), 0, z3, h, tab, G)
    return tab


def test_per_row_table_is_cubic_table():
    """kernel.cubic_table_rows (the forms in s = z / h, h the tissue thickness, as sums of per-layer
    columns) against cubic_table (s = z / l) on random models: the same energy, gradient, Hessian and
    order-4 step at random coefficients, to round-off (measured <= 4e-15 relative)."""
    rng = np.random.default_rng(5)
    pw = np.empty(18)
    for cos in (True, False):
        for _ in range(100):
            nl = int(rng.integers(1, 5))
            T, K = rng.uniform(0.01, 30, nl), rng.uniform(1e-3, 1.0, nl)
            l = T.sum() * rng.uniform(1, 3)
            z3 = l * rng.uniform(0.5, 1)
            ref = np.empty(kernel._NTAB)
            kernel.cubic_table(l, T, K, z3, cos, ref, np.empty(kernel._NMU))
            tab = _rows_table(l, T, K, z3, cos)
            kb, F = rng.uniform(1, 100), rng.uniform(-500, 500)
            c0, c1 = rng.normal(0, 0.2 * l, 2)
            for grad in (True, False):
                a = np.array(kernel._energy3c(c0, c1, ref, kb, F, grad, pw))
                b = np.array(kernel._energy3c(c0, c1, tab, kb, F, grad, pw))
                np.testing.assert_allclose(b, a, rtol=1e-13, atol=1e-13 * np.abs(a).max())
            a = np.array(kernel._step4c(c0, c1, F, kb, ref, pw)[1:])
            b = np.array(kernel._step4c(c0, c1, F, kb, tab, pw)[1:])
            np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12 * np.abs(a).max())


def test_without_error_estimate_the_answer_is_the_same_and_says_so():
    rng = np.random.default_rng(5)
    kw = _random_batch(rng, 300)
    with_est = ritz.solve_batch(**kw, parallel=False)
    without = ritz.solve_batch(**kw, parallel=False, error_estimate=False)
    for f in FIELDS + ("iterations", "order"):
        np.testing.assert_array_equal(getattr(without, f), getattr(with_est, f), err_msg=f)
    assert with_est.error_estimated and np.isfinite(with_est.error_estimate_mm).all()
    assert not without.error_estimated and np.isnan(without.error_estimate_mm).all()
    assert not without.order_converged.any()  # not shown without an estimate
    r = without[0]
    assert r.error_estimated is False and np.isnan(r.error_estimate_mm) and r.order_converged is False
    with pytest.raises(InputError, match="error_estimate"):
        ritz.solve_batch(kw["force"], order="auto", error_estimate=False)
    with pytest.raises(InputError, match="error_estimate"):
        ritz.solve_batch(kw["force"], error_estimate="no")


@pytest.mark.parametrize("error_estimate", [True, False])
def test_closed_form_failure_report_is_the_reference_one(monkeypatch, error_estimate):
    """Forces far beyond any needle overflow the energy: the closed form hands those samples to the
    Gauss path, so the per-sample failure report is the reference's."""
    msgs = []
    for fast_path in (False, True):
        monkeypatch.setattr(solver, "_FAST", fast_path)
        with pytest.raises(ConvergenceError) as exc:
            ritz.solve_batch(np.array([100.0, 1e200, 300.0, 1e250]), parallel=False,
                             error_estimate=error_estimate)
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1] and "2 of 4 samples" in msgs[1] and "sample 1" in msgs[1]


# a three-layer model for the energy checks (mm, N/mm^2, N mm, N)
L, T3, K3, Z3, KB, F3 = 90.0, np.array([20.0, 12.0, 5.0]), np.array([0.3, 0.02, 1.1]), 80.0, 40.0, 250.0


def _reference_energy(order, cos):
    """The Ritz energy of order `order` on the model above, computed independently of the kernel: the spring
    energy integrated by a 60-point Gauss rule per layer in NumPy on the Legendre basis."""
    x, w = np.polynomial.legendre.leggauss(60)
    edges = np.concatenate([[0.0], np.cumsum(T3)])

    def energy(c):
        es = 0.0
        for j in range(T3.size):
            z = edges[j] + (x + 1) * T3[j] / 2
            v = basis.evaluate(z / L, order) @ c
            dv = basis.evaluate(z / L, order, 1) @ c / L
            y = v * v * (1 + dv * dv) if cos else v * v
            es += K3[j] * T3[j] / 2 * np.sum(w * (0.5 * y + 0.25 * y * y))
        return 0.5 * KB * c @ c + es - F3 * basis.evaluate(np.array([Z3 / L]), order)[0] @ c

    return energy


def _differences(energy, c, h=1e-4):
    """Gradient and Hessian of energy at c by central differences."""
    n = c.size
    e = np.eye(n) * h
    grad = [(energy(c + e[i]) - energy(c - e[i])) / (2 * h) for i in range(n)]
    hess = [[(energy(c + e[i] + e[j]) - energy(c + e[i] - e[j]) - energy(c - e[i] + e[j])
              + energy(c - e[i] - e[j])) / (4 * h * h) for j in range(n)] for i in range(n)]
    return np.array(grad), np.array(hess)


def _assert_derivatives(energy, c, g, H):
    """g and H (full matrix) against central differences of energy at c. With an energy ~1e3 N mm and
    h = 1e-4, the Hessian's round-off is ~1e-16 * 1e3 / h^2 ~ 1e-5."""
    grad, hess = _differences(energy, c)
    np.testing.assert_allclose(g, grad, rtol=1e-7, atol=1e-7 * abs(g[0]))
    np.testing.assert_allclose(H, hess, rtol=1e-5, atol=1e-6 * max(np.diag(H)))


def _table(kind, cos):
    """The order-3 table of the three-layer model: one model's (cubic_table) or a batch row's."""
    if kind == "rows":
        return _rows_table(L, T3, K3, Z3, cos)
    tab = np.empty(kernel._NTAB)
    kernel.cubic_table(L, T3, K3, Z3, cos, tab, np.empty(kernel._NMU))
    return tab


@pytest.mark.parametrize("kind", ["model", "rows"])
@pytest.mark.parametrize("cos", [True, False])
def test_closed_form_energy_is_the_integral(cos, kind):
    """The table's energy, gradient and Hessian against an independent computation: the spring
    energy integrated by a 60-point Gauss rule per layer in NumPy, differentiated by central differences."""
    tab = _table(kind, cos)
    energy = _reference_energy(3, cos)
    c = np.array([7.0, -2.5])
    pi, eb, es, wk, g0, g1, h00, h10, h11 = kernel._energy3c(c[0], c[1], tab, KB, F3, True, np.empty(18))
    assert pi == pytest.approx(energy(c), rel=1e-13)
    assert kernel._energy3c(c[0], c[1], tab, KB, F3, False, np.empty(18))[0] == pytest.approx(pi, rel=1e-13)
    _assert_derivatives(energy, c, [g0, g1], [[h00, h10], [h10, h11]])


@pytest.mark.parametrize("cos", [True, False])
def test_order4_estimate_equals_reference_on_stiff_tissue(monkeypatch, cos):
    """The order-3 estimate's order-4 solve (kernel._newton4: monomial basis at the Gauss points, scalar
    Newton state) against the reference loops and against the previous unrolled Gauss-point order-4
    solve (solver._MONOMIAL4 = False), every parameter random, tissue up to 10^4 x Table 1 (where an
    order-4 closed form in moments lost up to 8 digits), loads near the bone: estimates equal to 1e-9
    relative (or round-off of the deflection, 1e-12 of max |v|, where the estimate itself is tiny)."""
    kw = _stiff_batch(3000)
    model = RitzModel(cos_term=cos)
    monkeypatch.setattr(solver, "_STEP4", False)  # the full order-4 solve (the one-step: below)
    ref, new = _both(monkeypatch, lambda: ritz.solve_batch(**kw, model=model, parallel=False))
    monkeypatch.setattr(solver, "_MONOMIAL4", False)
    prev = ritz.solve_batch(**kw, model=model, parallel=False)
    _assert_same(ref, new)
    for other in (ref, prev):
        atol = 1e-12 * np.abs(other.max_deflection_mm)
        err = np.abs(new.error_estimate_mm - other.error_estimate_mm)
        assert (err <= np.maximum(1e-9 * other.error_estimate_mm, atol)).all(), err.max()
        np.testing.assert_array_equal(new.converged, other.converged)


def _stiff_batch(n, seed=23):
    rng = np.random.default_rng(seed)
    kw = _random_batch(rng, n)
    kw["youngs_modulus_MPa"] = rng.uniform(50e3, 210e3, n)
    kw["k_N_per_mm2"] = np.array([0.048, 0.023]) * np.exp(rng.uniform(np.log(0.1), np.log(1e4), (n, 2)))
    kw["load_point_mm"] = kw["free_length_mm"] * np.exp(rng.uniform(np.log(0.01), 0.0, n))
    return kw


@pytest.mark.parametrize("cos", [True, False])
def test_one_step_estimate_against_the_full_order4_solve(monkeypatch, cos):
    """The default order-3 estimate takes one order-4 Newton step from the order-3 answer (kernel._step4c)
    instead of solving order 4. Newton's error after one step is quadratic in the step, so the estimate
    e moves by a relative O(e / |v|max): asserted <= 15 e / |v|max and <= 50 % (measured over 20,000
    stiff random models: <= 12 e / |v|max, <= 40 %, the latter where order 3 is far off: e ~ 0.1-1
    |v|max). On the paper's model (300 N) the two agree to 2e-5 relative; order_converged flags equal.
    Everything but the estimate is the same answer."""
    kw = _stiff_batch(3000, seed=5)
    model = RitzModel(cos_term=cos)
    step = ritz.solve_batch(**kw, model=model, parallel=False)
    monkeypatch.setattr(solver, "_STEP4", False)
    full = ritz.solve_batch(**kw, model=model, parallel=False)
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(step, f), getattr(full, f), err_msg=f)
    e, v = full.error_estimate_mm, np.abs(full.max_deflection_mm)
    err = np.abs(step.error_estimate_mm - e)
    assert (err <= np.minimum(15 * e / v, 0.5) * e + 1e-12 * v).all()
    assert (err > 1e-6 * e).mean() > 0.5  # it is a different number (not the full solve by accident)
    np.testing.assert_array_equal(step.converged, full.converged)
    F = np.linspace(-300.0, 300.0, 61)
    paper = ritz.solve_batch(F, model=model, parallel=False)
    monkeypatch.setattr(solver, "_STEP4", True)
    paper1 = ritz.solve_batch(F, model=model, parallel=False)
    np.testing.assert_allclose(paper1.error_estimate_mm, paper.error_estimate_mm, rtol=5e-5, atol=1e-15)


@pytest.mark.parametrize("kind", ["model", "rows"])
@pytest.mark.parametrize("cos", [True, False])
def test_one_step_is_the_newton_step_of_the_order4_energy(cos, kind):
    """kernel._step4c (order-4 gradient and Hessian at c = (c0, c1, 0) from the table's closed forms)
    against -H^-1 g of the independent NumPy order-4 energy by central differences, and against the same
    step on the Gauss points (kernel._energy4g, exact: to round-off)."""
    GX, GW = basis.gauss_tables()
    tab = _table(kind, cos)
    c = np.array([7.0, -2.5, 0.0])
    pd, *d = kernel._step4c(c[0], c[1], F3, KB, tab, np.empty(18))
    g, H = _differences(_reference_energy(4, cos), c)
    assert pd
    np.testing.assert_allclose(d, -np.linalg.solve(H, g), rtol=1e-5)
    tab4 = np.empty(3 + 2 * T3.size * 15)
    nq = kernel.quartic_points(L, T3, K3, Z3, cos, tab4, GX, GW)
    r = kernel._energy4g(c[0], c[1], 0.0, tab4, nq, 1.0 / L, cos, KB, F3, True)
    h = r[7:]
    Hg = np.array([[h[0], h[1], h[3]], [h[1], h[2], h[4]], [h[3], h[4], h[5]]])
    np.testing.assert_allclose(d, -np.linalg.solve(Hg, r[4:7]), rtol=1e-12, atol=1e-12 * np.abs(d).max())


def test_order4_estimate_is_the_sup_of_the_change_to_an_order4_solve(monkeypatch):
    """Physics of the estimate: sup over the 65-point grid of |v_4 - v_3|, with v_4 solved independently
    (order=4 from rest) and v_3 the order-3 answer (measured: 1.1e-10 relative; the two order-4 solves
    start from different points and stop by Newton's tolerance). For the full order-4 solve (the
    default's one step: the test above)."""
    monkeypatch.setattr(solver, "_STEP4", False)
    rng = np.random.default_rng(2)
    kw = _random_batch(rng, 200)
    b3 = ritz.solve_batch(**kw, parallel=False)
    b4 = ritz.solve_batch(**kw, parallel=False, order=4, error_estimate=False)
    phi = basis.evaluate(basis.GRID, 4)
    dv = b4.basis_coefficients_mm @ phi.T - b3.basis_coefficients_mm @ phi[:, :2].T
    sup = np.abs(dv).max(axis=1)
    np.testing.assert_allclose(b3.error_estimate_mm, sup, rtol=1e-8,
                               atol=1e-13 * np.abs(b3.max_deflection_mm).max())


@pytest.mark.parametrize("cos", [True, False])
def test_order4_monomial_energy_is_the_integral(cos):
    """kernel._energy4g (order 4, basis in monomial form at the Gauss points) against an independent
    NumPy quadrature (60 points per layer, the Legendre basis) and its central differences."""
    GX, GW = basis.gauss_tables()
    tab = np.empty(3 + 2 * T3.size * 15)
    nq = kernel.quartic_points(L, T3, K3, Z3, cos, tab, GX, GW)
    energy = _reference_energy(4, cos)
    c = np.array([7.0, -2.5, 1.5])
    r = kernel._energy4g(c[0], c[1], c[2], tab, nq, 1.0 / L, cos, KB, F3, True)
    assert r[0] == pytest.approx(energy(c), rel=1e-13)
    assert kernel._energy4g(c[0], c[1], c[2], tab, nq, 1.0 / L, cos, KB, F3, False)[0] == pytest.approx(r[0], rel=1e-13)
    h00, h10, h11, h20, h21, h22 = r[7:]
    _assert_derivatives(energy, c, r[4:7], [[h00, h10, h20], [h10, h11, h21], [h20, h21, h22]])


def test_order4_leaves_overflow_to_the_gauss_path():
    """Beyond |c| = 1e30 mm the monomial Newton hands the sample back untouched (kernel.FALLBACK)."""
    GX, GW = basis.gauss_tables()
    T, K = np.array([22.0, 10.0]), np.array([0.048, 0.023])
    tab = np.empty(3 + 2 * T.size * 15)
    nq = kernel.quartic_points(84.18, T, K, 84.18, True, tab, GX, GW)
    c = np.array([1e31, -1e30, 0.0])
    assert kernel._newton4(c, 300.0, 40.0, tab, nq, 1 / 84.18, True) == (0, kernel.FALLBACK)
    np.testing.assert_array_equal(c, [1e31, -1e30, 0.0])
    c = np.array([20.0, -5.0, 0.0])
    it, st = kernel._newton4(c, 300.0, 40.0, tab, nq, 1 / 84.18, True)
    assert st == kernel.OK and 1 <= it <= 10 and c[2] != 0.0


def test_order4_grid_sup_equals_the_scan():
    """kernel._sup4 evaluates |v| only at s = 1 and next to the interior critical points of v: the same
    number as the scan of all 65 grid points (exactly: the same expression per point), coefficients over
    nine decades, with and without the s^4 term."""
    rng = np.random.default_rng(0)
    g = basis.GRID
    M = kernel._M4  # basis.monomial_matrix(4)[:, 2:] to round-off
    for i in range(20000):
        x = rng.normal(0.0, 1.0, 3) * 10.0 ** rng.uniform(-6, 3, 3)
        if i % 5 == 0:
            x[2] = 0.0
        a = x[0] * M[0, 0] + x[1] * M[1, 0] + x[2] * M[2, 0]  # as the kernel sums them
        b = x[1] * M[1, 1] + x[2] * M[2, 1]
        c = x[2] * M[2, 2]
        assert kernel._sup4(x[0], x[1], x[2], g) == np.abs(g * g * (a + g * (b + g * c))).max()
