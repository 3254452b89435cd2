"""Fixtures: the synthetic CT phantom of phantom.py."""

import pytest

from phantom import phantom_arrays, to_image


@pytest.fixture
def phantom_ct(tmp_path):
    import SimpleITK as sitk

    hu, _ = phantom_arrays()
    path = tmp_path / "phantom_ct.nii.gz"
    sitk.WriteImage(sitk.Cast(to_image(hu), sitk.sitkInt16), str(path))
    return path
