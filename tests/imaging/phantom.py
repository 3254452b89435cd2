"""Synthetic CT phantom with analytic geometry (LPS direction, 2 mm voxels)."""

import numpy as np

SPACING = 2.0
R_BODY, R_MUSCLE, R_BONE = 50.0, 40.0, 15.0   # mm: fat 40..50, muscle 15..40, bone < 15
HU = {"air": -1000.0, "fat": -100.0, "muscle": 40.0, "bone": 700.0}


def phantom_arrays(n=(40, 64, 64)):
    """(hu, radius) arrays [z, y, x]; a cylinder along z centred in the image."""
    nz, ny, nx = n
    j, i = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    r = SPACING * np.hypot(i - (nx - 1) / 2, j - (ny - 1) / 2)
    hu = np.full((ny, nx), HU["air"], np.float32)
    hu[r <= R_BODY] = HU["fat"]
    hu[r <= R_MUSCLE] = HU["muscle"]
    hu[r <= R_BONE] = HU["bone"]
    return np.repeat(hu[None], nz, 0), np.repeat(r[None], nz, 0)


def to_image(arr, origin=(100.0, 50.0, -20.0)):
    import SimpleITK as sitk

    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((SPACING,) * 3)
    img.SetOrigin(origin)
    img.SetDirection((-1.0, 0, 0, 0, -1.0, 0, 0, 0, 1.0))  # LPS as in the example CT
    return img


