"""Figure of the Ritz model: the paper's Fig. 5, v(z) per force (the ratio map is in paper.py)."""

from __future__ import annotations

from pathlib import Path


def plot_deflection(results, path: str | Path | None = None, model=None, ax=None, n: int = 201,
                    title: str | None = None):
    """Draw v(z) for each solved force (paper Fig. 5). results: RitzResult list or a BatchResult.

    Tissue layers of `model` are shaded. Writes `path` (PNG/PDF/SVG) atomically when given.
    Returns the matplotlib Figure.
    """
    import matplotlib

    if path is not None and ax is None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if hasattr(results, "results") and callable(results.results):
        results = results.results()
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(6.4, 4.2), layout="constrained")
    else:
        fig = ax.figure
    if model is not None:
        za = 0.0
        shades = ("#d9c2b8", "#f3e3b5", "#cfe0c3", "#c9d7ea")
        for j, layer in enumerate(model.layers):
            ax.axvspan(za, za + layer.thickness_mm, color=shades[j % len(shades)], alpha=0.6, lw=0,
                       label=f"{layer.name} (k={layer.k_N_per_mm2:g} N/mm²)")
            za += layer.thickness_mm
    for r in results:
        z, v = r.curve(n)
        ax.plot(z, v, lw=1.8, label=f"F = {r.force_N:g} N: tip {r.tip_deflection_mm:.2f} mm (p={r.order})")
    ax.set_xlabel("distance from bone z [mm]")
    ax.set_ylabel("needle deflection v(z) [mm]")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlim(left=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(title or "Needle deflection under the reduction force (Rayleigh-Ritz)")
    if path is not None:
        from needletissue.runinfo import save_figure

        save_figure(fig, path)
    return fig

