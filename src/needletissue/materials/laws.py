"""Strain-energy functions FElupe lacks, in FElupe's form W(C, **parameters) on tensortrax tensors.

Everything else (Neo-Hooke, 2-parameter Mooney-Rivlin, Yeoh, Ogden) is FElupe's own.
"""

from __future__ import annotations

from tensortrax.math import trace
from tensortrax.math.linalg import det


def mooney_rivlin_5(C, C10, C01, C20, C11, C02):
    """Isochoric 5-parameter Mooney-Rivlin (as in ANSYS), on the distortional invariants of C.

    W = C10 (I1-3) + C01 (I2-3) + C20 (I1-3)^2 + C11 (I1-3)(I2-3) + C02 (I2-3)^2.
    Initial shear modulus mu0 = 2 (C10 + C01).
    """
    J3 = det(C) ** (-1 / 3)
    I1 = J3 * trace(C)
    I2 = (I1**2 - J3**2 * trace(C @ C)) / 2
    a, b = I1 - 3, I2 - 3
    return C10 * a + C01 * b + C20 * a**2 + C11 * a * b + C02 * b**2
