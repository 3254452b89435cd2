"""Paper-scale needle model: linear tets, 1 mm needles, 3 mm elsewhere, ~1.33 M tets, 300 N."""
import json, time
from needletissue.models.needle import NeedleModelConfig, run_needle_model, with_geometry

if __name__ == "__main__":
    cfg = with_geometry(NeedleModelConfig(forces=(300.0,), order=1, formulation="mixed", ritz=True, progress=True),
                        needle_mesh_size=1.0, mesh_size=3.0, far_mesh_size=3.0, half_width=140.0)
    t = time.perf_counter()
    res = run_needle_model(cfg, "/tmp/paperscale/out")
    print("WALL", time.perf_counter() - t)
    d = res.to_dict() if hasattr(res, "to_dict") else res
    print(json.dumps({k: d[k] for k in ("mesh", "wall_time_s")}, default=str))
    print(json.dumps(d["results"], default=str)[:1500])
