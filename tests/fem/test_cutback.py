"""Load stepping: cut-back is triggered and recovers; an impossible load raises ConvergenceError."""

import numpy as np
import pytest

from needletissue.errors import ConvergenceError
from needletissue.fem import FEModel, Fixed, PrescribedDisplacement, TaggedMesh, solve


@pytest.fixture(scope="module")
def block():
    return TaggedMesh.box((10, 10, 10), (3, 3, 3), region="adipose")


def test_cutback_recovers_same_answer(block):
    """Stretch 2.2 of adipose (Ogden alpha = 16.2) in one increment with few Newton iterations fails,
    is cut back, and reaches the state a fine fixed stepping reaches (path-independent elasticity)."""
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, 12.0))]
    hard = solve(FEModel(block, {"adipose": "adipose"}), bcs, [1.0], progress=False, maxiter=6)[-1]
    assert hard.cutbacks > 0
    easy = solve(FEModel(block, {"adipose": "adipose"}), bcs, [1.0], progress=False, initial_step=0.02,
                 max_step=0.02, maxiter=30)[-1]
    assert easy.steps == 50
    np.testing.assert_allclose(hard.displacement, easy.displacement, atol=1e-7)
    np.testing.assert_allclose(hard.reaction_forces["zmax"], easy.reaction_forces["zmax"], rtol=1e-7)


def test_impossible_load_raises_naming_load_factor(block):
    """Pushing the top 12 mm down through a 10 mm block inverts it: no equilibrium beyond ~10/12."""
    model = FEModel(block, {"adipose": "adipose"})
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, -12.0))]
    with pytest.raises(ConvergenceError, match=r"load factor (0\.\d+)") as info:
        solve(model, bcs, [0.5, 1.0], progress=False, min_step=0.01)
    import re

    reached = float(re.search(r"load factor ([0-9.]+)", str(info.value)).group(1))
    assert 0.5 <= reached < 10 / 12
    # the model is left at the last converged state, not an unconverged one
    assert np.abs(model.field[0].values[:, 2]).max() <= 12 * reached + 1e-9


def test_line_search_reaches_the_same_state(block):
    """The line search only shortens Newton steps: the converged state is the fixed-stepping one."""
    bcs = [Fixed("zmin"), PrescribedDisplacement("zmax", (0, 0, 12.0))]
    ls = solve(FEModel(block, {"adipose": "adipose"}), bcs, [1.0], progress=False, maxiter=30, linesearch=True)[-1]
    easy = solve(FEModel(block, {"adipose": "adipose"}), bcs, [1.0], progress=False, initial_step=0.02,
                 max_step=0.02, maxiter=30)[-1]
    np.testing.assert_allclose(ls.displacement, easy.displacement, atol=1e-7)
    np.testing.assert_allclose(ls.reaction_forces["zmax"], easy.reaction_forces["zmax"], rtol=1e-7)
