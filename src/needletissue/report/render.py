"""Report figures drawn from results the engines wrote (no physics here): an off-screen render of a
deformed VTU, and maximum needle deformation against force (FE, Ritz, the paper's values)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from needletissue.report.paper import PAPER
from needletissue.runinfo import write_atomic


def render_vtu(vtu: str | Path, png: str | Path, scene) -> Path:
    """A result VTU drawn as models.render draws it (scene: models.render.RenderScene): bone opaque, tissue
    translucent, needles and clamp by |u|, undeformed outline, force arrow, axes, colour bar beside."""
    from needletissue.models.render import offscreen, render_vtu as render

    offscreen()

    return render(vtu, png, scene)


def caption(png: str | Path) -> str:
    """A PNG's caption: its "Description" text (the figure writers put what the figure shows there), or
    "" when it has none."""
    try:
        from PIL import Image

        with Image.open(png) as im:
            return str(getattr(im, "text", {}).get("Description", ""))
    except Exception:  # not a PNG we can read: the file name stands as the caption
        return ""


def describe(png: str | Path, text: str) -> Path:
    """Write `text` into a PNG's "Description" (the report's caption; it travels with a shared PNG).
    The pixels are unchanged; rewritten atomically."""
    from PIL import Image
    from PIL.PngImagePlugin import PngInfo

    with Image.open(png) as im:
        im.load()
        info = PngInfo()
        for k, v in getattr(im, "text", {}).items():
            if k != "Description":
                info.add_itxt(k, v)
        info.add_itxt("Description", text)
        buf = io.BytesIO()
        im.save(buf, format="png", pnginfo=info)
    return write_atomic(png, buf.getvalue())


def plot_theory_vs_fe(results: list[dict], path: str | Path, title: str, dpi: int = 110) -> Path:
    """Maximum needle deformation (FE) and Ritz tip deflection against force, with the paper's values
    (FE 5.8152 / 10.8990 / 18.0620 mm, Ritz 17.63 mm at 300 N) as markers: the paper's Fig. 12 analogue."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = [r["force_N"] for r in results]
    fig, ax = plt.subplots(figsize=(5.6, 4))
    ax.plot(f, [r["max_needle_deformation_mm"] for r in results], "o-", label="FE, max needle deformation")
    ritz = [r.get("ritz_tip_deflection_mm") for r in results]
    if any(v is not None for v in ritz):
        ax.plot(f, [np.nan if v is None else v for v in ritz], "s--", label="Ritz, tip deflection")
    pf = [100.0, 200.0, 300.0]
    ax.plot(pf, [PAPER[f"fe_max_needle_deformation_{x:g}N_mm"].value for x in pf], "kx", ms=8,
            label="paper FE (Sec. 3.3)")
    ax.plot([300.0], [PAPER["ritz_tip_deflection_300N_mm"].value], "k+", ms=10, label="paper Ritz (Sec. 2.3)")
    ax.set_xlabel("reduction force (N)")
    ax.set_ylabel("needle deformation (mm)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    text = (f"{title}: maximum needle deformation (FE) and Ritz tip deflection against the reduction force "
            f"({', '.join(f'{x:g}' for x in f)} N), with the paper's FE (x) and Ritz (+) values.")
    fig.savefig(buf, format="png", dpi=dpi, metadata={"Description": text})
    plt.close(fig)
    return write_atomic(path, buf.getvalue())


def try_render(vtu, png, scene, notes: list, figures: list) -> None:
    """Render in a child process; on a crash add a note instead of a figure."""
    from needletissue.models.render import isolated

    try:
        figures.append(isolated(render_vtu, vtu, png, scene))
    except Exception as exc:  # the numbers stand without the picture
        notes.append(f"render of {Path(vtu).name} failed: {exc}")
