"""Thickness along a path: layered slab (exact layer thicknesses, 1/cos for oblique paths)."""

import numpy as np
import pytest

from labelmaps import layered_slab, make_seg
from needletissue.errors import InputError
from needletissue.geometry.thickness import thickness_along

H = 2.0  # mm voxels: fat 5 voxels = 10 mm, muscle 11 voxels = 22 mm (paper Z2, Z1)


@pytest.fixture(scope="module")
def slab():
    arr, tissues = layered_slab(nxy=50)
    # identity direction so that +z (superior) is up the array's axis 0
    return make_seg(arr, tissues, spacing=H, origin=(0.0, 0.0, 0.0), direction=(1, 0, 0, 0, 1, 0, 0, 0, 1))


def test_perpendicular_path(slab):
    r = thickness_along(slab, (11.0, 11.0, 100.0), (0, 0, -1))  # step 0.2 mm = tolerance
    assert r.bone_hit
    # voxel k covers z in [2k-1, 2k+1]; fat occupies k = 31..35 -> z 61..71, skin at z = 71
    assert r.skin_mm == pytest.approx(100 - (2 * 35 + 1), abs=0.2)
    assert r.thickness_by_tissue["adipose"] == pytest.approx(10.0, abs=0.2)
    assert r.thickness_by_tissue["iliopsoas"] == pytest.approx(22.0, abs=0.2)
    assert r.soft_tissue_thickness_mm == pytest.approx(32.0, abs=0.2)
    assert [s.tissue for s in r.segments] == ["adipose", "iliopsoas"]


@pytest.mark.parametrize("angle", [20.0, 40.0])
def test_oblique_path_scales_with_one_over_cos(slab, angle):
    a = np.radians(angle)
    d = (np.sin(a), 0.0, -np.cos(a))
    r = thickness_along(slab, (3.0, 11.0, 80.0), d)
    # staircase along x does not matter: the layers are flat in z; step error ~ 0.2 mm / cos
    assert r.soft_tissue_thickness_mm == pytest.approx(32.0 / np.cos(a), abs=0.5)
    assert r.thickness_by_tissue["adipose"] == pytest.approx(10.0 / np.cos(a), abs=0.5)


def test_miss_and_bad_input(slab):
    r = thickness_along(slab, (11.0, 11.0, 100.0), (0, 0, 1))  # away from the body
    assert not r.bone_hit and r.soft_tissue_thickness_mm is None
    with pytest.raises(InputError, match="direction"):
        thickness_along(slab, (0, 0, 0), (0, 0, 0))
    with pytest.raises(InputError, match="entry"):
        thickness_along(slab, "1,2", (0, 0, 1))
