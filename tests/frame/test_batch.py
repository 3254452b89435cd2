"""frame.solve_batch (issue #14, the batch rate): anchored cells and lanes of solves integrated together must
give, row by row, the answer of frame.pose for the same wrench (both converge the same scaled residual,
TOL = 1e-9 of the load, so the clamp pose agrees to ~1e-7 of its size); a row that does not converge raises;
bad input names its field."""

import types

import numpy as np
import pytest

from needletissue import frame
from needletissue.errors import ConvergenceError, InputError
from needletissue.frame import FrameModel, solver

MODELS = {
    "two pins": {},
    "one pin": {"needles": 1},
    "elastic clamp": {"clamp": "elastic", "clamp_E_MPa": 2e4},
    "rigid root": {"root": "rigid"},
    "plastic pin": {"plastic": True},   # lanes do not take the plastic section: the per-row path
}


def _wrenches(seed, n_near=240, n_far=40):
    """A cloud around one nominal wrench (sensor noise: a few N and 100 N mm) and full-range rows."""
    rng = np.random.default_rng(seed)
    F = np.vstack([np.array([20.0, 250.0, 30.0]) + rng.normal(0, 3.0, (n_near, 3)),
                   rng.uniform(-1, 1, (n_far, 3)) * [220.0, 220.0, 60.0]])
    M = np.vstack([rng.normal(0, 100.0, (n_near, 3)), rng.uniform(-2000, 2000, (n_far, 3))])
    return F, M


def _assert_rows_equal(b, rows, F, M, model):
    for i in rows:
        u, rot, dmax, _ = frame.pose(F[i], M[i], model=model)
        scale = max(float(np.abs(u).max()), 1.0)
        assert np.allclose(b.clamp_displacement_mm[i], u, rtol=0, atol=1e-7 * scale), (i, b.clamp_displacement_mm[i], u)
        assert np.allclose(b.clamp_rotation_rad[i], rot, rtol=0, atol=1e-9 + 1e-7 * np.abs(rot).max()), i
        assert abs(b.max_needle_deflection_mm[i] - dmax) <= 1e-7 * scale, i


@pytest.mark.parametrize("name", list(MODELS))
def test_batch_rows_equal_pose(name):
    """Near rows share an anchor (with its tangent derivatives), far rows fall in their own cells or start from
    rest; every checked row equals a cold pose() to 1e-7 of the displacement."""
    model = FrameModel(**MODELS[name])
    F, M = _wrenches(1)
    b = frame.solve_batch(F, M, model=model)
    rng = np.random.default_rng(2)
    rows = list(rng.choice(240, 5, replace=False)) + list(240 + rng.choice(40, 4, replace=False))
    _assert_rows_equal(b, rows, F, M, model)
    assert b.iterations.shape == (F.shape[0],) and (b.iterations >= 1).all()


def test_batch_auto_equals_rest():
    """The anchored lanes and the per-row solve from rest agree on every row (a large cloud: one anchor with its
    derivatives; the far rows from rest); the anchored solve takes fewer quasi-Newton steps on the cloud."""
    model = FrameModel()
    F, M = _wrenches(3, n_near=1100, n_far=60)
    a = frame.solve_batch(F, M, model=model)
    r = frame.solve_batch(F, M, model=model, method="rest")
    for x, y, tol in ((a.clamp_displacement_mm, r.clamp_displacement_mm, 2e-6),
                      (a.clamp_rotation_rad, r.clamp_rotation_rad, 2e-8),
                      (a.max_needle_deflection_mm, r.max_needle_deflection_mm, 2e-6)):
        assert np.abs(x - y).max() < tol
    assert a.iterations[:1100].mean() < 0.5 * r.iterations[:1100].mean()


def test_anchor_tangent_derivatives():
    """The anchor's dH/dW (Jacobians along the answer's first-order path, no solves) equals central differences of
    the exact inverse tangents at the solved neighbouring wrenches +- 3 N / 100 N mm to 1 % (measured 0.01-0.35 %);
    a small wrench's anchor is polished to its floor, not dropped for the rest state (with a polish below the
    residual's rounding floor this one failed)."""
    disc = solver._cached_disc(FrameModel(), False)
    W = np.array([20.0, 250.0, 30.0, 100.0, -50.0, 80.0])
    D = solver._anchor(disc, W)[4]
    for d, e in enumerate((3.0, 3.0, 3.0, 100.0, 100.0, 100.0)):
        dw = np.zeros(6)
        dw[d] = e
        C = (solver._anchor(disc, W + dw)[3] - solver._anchor(disc, W - dw)[3]) / (2 * e)
        assert np.abs(D[d] - C).max() < 1e-2 * np.abs(C).max(), d
    assert solver._anchor(disc, np.array([-37.7, -36.8, -26.4, 0.0, 0.0, 0.0]))[1].any()


def test_lane_failures_are_solved_again(monkeypatch):
    """With no quasi-Newton step allowed in the lanes every row fails there; the per-row path solves it again
    and the answers are unchanged."""
    model = FrameModel()
    F, M = _wrenches(4, n_near=220, n_far=10)
    want = frame.solve_batch(F, M, model=model)
    monkeypatch.setattr(solver, "BROYDEN_MAXIT", 0)
    got = frame.solve_batch(F, M, model=model)
    assert np.abs(got.clamp_displacement_mm - want.clamp_displacement_mm).max() < 2e-6
    # the lanes stop before their first step (0 iterations): every row is the per-row path's, step for step
    assert (got.iterations == frame.solve_batch(F, M, model=model, method="rest").iterations).all()


@pytest.mark.parametrize("method", ["auto", "rest"])
def test_non_convergence_raises(method, monkeypatch):
    """A row the kernel reports unconverged is never returned: ConvergenceError naming the row's wrench."""
    real = solver._kernel()

    def failing(fn):
        def run(*args):
            fn(*args)
            args[-1][args[0][:, 1] == 301.0, 1] = real.MAX_ITER  # status (rows, 2): that wrench did not converge
        return run

    fake = types.SimpleNamespace(**{n: getattr(real, n) for n in dir(real) if not n.startswith("__")})
    fake.batch_anchor = failing(real.batch_anchor)
    fake.batch = failing(real.batch)
    monkeypatch.setattr(solver, "_KERNEL", fake)
    F = np.array([[0.0, 300.0, 0.0], [0.0, 301.0, 0.0], [0.0, 302.0, 0.0]])
    with pytest.raises(ConvergenceError, match=r"1 of 3 wrenches did not converge; first row 1: force \[0.0, 301.0"):
        frame.solve_batch(F, model=FrameModel(), method=method)


def test_bad_input():
    m = FrameModel()
    with pytest.raises(InputError, match="method"):
        frame.solve_batch([[0, 300.0, 0]], model=m, method="fast")
    with pytest.raises(InputError, match="force_N.*shape"):
        frame.solve_batch([[0, 300.0]], model=m)
    with pytest.raises(InputError, match="moment_Nmm"):
        frame.solve_batch([[0, 300.0, 0]], [[0, 0, 0], [0, 0, 0]], model=m)
    with pytest.raises(InputError, match="moment_Nmm.*finite"):
        frame.solve_batch([[0, 300.0, 0]], [[0, np.inf, 0]], model=m)
    with pytest.raises(InputError, match="force_N.*validity"):  # beyond the model's range in one row of many
        frame.solve_batch([[0, 300.0, 0]] * 300 + [[0, 1e5, 0]], model=m)


def test_small_wrenches_converge_and_are_linear():
    """A wrench far below a newton (a control loop at rest reads sensor noise) converges and follows the linear
    response: the residual's rounding floor once made every wrench under ~0.5 N raise ConvergenceError."""
    per_newton = np.asarray(frame.solve((1e-2, 0.0, 0.0)).clamp_displacement_mm) / 1e-2
    for f in (1e-3, 1e-6):
        u = np.asarray(frame.pose((f, 0.0, 0.0))[0]) / f
        assert u[0] == pytest.approx(per_newton[0], rel=1e-4)
    F = np.random.default_rng(3).uniform(-1e-3, 1e-3, (400, 3))
    rows = frame.solve_batch(F)
    cold = np.asarray(frame.pose(F[0])[0])
    assert np.abs(rows.clamp_displacement_mm[0] - cold).max() < 1e-9
    assert np.all(np.isfinite(rows.clamp_displacement_mm))
