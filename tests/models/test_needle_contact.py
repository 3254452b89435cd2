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

    # the coarse mesh of the other needle-model tests: at 4/12 mm gmsh's high-order optimiser once
    # aborted the process ("Failed to reach critical value ... ScaledJac")
    args = ["fe", "needle", "--needles", "1", "--needle-mesh-size", "2.5", "--mesh-size", "8",
            "--far-mesh-size", "30", "--interfaces", "paper", option, value]
    p = subprocess.run([sys.executable, "-c", "from needletissue.cli import main; main()", *args],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    assert named in p.stderr and "Traceback" not in p.stderr


# The needle model with the paper's interfaces against bonded on the same coarse mesh (more compliant,
# a gap behind the pin, interpenetration below dhat) is the README's contact example, run and checked by
# tests/test_readme.py.
