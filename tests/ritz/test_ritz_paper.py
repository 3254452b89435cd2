"""The paper's numbers against the model, and Vesic's foundation stiffness (docs/ritz.md)."""

import math

import numpy as np
import pytest

from needletissue import ritz
from needletissue.ritz import paper
from needletissue.ritz.foundation import vesic_k
from needletissue.ritz.model import NEEDLE_E_MPA


def test_defaults_reproduce_paper_tip_deflection():
    """Paper: 17.63 mm at 300 N (cubic trial function), printed to 0.01 mm -> tolerance 0.005 mm."""
    assert ritz.solve(300.0).tip_deflection_mm == pytest.approx(paper.TIP_300N_MM, abs=0.005)


def test_default_needle_modulus_is_papers_table2():
    from needletissue import materials

    assert materials.get("needle").parameters["E"] == NEEDLE_E_MPA


def test_paper_ratio_is_out_of_reach_but_2_5008_is_reachable():
    """w(300)/w(100) <= 3 < 3.5008 on the whole 17.63 mm family; the reading 'to 250.08 %' is matched
    by one (d, l) that then also gives 17.63 mm."""
    c = paper.curve_17_63(np.array([2.5, 3.5, 5.0, 6.0]))
    assert np.all(c.ratio_300_100 < 3.0)
    d, l = paper.match_two_numbers(2.5008)
    m = ritz.RitzModel(diameter_mm=d, free_length_mm=l)
    w100, w300 = (ritz.solve(F, m).tip_deflection_mm for F in (100.0, 300.0))
    assert w300 == pytest.approx(17.63, abs=1e-6) and w300 / w100 == pytest.approx(2.5008, abs=1e-6)


def test_fe_growth_is_superlinear():
    """The paper's FE numbers grow faster than linearly (x3.106 from 100 to 300 N), which no hardening
    spring model can produce; its Ritz value 17.63 and FE 18.062 differ by the stated 0.432 mm."""
    g = paper.fe_growth()
    assert g["300/100"] > 3.0 and g["200/100"] < 2.0 and g["300/200"] > 1.5
    assert paper.FE_MAX_MM[300.0] - paper.TIP_300N_MM == pytest.approx(0.432, abs=1e-9)


def test_vesic_k_scaling_laws():
    """k = 0.65 (Es d^4 / (Eb I))^(1/12) Es / (1 - nu^2): independent of d for a round needle,
    proportional to Es^(13/12), to Eb^(-1/12) and to 1 / (1 - nu^2)."""
    k = vesic_k(0.14, 0.45)
    assert vesic_k(0.14, 0.45, diameter_mm=2.0) == pytest.approx(k, rel=1e-14)
    assert vesic_k(0.28, 0.45) / k == pytest.approx(2 ** (13 / 12), rel=1e-14)
    assert vesic_k(0.14, 0.45, needle_E_MPa=2 * NEEDLE_E_MPA) / k == pytest.approx(2 ** (-1 / 12), rel=1e-14)
    assert vesic_k(0.14, 0.0) / k == pytest.approx(1 - 0.45**2, rel=1e-14)
    assert k == pytest.approx(0.65 * (64 * 0.14 / (math.pi * NEEDLE_E_MPA)) ** (1 / 12) * 0.14 / (1 - 0.45**2))
