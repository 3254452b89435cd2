"""Data loader: shared data first, package copies as fallback, identical bytes."""

import hashlib

import pytest

from needletissue.errors import InputError
from needletissue.imaging import data


@pytest.mark.data
def test_package_copy_is_the_fallback_and_unmodified(tmp_path, monkeypatch):
    shared = data.require_shared(data.CT_NAME)
    monkeypatch.setenv("NEEDLETISSUE_DATA", str(tmp_path))  # empty folder: falls back to the package
    pkg = data.data_path(data.CT_NAME)
    assert pkg.is_relative_to(data.PACKAGE_DATA)
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()  # noqa: E731
    assert digest(pkg) == digest(shared)
    for lic in ("pelvis_ct/LICENSE-Apache-2.0", "pelvis_ct/NOTICE", "pelvis_ssm/LICENSE"):
        assert (data.PACKAGE_DATA / lic).is_file()
    with pytest.raises(InputError, match="not found"):
        data.data_path("pelvis_ct/nothing.nii.gz")
    with pytest.raises(FileNotFoundError, match="NEEDLETISSUE_DATA"):
        data.require_shared(data.CT_NAME)


def test_environment_variable_wins(tmp_path, monkeypatch):
    (tmp_path / "pelvis_ct").mkdir()
    (tmp_path / data.CT_NAME).write_bytes(b"x")
    monkeypatch.setenv("NEEDLETISSUE_DATA", str(tmp_path))
    assert data.data_path(data.CT_NAME) == tmp_path / data.CT_NAME
