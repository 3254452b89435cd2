"""Elastic-validity check (models.strength) and the clamp rigid fit / root slope post-processing of the
needle model, on synthetic data (no FE solve: fast)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from needletissue.materials import get
from needletissue.models.needle.model import rigid_fit, root_slope
from needletissue.models.strength import strength_check


def _fake(vm_by_region):
    tags = {r: i for i, r in enumerate(vm_by_region)}
    vm = np.concatenate([np.asarray(v, float) for v in vm_by_region.values()])
    region = np.concatenate([np.full(len(v), tags[r]) for r, v in vm_by_region.items()])
    return SimpleNamespace(cell_data={"von_mises_MPa": vm, "region": region}, region_tags=tags)


def test_strengths_are_sourced_material_properties():
    for name in ("needle", "cortical_bone", "cancellous_bone", "clamp"):
        m = get(name)
        assert m.strength > 0 and m.strength_source, name
    assert get("needle").strength == pytest.approx(880.0)   # annealed Ti-6Al-4V yield
    assert get("muscle").strength is None


def test_utilisation_is_stress_over_strength_and_warns_past_one():
    ys, sc = get("needle").strength, get("cortical_bone").strength
    fe = _fake({"needle_1": [0.2 * ys, 0.5 * ys], "needle_2": [1.5 * ys], "cortical_bone": [0.9 * sc],
                "muscle": [0.01]})
    out = strength_check(fe, {"needle_1": "needle", "needle_2": "needle", "cortical_bone": "cortical_bone",
                              "muscle": "muscle"})
    assert out["strength_utilisation"]["needle_1"] == pytest.approx(0.5)
    assert out["needle_yield_utilisation"] == pytest.approx(1.5)
    assert out["bone_strength_utilisation"] == pytest.approx(0.9)
    assert "muscle" not in out["strength_utilisation"] and out["max_von_mises_MPa"]["muscle"] == 0.01
    assert len(out["validity_warnings"]) == 1 and out["validity_warnings"][0].startswith("needle_2")


def test_rigid_fit_recovers_a_finite_rotation_and_the_centre_motion():
    rng = np.random.default_rng(1)
    x = rng.uniform(-20, 20, (200, 3))
    rv = np.array([0.05, -0.2, 0.1])
    R, t, c = Rotation.from_rotvec(rv).as_matrix(), np.array([1.0, -2.0, 0.5]), np.array([0.0, 0.0, 90.0])
    u = x @ R.T + t - x
    rot, cu, rms = rigid_fit(x, u, c)
    np.testing.assert_allclose(rot, rv, atol=1e-12)
    np.testing.assert_allclose(cu, R @ c + t - c, atol=1e-10)
    assert rms < 1e-10


def test_root_slope_of_a_cubic_axis_is_exact():
    z = np.linspace(-30, 100, 261)
    disp = np.stack([0.01 * z + 1e-4 * z**2 - 1e-6 * z**3, -0.02 * z + 0.3, 0 * z], axis=1)
    slope, u0 = root_slope(z, disp, half_window=5.0)
    np.testing.assert_allclose(slope, [0.01, -0.02], atol=1e-12)
    np.testing.assert_allclose(u0, [0.0, 0.3, 0.0], atol=1e-12)
    assert np.isnan(root_slope(z[::50], disp[::50], 5.0)[0]).all()   # too few nodes: no estimate
