"""Cost of frictional contact against the bonded model on the same mesh (ratio).

Model: the two pressed blocks of tests/fem/test_contact.py (10 x 10 mm, G = 10 / 1 MPa, h = 2.5 mm,
1 mm prescribed compression in two steps): bonded (conforming) vs contact with mu = 0.3 on the
split interface (ipctk barrier + lagged friction, dhat = 0.01 mm). pytest-benchmark medians; the
contact/bonded ratio of the medians and the Newton iterations are stored in extra_info.

The needle model (bonded vs the paper's interfaces) is timed by
`needletissue.models.contact.compare_interfaces` (wall times and their ratio in its result).
"""

from __future__ import annotations

import numpy as np
import pytest

from needletissue.fem.contact import ContactSettings
from needletissue.models.contact_verify import pressed_blocks

_MEDIANS: dict[str, float] = {}


def _run(friction):
    return pressed_blocks(2.5, friction, ContactSettings(dhat=1e-2, youngs_modulus=3.0), factors=(0.5, 1.0))[1]


@pytest.mark.parametrize("case", ["bonded", "contact"])
def test_contact_vs_bonded(benchmark, case):
    friction = None if case == "bonded" else {"lower-upper": 0.3}
    sol = benchmark.pedantic(_run, args=(friction,), rounds=3, iterations=1)
    _MEDIANS[case] = benchmark.stats.stats.median
    benchmark.extra_info["newton_iterations"] = sol.newton_iterations
    benchmark.extra_info["substeps"] = sol.substeps
    if case == "contact" and "bonded" in _MEDIANS:
        benchmark.extra_info["ratio_contact_to_bonded"] = _MEDIANS["contact"] / _MEDIANS["bonded"]
    assert np.isfinite(sol.steps[-1].displacement).all()
