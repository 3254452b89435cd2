"""Figures of material curves (Matplotlib, Agg): the paper's muscle and adipose uniaxial curves."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from needletissue.materials import closed_form as cf
from needletissue.materials import curves, stability
from needletissue.runinfo import save_figure


def plot_curves(names=("muscle", "adipose"), mode: str = "uniaxial", stretch_min: float = 0.7,
                stretch_max: float = 1.6, points: int = 181, out: str | Path | None = None):
    """One panel per material: closed-form nominal stress (MPa) vs stretch, tension and compression,
    the Drucker-stable stretch range shaded, its ends marked. Returns the figure; saves a PNG to `out`.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(names), figsize=(5.2 * len(names), 4.0), squeeze=False)
    for ax, name in zip(axes[0], names):
        mat = curves.hyperelastic(name)
        lam = np.linspace(stretch_min, stretch_max, points)
        P = cf.nominal_stress(mat.model, mat.parameters, mode, lam)
        lo, hi = stability.stable_range(mat.model, mat.parameters, mode)
        ax.axvspan(max(lo, stretch_min), min(hi, stretch_max), color="tab:green", alpha=0.12,
                   label=f"Drucker-stable {lo:.3g} - {hi:.3g}" + (" (window end)" if hi >= stability.STRETCH_WINDOW[1] else ""))
        stable = (lam >= lo) & (lam <= hi)
        ax.plot(lam, np.where(stable, P, np.nan), color="tab:blue", lw=2, label=f"{mat.model}")
        if (~stable).any():
            ax.plot(lam, np.where(stable, np.nan, P), color="tab:red", lw=2, ls="--", label="unstable")
        for end in (lo, hi):
            if stretch_min < end < stretch_max:
                ax.axvline(end, color="tab:red", lw=0.8)
        ax.axhline(0, color="k", lw=0.5)
        ax.axvline(1, color="k", lw=0.5)
        ax.set_title(f"{mat.name} ({mode}, incompressible)")
        ax.set_xlabel("stretch λ = 1 + ε")
        ax.set_ylabel("nominal stress P (MPa)")
        ax.legend(loc="upper left", fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    if out is not None:
        save_figure(fig, out)
    return fig


def plot_fit(result, data, out: str | Path):
    """Data points and the fitted closed-form curve, unstable part dashed."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    lam = np.linspace(min(1.0, data.stretch.min()), max(1.0, data.stretch.max()), 200)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", stability.UnstableMaterialWarning)
        P = result.predict(lam)
    lo, hi = result.stable_range
    stable = (lam >= lo) & (lam <= hi)
    fig, ax = plt.subplots(figsize=(5.2, 4.0))
    ax.plot(data.stretch, data.nominal_stress_MPa, "ko", ms=4, label="data")
    ax.plot(lam, np.where(stable, P, np.nan), "tab:blue", label=f"{result.model} fit (R² = {result.r2:.5f})")
    if (~stable).any():
        ax.plot(lam, np.where(stable, np.nan, P), "tab:red", ls="--", label="unstable")
    ax.set_xlabel("stretch λ")
    ax.set_ylabel("nominal stress P (MPa)")
    ax.set_title(f"{result.mode} fit, RMSE {result.rmse_MPa:.3g} MPa")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    save_figure(fig, out)
    return fig
