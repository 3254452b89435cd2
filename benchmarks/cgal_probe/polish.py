"""The smooth route's own quality passes (gmsh optimiser, relocation with sliding interface nodes, sliver
removal, polish) on a CGAL labelled-image mesh: does the 10-degree goal become reachable?"""
import json, sys, time
import numpy as np, meshio
import os
SHIFT = float(os.environ.get("SHIFT", "1.0"))  # mm: a flat element this thin may change tissue (the route: 1/3 voxel)
from needletissue.geometry import smooth
from needletissue.geometry.relocate_kernel import min_dihedral

m = meshio.read(sys.argv[1])
info = json.load(open(sys.argv[2]))
ci = [i for i, c in enumerate(m.cells) if c.type == "tetra"]
cells = np.vstack([m.cells[i].data for i in ci]).astype(np.int64)
tag = np.concatenate([m.cell_data["medit:ref"][i] for i in ci]).astype(np.int64)
used, inv = np.unique(cells, return_inverse=True)
nodes, cells = m.points[used].astype(float), inv.reshape(-1, 4)
first = {}


def report(stage, t0):
    v = smooth.signed_volume(nodes, cells)
    md = min_dihedral(np.ascontiguousarray(nodes), np.ascontiguousarray(cells))
    vols = {int(l): abs(v[tag == l]).sum() for l in np.unique(tag)}
    err = {l: 100 * (vols[l] / (info["counts"][str(l)] * 27.0) - 1) for l in vols}
    first.setdefault("vols", vols)
    moved = max(abs(vols[l] / first["vols"][l] - 1) for l in vols) * 100
    print(f"{stage:28s} {len(cells):7d} tets  min {md.min():5.2f}  p1 {np.percentile(md, 1):5.2f}  <10: {(md < 10).sum():4d}"
          f"  worst vol {max(err.values(), key=abs):+.2f} %  tissue volumes moved <= {moved:.3f} %"
          f"  {time.process_time() - t0:6.1f} s CPU", flush=True)
t0 = time.process_time()
v = smooth.signed_volume(nodes, cells); cells[v < 0] = cells[v < 0][:, [0, 2, 1, 3]]
report("CGAL", t0)
nodes, cells, tag = smooth.gmsh_optimize(nodes, cells, tag, smooth.OPTIMIZE_THRESHOLD)
v = smooth.signed_volume(nodes, cells); cells[v < 0] = cells[v < 0][:, [0, 2, 1, 3]]
report("+ gmsh optimiser", t0)
fixed, slide, pinned = smooth._move_constraints(nodes, cells, tag, [])
nodes, n = smooth.relocate_nodes(nodes, cells, fixed, target_deg=smooth.RELOCATE_TARGET, slide=slide)
report(f"+ relocation ({n} moves)", t0)
nodes, cells, tag, n = smooth.remove_slivers(nodes, cells, tag, smooth.SLIVER_TARGET, SHIFT, pinned=pinned, frozen=[])
report(f"+ sliver removal ({n} ops)", t0)
nodes, n, worst = smooth.polish_nodes(nodes, cells, tag, smooth.POLISH_TARGET, [])
report(f"+ polish ({n} moves)", t0)
if worst < smooth.SLIVER_TARGET:
    pinned = smooth._move_constraints(nodes, cells, tag, [])[2]
    nodes, cells, tag, n = smooth.remove_slivers(nodes, cells, tag, smooth.SLIVER_TARGET, SHIFT, pinned=pinned, frozen=[])
    nodes, n2, _ = smooth.polish_nodes(nodes, cells, tag, smooth.POLISH_TARGET, [])
    report(f"+ 2nd pass ({n} ops, {n2} moves)", t0)
