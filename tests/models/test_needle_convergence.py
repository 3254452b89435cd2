"""Richardson extrapolation against closed forms."""

import pytest

from needletissue.errors import InputError
from needletissue.models.needle.convergence import richardson


@pytest.mark.parametrize("p, r", [(2.0, 2.0), (1.3, 1.4), (3.0, 1.5)])
def test_recovers_order_and_limit_of_power_law(p, r):
    f0, C, h = 17.5, -3.0, 2.0
    f = [f0 + C * (h / r**k) ** p for k in range(3)]
    fit = richardson(*f, ratio=r)
    assert fit.order == pytest.approx(p, rel=1e-9)
    assert fit.extrapolated == pytest.approx(f0, rel=1e-12)
    assert fit.fine_error_estimate == pytest.approx(abs(C) * (h / r**2) ** p, rel=1e-9)


def test_oscillating_levels_rejected():
    with pytest.raises(InputError):
        richardson(1.0, 1.2, 1.1, ratio=1.4)


def test_levels_whose_change_grows_with_refinement_are_rejected():
    """Monotone but diverging (observed order <= 0; the smooth mesher's bonded family 5.625 / 4.5 / 3.6 mm gave
    7.114 / 7.050 / 6.908 mm): extrapolating would go the wrong way."""
    with pytest.raises(InputError, match="observed order <= 0"):
        richardson(7.1144, 7.0497, 6.9079, ratio=1.25)
    with pytest.raises(InputError, match="observed order <= 0"):
        richardson(1.0, 1.5, 2.0, ratio=1.4)   # order exactly 0
