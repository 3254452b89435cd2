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


@pytest.mark.slow
def test_paper_interfaces_reach_300_N_in_equilibrium_without_interpenetration():
    """The default contact case (one needle, the paper's interfaces, 100/200/300 N) at a reduced mesh
    size (tissue 8, needle 2.5, far 30 mm): converges to 300 N; the reactions balance the applied force
    (contact forces are internal) to 1 %; no interface interpenetrates by dhat; contact is more
    compliant than bonded on the same mesh (the tissue slides along the needle and opens behind it)."""
    import numpy as np

    from needletissue.models.contact import NeedleContact
    from needletissue.models.needle import NeedleModelConfig, run_needle_model, with_geometry

    cfg = with_geometry(NeedleModelConfig(forces=(100.0, 200.0, 300.0), ritz=False), needles=1,
                        mesh_size=8.0, needle_mesh_size=2.5, far_mesh_size=30.0)
    contact = NeedleContact("paper")
    r = run_needle_model(cfg, **contact.hooks())
    bonded = run_needle_model(cfg)
    dhat = contact.item_list[0].settings.dhat
    for res, row, b in zip(r.results, r.extra["contact"]["per_force"], bonded.results):
        applied = res.force_N * np.asarray(cfg.direction)
        reactions = np.sum([np.asarray(v) for v in res.fe.reaction_forces.values()], axis=0)
        assert np.linalg.norm(reactions + applied) < 0.01 * res.force_N
        assert row["max_interpenetration_mm"] < dhat
        assert set(row["interfaces"]) == {"needle-muscle", "muscle-bone", "bone-needle"}
        assert row["interfaces"]["bone-needle"]["normal_force_N"] > 0
        assert res.max_needle_deformation_mm > 1.02 * b.max_needle_deformation_mm
        # the stall's signature: the muscle under the adipose squeezed the needle-muscle barrier to
        # 1.5e-4..2.4e-4 mm (0.002 dhat) and Newton cycled there (docs/contact.md); now > 0.01 dhat
        assert row["interfaces"]["needle-muscle"]["min_barrier_distance_mm"] > 0.01 * dhat


@pytest.mark.slow
def test_contact_substeps_same_answer_with_fewer_factorisations(monkeypatch):
    """Modified-Newton substeps in contact runs (fem.solve's default since 2026-12-03): the coarse one-needle
    model with the paper's interfaces, 30 N in one increment (the answer of smoothed friction depends on
    the increments, docs/contact.md, so both runs take the same one), converges to the same deflection
    (to the Newton tolerance: 1e-6 relative) in fewer Newton iterations (each a tangent and an LU)."""
    import importlib

    from needletissue.models.contact import NeedleContact
    from needletissue.models.needle import NeedleModelConfig, model, run_needle_model, with_geometry

    monkeypatch.setattr(model, "CONTACT_FIRST_INCREMENT", 1.0)
    cfg = with_geometry(NeedleModelConfig(forces=(30.0,), ritz=False), needles=1,
                        mesh_size=8.0, needle_mesh_size=2.5, far_mesh_size=30.0)
    runs = {}
    for substeps in (None, 0):
        if substeps == 0:
            monkeypatch.setattr(importlib.import_module("needletissue.fem.solve"), "SUBSTEPS", 0)
        runs[substeps] = run_needle_model(cfg, **NeedleContact("paper").hooks()).results[0]
    plain, sub = runs[0].fe, runs[None].fe
    assert sub.newton_substeps > 0 and plain.newton_substeps == 0
    assert sub.steps == plain.steps == 1 and sub.cutbacks == plain.cutbacks == 0
    assert sub.newton_iterations < plain.newton_iterations
    assert runs[None].max_needle_deformation_mm == pytest.approx(runs[0].max_needle_deformation_mm, rel=1e-6)
