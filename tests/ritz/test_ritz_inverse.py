"""Inverse use: force for a deflection, calibration of one parameter (round trips)."""

import pytest

from needletissue import ritz
from needletissue.errors import InputError
from needletissue.ritz import RitzModel
from needletissue.ritz.inverse import calibrate, force_for_deflection


@pytest.mark.parametrize("F", [37.0, 300.0, -1200.0])
@pytest.mark.parametrize("at", ["tip", "load_point"])
def test_force_for_deflection_round_trip(F, at):
    m = RitzModel(load_point_mm=70.0)
    r = ritz.solve(F, m)
    w = r.tip_deflection_mm if at == "tip" else r.load_point_deflection_mm
    c = force_for_deflection(w, m, at=at)
    assert c.value == pytest.approx(F, rel=1e-9)


@pytest.mark.parametrize("parameter,truth", [("free_length", 95.0), ("diameter", 5.5), ("k:adipose", 3.0),
                                             ("k:muscle", 0.4)])
def test_calibrate_round_trip(parameter, truth):
    base = RitzModel()
    if parameter == "free_length":
        true_model = base.replace(free_length_mm=truth)
    elif parameter == "diameter":
        true_model = base.replace(diameter_mm=truth)
    else:
        true_model = base.with_layer_k(parameter[2:], truth)
    F = 450.0
    w = ritz.solve(F, true_model).tip_deflection_mm
    c = calibrate(parameter, F, w, base)
    assert c.value == pytest.approx(truth, rel=1e-6)
    assert c.result.tip_deflection_mm == pytest.approx(w, rel=1e-10)


def test_calibrate_rejects_unreachable_and_bad_names():
    with pytest.raises(InputError, match="not reachable"):
        calibrate("k:muscle", 300.0, 40.0)  # stiffer or softer muscle cannot move the tip that far
    with pytest.raises(InputError, match="layer"):
        calibrate("k:bone", 300.0, 10.0)
    with pytest.raises(InputError, match="parameter"):
        calibrate("width", 300.0, 10.0)
    with pytest.raises(InputError, match="sign"):
        calibrate("diameter", 300.0, -10.0)
