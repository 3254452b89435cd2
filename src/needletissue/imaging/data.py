"""Where the example data live: $NEEDLETISSUE_DATA, else <repo>/../shared/data, else package data.

The package ships unmodified copies of the example CT (Apache-2.0, TotalSegmentator) and the mean
pelvis surfaces (MPL-2.0) with their licence texts, so the demo runs without ../shared.
"""

from __future__ import annotations

import os
from pathlib import Path

from needletissue.errors import InputError

CT_NAME = "pelvis_ct/example_ct.nii.gz"
LABELS_NAME = "pelvis_ct/example_seg_fast_force_split.nii.gz"
SSM_NAMES = (
    "pelvis_ssm/LLP26_mean_hip_xpos.stl",
    "pelvis_ssm/LLP26_mean_hip_xneg.stl",
    "pelvis_ssm/LLP26_mean_sacrum.stl",
)

_REPO_ROOT = Path(__file__).resolve().parents[3]
PACKAGE_DATA = Path(__file__).resolve().parents[1] / "data"


def shared_data_dir() -> Path | None:
    """$NEEDLETISSUE_DATA or <repo root>/../shared/data when it exists, else None."""
    env = os.environ.get("NEEDLETISSUE_DATA")
    if env:
        return Path(env)
    cand = _REPO_ROOT.parent / "shared" / "data"
    return cand if cand.is_dir() else None


def data_path(name: str, *, allow_package: bool = True) -> Path:
    """Path of a data file (e.g. CT_NAME): shared data first, then the copy shipped in the package."""
    shared = shared_data_dir()
    if shared is not None and (shared / name).is_file():
        return shared / name
    if allow_package and (PACKAGE_DATA / name).is_file():
        return PACKAGE_DATA / name
    where = f"{shared}" if shared is not None else "$NEEDLETISSUE_DATA / <repo>/../shared/data"
    raise InputError("data", f"{name} not found in {where}"
                     + (" nor in the package data" if allow_package else ""))


def require_shared(name: str) -> Path:
    """For tests: the file from ../shared/data, or a clear failure message (never a silent skip)."""
    shared = shared_data_dir()
    if shared is None or not (shared / name).is_file():
        raise FileNotFoundError(
            f"test data {name} is missing: set NEEDLETISSUE_DATA or provide {_REPO_ROOT.parent}/shared/data "
            "(see shared/data/README.md); CI has it")
    return shared / name
