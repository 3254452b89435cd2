"""Figures of the needle model: deformed model (PyVista, off-screen) and needle deflection curves with
the Rayleigh-Ritz v(z) laid over (Matplotlib)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def plot_deformed(result, path: Path, scale: float = 1.0) -> Path:
    """Deformed model at the largest force (models.render: bone opaque, tissue translucent, needles and
    clamp by |u|, undeformed needle axes and clamp, force arrow at the load point, axes with the frame,
    colour bar beside the model). Rendered off-screen and written atomically."""
    from needletissue.models.needle.model import FRAME
    from needletissue.models.render import Regions, build, grid_from_arrays, render

    r = result.results[-1]
    fe = r.fe
    grid = grid_from_arrays(fe.points, fe.cells, fe.displacement, fe.cell_data["region"])
    regions = Regions({i: n for n, i in fe.region_tags.items()},
                      {fe.region_tags[n]: m for n, m in fe.materials.items() if n in fe.region_tags})
    return render(build(grid, regions, scene(result, scale), r.force_N, FRAME), path)


def scene(result, scale: float = 1.0):
    """The static render's scene of a needle model result at its largest force: the force along the
    configured direction at the load point (gripper centre + load_offset), the needles along z."""
    from needletissue.models.render import RenderScene

    r = result.results[-1]
    g = result.config.geometry
    return RenderScene(f"Needle FE model, {g.needles} needle{'s' if g.needles > 1 else ''}, {r.force_N:g} N, "
                       f"max needle deformation {r.max_needle_deformation_mm:.2f} mm", result.config.direction,
                       load_point_mm=tuple(result.config.load_point), scale=scale)


def plot_deflection_curves(result, path: Path) -> Path:
    """Deflection along each needle axis (FE) and the Ritz v(z) at the full force and per needle."""
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from needletissue.runinfo import write_atomic

    g = result.config.geometry
    fig, ax = plt.subplots(figsize=(7, 5))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(result.results):
        c = colours[i % len(colours)]
        for j, (name, curve) in enumerate(r.curves.items()):
            ax.plot(curve.z_mm, curve.deflection_mm, color=c, ls="-" if j == 0 else "-.",
                    label=f"FE {name}, {r.force_N:g} N")
        if r.ritz:
            z = np.linspace(0, g.free_length, 200)
            ax.plot(z, r.ritz[0].deflection(z), color=c, ls="--", label=f"Ritz, {r.force_N:g} N")
            if g.needles > 1:
                ax.plot(z, r.ritz[1].deflection(z), color=c, ls=":",
                        label=f"Ritz, {r.force_N / g.needles:g} N per needle")
    for zi in (0.0, g.muscle_thickness, g.tissue_thickness):
        ax.axvline(zi, color="grey", lw=0.5)
    ax.axvspan(g.free_length - g.grip_length, g.free_length, color="grey", alpha=0.15, label="clamp")
    ax.set_xlabel("z along the needle from the bone surface (mm)")
    ax.set_ylabel("deflection along the force (mm)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.partial.png")
    forces = ", ".join(f"{r.force_N:g}" for r in result.results)
    fig.savefig(tmp, dpi=150, metadata={"Description": (
        f"Needle FE model ({g.needles} needle{'s' if g.needles > 1 else ''}, free length {g.free_length:g} mm): "
        f"deflection along the force of each needle axis (FE, solid) against z from the bone surface at {forces} "
        "N, with the Rayleigh-Ritz v(z) at the full force (dashed) and per needle (dotted); grey lines: layer "
        "interfaces; shaded: the clamp.")})
    plt.close(fig)
    write_atomic(path, tmp.read_bytes())
    tmp.unlink()
    return path
