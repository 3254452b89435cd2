"""The default needle model's output files: the render's child process beside the other files (write_outputs)
against the same files one after another with the render last (the code before 2026-12-03), in one process,
alternating, three times each (docs/bench.md, "Levers").

    python benchmarks/needle_outputs_ab.py
"""

import dataclasses
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from needletissue.fem.result import write_series
from needletissue.models.needle.model import FRAME, NeedleModelConfig, run_needle_model, write_outputs
from needletissue.models.needle.plot import plot_deflection_curves, scene
from needletissue.models.render import isolated, render_vtu


def one_after_another(res, out: Path):
    """The files as written before 2026-12-03: every VTU, the series, the figure, then the render."""
    out.mkdir()
    for r in res.results:
        r.fe.write_vtu(out / f"needle_{r.force_N:g}N.vtu", frame=FRAME, force_N=r.force_N)
    write_series(out / "needle.pvd", [(r.force_N, f"needle_{r.force_N:g}N.vtm") for r in res.results])
    plot_deflection_curves(res, out / "needle_deflection.png")
    isolated(render_vtu, out / f"needle_{res.results[-1].force_N:g}N.vtu", out / "needle_deformed.png", scene(res))


def main():
    res = run_needle_model(dataclasses.replace(NeedleModelConfig(), ritz=False))
    variants = {"old": lambda out: one_after_another(res, out), "new": lambda out: write_outputs(res, out)}
    seconds = {name: [] for name in variants}
    for _ in range(3):
        for name, write in variants.items():
            tmp = Path(tempfile.mkdtemp())
            t0 = time.perf_counter()
            write(tmp / "o")
            seconds[name].append(time.perf_counter() - t0)
            shutil.rmtree(tmp)
    print({k: [f"{x:.2f}" for x in v] for k, v in seconds.items()},
          "medians", {k: round(statistics.median(v), 2) for k, v in seconds.items()})


if __name__ == "__main__":  # the render's child process is spawned: it imports this module
    main()
