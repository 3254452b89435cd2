"""Figure: each pin's lateral deflection along z per wrench (bone, layers and clamp shaded)."""

from __future__ import annotations

import numpy as np


def plot_frame(results, model, path=None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from needletissue.runinfo import save_figure

    fig, ax = plt.subplots(figsize=(6.5, 4.5), layout="constrained")
    if model.root == "bone":
        ax.axvspan(-model.depth_mm, 0, color="0.85", label="bone")
    z = 0.0
    for la, c in zip(model.layers if model.tissue else (), ("#f4c7c3", "#fce8b2", "#d9ead3", "#cfe2f3")):
        ax.axvspan(z, z + la.thickness_mm, color=c, alpha=0.6, label=la.name)
        z += la.thickness_mm
    if model.clamp_length_mm > 0:
        ax.axvspan(model.clamp_bottom_mm, model.free_length_mm, color="0.6", alpha=0.4, label="clamp")
    for r in results:
        for i, n in enumerate(r.needles):
            u = np.hypot(n.curve_u_mm[:, 0], n.curve_u_mm[:, 1])
            ax.plot(n.curve_z_mm, u, ls="-" if i == 0 else "--",
                    label=f"F=({', '.join(f'{x:g}' for x in r.force_N)}) N, pin {i + 1}")
    ax.set_xlabel("z along the pin from the bone surface [mm]")
    ax.set_ylabel("lateral deflection |u_xy| [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    if path is not None:
        save_figure(fig, path)
    return fig
