"""Consistency of the paper's reported numbers with the Ritz model (docs/ritz.md, "Paper consistency").

Paper: Ritz tip deflection 17.63 mm at 300 N, "+250.08 %" relative to 100 N (ratio 3.5008); FE
maximum needle deformation 5.8152, 10.8990, 18.0620 mm at 100, 200, 300 N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from needletissue.ritz.model import RitzModel

TIP_300N_MM = 17.63
RATIO_300_100 = 3.5008  # "+250.08 %"
FE_MAX_MM = {100.0: 5.8152, 200.0: 10.8990, 300.0: 18.0620}


def free_length_for(diameter_mm: float, deflection_mm: float = TIP_300N_MM, force_N: float = 300.0,
                    model: RitzModel | None = None, order=3) -> float:
    """Free length (mm) at which a needle of this diameter deflects deflection_mm at force_N."""
    from needletissue.ritz.inverse import calibrate

    model = (model or RitzModel()).replace(diameter_mm=diameter_mm)
    return calibrate("free_length", force_N, deflection_mm, model, order=order).value


@dataclass(frozen=True)
class Curve17:
    """The (d, l) pairs that reproduce 17.63 mm at 300 N, and w(100), w(200) on them."""

    diameter_mm: np.ndarray
    free_length_mm: np.ndarray
    tip_100_mm: np.ndarray
    tip_200_mm: np.ndarray
    ratio_300_100: np.ndarray


def curve_17_63(diameters_mm=np.arange(2.5, 7.01, 0.25), model: RitzModel | None = None, order=3) -> Curve17:
    from needletissue.ritz.solver import solve_batch

    model = model or RitzModel()
    d = np.asarray(diameters_mm, float)
    l = np.array([free_length_for(x, model=model, order=order) for x in d])
    F = np.repeat([[100.0, 200.0, 300.0]], d.size, 0).ravel()
    b = solve_batch(F, diameter_mm=np.repeat(d, 3), free_length_mm=np.repeat(l, 3), model=model, order=order,
                    parallel=False)
    w = b.tip_deflection_mm.reshape(-1, 3)
    return Curve17(d, l, w[:, 0], w[:, 1], w[:, 2] / w[:, 0])


def match_two_numbers(ratio: float, deflection_mm: float = TIP_300N_MM, model: RitzModel | None = None,
                      order=3, d_range=(2.0, 8.0)) -> tuple[float, float]:
    """(d, l) that give deflection_mm at 300 N AND w(300)/w(100) = ratio (needs ratio < 3)."""
    from needletissue.ritz.solver import solve

    model = model or RitzModel()

    def g(d):
        l = free_length_for(d, deflection_mm, model=model, order=order)
        m = model.replace(diameter_mm=d, free_length_mm=l)
        return deflection_mm / solve(100.0, m, order).tip_deflection_mm - ratio

    d = brentq(g, *d_range, xtol=1e-10)
    return d, free_length_for(d, deflection_mm, model=model, order=order)


def ratio_map(k_scale=np.geomspace(0.1, 1e4, 60), diameters_mm=(3.0, 4.0, 5.0, 6.0),
              model: RitzModel | None = None, order=3) -> dict:
    """w(300)/w(100) when both layer k's are multiplied by k_scale, for needles on the 17.63 curve."""
    from needletissue.ritz.solver import solve_batch

    model = model or RitzModel()
    out = {"k_scale": np.asarray(k_scale, float)}
    k0 = np.array([la.k_N_per_mm2 for la in model.layers])
    for cos in (True, False):
        m = model.replace(cos_term=cos)
        for d in diameters_mm:
            l = free_length_for(d, model=model, order=order)
            K = np.tile(k0[None] * out["k_scale"][:, None], (2, 1))
            F = np.repeat([100.0, 300.0], out["k_scale"].size)
            b = solve_batch(F, diameter_mm=d, free_length_mm=l, k_N_per_mm2=K, model=m, order=order,
                            parallel=False)
            w = b.tip_deflection_mm.reshape(2, -1)
            out[(cos, d)] = w[1] / w[0]
    return out


def fe_growth() -> dict:
    """The FE numbers' own growth: ratios to the 100 N value and the linear expectation."""
    w = FE_MAX_MM
    return {"200/100": w[200.0] / w[100.0], "300/100": w[300.0] / w[100.0], "300/200": w[300.0] / w[200.0],
            "linear": {"200/100": 2.0, "300/100": 3.0, "300/200": 1.5}}


def plot_consistency(path=None, curve: Curve17 | None = None, rmap: dict | None = None):
    """Two panels: the (d, l) family reproducing 17.63 mm; w(300)/w(100) against the bound 3."""
    import matplotlib.pyplot as plt

    from needletissue.ritz.plot import save

    curve = curve or curve_17_63()
    rmap = rmap or ratio_map()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2), layout="constrained")
    a.plot(curve.diameter_mm, curve.free_length_mm, "o-", ms=3)
    a.axvspan(5.0, 6.0, color="0.85", label="usual Schanz pins (5-6 mm)")
    a.set_xlabel("needle diameter d [mm]")
    a.set_ylabel("free length l giving 17.63 mm at 300 N [mm]")
    a.grid(alpha=0.3)
    a.legend()
    a.set_title("(a) needles that reproduce the paper's 17.63 mm")
    for key, r in rmap.items():
        if key == "k_scale":
            continue
        cos, d = key
        b.semilogx(rmap["k_scale"], r, ls="-" if cos else "--", label=f"d={d:g} mm{'' if cos else ', no cos'}")
    b.axhline(3.0, color="k", lw=1, label="bound w(300)/w(100) <= 3")
    b.axhline(RATIO_300_100, color="r", lw=1, label='paper "+250.08 %" = 3.5008')
    b.axhline(FE_MAX_MM[300.0] / FE_MAX_MM[100.0], color="m", lw=1, ls=":", label="paper FE 18.062/5.8152")
    b.axvline(1.0, color="0.5", lw=0.8, ls=":")
    b.set_xlabel("layer stiffness k / paper's k (Table 1)")
    b.set_ylabel("w(300 N) / w(100 N)")
    b.set_ylim(0.9, 3.7)
    b.grid(alpha=0.3)
    b.legend(fontsize=7, loc="lower left")
    b.set_title("(b) hardening springs: response is sub-linear")
    if path is not None:
        save(fig, path)
    return fig
