"""Synthetic tissue label maps with analytic geometry for the geometry tests."""

import numpy as np


def make_seg(arr, tissues, spacing=2.0, origin=(10.0, -20.0, 5.0), direction=(-1, 0, 0, 0, -1, 0, 0, 0, 1)):
    import SimpleITK as sitk

    from needletissue.imaging.segment import Segmentation

    img = sitk.GetImageFromArray(np.asarray(arr, np.uint8))
    img.SetSpacing((spacing,) * 3)
    img.SetOrigin(origin)
    img.SetDirection(tuple(float(v) for v in direction))
    return Segmentation(labels=img, tissues=dict(tissues))


def ball(n, radius_vox):
    c = (n - 1) / 2
    k, j, i = np.meshgrid(*[np.arange(n)] * 3, indexing="ij")
    return np.sqrt((i - c) ** 2 + (j - c) ** 2 + (k - c) ** 2) <= radius_vox


def nested_boxes(n=16):
    """Bone cube inside a muscle cube inside an adipose cube (labels 1, 10, 3)."""
    a = np.zeros((n, n, n), np.uint8)
    a[2:-2, 2:-2, 2:-2] = 3
    a[4:-4, 4:-4, 4:-4] = 10
    a[6:-6, 6:-6, 6:-6] = 1
    return a, {"cortical_bone": 1, "adipose": 3, "gluteus_maximus": 10}


def layered_slab(nz=40, nxy=12, fat_vox=5, muscle_vox=11):
    """Along z (array axis 0, top = high k): air, fat, muscle, then bone to the bottom."""
    a = np.zeros((nz, nxy, nxy), np.uint8)
    top = nz - 4
    a[:top - fat_vox - muscle_vox] = 2                    # cancellous bone
    a[top - fat_vox - muscle_vox:top - fat_vox] = 10      # muscle
    a[top - fat_vox:top] = 3                              # adipose
    return a, {"cancellous_bone": 2, "adipose": 3, "iliopsoas": 10}
