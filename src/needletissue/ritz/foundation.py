"""Winkler spring stiffness of a tissue from its elastic modulus (beam on an elastic foundation).

Vesic, A. B. (1961). Bending of beams resting on isotropic elastic solid. Journal of the Engineering
Mechanics Division, ASCE, 87(EM2), 35-53: for a beam of width B and bending stiffness E_b I_b on an
elastic half-space (E_s, nu_s), the modulus of subgrade reaction per unit beam length is

    k = 0.65 * (E_s B^4 / (E_b I_b))^(1/12) * E_s / (1 - nu_s^2).

For a round needle (B = d, I = pi d^4 / 64) the diameter cancels inside the 12th root:
k = 0.65 (64 E_s / (pi E_b))^(1/12) E_s / (1 - nu_s^2). Units: E in MPa -> k in N/mm per mm (N/mm^2),
the unit of the paper's Table 1 stiffness.
"""

from __future__ import annotations

import math

from needletissue.errors import check_number
from needletissue.ritz.model import NEEDLE_E_MPA


def vesic_k(tissue_E_MPa: float, tissue_nu: float, diameter_mm: float = 5.0,
            needle_E_MPa: float = NEEDLE_E_MPA) -> float:
    """Vesic's spring stiffness k (N/mm^2) of a tissue layer around a needle of diameter d."""
    Es = check_number("tissue_E_MPa", tissue_E_MPa, gt=0)
    nu = check_number("tissue_nu", tissue_nu, gt=-1, lt=0.5)
    d = check_number("diameter_mm", diameter_mm, gt=0)
    Eb = check_number("needle_E_MPa", needle_E_MPa, gt=0)
    inertia = math.pi * d**4 / 64.0
    return 0.65 * (Es * d**4 / (Eb * inertia)) ** (1.0 / 12.0) * Es / (1.0 - nu**2)
