"""Reading CT volumes and label maps with SimpleITK, keeping spacing, origin and direction.

Coordinates: SimpleITK/ITK physical coordinates, i.e. LPS millimetres (x to the patient's Left,
y Posterior, z Superior) as given by the image header. NumPy arrays from SimpleITK are indexed
[k, j, i] = [z, y, x].
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from needletissue.errors import InputError


def _sitk():
    import SimpleITK as sitk

    return sitk


def read_image(path: str | Path, field: str = "image"):
    """A NIfTI/NRRD/MHA file or a DICOM series folder -> SimpleITK image; errors name the file."""
    sitk = _sitk()
    path = Path(path)
    if not path.exists():
        raise InputError(field, f"{path}: no such file or folder")
    try:
        if path.is_dir():
            reader = sitk.ImageSeriesReader()
            series = reader.GetGDCMSeriesIDs(str(path))
            if not series:
                raise InputError(field, f"{path}: folder holds no DICOM series")
            files = reader.GetGDCMSeriesFileNames(str(path), series[0])
            reader.SetFileNames(files)
            image = reader.Execute()  # applies RescaleSlope/Intercept -> HU
        else:
            _check_nifti_spacing(path, field)
            check_complete(path, field)  # ITK reads a truncated file silently (zeros)
            image = sitk.ReadImage(str(path))
    except InputError:
        raise
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else "unreadable"
        raise InputError(field, f"{path}: not a readable image ({first[:160]})") from None
    check_geometry(image, f"{field} {path}")
    if image.GetDimension() != 3:
        raise InputError(field, f"{path}: expected a 3D volume, got {image.GetDimension()}D")
    return image


def _check_nifti_spacing(path: Path, field: str) -> None:
    """ITK silently replaces a zero NIfTI pixdim by 1 mm: check the header ourselves."""
    if not path.name.lower().endswith((".nii", ".nii.gz")):
        return
    import gzip
    import struct

    opener = gzip.open if path.name.lower().endswith(".gz") else open
    try:
        with opener(path, "rb") as f:
            head = f.read(108)
    except OSError:  # not a NIfTI after all: SimpleITK reports it below
        return
    if len(head) < 108:
        return
    end = "<" if struct.unpack("<i", head[:4])[0] in (348, 540) else ">"
    if struct.unpack(f"{end}i", head[:4])[0] == 540:  # NIfTI-2: pixdim are doubles at 104
        return
    zooms = np.asarray(struct.unpack(f"{end}8f", head[76:108])[1:4], float)
    if zooms.size < 3 or not np.all(np.isfinite(zooms)) or np.any(zooms <= 0):
        raise InputError(field, f"{path}: voxel spacing missing or zero in the NIfTI header "
                         f"(pixdim {tuple(zooms)}); must be > 0 mm")


def check_complete(path: str | Path, field: str) -> None:
    """A NIfTI file must hold every voxel its header promises, a .gz its whole, intact stream (read to
    the end: gzip checks its CRC and length there), and no NaN or infinite voxel (SimpleITK's NIfTI
    reader turns NaN into 0, so this is checked on the raw data while it streams by)."""
    path = Path(path)
    if not path.name.lower().endswith((".nii", ".nii.gz")):
        return
    import gzip
    import zlib

    import nibabel

    try:
        hdr = nibabel.load(str(path)).header
        shape, dtype = hdr.get_data_shape(), hdr.get_data_dtype()
        offset = int(hdr.get_data_offset()) or int(getattr(hdr, "single_vox_offset", 352))
    except Exception:  # not a NIfTI nibabel understands: SimpleITK reports it
        return
    need = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    floating = np.issubdtype(dtype, np.floating)
    got, bad, rest = 0, 0, b""
    try:
        with (gzip.open if path.name.lower().endswith(".gz") else open)(path, "rb") as f:
            while chunk := f.read(1 << 22):
                start = max(0, offset - got)
                got += len(chunk)
                if floating and start < len(chunk):
                    data = rest + chunk[start:]
                    n = len(data) // dtype.itemsize * dtype.itemsize
                    bad += int(np.count_nonzero(~np.isfinite(np.frombuffer(data[:n], dtype=dtype))))
                    rest = data[n:]
    except (EOFError, gzip.BadGzipFile, zlib.error, OSError) as exc:
        raise InputError(field, f"{path}: damaged or truncated file ({exc}); the header promises {shape} "
                                "voxels") from None
    if got < need:
        raise InputError(field, f"{path}: truncated: {got:,} bytes of the {need:,} that the header's "
                                f"{shape} voxels need (file cut short?)")
    if bad:
        raise InputError(field, f"{path}: {bad:,} voxels are NaN or infinite")


def check_finite(image, what: str) -> None:
    """NaN or infinite voxels would pass every threshold test silently: reject them."""
    arr = np.asarray(_sitk().GetArrayViewFromImage(image))
    if np.issubdtype(arr.dtype, np.floating):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise InputError(what, f"{bad:,} of {arr.size:,} voxels are NaN or infinite")


def check_geometry(image, what: str) -> None:
    """Spacing must be positive and finite (a zero or missing spacing makes every length wrong)."""
    sp = np.asarray(image.GetSpacing(), float)
    if not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise InputError(what, f"voxel spacing must be positive and finite, got {tuple(sp)} mm")
    if np.any(sp < 1e-3):
        raise InputError(what, f"voxel spacing {tuple(sp)} mm is implausibly small (missing spacing?)")
    d = np.asarray(image.GetDirection(), float).reshape(image.GetDimension(), image.GetDimension())
    if not np.allclose(d @ d.T, np.eye(len(d)), atol=1e-4):
        raise InputError(what, "direction cosines are not orthonormal")


def same_grid(a, b, tol: float = 1e-3) -> bool:
    return (a.GetSize() == b.GetSize()
            and np.allclose(a.GetSpacing(), b.GetSpacing(), atol=tol)
            and np.allclose(a.GetOrigin(), b.GetOrigin(), atol=tol * 10)
            and np.allclose(a.GetDirection(), b.GetDirection(), atol=tol))


def grid_description(image) -> str:
    return (f"size {image.GetSize()}, spacing {tuple(round(s, 4) for s in image.GetSpacing())} mm, "
            f"origin {tuple(round(o, 3) for o in image.GetOrigin())} mm")


def read_ct(path: str | Path):
    """CT in Hounsfield units; data that do not look like HU raise InputError saying so."""
    image = read_image(path, "CT")
    check_finite(image, f"CT {path}")
    arr = _sitk().GetArrayViewFromImage(image)
    check_hounsfield(np.asarray(arr), f"CT {path}")
    return image


def check_hounsfield(arr: np.ndarray, what: str) -> None:
    """HU: air near -1000 outside the body, values within the scanner range [-1100, 4100] mostly.

    A CT that was stored without RescaleIntercept (0..4095), normalised (0..1) or an MR image fails.
    """
    if arr.size == 0:
        raise InputError(what, "empty image")
    lo, hi = np.percentile(arr, [0.5, 99.5])
    if lo > -500:
        raise InputError(what, f"does not look like Hounsfield units: 0.5th percentile {lo:.4g} "
                         "(air should be about -1000 HU); apply RescaleSlope/RescaleIntercept first")
    if hi > 5000 or lo < -3100:
        raise InputError(what, f"does not look like Hounsfield units: 0.5..99.5 percentile range "
                         f"{lo:.4g}..{hi:.4g} (expected within about -1100..4100 HU)")


def read_labels(path: str | Path, reference=None):
    """A label map (integer image); on another grid than `reference` it is an error, not resampled."""
    image = read_image(path, "labels")
    arr = _sitk().GetArrayViewFromImage(image)
    if not np.issubdtype(np.asarray(arr).dtype, np.integer):
        a = np.asarray(arr)
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise InputError("labels", f"{path}: not a label map (non-integer values)")
    if reference is not None and not same_grid(image, reference):
        raise InputError("labels", f"{path}: label map is on another grid ({grid_description(image)}) "
                         f"than the CT ({grid_description(reference)})")
    return image

