"""Figures of the anatomical pelvis model: off-screen renders (PyVista) and comparison plots (Matplotlib)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def figures(res, fe_last, mesh, out_dir) -> list[str]:
    """pelvis_deformation.png (section through the needles, |u| at the largest force),
    pelvis_needle_vs_force.png (FE, Ritz, paper), pelvis_tissue_deformation.png (per region)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [_render(res, fe_last, mesh, out_dir / "pelvis_deformation.png")]
    files += _plots(res, out_dir)
    return [str(f) for f in files]


def _render(res, fe_last, mesh, path):
    os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
    import pyvista as pv

    pv.OFF_SCREEN = True
    cells = mesh.cells
    ctype = pv.CellType.QUADRATIC_TETRA if cells.shape[1] == 10 else pv.CellType.TETRA
    conn = np.hstack([np.full((len(cells), 1), cells.shape[1]), cells]).ravel()
    grid = pv.UnstructuredGrid(conn, np.full(len(cells), ctype, np.uint8), mesh.points)
    u = fe_last.displacement
    grid.point_data["|u| mm"] = np.linalg.norm(u, axis=1)
    tag = np.zeros(len(cells), int)
    steel_tags = []
    for i, (name, ids) in enumerate(mesh.regions.items()):
        tag[ids] = i
        if str(name).startswith(("needle", "clamp")):
            steel_tags.append(i)
    grid.cell_data["region"] = tag
    grid = grid.linear_copy()
    axes = np.array(res.site["needle_axes_mm"], float)
    d = np.asarray(res.site["direction"], float)
    f = np.asarray(res.force_vector_unit, float)
    normal = np.cross(d, f)
    normal /= np.linalg.norm(normal)
    on_needle = axes[0].mean(axis=0)
    # Outer surface of the anatomy (translucent) and the needles + clamp (opaque), coloured by |u|.
    # (Clipping/slicing the quadratic grid segfaulted in VTK 9.x on this machine; surfaces do not.)
    body = grid.extract_surface(algorithm="dataset_surface")
    steel = grid.extract_cells(np.nonzero(np.isin(tag, steel_tags))[0]).extract_surface(algorithm="dataset_surface")
    p = pv.Plotter(off_screen=True, window_size=(1400, 1000))
    p.add_mesh(body, scalars="|u| mm", cmap="viridis", opacity=0.25, show_scalar_bar=False)
    p.add_mesh(steel, scalars="|u| mm", cmap="viridis",
               scalar_bar_args={"title": f"|u| (mm) at {res.results[-1].force_N:.0f} N"})
    p.camera_position = [tuple(on_needle + 260 * normal), tuple(on_needle), (0, 0, 1)]
    p.add_text("model surface (translucent), needles and clamp; view normal to the needle-force plane",
               font_size=10)
    p.screenshot(str(path))
    p.close()
    return path


def _plots(res, out_dir):
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from needletissue.models.pelvis import PAPER

    F = [r.force_N for r in res.results]
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.plot(F, [r.max_needle_deformation_mm for r in res.results], "o-", label="FE, this model")
    ax.plot(F, [r.ritz_tip_deflection_mm for r in res.results], "s--", label="Ritz, measured layers")
    ax.plot(PAPER["forces_N"], PAPER["max_needle_deformation_mm"], "k^:", label="paper FE")
    ax.plot([300.0], [PAPER["ritz_tip_deflection_mm_300N"]], "kx", ms=9, label="paper Ritz (300 N)")
    ax.set_xlabel("reduction force (N)")
    ax.set_ylabel("max needle deformation (mm)")
    ax.grid(alpha=0.3)
    ax.legend()
    f1 = out_dir / "pelvis_needle_vs_force.png"
    fig.tight_layout()
    fig.savefig(f1, dpi=130)
    plt.close(fig)

    last = res.results[-1].max_deformation_mm
    names = sorted(last, key=lambda k: -last[k])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.barh(names[::-1], [last[n] for n in names[::-1]], color="tab:blue")
    if "adipose" in last:
        ax.plot([PAPER["adipose_max_deformation_mm_300N"]], [names[::-1].index("adipose")], "r*", ms=12,
                label="paper adipose, 300 N")
        ax.legend()
    ax.set_xlabel(f"max deformation at {res.results[-1].force_N:.0f} N (mm)")
    ax.grid(alpha=0.3, axis="x")
    f2 = out_dir / "pelvis_tissue_deformation.png"
    fig.tight_layout()
    fig.savefig(f2, dpi=130)
    plt.close(fig)
    return [f1, f2]


def comparison_markdown(res) -> str:
    """The comparison table (ours beside the paper's) as Markdown, written next to the results."""

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3f}"
        if isinstance(v, (list, tuple)):
            return " / ".join(fmt(x) for x in v)
        return str(v)

    lines = ["| quantity | this model | paper | difference |", "|---|---|---|---|"]
    for row in res.comparison:
        lines.append(f"| {row['quantity']} | {fmt(row['ours'])} | {fmt(row['paper'])} | {fmt(row['difference'])} |")
    last = res.results[-1]
    lines += ["", f"Max deformation per region at {last.force_N:.0f} N (mm): "
              + ", ".join(f"{k} {v:.3f}" for k, v in sorted(last.max_deformation_mm.items(), key=lambda kv: -kv[1]))]
    return "\n".join(lines) + "\n"


def render_in_subprocess(out_dir) -> dict:
    """Render the figures from the written VTU/JSON in a child process (VTK off-screen rendering has
    crashed with a segfault inside long runs on this machine). Returns {"files": [...]} or {"error"}."""
    import subprocess
    import sys

    code = ("import sys; from needletissue.models.pelvis.report import figures_from_files; "
            "print('\\n'.join(figures_from_files(sys.argv[1])))")
    env = dict(os.environ, PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg")
    r = subprocess.run([sys.executable, "-c", code, str(out_dir)], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        return {"error": f"figure process exited with {r.returncode}: {r.stderr.strip()[-300:]}"}
    return {"files": [ln for ln in r.stdout.splitlines() if ln.strip()]}


def figures_from_files(out_dir) -> list[str]:
    """Figures from pelvis_results.json and the largest force's VTU in out_dir."""
    import json
    from types import SimpleNamespace as NS

    import meshio

    out_dir = Path(out_dir)
    d = json.loads((out_dir / "pelvis_results.json").read_text(encoding="utf-8"))
    last = d["results"][-1]
    m = meshio.read(out_dir / last["vtu"])  # relative to out_dir (relocatable); absolute in old files
    cells = m.cells[0].data
    reg = np.asarray(m.cell_data["region"][0])
    tags = d["mesh"].get("region_tags") or {}
    names = {int(v): k for k, v in tags.items()}
    mesh = NS(points=m.points, cells=cells,
              regions={names.get(int(i), str(i)): np.nonzero(reg == i)[0] for i in np.unique(reg)})
    res = NS(site=d["site"], force_vector_unit=d["force_vector_unit"],
             results=[NS(force_N=r["force_N"], max_needle_deformation_mm=r["max_needle_deformation_mm"],
                         ritz_tip_deflection_mm=r["ritz_tip_deflection_mm"],
                         max_deformation_mm=r["max_deformation_mm"]) for r in d["results"]])
    files = _plots(res, out_dir)  # first: a VTK crash in the render must not lose the plots
    files.append(_render(res, NS(displacement=m.point_data["displacement"]), mesh, out_dir / "pelvis_deformation.png"))
    return [str(f) for f in files]
