"""The per-cell fields of a result against closed forms: principal stretches of F = R diag(l) Q^T."""

import numpy as np
from scipy.spatial.transform import Rotation

from needletissue.fem.result import principal_stretches


def test_principal_stretches_are_the_singular_values_of_f_in_ascending_order():
    rng = np.random.default_rng(7)
    n = 40_000  # more than one of eigh3's blocks
    stretch = rng.uniform(0.5, 2.0, (n, 3))
    stretch[:5000, 1] = stretch[:5000, 0]  # two equal stretches
    stretch[5000:6000] = 1.0  # none (F a rotation)
    R = Rotation.random(n, random_state=1).as_matrix()
    Q = Rotation.random(n, random_state=2).as_matrix()
    F = np.einsum("nij,nj,nkj->nik", R, stretch, Q).reshape(4, n // 4, 3, 3)
    lam = principal_stretches(F)
    assert lam.shape == (4, n // 4, 3)
    np.testing.assert_allclose(lam.reshape(n, 3), np.sort(stretch, axis=1), rtol=0, atol=2e-14)
