"""Grading the smooth route (issue 16 items 1/4): the stages measured one by one on the example CT.

    PYTHONPATH=src python benchmarks/graded_smooth_stages.py [--far 12] [--filter 1] [--rounds 6] [--algorithm 1]

Stages (docs/pelvis_model.md, "Grading the smooth route: label simplification + gmsh reparametrisation"):
1. the route's label array (3 mm, pins' corridor cut out) simplified with the local target size
   h(d) = near + (far - near) * min(d / radius, 1), d the distance to the corridor: a 3^3 majority filter
   where h >= 3 voxels, then a 5^3 one where h >= 5 voxels (`--filter` scales the thresholds, 0: off);
2. the route's smooth shared interfaces (geometry.smooth.smooth_interfaces) of that array;
3. every interface patch (label pair, manifold component; the crop's flat cut faces apart from the skin;
   the fan of each vertex where a patch's boundary touches itself apart) a gmsh discrete surface,
   reparametrised (createGeometry) and remeshed to h (MeshAdapt); patches gmsh cannot reparametrise (closed
   pockets, pinched fans) keep their triangles, and so do the curves around them; patches whose new
   triangles cross another patch (edge_face_crossings, then TetGen's own check -d) or whose remeshing fails
   are put back and the stage repeated (`--rounds`);
4. TetGen on the remeshed interfaces plus the exact pins and clamp (the route's own call), if nothing crosses.
Each line: what the stage made, its CPU time, and the tissue volumes against the label map it started from.
Not the model's mesher: an experiment (not merged). Needs ../shared/data.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

ALGORITHM = 1   # gmsh 2D: MeshAdapt (Frontal-Delaunay, 6, failed with "Could not insert point" on a patch)


def simplify(arr, sp, near, far, radius, scale, corridor):
    """Distance-graded majority filter (stage 1). arr (z, y, x), sp (x, y, z) mm."""
    from scipy import ndimage

    d = ndimage.distance_transform_edt(arr != corridor, sampling=sp[::-1])
    h = near + (far - near) * np.clip(d / radius, 0, 1)
    out = arr.copy()
    labs = [int(v) for v in np.unique(arr) if v != corridor]
    for k in (1, 2):
        sel = (h >= (2 * k + 1) * sp.min() * scale) & (arr != corridor)
        if not sel.any():
            continue
        best = np.zeros(arr.shape, np.float32)
        arg = out.copy()
        for lab in labs:
            c = ndimage.uniform_filter((out == lab).astype(np.float32), 2 * k + 1, mode="nearest")
            m = c > best + 1e-6
            best[m], arg[m] = c[m], lab
        out[sel] = arg[sel]
    return out


def _components(P, F, pid):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    tri = np.tile(np.arange(len(F)), 3)
    key = e[:, 0] * len(P) + e[:, 1]
    o = np.argsort(key, kind="stable")
    key, tri = key[o], tri[o]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    cnt = np.diff(np.r_[start, len(key)])
    two = start[cnt == 2]
    a, b = tri[two], tri[two + 1]
    link = pid[a] == pid[b]
    return connected_components(coo_matrix((np.ones(link.sum()), (a[link], b[link])), shape=(len(F),) * 2),
                                directed=False)


def patches(P, F, BL):
    """Manifold components of each label-pair patch: (n, component of each triangle). The fan of every
    pinch vertex (where a patch's boundary touches itself: gmsh cannot reparametrise that) is a patch of its
    own, so that the rest can be remeshed."""
    pid = np.minimum(BL[:, 0], BL[:, 1]) * 256 + np.maximum(BL[:, 0], BL[:, 1])
    # triangles flat in one axis (the crop's cut faces, kept flat by the route) are patches of their own: the
    # skin and a cut face meet at a fold, and their union is often pinched there
    flat = np.ptp(P[F], axis=1) == 0
    pid = pid * 4 + np.where(flat.any(1), 1 + np.argmax(flat, 1), 0)
    for _ in range(3):
        n, comp = _components(P, F, pid)
        ok, order, bounds = parametrisable(F, comp, n)
        pinch = []
        for i in np.flatnonzero(~ok):
            ff = F[order[bounds[i]:bounds[i + 1]]]
            ee = np.sort(np.concatenate([ff[:, [0, 1]], ff[:, [1, 2]], ff[:, [2, 0]]]), axis=1)
            from needletissue.geometry.tetmesh import unique_rows
            first, _, cnt = unique_rows(ee)
            deg = np.bincount(ee[first][cnt == 1].ravel(), minlength=len(P))
            pinch.append(np.flatnonzero(deg > 2))
        pinch = np.concatenate(pinch) if pinch else np.zeros(0, np.int64)
        fan = np.isin(F, pinch).any(1)
        if not fan.any() or np.all(pid[fan] >= 1 << 40):
            break
        pid = np.where(fan, (1 << 40) + comp.astype(np.int64), pid)   # one fan patch per component it was cut from
    return _components(P, F, pid)


def parametrisable(F, comp, n):
    """Components whose boundary is simple loops (every boundary vertex on two boundary edges) and not empty."""
    from needletissue.geometry.tetmesh import unique_rows

    ok = np.zeros(n, bool)
    order = np.argsort(comp, kind="stable")
    bounds = np.searchsorted(comp[order], np.arange(n + 1))
    for i in range(n):
        ff = F[order[bounds[i]:bounds[i + 1]]]
        ee = np.sort(np.concatenate([ff[:, [0, 1]], ff[:, [1, 2]], ff[:, [2, 0]]]), axis=1)
        first, _, cnt = unique_rows(ee)
        be = ee[first][cnt == 1]
        ok[i] = len(be) > 0 and not np.any(cnt > 2) and np.bincount(be.ravel()).max() <= 2
    return ok, order, bounds


def remesh(P, F, BL, S, near, far, radius, keep):
    """Stage 3 once: gmsh reparametrisation + remeshing of the components not in `keep` (bool per component).
    Returns points, triangles, boundary labels, source component (-1-c: kept)."""
    import gmsh

    from needletissue.geometry.tetmesh import unique_rows

    n, comp = patches(P, F, BL)
    ok, order, bounds = parametrisable(F, comp, n)
    ok &= ~keep[:n] if len(keep) >= n else ok
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("graded")
        owner = np.zeros(len(P), int)
        for i in range(n):
            gmsh.model.addDiscreteEntity(2, i + 1)
        for i in range(n):
            ff = F[order[bounds[i]:bounds[i + 1]]]
            nn = np.unique(ff)
            nn = nn[owner[nn] == 0]
            owner[nn] = i + 1
            gmsh.model.mesh.addNodes(2, i + 1, nn + 1, P[nn].ravel())
            gmsh.model.mesh.addElementsByType(i + 1, 2, [], (ff + 1).ravel())
        gmsh.model.mesh.createTopology()
        bad = {i + 1 for i in range(n) if not ok[i]}
        curves = [(1, c) for _, c in gmsh.model.getEntities(1)
                  if not any(int(u) in bad for u in gmsh.model.getAdjacencies(1, c)[0])]
        gmsh.model.mesh.createGeometry(curves + [(2, i + 1) for i in range(n) if ok[i]])
        gmsh.model.removeEntities([(2, t) for t in sorted(bad)])   # kept as they are, outside gmsh
        f = gmsh.model.mesh.field
        f.add("Distance", 1)
        pts = [gmsh.model.geo.addPoint(*x) for x in S[::max(1, len(S) // 3000)]]
        gmsh.model.geo.synchronize()
        f.setNumbers(1, "PointsList", pts)
        f.add("Threshold", 2)
        for k, v in dict(InField=1, SizeMin=near, SizeMax=far, DistMin=0, DistMax=radius).items():
            f.setNumber(2, k, v)
        f.setAsBackgroundMesh(2)
        for k, v in dict(MeshSizeExtendFromBoundary=0, MeshSizeFromPoints=0, MeshSizeFromCurvature=0,
                         Algorithm=ALGORITHM).items():
            gmsh.option.setNumber("Mesh." + k, v)
        gmsh.model.mesh.generate(2)
        nt, nx, _ = gmsh.model.mesh.getNodes()
        X = np.full((int(nt.max()) + 1, 3), np.nan)
        X[nt.astype(int)] = nx.reshape(-1, 3)
        comp_bl = np.zeros((n, 2), np.int64)
        comp_bl[comp] = BL
        tr, lab, src, nan = [], [], [], []
        for _, s in gmsh.model.getEntities(2):
            el = gmsh.model.mesh.getElements(2, s)[2]
            t = np.asarray(el[0] if len(el) else [], np.int64).reshape(-1, 3)
            if np.isnan(X[t]).any():
                nan.append(s)
            tr.append(t)
            lab.append(np.repeat(comp_bl[s - 1][None], len(t), 0))
            src.append(np.full(len(t), s - 1))
    finally:
        gmsh.finalize()
    for t in sorted(bad):
        sel = order[bounds[t - 1]:bounds[t]]
        tr.append(F[sel] + len(X))
        lab.append(BL[sel])
        src.append(np.full(len(sel), -t))
    X = np.vstack([X, P])
    T, L, SRC = np.concatenate(tr), np.concatenate(lab), np.concatenate(src)
    used, inv = np.unique(T, return_inverse=True)
    T, X = inv.reshape(T.shape), X[used]
    first, inv, _ = unique_rows(np.round(np.nan_to_num(X, nan=-1e9) * 1e6).astype(np.int64))   # gmsh points = old
    T, X = inv[T], X[first]
    return X, T, L, SRC, n, int(len(bad)), nan


def tetgen_skipped(points, faces):
    """Input triangles TetGen's intersection check (-d) skips (it writes them to a file in the working
    directory): indices into faces. Catches what edge_face_crossings does not (exactly touching segments)."""
    import contextlib
    import io
    import os
    import tempfile

    import tetgen

    from needletissue.geometry.tetmesh import unique_rows

    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        os.chdir(tmp)
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                try:
                    tetgen.TetGen(points, faces.astype(np.int32)).tetrahedralize(switches="pdQ")
                except Exception:
                    pass
            f = os.path.join(tmp, "tetgen-tmpfile_skipped.face")
            bad = np.loadtxt(f, skiprows=1, usecols=(1, 2, 3), ndmin=2).astype(np.int64) if os.path.exists(f) \
                else np.zeros((0, 3), np.int64)
        finally:
            os.chdir(cwd)
    if not len(bad):
        return np.zeros(0, np.int64)
    both = np.vstack([np.sort(faces, 1), np.sort(bad, 1)])
    _, inv, _ = unique_rows(both)
    return np.flatnonzero(np.isin(inv[:len(faces)], inv[len(faces):]))


def main():
    from needletissue.geometry import pelvis as gp
    from needletissue.geometry import smooth
    from needletissue.geometry.tetmesh import MeshConfig, unique_rows
    from needletissue.imaging.segment import segment

    ap = argparse.ArgumentParser()
    ap.add_argument("--near", type=float, default=3.0)
    ap.add_argument("--far", type=float, default=12.0)
    ap.add_argument("--radius", type=float, default=35.0)
    ap.add_argument("--filter", type=float, default=1.0)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--algorithm", type=int, default=ALGORITHM, help="gmsh Mesh.Algorithm for the patches")
    a = ap.parse_args()
    globals()["ALGORITHM"] = a.algorithm
    rows = []

    def row(stage, made, cpu, note=""):
        rows.append(f"| {stage} | {made} | {cpu:.1f} | {note} |")
        print(rows[-1], flush=True)

    cap, name = {}, {}
    orig = smooth.smooth_interfaces

    def interfaces(arr, spacing, **kw):   # stage 1 hooked in front of the route's own stage 2
        sp = np.asarray(spacing, float)
        t = time.process_time()
        out = simplify(arr, sp, a.near, a.far, a.radius, a.filter, smooth.CORRIDOR) if a.filter > 0 else arr
        cap["arr0"], cap["arr1"], cap["vox"] = arr, out, float(np.prod(sp))
        v0, v1 = np.bincount(arr.ravel(), minlength=256), np.bincount(out.ravel(), minlength=256)
        row("1 label simplification", f"{int(np.count_nonzero(out != arr)):,} voxels changed", time.process_time() - t,
            "vs label map: " + ", ".join(f"{name[k]} {100 * (v1[k] / v0[k] - 1):+.1f} %" for k in np.flatnonzero(v0[1:255]) + 1))
        t = time.process_time()
        s = orig(out, spacing, **kw)
        cap["surf"], cap["t_surf"] = s, time.process_time() - t
        return s

    class Stop(Exception):
        pass

    def tetgen(points, faces, cfg, bound):
        cap["plc"] = (points, faces)
        raise Stop

    orig_tg = smooth._tetgen
    smooth.smooth_interfaces, smooth._tetgen = interfaces, tetgen
    t = time.process_time()
    vol = gp.ct_label_volume()
    site = gp.standard_site(vol)
    vol = gp.crop_to_site(vol, site)
    d = gp.data_dir() / "pelvis_ct"
    seg = segment(d / "example_ct.nii.gz", d / "example_seg_fast_force_split.nii.gz")
    name.update({i: n.removesuffix("_right") for n, i in seg.tissues.items()})
    name[seg.tissues["cancellous_bone"]] = "bone"   # the route meshes one bone region
    row("0 label volume + segmentation", "", time.process_time() - t)
    t = time.process_time()
    try:
        gp.build_mesh_smooth(seg, vol, site, mesh_size=a.near)
    except Stop:
        pass
    finally:
        smooth.smooth_interfaces, smooth._tetgen = orig, orig_tg
    s = cap["surf"]
    P, F, BL = s.points, s.faces, s.boundary_labels
    plcP, plcF = cap["plc"]
    S, SF = plcP[len(P):], plcF[len(F):] - len(P)
    v_lab = np.bincount(cap["arr0"].ravel(), minlength=256) * cap["vox"]
    tissues = np.flatnonzero(v_lab[1:255] > 0) + 1

    def vs_labels(X, T, L):
        v = smooth.label_volumes(X, T, L)
        return "vs label map: " + ", ".join(f"{name[k]} {100 * (v[k] / v_lab[k] - 1):+.1f} %" for k in tissues)

    row("2 smooth interfaces (3 mm)", f"{len(F):,} triangles (+ {len(SF):,} on pins / clamp)", cap["t_surf"],
        vs_labels(P, F, BL))
    keep = np.zeros(len(F), bool)
    for r in range(a.rounds):
        t = time.process_time()
        X, T, L, SRC, n, kept, nan = remesh(P, F, BL, S, a.near, a.far, a.radius, keep)
        PP, FF = np.vstack([X, S]), np.vstack([T, SF + len(X)])
        e, f = smooth.edge_face_crossings(PP, FF) if not nan else (np.zeros(0, int), np.zeros(0, int))
        edges = smooth.unique_edges(FF)
        hit = np.unique(np.r_[SRC[f[f < len(T)]], [s - 1 for s in nan]])
        # the components of the crossing edges' triangles as well
        ein = np.isin(FF[:len(T)], edges[e]).sum(1) >= 2
        hit = np.unique(np.r_[hit, SRC[ein]])
        hit = hit[hit >= 0]
        first, _, cnt = unique_rows(np.sort(FF, 1))   # a triangle two patches both made: once
        once = np.zeros(len(FF), bool)
        once[first] = True
        FF = FF[once]
        skipped = tetgen_skipped(PP, FF) if len(e) == 0 and not nan else np.zeros(0, np.int64)
        hit = np.unique(np.r_[hit, SRC[np.flatnonzero(once[:len(T)])[skipped[skipped < once[:len(T)].sum()]]]])
        hit = hit[hit >= 0].astype(np.int64)
        row(f"3 gmsh remesh, round {r + 1}", f"{len(T):,} triangles; {n} patches, {kept} kept; "
            f"{len(e)} crossings, {len(skipped)} skipped by TetGen -d, {len(nan)} failed", time.process_time() - t,
            vs_labels(X, T, L))
        if len(e) == 0 and not nan and len(skipped) == 0:
            break
        keep[hit] = True
    else:
        print("| 4 TetGen | not run: the remeshed interfaces still cross | - | |")
        return
    t = time.process_time()
    nodes, elem, attr = smooth._tetgen(PP, FF, MeshConfig(size=a.near, method="smooth"), None)
    q = smooth.vol_min_dihedral(nodes[elem])[1]
    row("4 TetGen (before the route's optimisation)", f"{len(elem):,} tets, {len(nodes):,} nodes",
        time.process_time() - t, f"min / 1st pct dihedral {q.min():.1f} / {np.percentile(q, 1):.1f} deg")


if __name__ == "__main__":
    main()
