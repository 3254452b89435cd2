"""Figures of the anatomical pelvis model: the off-screen render (models.render) and comparison plots
(Matplotlib)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def render_scene(data: dict):
    """The static render's scene (models.render.RenderScene) of a pelvis result (PelvisResult.to_dict or
    pelvis_results.json): the force along force_vector_unit on the clamp, the view across needle 1 and the
    force, framed on the needle site (the anatomy around it as context)."""
    from needletissue.models.render import RenderScene

    base, top = (np.asarray(p, float) for p in data["site"]["needle_axes_mm"][0])
    f = data["results"][-1]["force_N"]
    source = str(data["site"].get("source") or "").removeprefix("segmentation:")  # the smooth route's CT
    source = ("ssm" if source.startswith("ssm") else "ct" if source else "").upper()  # "ct:<files>" -> CT
    return RenderScene(f"Anatomical model{f' ({source})' if source else ''}, 2 needles and a clamp, {f:g} N",
                       tuple(data["force_vector_unit"]), tuple(top - base), focus_steel=True,
                       cut=True)


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
    fig.savefig(f1, dpi=130, metadata={"Description": "Anatomical model: maximum needle deformation (FE) and "
                                                      "Ritz tip deflection with the measured layers against the "
                                                      "reduction force, with the paper's values."})
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
    fig.savefig(f2, dpi=130, metadata={"Description": f"Anatomical model: maximum deformation |u| (mm) of each "
                                                      f"region at {res.results[-1].force_N:.0f} N."})
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
    from needletissue.models.render import offscreen

    env = offscreen(dict(os.environ, PYVISTA_OFF_SCREEN="true", MPLBACKEND="Agg"))
    r = subprocess.run([sys.executable, "-c", code, str(out_dir)], capture_output=True, text=True, env=env)
    if r.returncode != 0:
        return {"error": f"figure process exited with {r.returncode}: {r.stderr.strip()[-300:]}"}
    return {"files": [ln for ln in r.stdout.splitlines() if ln.strip()]}


def figures_from_files(out_dir) -> list[str]:
    """Figures from pelvis_results.json and the largest force's VTU in out_dir."""
    import json
    from types import SimpleNamespace as NS

    from needletissue.models.render import render_vtu

    out_dir = Path(out_dir)
    d = json.loads((out_dir / "pelvis_results.json").read_text(encoding="utf-8"))
    res = NS(results=[NS(force_N=r["force_N"], max_needle_deformation_mm=r["max_needle_deformation_mm"],
                         ritz_tip_deflection_mm=r["ritz_tip_deflection_mm"],
                         max_deformation_mm=r["max_deformation_mm"]) for r in d["results"]])
    files = _plots(res, out_dir)  # first: a VTK crash in the render must not lose the plots
    # relative to out_dir (relocatable); absolute in old files
    files.append(render_vtu(out_dir / d["results"][-1]["vtu"], out_dir / "pelvis_deformation.png", render_scene(d)))
    return [str(f) for f in files]
