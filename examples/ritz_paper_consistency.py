"""Paper consistency of the Ritz model: which (d, l) give 17.63 mm at 300 N, the w(300)/w(100) bound,
the paper's FE growth, Vesic's k next to Table 1, and the paper's Fig. 5 for the chosen defaults.

    MPLBACKEND=Agg python examples/ritz_paper_consistency.py [OUT_DIR]   (default docs/figures)

Writes ritz_fig5.png, ritz_consistency.png and ritz_consistency.json (+ config/versions/results).
"""

import sys
from pathlib import Path

import numpy as np

from needletissue import ritz
from needletissue.ritz import paper
from needletissue.ritz.foundation import vesic_k
from needletissue.runinfo import write_json, write_run_files

out = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/figures")
model = ritz.RitzModel()
results = ritz.solve_forces([100.0, 200.0, 300.0], model)
ritz.plot_deflection(results, out / "ritz_fig5.png", model=model,
                     title="Paper Fig. 5 (Ritz, p = 3): d = 5 mm, l = 84.18 mm")
curve = paper.curve_17_63()
rmap = paper.ratio_map()
paper.plot_consistency(out / "ritz_consistency.png", curve, rmap)
d25, l25 = paper.match_two_numbers(2.5008)
auto = ritz.solve_forces([100.0, 200.0, 300.0], model, order="auto")
summary = {
    "defaults": model.to_dict(),
    "tip_mm_p3": {r.force_N: r.tip_deflection_mm for r in results},
    "tip_mm_auto": {r.force_N: [r.tip_deflection_mm, r.order, r.error_estimate_mm] for r in auto},
    "ratio_300_100_p3": results[2].tip_deflection_mm / results[0].tip_deflection_mm,
    "curve_17_63": {"diameter_mm": curve.diameter_mm, "free_length_mm": curve.free_length_mm,
                    "tip_100_mm": curve.tip_100_mm, "ratio_300_100": curve.ratio_300_100},
    "max_ratio_in_map": max(float(np.max(v)) for k, v in rmap.items() if k != "k_scale"),
    "reading_to_250_08_percent": {"diameter_mm": d25, "free_length_mm": l25},
    "fe_growth": paper.fe_growth(),
    "vesic_k": {f"{name} E={E} nu={nu}": vesic_k(E, nu) for name, E in (("muscle", 0.14), ("adipose", 0.06))
                for nu in (0.45, 0.49)},
}
write_json(out / "ritz_consistency.json", summary)
write_run_files(out, model.to_dict(), summary)
for k, v in summary.items():
    print(k, v)
