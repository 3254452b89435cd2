"""Volumetric locking of nearly incompressible tissue (muscle, K = 1e4 mu0): a block sheared at its
top. Mixed P2/P0 converges under refinement and does not depend on K; linear tetrahedra (whose
one-point rule makes them identical to P1/P0) are far too stiff. This is why tissue uses
order=2, formulation="mixed"."""

import pytest

from needletissue import materials
from needletissue.fem import FEModel, Fixed, LockingWarning, SurfaceForce, TaggedMesh, solve

MU0 = materials.get("muscle").initial_shear_modulus


def top_shift(n, order, formulation, ratio):
    m = TaggedMesh.box((20, 20, 10), (n + 1, n + 1, n // 2 + 1), region="muscle")
    model = FEModel(m, {"muscle": "muscle"}, order=order, formulation=formulation, bulk={"muscle": ratio * MU0})
    r = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (5.0, 0, 0))], [1.0], progress=False, results=False)[-1]
    return r.displacement[model.mesh.surface_nodes("zmax"), 0].mean()


def test_mixed_p2p0_does_not_lock_and_linear_does():
    p2_coarse = top_shift(4, 2, "mixed", 1e4)
    p2_fine = top_shift(8, 2, "mixed", 1e4)
    assert p2_fine == pytest.approx(p2_coarse, rel=0.03)  # converged to a few %
    # insensitive to the bulk modulus (no locking): 100x K changes the answer by < 1 %
    assert top_shift(4, 2, "mixed", 1e2) == pytest.approx(p2_coarse, rel=0.01)
    with pytest.warns(LockingWarning, match="muscle 1e\\+04"):  # order 1 says that it locks
        p1 = top_shift(8, 1, "displacement", 1e4)
        assert p1 == pytest.approx(top_shift(8, 1, "mixed", 1e4), rel=1e-9)  # P1/P0 == one-point P1
    assert p1 < 0.85 * p2_fine  # > 15 % too stiff at 8 elements per side


def test_only_linear_tetrahedra_with_tissue_warn_of_locking():
    import warnings

    m = TaggedMesh.box((20, 20, 10), (3, 3, 2), region="muscle")
    with warnings.catch_warnings():
        warnings.simplefilter("error", LockingWarning)
        FEModel(m, {"muscle": "muscle"}, order=2, formulation="mixed")
        FEModel(m, {"muscle": "cortical_bone"}, order=1)  # a compressible solid does not lock
    with pytest.warns(LockingWarning, match="order=2"):
        FEModel(m, {"muscle": "muscle"}, order=1)
