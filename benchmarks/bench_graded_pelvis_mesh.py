"""Quality / fidelity / speed of the anatomical model's smooth mesh (`fe pelvis --mesher smooth`): the uniform
surface-nets route against the graded CGAL route (geometry.graded), on the model crop of the example CT (or of the
SSM's label volume) with the needles and the clamp inserted exactly.

    PYTHONPATH=src python benchmarks/bench_graded_pelvis_mesh.py [--source ct|ssm] [--sizes 3] [--far 4] [--uniform]

Each row is one `build_mesh_smooth` (the label map made once before, as `fe pelvis --mesher smooth` makes it). Fidelity is geometry.fidelity's on the
tissue regions (the label map the mesh was made from; the needles and the clamp are left out, so the voxels
they occupy count as outside in Dice). Goals (issue 16): min dihedral >= 10 deg, 1st percentile >= 20 deg;
every tissue within 3 % of its label volume; Dice >= 0.9 for bone and muscles; Hausdorff 95 % <= one voxel;
CT -> mesh < 60 s. Times include the CGAL helper's run (a child process), not its one-off compilation.
"""

from __future__ import annotations

import argparse
import os
import resource
import time

MUSCLES = ("gluteus_maximus", "gluteus_medius", "gluteus_minimus", "iliopsoas")


def _cpu():
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def row(seg, v, site, size, far):
    from needletissue.geometry import pelvis as gp
    from needletissue.geometry import tetmesh
    from needletissue.geometry.fidelity import mesh_fidelity

    seen = {}
    orig = tetmesh.tet_mesh

    def capture(seg_, *a, config=None, **kw):
        seen["config"], seen["mesh"] = config, orig(seg_, *a, config=config, **kw)
        return seen["mesh"]

    tetmesh.tet_mesh = capture
    try:
        t, c = time.perf_counter(), _cpu()
        pm = gp.build_mesh_smooth(seg, v, site, mesh_size=size, far_size=far)
        wall, cpu = time.perf_counter() - t, _cpu() - c
    finally:
        tetmesh.tet_mesh = orig
    tm = seen["mesh"]
    fid = mesh_fidelity(seg, tm, seen["config"], solids=[n for n in tm.regions if n not in seg.tissues])
    names = [n for n in fid.volume_error if n not in ("cortical_bone", "cancellous_bone")]
    worst = max(names, key=lambda n: abs(fid.volume_error[n]))
    dice_keys = [k for k in fid.dice if k == "bone" or k.removesuffix("_right").removesuffix("_left") in MUSCLES]
    return {"route": "uniform" if far is None or far <= size else f"graded -> {far:g}", "size": size,
            "tets": len(pm.cells), "wall_s": wall, "cpu_s": cpu, "min": fid.min_dihedral_deg,
            "p01": fid.p01_dihedral_deg, "below10": fid.n_below_10deg, "worst": (worst, fid.volume_error[worst]),
            "dice_min": min((fid.dice[k], k) for k in dice_keys), "h95": fid.hausdorff95_voxels,
            "errors": fid.volume_error}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[3.0], help="element sizes at the needles, mm")
    ap.add_argument("--far", type=float, default=4.0, help="far size as a multiple of the size (graded rows)")
    ap.add_argument("--uniform", action="store_true", help="also the uniform surface-nets route at each size")
    ap.add_argument("--source", choices=("ct", "ssm"), default="ct", help="the example CT or the mean SSM")
    a = ap.parse_args()
    from needletissue.geometry import pelvis as gp
    from needletissue.models.pelvis.model import PelvisConfig, smooth_label_map

    t = time.perf_counter()
    seg, vol = smooth_label_map(PelvisConfig(source=a.source, mesher="smooth"))
    seg_wall = time.perf_counter() - t
    site = gp.standard_site(vol, "supra_acetabular")
    v = gp.crop_to_site(vol, site)
    print(f"{a.source}: label map {seg_wall:.1f} s wall; load average {os.getloadavg()[0]:.1f}")
    print("| route | size (mm) | tets | wall / CPU (s) | min / 1st pct dihedral (deg), < 10 | worst tissue volume |"
          " min Dice (bone, muscles) | Hausdorff 95 % (voxels) |")
    print("|---|---|---|---|---|---|---|---|")
    for size in a.sizes:
        for far in ([None] if a.uniform else []) + [a.far * size]:
            r = row(seg, v, site, size, far)
            print(f"| {r['route']} | {size:g} | {r['tets']:,} | {r['wall_s']:.1f} / {r['cpu_s']:.1f} | "
                  f"{r['min']:.2f} / {r['p01']:.2f}, {r['below10']} | {r['worst'][0]} {100 * r['worst'][1]:+.1f} % | "
                  f"{r['dice_min'][0]:.3f} ({r['dice_min'][1]}) | {r['h95']:.2f} |", flush=True)
            print("  volumes: " + ", ".join(f"{k} {100 * e:+.1f} %" for k, e in r["errors"].items()), flush=True)


if __name__ == "__main__":
    main()
