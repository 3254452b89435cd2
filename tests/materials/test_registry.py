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


@pytest.mark.parametrize("params,match", [
    (dict(mu=[0.001, 0.002], alpha=[10.0]), "same number of terms"),
    (dict(mu=[0.001], alpha=[0.0]), "alpha must be non-zero"),
    (dict(mu=["x"], alpha=[10.0]), r"parameters.mu\[0\]: expected a number"),
    (dict(mu=[float("nan")], alpha=[10.0]), "must be finite"),
    (dict(mu=[0.001], alpha=[10.0], beta=1.0), "unknown beta"),
])
def test_bad_user_parameters_name_the_field(tmp_path, params, match):
    with pytest.raises(InputError, match=match):
        materials.Material("bad", "ogden", params)


def test_toml_material_round_trip(tmp_path):
    p = tmp_path / "m.toml"
    p.write_text('[stiff_fat]\nmodel = "mooney_rivlin"\nparameters = { C10 = 0.01, C01 = 0.002 }\n'
                 'bulk_modulus = 3.5\n')
    (m,) = materials.load_toml(p)
    assert materials.get("stiff_fat") is m and m.bulk == 3.5
    assert m.initial_shear_modulus == pytest.approx(0.024)
    assert m.stable_range("uniaxial") == (0.2, 5.0)  # MR with C10, C01 > 0 is Drucker-stable
    np.testing.assert_allclose(m.nominal_stress("uniaxial", [1.0, 1.2]),
                               [0.0, 2 * (1.2 - 1.2**-2) * (0.01 + 0.002 / 1.2)], rtol=1e-14)
