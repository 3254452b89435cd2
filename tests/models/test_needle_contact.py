"""The paper's frictional interfaces as an option of the needle model (needletissue.models.contact)."""

import pytest

from needletissue.errors import InputError


def test_needle_contact_rejects_bad_options_before_meshing():
    from needletissue.models.contact import NeedleContact

    with pytest.raises(InputError, match="interfaces"):
        NeedleContact("glued")
    with pytest.raises(InputError, match="needle-muscle"):
        NeedleContact("paper", {"needle-muscle": -0.3})
    assert set(NeedleContact("paper").hooks()) == {"mesh_hook", "items", "report"}


@pytest.mark.parametrize("option, value, named", [
    ("--contact-dhat", "0", "--contact-dhat"), ("--contact-eps-v", "-1", "--contact-eps-v"),
    ("--friction", "needle-muscle=-0.3", "--friction needle-muscle"), ("--friction", "lung-needle=0.3", "'lung-needle'")])
def test_bad_contact_cli_options_are_one_line_exit_2(option, value, named):
    """Checked before the solve (the last one, a pair absent from the mesh, after meshing: ~10 s)."""
    import subprocess
    import sys

    args = ["fe", "needle", "--needles", "1", "--needle-mesh-size", "4", "--mesh-size", "12",
            "--far-mesh-size", "12", "--interfaces", "paper", option, value]
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *args],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    assert named in p.stderr and "Traceback" not in p.stderr


@pytest.mark.slow
def test_needle_model_with_paper_interfaces_is_more_compliant_and_opens_a_gap():
    """Coarse one-needle model at 30 N, bonded vs the paper's frictional interfaces on the same mesh:
    contact lets the tissue slide and separate, so the needle deflects more than bonded; the muscle
    opens behind the needle (gap > 0); the barrier keeps interpenetration below dhat; the supports
    carry the applied force (equilibrium with the contact item's forces inside the model)."""
    from needletissue.models.contact import compare_interfaces
    from needletissue.models.needle import NeedleModelConfig, with_geometry

    cfg = with_geometry(NeedleModelConfig(forces=(30.0,), ritz=False), needles=1, needle_mesh_size=3.0,
                        mesh_size=8.0)
    res = compare_interfaces(cfg)
    (row,) = res.rows
    assert set(res.interfaces) == {"needle-muscle", "muscle-bone", "bone-needle"}
    assert row.needle_max_contact_mm > row.needle_max_bonded_mm
    assert row.max_gap_opening_mm["needle-muscle"] > 0.05
    assert row.max_interpenetration_mm < res.settings["needle-muscle"]["dhat_mm"]
    assert res.cost_ratio > 1
