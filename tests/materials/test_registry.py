"""The registry's FElupe materials reproduce the small-strain shear modulus of each law."""

import numpy as np
import pytest

from needletissue import materials
from needletissue.errors import InputError


@pytest.mark.parametrize("name", ["muscle", "adipose", "cortical_bone", "cancellous_bone", "needle", "clamp"])
def test_small_strain_shear_modulus(name):
    mat = materials.get(name)
    gamma = 1e-3
    F = np.eye(3)[:, :, None, None].copy()
    F[0, 1] += gamma
    P = mat.umat().gradient([F, None])[0]
    # simple shear: P12 = mu0 * gamma + O(gamma^2)
    assert P[0, 1].item() / gamma == pytest.approx(mat.initial_shear_modulus, rel=2e-3)


def test_unknown_material_lists_known_names():
    with pytest.raises(InputError, match="known: muscle, adipose"):
        materials.get("skin")
