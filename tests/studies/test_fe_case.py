"""The fe_needle study model's parameters map onto the needle model's config (no FE solve: fast)."""

from __future__ import annotations

import numpy as np
import pytest

from needletissue.errors import InputError
from needletissue.studies.case_fe_needle import case_config
from needletissue.studies.config import parse_study
from needletissue.studies.models import get_model


def test_direction_angle_offset_load_path_and_mesh_ratio():
    cfg = case_config({"needles": 2, "forces_N": "50, 100,300", "direction_angle_deg": 90.0,
                       "diameter_mm": 4.5, "needle_mesh_size_per_diameter": 0.4, "spacing_mm": 50.0,
                       "depth_mm": 20.0, "cortical_thickness_mm": 2.5, "load_offset_x_mm": 10.0})
    assert cfg.forces == (50.0, 100.0, 300.0)
    np.testing.assert_allclose(cfg.direction, [1.0, 0.0, 0.0], atol=1e-15)   # 90 deg: in the needles' plane
    g = cfg.geometry
    assert (g.needles, g.spacing, g.depth, g.cortical_thickness) == (2, 50.0, 20.0, 2.5)
    assert g.needle_mesh_size == pytest.approx(0.4 * 4.5)
    # force along x at an offset along x: no moment; along y it twists the clamp about z by x * F
    np.testing.assert_allclose(cfg.moment(100.0), [0, 0, 0], atol=1e-12)
    y = case_config({"force_N": 100.0, "load_offset_x_mm": 10.0})
    assert y.direction == (0.0, 1.0, 0.0) and y.forces == (100.0,)
    np.testing.assert_allclose(y.moment(100.0), [0, 0, 1000.0])
    np.testing.assert_allclose(y.load_point, [10.0, 0.0, y.geometry.gripper_centre])


@pytest.mark.parametrize("fixed, field", [
    ({"forces_N": "100,200", "force_N": 100.0}, "fixed.forces_N"),
    ({"forces_N": "100,-5"}, "fixed.forces_N"),
    ({}, "parameters.force_N"),
    ({"force_N": 100.0, "needle_mesh_size_mm": 2.0, "needle_mesh_size_per_diameter": 0.4},
     "fixed.needle_mesh_size_per_diameter"),
])
def test_bad_force_or_mesh_settings_name_the_field(fixed, field):
    cfg = parse_study({"study": {"model": "fe_needle", "method": "grid"}, "fixed": fixed,
                       "parameters": {"diameter_mm": {"values": [5.0]}}})
    with pytest.raises(InputError) as e:
        get_model("fe_needle").check_config(cfg)
    assert e.value.field == field


def test_sweep_configs_are_valid():
    from pathlib import Path

    from needletissue.studies.config import load_study
    from needletissue.studies.sampling import design

    root = Path(__file__).resolve().parents[2] / "benchmarks" / "frame_sweep" / "studies"
    n = 0
    for p in sorted(root.glob("*.toml")):
        cfg = load_study(p)
        fixed = dict(cfg.fixed)
        for _, case in design(cfg).iterrows():
            case_config({**fixed, **{k: case[k] for k in case.index if k != "case_id"}})  # geometry validates
            n += 1
    assert n >= 30   # the sweep size
