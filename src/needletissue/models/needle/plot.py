"""Figures of the needle model: deformed model (PyVista, off-screen) and needle deflection curves with
the Rayleigh-Ritz v(z) laid over (Matplotlib)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def plot_deformed(result, path: Path, scale: float = 1.0) -> Path:
    """Deformed model at the largest force, true scale, coloured by |u| (mm); a clip at y = 0
    shows the needles inside the tissue. Rendered off-screen and written atomically."""
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    import pyvista as pv

    from needletissue.runinfo import write_atomic

    r = result.results[-1]
    fe = r.fe
    cells = fe.cells[:, :4]
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: cells}, fe.points)
    grid.point_data["|u| (mm)"] = np.linalg.norm(fe.displacement, axis=1)
    grid.point_data["u"] = fe.displacement
    grid.cell_data["region"] = fe.cell_data["region"]
    # Cut at y = 0 in the reference configuration (shows the needles inside the tissue), then warp.
    clipped = grid.clip(normal="y", origin=(0, 0, 0), invert=False, crinkle=True).warp_by_vector("u", factor=scale)
    pl = pv.Plotter(off_screen=True, window_size=(1400, 1000))
    pl.add_mesh(clipped, scalars="|u| (mm)", cmap="viridis", show_edges=False,
                scalar_bar_args={"vertical": True, "position_x": 0.88, "position_y": 0.2})
    pl.add_mesh(clipped.extract_feature_edges(), color="black", line_width=0.5, opacity=0.3)
    pl.add_text(f"{r.force_N:g} N, deformed x{scale:g}: max needle deformation "
                f"{r.max_needle_deformation_mm:.2f} mm", font_size=12)
    pl.camera_position = "xz"
    pl.camera.azimuth = 25
    pl.camera.elevation = 15
    tmp = path.with_name(f".{path.stem}.partial.png")
    pl.screenshot(str(tmp))
    pl.close()
    write_atomic(path, tmp.read_bytes())
    tmp.unlink()
    return path


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
    fig.savefig(tmp, dpi=150)
    plt.close(fig)
    write_atomic(path, tmp.read_bytes())
    tmp.unlink()
    return path
