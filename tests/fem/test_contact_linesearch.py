"""The contact line search (SlopeLinesearch) on one-dimensional potentials with a closed-form Newton path."""

import felupe as fem
import numpy as np
import pytest
import scipy.sparse as sp

from needletissue.fem.contact.item import SlopeLinesearch


def _newton(r, dr, x0, plugins):
    return fem.newtonraphson(np.array([x0]), fun=r, jac=lambda x: sp.csr_matrix(np.diag(dr(x))),
                             solve=lambda A, b: b / A.diagonal(), tol=1e-10, maxiter=20, plugins=plugins,
                             verbose=0)


def test_a_period_2_newton_cycle_is_cut_at_the_potentials_minimum():
    """r = sign(x) sqrt|x|, the gradient of the convex (2/3)|x|^1.5 (its second derivative is
    singular at the minimum, like a kinked tangent): the full Newton step is x -> -x for every x, a
    period-2 cycle; the slope s(a) = r(x + a dx) dx is -s(0) at a = 1, so the interpolated a = 1/2
    lands on the root."""
    r = lambda x: np.sign(x) * np.sqrt(np.abs(x))
    dr = lambda x: 0.5 / np.sqrt(np.abs(x))
    with pytest.raises(fem.NewtonConvergenceError):
        _newton(r, dr, 0.3, [])
    res = _newton(r, dr, 0.3, [SlopeLinesearch()])
    assert res.success and abs(res.x[0]) < 1e-12 and res.iterations <= 2


def test_newton_divergence_on_a_convex_potential_is_damped():
    """r = arctan(x), the gradient of a convex potential: full Newton steps from x0 = 1.5 grow
    without bound (|x0| > 1.39); with the slope line search Newton reaches the root."""
    r, dr = np.arctan, lambda x: 1 / (1 + x**2)
    with pytest.raises(fem.NewtonConvergenceError), np.errstate(all="ignore"):
        _newton(r, dr, 1.5, [])
    res = _newton(r, dr, 1.5, [SlopeLinesearch()])
    assert res.success and abs(res.x[0]) < 1e-10
