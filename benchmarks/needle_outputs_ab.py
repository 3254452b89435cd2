"""The default needle model's output files: the render's child process beside the other files (write_outputs)
against the same files one after another with the render last (the code before 2026-12-03), in one process,
alternating, three times each (docs/bench.md, "Levers").

    python benchmarks/needle_outputs_ab.py
"""
import time, dataclasses, tempfile, shutil, statistics
from pathlib import Path
from needletissue.models.needle.model import run_needle_model, NeedleModelConfig, FRAME, write_outputs
from needletissue.models.needle.plot import plot_deflection_curves, scene
from needletissue.models.render import isolated, render_vtu
from needletissue.fem.result import write_series
def main():
    global res
    cfg = dataclasses.replace(NeedleModelConfig(), ritz=False)
    res = run_needle_model(cfg)
    def old(out):
        out.mkdir()
        for r in res.results:
            r.fe.write_vtu(out / f"needle_{r.force_N:g}N.vtu", frame=FRAME, force_N=r.force_N)
        write_series(out / "needle.pvd", [(r.force_N, f"needle_{r.force_N:g}N.vtm") for r in res.results])
        plot_deflection_curves(res, out / "needle_deflection.png")
        isolated(render_vtu, out / f"needle_{res.results[-1].force_N:g}N.vtu", out / "needle_deformed.png", scene(res))
    def new(out):
        write_outputs(res, out)
    t = {"old": [], "new": []}
    for i in range(3):
        for name, fn in (("old", old), ("new", new)):
            d = Path(tempfile.mkdtemp()) / "o"
            t0 = time.perf_counter(); fn(d); t[name].append(time.perf_counter() - t0)
            shutil.rmtree(d.parent)
    print({k: ["%.2f" % x for x in v] for k, v in t.items()}, "medians", {k: round(statistics.median(v), 2) for k, v in t.items()})
    
if __name__ == "__main__":
    main()
