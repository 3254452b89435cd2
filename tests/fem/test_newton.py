"""Newton's method of fem.solve: the tangent is the derivative of the residual (checked by finite
differences, every material law of the needle model; docs/bench.md, "Newton")."""

import numpy as np
import pytest
from felupe.tools._newton import fun_items, jac_items, update

from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve


def directional_error(body, x, v, h):
    """|(r(x + h v) - r(x - h v)) / 2h - K(x) v| / |K(x) v| for one body."""
    rp = fun_items([body], update(x, h * v))
    rm = fun_items([body], update(x, -h * v))
    fun_items([body], x)  # K at x: the body's matrix uses its last evaluated state
    Kv = jac_items([body], x) @ v
    return np.linalg.norm((rp - rm) / (2 * h) - Kv) / np.linalg.norm(Kv), Kv


@pytest.fixture(scope="module")
def loaded():
    """Bone / muscle (5-parameter Mooney-Rivlin) / adipose (Ogden) column, quadratic tets, sheared and
    pulled to finite strain (principal stretches beyond 1.2 in the tissue)."""
    mesh = TaggedMesh.box((6, 6, 12), (3, 3, 7), layers={"cortical_bone": (0, 2), "muscle": (2, 8),
                                                         "adipose": (8, 12)})
    model = FEModel(mesh, {"cortical_bone": "cortical_bone", "muscle": "muscle", "adipose": "adipose"},
                    order=2, formulation="displacement")
    r = solve(model, [Fixed("zmin"), SurfaceForce("zmax", (0.2, 0.0, 0.4))], [1.0], progress=False)[-1]
    lam = r.cell_data["principal_stretches"]
    assert lam[:, 2].max() > 1.2  # finite strain: a wrong geometric or material tangent would show
    return model


@pytest.mark.parametrize("region", ["cortical_bone", "muscle", "adipose"])
def test_tangent_is_the_derivative_of_the_residual(loaded, region):
    """Central differences of each body's residual along a random direction match its assembled
    tangent to 1e-6 (the O(h^2) error is ~1e-9 here); a tangent off by 0.1 % fails the same test."""
    body = loaded.bodies[region]
    x = loaded.field
    v = np.random.default_rng(1).normal(size=x[0].values.size) * 1e-2
    err, Kv = directional_error(body, x, v, 1e-3)
    assert err < 1e-6
    # the check is not vacuous: the same comparison with a 0.1 % wrong tangent fails it
    rp = fun_items([body], update(x, 1e-3 * v))
    rm = fun_items([body], update(x, -1e-3 * v))
    fun_items([body], x)
    assert np.linalg.norm((rp - rm) / 2e-3 - 1.001 * Kv) / np.linalg.norm(Kv) > 1e-4
