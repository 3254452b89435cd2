"""Needle model: paper interfaces (needle-muscle 0.3, muscle-bone 0.3, bone-needle 0.9) vs bonded.

One needle, coarse mesh, 100/200/300 N. Writes results/contact_needle/ (config.toml, versions.json,
results.json). Run: nice python examples/contact_needle_compare.py  (about 10-20 min on 2 cores).
"""

import dataclasses
import sys
from pathlib import Path

from needletissue.models.contact import compare_interfaces
from needletissue.models.needle import NeedleModelConfig, with_geometry
from needletissue.runinfo import write_run_files

out = Path(sys.argv[1] if len(sys.argv) > 1 else "results/contact_needle")
cfg = with_geometry(NeedleModelConfig(progress=True), needles=1, needle_mesh_size=2.5, mesh_size=6)
res = compare_interfaces(cfg)
results = {"interfaces": res.interfaces, "settings": res.settings,
           "rows": [dataclasses.asdict(r) for r in res.rows],
           "wall_time_bonded_s": res.wall_time_bonded_s, "wall_time_contact_s": res.wall_time_contact_s,
           "cost_ratio": res.cost_ratio}
write_run_files(out, {"needles": 1, "needle_mesh_size_mm": 2.5, "mesh_size_mm": 6,
                      "forces_N": list(cfg.forces), "interfaces": "paper"}, results)
for r in res.rows:
    print(r)
print(f"cost ratio contact/bonded: {res.cost_ratio:.2f} ({res.wall_time_contact_s:.0f} s / {res.wall_time_bonded_s:.0f} s)")
