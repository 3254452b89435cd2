"""Closed-form incompressible load cases vs FElupe's ViewMaterialIncompressible (same stretches, same laws).

pytest-benchmark groups each law; the FElupe row is the baseline of its group (ratios in the table).
"""

import numpy as np
import pytest

from needletissue import materials
from needletissue.materials import closed_form as cf
from needletissue.materials import stability

N = 10_000
STRETCH = np.linspace(0.7, 1.6, N)


@pytest.mark.parametrize("name", ["muscle", "adipose"])
def test_closed_form_uniaxial(benchmark, name):
    m = materials.get(name)
    benchmark.group = f"uniaxial {name} ({N} stretches)"
    P = benchmark(cf.nominal_stress, m.model, m.parameters, "uniaxial", STRETCH)
    assert P.shape == (N,)


@pytest.mark.parametrize("name", ["muscle", "adipose"])
def test_felupe_view_uniaxial(benchmark, name):
    import felupe as fem

    m = materials.get(name)
    view = fem.ViewMaterialIncompressible(m.isochoric())
    benchmark.group = f"uniaxial {name} ({N} stretches)"
    _, P, _ = benchmark(view.uniaxial, STRETCH)
    np.testing.assert_allclose(P, cf.nominal_stress(m.model, m.parameters, "uniaxial", STRETCH), rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize("name", ["muscle", "adipose"])
def test_drucker_margin(benchmark, name):
    m = materials.get(name)
    benchmark.group = f"Drucker check ({N} states)"
    L = cf.principal_stretches("uniaxial", STRETCH)
    benchmark(stability.drucker_margin, m.model, m.parameters, L)


@pytest.mark.parametrize("name", ["muscle"])
def test_felupe_is_stable(benchmark, name):
    import felupe as fem

    m = materials.get(name)
    umat = m.isochoric() & fem.Volumetric(bulk=m.bulk)
    L = cf.principal_stretches("uniaxial", STRETCH)
    F = np.zeros((3, 3, 1, N))
    for a in range(3):
        F[a, a, 0] = L[a]
    benchmark.group = f"Drucker check ({N} states)"
    benchmark(umat.is_stable, [F, None])
