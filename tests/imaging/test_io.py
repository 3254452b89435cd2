"""Reading: geometry kept, DICOM series, bad input names the file and the problem."""

import numpy as np
import pytest
import SimpleITK as sitk

from phantom import phantom_arrays, to_image
from needletissue.errors import InputError
from needletissue.imaging.io import read_ct, read_image, read_labels


def test_nifti_geometry_kept(phantom_ct):
    img = read_ct(phantom_ct)
    assert img.GetSpacing() == (2.0, 2.0, 2.0)
    assert np.allclose(img.GetOrigin(), (100.0, 50.0, -20.0))
    assert np.allclose(img.GetDirection(), (-1, 0, 0, 0, -1, 0, 0, 0, 1))


def test_dicom_series_round_trip(tmp_path):
    hu, _ = phantom_arrays((6, 64, 64))
    img = sitk.Cast(to_image(hu, origin=(10.0, 20.0, 30.0)), sitk.sitkInt16)
    img.SetDirection((1, 0, 0, 0, 1, 0, 0, 0, 1))
    w = sitk.ImageFileWriter()
    w.KeepOriginalImageUIDOn()
    for k in range(img.GetDepth()):
        sl = img[:, :, k]
        pos = img.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, val in {"0008|0060": "CT", "0020|000d": "1.2.3", "0020|000e": "1.2.3.4",
                         "0020|0013": str(k + 1), "0020|0032": "\\".join(map(str, pos)),
                         "0020|0037": "1\\0\\0\\0\\1\\0", "0028|0030": "2\\2",
                         "0018|0050": "2", "0028|1052": "0", "0028|1053": "1"}.items():
            sl.SetMetaData(tag, val)
        w.SetFileName(str(tmp_path / f"s{k:03d}.dcm"))
        w.Execute(sl)
    back = read_ct(tmp_path)
    assert back.GetSize() == img.GetSize()
    assert np.allclose(back.GetSpacing(), (2, 2, 2))
    assert np.allclose(back.GetOrigin(), (10, 20, 30))
    assert np.array_equal(sitk.GetArrayFromImage(back), sitk.GetArrayFromImage(img))


def test_not_an_image(tmp_path):
    bad = tmp_path / "notes.nii.gz"
    bad.write_text("not an image")
    with pytest.raises(InputError, match="notes.nii.gz.*not a readable image"):
        read_image(bad, "CT")
    with pytest.raises(InputError, match="no such file"):
        read_image(tmp_path / "missing.nii.gz")


def test_zero_spacing_is_an_error(tmp_path):
    import struct

    hu, _ = phantom_arrays((4, 64, 64))
    p = tmp_path / "zero_spacing.nii"
    sitk.WriteImage(sitk.Cast(to_image(hu), sitk.sitkInt16), str(p))
    raw = bytearray(p.read_bytes())
    raw[80:84] = struct.pack("<f", 0.0)     # pixdim[1] = 0: a header without x spacing
    raw[252:256] = struct.pack("<hh", 0, 0)  # qform_code = sform_code = 0 -> spacing from pixdim
    p.write_bytes(bytes(raw))
    with pytest.raises(InputError, match="zero_spacing.nii"):
        read_ct(p)


def test_non_hu_detected(tmp_path):
    hu, _ = phantom_arrays((4, 64, 64))
    p = tmp_path / "raw.nii.gz"
    sitk.WriteImage(sitk.Cast(to_image(hu + 1024), sitk.sitkUInt16), str(p))  # no RescaleIntercept
    with pytest.raises(InputError, match="Hounsfield"):
        read_ct(p)


def test_labels_on_another_grid(phantom_ct, tmp_path):
    hu, _ = phantom_arrays((40, 64, 64))
    lab = to_image(np.zeros_like(hu, dtype=np.uint8), origin=(103.0, 50.0, -20.0))
    p = tmp_path / "shifted_labels.nii.gz"
    sitk.WriteImage(lab, str(p))
    with pytest.raises(InputError, match="shifted_labels.nii.gz.*another grid"):
        read_labels(p, reference=read_ct(phantom_ct))


@pytest.fixture
def ct_files(tmp_path):
    hu, _ = phantom_arrays((12, 48, 48))
    img = sitk.Cast(to_image(hu), sitk.sitkInt16)
    gz, raw = tmp_path / "ct.nii.gz", tmp_path / "ct.nii"
    sitk.WriteImage(img, str(gz), useCompression=True)
    sitk.WriteImage(img, str(raw))
    return hu, gz, raw


def test_truncated_or_cut_short_files_are_refused_naming_the_file(ct_files, tmp_path):
    """ITK read both silently (missing voxels as 0): the gzip stream is read to its end and the voxel
    bytes counted against the header."""
    hu, gz, raw = ct_files
    assert read_ct(gz).GetSize() == read_ct(raw).GetSize() == hu.shape[::-1]  # intact files still read
    cut_gz, cut_raw = tmp_path / "cut.nii.gz", tmp_path / "short.nii"
    cut_gz.write_bytes(gz.read_bytes()[:-100])
    cut_raw.write_bytes(raw.read_bytes()[: raw.stat().st_size - 2 * 48 * 48])  # one slice short
    with pytest.raises(InputError, match=r"cut.nii.gz: damaged or truncated") as exc:
        read_ct(cut_gz)
    assert exc.value.field == "CT"
    with pytest.raises(InputError, match=rf"short.nii: truncated: {raw.stat().st_size - 2 * 48 * 48:,} bytes "
                                         rf"of the {raw.stat().st_size:,}"):
        read_ct(cut_raw)
    from needletissue.geometry.pelvis import ct_label_volume

    with pytest.raises(InputError, match="cut.nii.gz: damaged or truncated"):
        ct_label_volume(cut_gz, raw)


@pytest.mark.parametrize("suffix", [".nii.gz", ".nrrd"])
def test_non_finite_voxels_are_refused(tmp_path, suffix):
    """SimpleITK's NIfTI reader turns NaN into 0 (so a NaN CT segmented silently): counted on the raw data."""
    hu, _ = phantom_arrays((12, 48, 48))
    a = hu.astype(np.float32)
    a[3, 10, 10], a[4, 20, 20] = np.nan, np.inf
    path = tmp_path / f"nan{suffix}"
    sitk.WriteImage(to_image(a), str(path))
    with pytest.raises(InputError, match=r"nan\.(nii\.gz|nrrd).*2 .*voxels are NaN or infinite"):
        read_ct(path)


def test_segment_cli_on_a_truncated_ct_writes_nothing(ct_files, tmp_path):
    import os
    import subprocess
    import sys

    _, gz, _ = ct_files
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(gz.read_bytes()[: gz.stat().st_size // 2])
    r = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", "segment", str(cut),
                        "--out", str(tmp_path / "seg")], capture_output=True, text=True, env=dict(os.environ))
    assert r.returncode == 2 and r.stderr.startswith("error: CT: ") and "cut.nii.gz" in r.stderr, r.stderr
    assert not (tmp_path / "seg").exists()
