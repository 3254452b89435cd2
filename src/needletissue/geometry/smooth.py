"""Smooth, conforming multi-tissue surfaces and tetrahedral meshes from a label map.

Route (one path from the label map to the mesh, `tet_mesh(..., method="smooth")`):
1. label map restricted / cropped / coarsened as for the voxel route (tetmesh._crop_and_coarsen), the two
   bone labels merged (the cortex is a one-voxel rule-based shell at 3 mm: see below);
2. edge contacts removed: a 2 x 2 voxel square whose diagonal carries one label and whose other two
   voxels carry others makes two sheets meet along a voxel edge; smoothed, they cross. The square is
   filled with the diagonal's label (a few hundred voxels of a CT, reported);
3. every interface between two labels (incl. background) as ONE triangle set: VTK SurfaceNets3D
   (PyVista `contour_labels`) with its constrained smoothing (each vertex moves at most
   `smoothing_scale` x the voxel diagonal; triple lines are smoothed as curves, so interfaces stay shared);
4. self-intersections repaired: the edge-triangle crossings (ipctk LBVH broad phase + exact segment /
   triangle test) are undone by pulling the vertices involved back towards their unsmoothed
   positions (which are exact voxel faces, intersection-free), halving their move until none is left;
5. TetGen on that PLC with region attributes (-A): each closed subdomain gets one attribute; its
   tissue is the volume-weighted majority label of its tetrahedra's centroids, so every tetrahedron of a
   subdomain has the same tissue and tissue boundaries are the smooth interfaces (no centroid staircase);
6. element optimisation with the interfaces fixed: gmsh's optimiser (gmsh_optimize), then a local
   relocation of the nodes of elements below 20 deg (relocate_nodes); interior nodes move freely, nodes
   on a smooth patch of one interface slide in its tangent plane (sliding_normals), because the worst
   elements have all four nodes on interfaces (measured on the CT);
7. sliver removal (remove_slivers): what step 6 leaves below the goal are flat elements capping an
   interface edge; 2-3 flips and edge removals within one tissue, a flat element (<= 1/3 voxel thick)
   handed to the tissue across its interface (an interface edge flip), interior edge splits and, last,
   collapses of edges <= 1/3 voxel; then step 6's relocation once more on the stars of the elements
   below 20 deg (polish_nodes: the splits' new nodes and the flips' new elements had not been
   relocated), and one more sliver pass + relocation if that leaves an element below the sliver target;
8. bone split back into cortical / cancellous per tetrahedron (the split is a rule, see imaging.segment),
   after steps 6-7: the split is no interface, so its element-staircase nodes are free during them. Each
   element's cortical fraction is sampled on the label map and the cortex keeps the label map's share of
   the bone volume (split_cortex).
See docs/imaging.md for the measured quality and fidelity.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from needletissue.errors import InputError

BONE = ("cortical_bone", "cancellous_bone")
COINCIDENT = 0.02   # smoothed points closer than this (x the voxel spacing) are pulled back
MIN_TRIANGLE_ANGLE = 15.0   # degrees; vertices of thinner interface triangles are pulled back (raw: 45)


def fix_edge_contacts(arr: np.ndarray, max_iter: int = 30) -> tuple[np.ndarray, int]:
    """Fill every 2x2 voxel square whose one diagonal is a label the other two voxels lack.

    Returns the new array and the number of voxels changed. Deterministic (fixed sweep order).
    """
    a = np.array(arr, copy=True)
    for _ in range(max_iter):
        n = 0
        for ax in range(3):
            for ay in range(ax + 1, 3):
                def sl(i, j):
                    t = [slice(None)] * 3
                    t[ax] = slice(i, a.shape[ax] - 1 + i)
                    t[ay] = slice(j, a.shape[ay] - 1 + j)
                    return tuple(t)
                p00, p11, p01, p10 = a[sl(0, 0)], a[sl(1, 1)], a[sl(0, 1)], a[sl(1, 0)]
                bad1 = (p00 == p11) & (p01 != p00) & (p10 != p00)
                bad2 = (p01 == p10) & (p00 != p01) & (p11 != p01) & ~bad1
                for bad, src, dst in ((bad1, (0, 0), (0, 1)), (bad2, (0, 1), (0, 0))):
                    idx = np.argwhere(bad)
                    if len(idx) == 0:
                        continue
                    si, di = idx.copy(), idx.copy()
                    si[:, ax] += src[0]
                    si[:, ay] += src[1]
                    di[:, ax] += dst[0]
                    di[:, ay] += dst[1]
                    a[tuple(di.T)] = a[tuple(si.T)]
                    n += len(idx)
        if n == 0:
            break
    return a, int(np.count_nonzero(a != arr))


def triangle_min_angle(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Smallest interior angle of each triangle, degrees."""
    t = points[faces]
    out = np.full(len(faces), 180.0)
    for i in range(3):
        a, b = t[:, (i + 1) % 3] - t[:, i], t[:, (i + 2) % 3] - t[:, i]
        c = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
        out = np.minimum(out, np.degrees(np.arccos(np.clip(c, -1, 1))))
    return out


def unique_edges(faces: np.ndarray) -> np.ndarray:
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    e.sort(axis=1)
    key = np.unique(e[:, 0] * (int(e.max()) + 1) + e[:, 1])
    return np.stack([key // (int(e.max()) + 1), key % (int(e.max()) + 1)], 1)


def edge_face_crossings(points: np.ndarray, faces: np.ndarray, edges: np.ndarray | None = None):
    """(edge ids, face ids) of triangle-set edges that cross a triangle they share no vertex with.

    Every transversal intersection of two triangles shows as such a crossing (the intersection segment
    ends where an edge of one pierces the other); touching on boundaries (voxel faces) is not counted.
    """
    import ipctk

    if edges is None:
        edges = unique_edges(faces)
    P = np.asfortranarray(points, float)
    bp = ipctk.LBVH()
    bp.build(P, np.asfortranarray(edges, np.int32), np.asfortranarray(faces, np.int32), 0.0)
    c = bp.detect_edge_face_candidates()
    if not c:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ef = np.array([(x.edge_id, x.face_id) for x in c], np.int64)
    e, f = ef[:, 0], ef[:, 1]
    E, F = edges[e], faces[f]
    share = (F[:, :, None] == E[:, None, :]).any(axis=(1, 2))
    e, f = e[~share], f[~share]
    o = points[edges[e, 0]]
    d = points[edges[e, 1]] - o
    v0 = points[faces[f, 0]]
    e1, e2 = points[faces[f, 1]] - v0, points[faces[f, 2]] - v0
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    ok = np.abs(det) > 1e-10 * scale           # not parallel (coplanar voxel faces only touch)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = o - v0
    u = np.einsum("ij,ij->i", s, h) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    eps = 1e-9
    hit = ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)
    return e[hit], f[hit]


@dataclass
class InterfaceSurfaces:
    """All tissue interfaces as one conforming triangle set (grid coordinates: index * spacing)."""

    points: np.ndarray
    faces: np.ndarray
    boundary_labels: np.ndarray          # (n_faces, 2) labels on the two sides
    info: dict = field(default_factory=dict)


class CorridorTooNarrow(InputError):
    """The solids' edges cross the tissue interfaces: the corridor of voxels relabelled around them is narrower than
    the interfaces' deviation from it (a voxel, or a graded mesh's element there)."""


@dataclass
class Solids:
    """Closed solids (needles, clamp) meshed exactly into the smooth route, LPS mm.

    points, faces: ONE conforming triangle set of all their surfaces (faces shared by two solids listed
    once), at the element size wanted on them. label(points, grow) -> index into names of the solid
    holding each point when every solid is grown by `grow` mm, -1 outside all. The label map is replaced by
    a corridor within `margin` mm of the solids (its smoothed wall stays clear of them); the corridor
    elements outside the solids take the tissue of the voxel at their centroid after the optimisation."""

    names: list
    points: np.ndarray
    faces: np.ndarray
    label: object
    margin: float


CORRIDOR = 255      # label of the corridor around the solids while meshing
SOLID0 = 240        # label of the first solid while meshing


def label_volumes(points, faces, boundary_labels, n_labels: int = 256) -> np.ndarray:
    """Volume enclosed by each label's interfaces (surface-nets faces point out of boundary_labels[:, 0])."""
    v = np.einsum("ij,ij->i", points[faces[:, 0]], np.cross(points[faces[:, 1]], points[faces[:, 2]])) / 6.0
    return (np.bincount(boundary_labels[:, 0], v, n_labels) - np.bincount(boundary_labels[:, 1], v, n_labels))


def restore_volumes(points, faces, boundary_labels, target, fixed, iterations: int = 3, fixed_labels=()):
    """Offset the interfaces along their normals so that each label encloses its `target` volume.

    Laplacian smoothing shrinks convex regions. Each label L gets a potential phi_L (phi of the
    background 0 = 0); the interface between a and b moves by phi_a - phi_b along its normal (out of a),
    which changes vol(L) by sum_M A_LM (phi_L - phi_M). That graph-Laplacian system is solved for the volume
    deficits, vertex moves are the area-weighted means over their faces, repeated `iterations` times
    (linearisation). Vertices in `fixed` do not move; labels in `fixed_labels` keep phi = 0 like the
    background (their faces are fixed: their volume is not theirs to restore). Returns the new points.
    """
    x = np.array(points, float, copy=True)
    a, b = boundary_labels[:, 0], boundary_labels[:, 1]
    labs = np.unique(boundary_labels)
    pos = np.full(int(labs.max()) + 1, -1)
    pos[labs] = np.arange(len(labs))
    ia, ib = pos[a], pos[b]
    for _ in range(iterations):
        t = x[faces]
        nA = 0.5 * np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])   # area vector, out of label a
        A = np.linalg.norm(nA, axis=1)
        deficit = target[labs] - label_volumes(x, faces, boundary_labels, len(target))[labs]
        K = np.zeros((len(labs), len(labs)))
        np.add.at(K, (ia, ia), A)
        np.add.at(K, (ib, ib), A)
        np.add.at(K, (ia, ib), -A)
        np.add.at(K, (ib, ia), -A)
        free = ~np.isin(labs, (0, *fixed_labels))
        phi = np.zeros(len(labs))
        phi[free] = np.linalg.lstsq(K[np.ix_(free, free)], deficit[free], rcond=None)[0]
        s = phi[ia] - phi[ib]                                          # mm, along the unit normal
        u = np.zeros_like(x)
        w = np.zeros(len(x))
        for k in range(3):
            np.add.at(u, faces[:, k], (s / np.maximum(A, 1e-300))[:, None] * nA * A[:, None])
            np.add.at(w, faces[:, k], A)
        u /= np.maximum(w, 1e-300)[:, None]
        u[fixed] = 0.0
        x += u
    return x


def smooth_interfaces(arr: np.ndarray, spacing, *, iterations: int = 16, scale: float = 0.3,
                      relaxation: float = 0.5, max_repair: int = 12, restore: bool = True,
                      flat=None) -> InterfaceSurfaces:
    """Surface nets of a label array (z, y, x), constrained smoothing, intersections repaired.

    flat: (lo, hi) voxel index ranges (x, y, z) whose border planes stay flat (default: the array's; a
    padded array passes its crop's)."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    from needletissue.geometry.tetmesh import unique_rows

    sp = np.asarray(spacing, float)
    arr, n_fixed = fix_edge_contacts(arr)
    grid = pv.ImageData(dimensions=arr.shape[::-1], spacing=sp)
    grid.point_data["labels"] = np.ascontiguousarray(arr).ravel()
    kw = dict(output_mesh_type="triangles", pad_background=True, scalars="labels")
    raw = grid.contour_labels("all", smoothing=False, **kw)
    sm = grid.contour_labels("all", smoothing=iterations > 0, smoothing_iterations=int(iterations),
                             smoothing_relaxation=float(relaxation), smoothing_scale=float(scale), **kw)
    if raw.n_points != sm.n_points or sm.n_cells == 0:
        raise InputError("labels", "surface nets: smoothed and raw point sets differ")  # VTK contract
    x0 = np.asarray(raw.points, float)
    x1 = np.asarray(sm.points, float)
    faces = np.asarray(sm.regular_faces, np.int64)
    bl = np.asarray(sm.cell_data["boundary_labels"]).astype(np.int64)
    # where a tissue touches itself at a voxel corner, surface nets emits coincident points (a pinch);
    # smoothed apart they open a hole in the interface. Merge them and keep them at the corner.
    first, rep, _ = unique_rows(np.round(x0 / sp * 1e6).astype(np.int64))   # np.unique(axis=0): 10x slower
    canon = first[rep]
    pinch = canon != np.arange(len(x0))
    faces = canon[faces]
    keep = (bl[:, 0] != bl[:, 1]) & (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) \
        & (faces[:, 0] != faces[:, 2])
    faces, bl = faces[keep], bl[keep]
    pinched = np.zeros(len(x0), bool)
    pinched[canon[pinch]] = True
    used, inv = np.unique(faces, return_inverse=True)     # drop the merged duplicates
    faces = inv.reshape(faces.shape)
    x0, x1, pinched = x0[used], x1[used], pinched[used]
    edges = unique_edges(faces)
    # vertices on the image / crop border planes stay put: the cut faces stay flat and its corners sharp
    idx = x0 / sp
    lo, hi = (np.zeros(3), np.asarray(arr.shape[::-1], float)) if flat is None else np.asarray(flat, float)
    on_border = np.any(np.isclose(idx, lo - 0.5) | np.isclose(idx, hi - 0.5), axis=1)
    w = np.where(on_border | pinched, 0.0, 1.0)
    vol0 = label_volumes(x0, faces, bl)   # = the voxel volumes (raw faces are voxel faces)
    vol_s = label_volumes(x1, faces, bl)
    if restore and iterations > 0:
        x1 = restore_volumes(x1, faces, bl, vol0, on_border | pinched)
    vol_r = label_volumes(x1, faces, bl)
    history = []
    for _ in range(max_repair):
        x = x0 + w[:, None] * (x1 - x0)
        e, f = edge_face_crossings(x, faces, edges)
        # points that smoothing made (nearly) coincide, e.g. across a one-voxel gap
        close = np.asarray(sorted(cKDTree(x).query_pairs(COINCIDENT * float(sp.min()))), np.int64).reshape(-1, 2)
        thin = faces[triangle_min_angle(x, faces) < MIN_TRIANGLE_ANGLE]
        history.append(int(len(e) + len(close) + len(thin)))
        if len(e) == 0 and len(close) == 0 and len(thin) == 0:
            break
        bad = np.unique(np.concatenate([edges[e].ravel(), faces[f].ravel(), close.ravel(), thin.ravel()]))
        w[bad] = np.where(w[bad] > 0.1, 0.5 * w[bad], 0.0)
    else:
        x = x0 + w[:, None] * (x1 - x0)
        if len(edge_face_crossings(x, faces, edges)[0]):
            raise InputError("labels", "smoothed interfaces still intersect after repair")
    open_edges = 0
    for lab in np.unique(bl):
        fl = faces[(bl[:, 0] == lab) | (bl[:, 1] == lab)]
        e = np.sort(np.concatenate([fl[:, [0, 1]], fl[:, [1, 2]], fl[:, [2, 0]]]), axis=1)
        open_edges += int(np.count_nonzero(unique_rows(e)[2] % 2))
    if open_edges:   # a tissue whose interfaces do not close would merge with its neighbour in TetGen
        raise InputError("labels", f"smoothed interfaces leave {open_edges} open edge(s)")
    moved = np.linalg.norm(x - x0, axis=1)
    present = np.flatnonzero(vol0[1:] > 0) + 1
    rel = lambda v: {int(k): float(v[k] / vol0[k] - 1) for k in present}  # noqa: E731
    vol_f = label_volumes(x, faces, bl)
    info = {"voxels_changed_edge_contacts": n_fixed, "n_points": int(len(x)), "n_triangles": int(len(faces)),
            "crossings_per_repair_pass": history, "border_vertices_fixed": int(on_border.sum()),
            "pinch_points_merged": int(pinch.sum()), "vertices_pulled_back": int(np.count_nonzero(w < 1)),
            "volume_change_smoothed": rel(vol_s), "volume_change_restored": rel(vol_r),
            "volume_change_final": rel(vol_f), "max_move_mm": float(moved.max()), "mean_move_mm": float(moved.mean())}
    return InterfaceSurfaces(points=x, faces=faces, boundary_labels=bl, info=info)


def _tetgen(points, faces, cfg, bound):
    import tetgen

    ratio, dihedral = cfg.tetgen_bounds()
    tg = tetgen.TetGen(np.asarray(points, float), np.asarray(faces, np.int32))
    try:
        nodes, elem, attr, _ = tg.tetrahedralize(
            plc=True, quality=True, minratio=ratio, mindihedral=dihedral,
            fixedvolume=bound is not None, maxvolume=-1.0 if bound is None else float(bound),
            regionattrib=True, optmaxdihedral=OPT_MAX_DIHEDRAL, opt_iterations=OPT_ITERATIONS,
            smooth_cirterion=1 if TETGEN_SMOOTHING else 0, smooth_maxiter=TETGEN_SMOOTHING,
            quiet=True, nowarning=True)
    except RuntimeError as exc:
        raise InputError("mesh", f"TetGen failed on the smoothed tissue interfaces: {exc}") from None
    return np.asarray(nodes, float), np.asarray(elem, np.int64)[:, :4], np.asarray(attr).ravel()


def gmsh_optimize(points: np.ndarray, cells: np.ndarray, tag: np.ndarray, threshold: float = 0.5,
                  workers: int = 2):
    """gmsh's tetrahedron optimiser (edge/face swaps, node relocation) on a multi-region mesh whose
    interface and boundary nodes stay fixed: they sit on one discrete surface, each region is a discrete
    volume of its own, so no element changes region and no interface moves. Elements with gmsh quality
    (gamma) below `threshold` are worked on. Returns (points, cells, tag), nodes renumbered.

    The regions are independent (their shared nodes are fixed), so with `workers` 2 the tissues are split
    into two groups of about equal element count, one optimised in a child process while this one does
    the other: gmsh's optimiser is single-threaded. Same result as one process (the per-region passes
    do not see each other)."""
    labels = np.unique(tag)
    groups = [labels]
    if workers > 1 and len(labels) > 1:
        counts = np.bincount(np.searchsorted(labels, tag), minlength=len(labels))
        groups, load = [[], []], [0, 0]
        for i in np.argsort(-counts, kind="stable"):   # greedy: largest tissue to the lighter group
            k = int(np.argmin(load))
            groups[k].append(labels[i])
            load[k] += counts[i]
        groups = [np.sort(np.asarray(g)) for g in groups]
    X = np.asarray(points, float)
    if len(groups) == 1:
        parts = [_gmsh_optimize_group(X, cells, tag, groups[0], threshold)]
    else:
        import tempfile
        from pathlib import Path

        from needletissue.geometry.child import start_in_child

        with tempfile.TemporaryDirectory(prefix="needletissue-gmsh-") as tmp:
            inp, out = str(Path(tmp) / "in.npz"), str(Path(tmp) / "out.npz")
            sel = np.isin(tag, groups[1])
            np.savez(inp, points=X, cells=cells[sel], tag=tag[sel], threshold=threshold)
            other = start_in_child("needletissue.geometry.smooth:_gmsh_optimize_file", {"inp": inp, "out": out},
                                   what="gmsh's optimiser")
            try:
                first = _gmsh_optimize_group(X, cells[~sel], tag[~sel], groups[0], threshold)
                other()
            except BaseException:   # stopped: the child must not write into tmp while it is removed
                other.stop()
                raise
            with np.load(out) as z:
                second = (z["nodes"], z["xyz"], z["cells"], z["tag"])
        parts = [first, second]
    if len(parts) == 1:
        nn, X, c, t = parts[0]
    else:   # gmsh renumbers nodes: the groups' shared (fixed, bit-identical) nodes are merged by position
        (n1, x1, c1, t1), (n2, x2, c2, t2) = parts
        from needletissue.geometry.tetmesh import unique_rows

        X = np.vstack([x1, x2])
        first, inv, _ = unique_rows(np.ascontiguousarray(X).view(np.int64))
        ids = first[inv]
        c = ids[np.concatenate([np.searchsorted(n1, c1), len(n1) + np.searchsorted(n2, c2)])]
        t = np.concatenate([t1, t2])
        order = np.argsort(t, kind="stable")      # regions in label order, as from one process
        c, t = c[order], t[order]
    c = np.asarray(c) if len(parts) > 1 else np.searchsorted(nn, c)
    used, inv = np.unique(c, return_inverse=True)
    return X[used], inv.reshape(c.shape), t


def _gmsh_optimize_file(inp: str, out: str) -> dict:
    """Child-process side of gmsh_optimize: one group of regions from / to .npz files."""
    with np.load(inp) as z:
        pts, cells, tag, thr = z["points"], z["cells"], z["tag"], float(z["threshold"])
    nn, xyz, c, t = _gmsh_optimize_group(pts, cells, tag, np.unique(tag), thr)
    np.savez(out, nodes=nn, xyz=xyz, cells=c, tag=t)
    return {}


def _gmsh_optimize_group(points, cells, tag, labels, threshold):
    """gmsh's optimiser on the regions `labels`; returns (gmsh's node tags sorted, their coordinates, cells
    as node tags, tag)."""
    import gmsh

    from needletissue.geometry.tetmesh import face_pairs

    inter, free, faces = face_pairs(cells, tag)
    sf = faces[np.concatenate([inter, free])]
    was_init = gmsh.isInitialized()
    if not was_init:
        from needletissue.geometry.gmsh_init import initialize  # keeps the SIGTERM handler

        initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("needletissue_optimize")
    try:
        gmsh.model.addDiscreteEntity(2, 1)
        snodes = np.unique(sf)
        gmsh.model.mesh.addNodes(2, 1, snodes + 1, points[snodes].ravel())
        gmsh.model.mesh.addElementsByType(1, 2, [], (sf + 1).ravel())
        placed = np.zeros(len(points), bool)
        placed[snodes] = True
        for i, lab in enumerate(labels, start=1):
            c = cells[tag == lab]
            gmsh.model.addDiscreteEntity(3, i, [1])
            nn = np.unique(c)
            nn = nn[~placed[nn]]
            placed[nn] = True
            gmsh.model.mesh.addNodes(3, i, nn + 1, points[nn].ravel())
            gmsh.model.mesh.addElementsByType(i, 4, [], (c + 1).ravel())
        gmsh.option.setNumber("Mesh.OptimizeThreshold", float(threshold))
        for _ in range(OPTIMIZE_PASSES):
            for method in OPTIMIZE_METHODS:
                gmsh.model.mesh.optimize(method, force=True)
        nt, xyz, _ = gmsh.model.mesh.getNodes()
        out_c, out_t = [], []
        for i, lab in enumerate(labels, start=1):
            _, en = gmsh.model.mesh.getElementsByType(4, i)
            out_c.append(en.reshape(-1, 4).astype(np.int64))
            out_t.append(np.full(len(out_c[-1]), lab))
    finally:
        gmsh.model.remove()
        if not was_init:
            gmsh.finalize()
    order = np.argsort(nt)
    return nt[order].astype(np.int64), xyz.reshape(-1, 3)[order], np.concatenate(out_c), np.concatenate(out_t)


def subtet_centroids(level: int) -> np.ndarray:
    """Barycentric coordinates (8^level, 4) of the centroids of the equal-volume sub-tetrahedra of `level`
    midpoint subdivisions (4 corner + 4 octahedron tetrahedra of 1/8 the volume each): equal-weight
    sample points of a tetrahedron."""
    T = [np.eye(4)]
    for _ in range(level):
        nxt = []
        for a, b, c, d in T:
            ab, ac, ad, bc, bd, cd = (a + b) / 2, (a + c) / 2, (a + d) / 2, (b + c) / 2, (b + d) / 2, (c + d) / 2
            nxt += [(a, ab, ac, ad), (ab, b, bc, bd), (ac, bc, c, cd), (ad, bd, cd, d),
                    (ab, ac, ad, bd), (ab, ac, bc, bd), (ac, ad, bd, cd), (ac, bc, bd, cd)]
        T = [np.array(t) for t in nxt]
    return np.array([t.mean(0) for t in T])


CORTEX_SAMPLE_LEVEL = 2   # 64 sample points per bone element for its cortical fraction


def split_cortex(points, cells, arr, spacing, cortical: int, cancellous: int, level: int = CORTEX_SAMPLE_LEVEL):
    """Cortical / cancellous per bone element (cells, grid coordinates) so that the cortex keeps the label
    map's cortical fraction of the bone volume. Each element's cortical fraction is sampled on the label
    map at the centroids of its 8^level equal sub-tetrahedra (a sample outside the voxel bone counts as
    cortex: the smoothed surface passes through the outer voxel layer); the elements with the largest
    fractions (ties: the one whose centroid is cortical first) are cortical until their volume reaches the
    label map's cortical fraction x the bone elements' volume. The result is the majority rule with its
    threshold moved so that the volume is kept: an element spans the one-voxel cortex, so any per-element
    rule misplaces ~8 % of the bone volume (measured), and the 0.5 majority's volume then depends on the
    sampling (-1.3 / +3.4 % on the CT at 64 / 8 points). Returns (is_cortical per element, info)."""
    canc = (arr == cancellous).ravel()
    nz, ny, nx = arr.shape
    # nearest voxel = floor(u), u in [0, n) after clipping the nodes; samples are convex combinations
    u = np.clip(points / spacing + 0.5, 0, np.array([nx, ny, nz]) - 1e-3).astype(np.float32)

    def is_canc(y):                                  # u >= 0: truncation is the floor
        i = y.astype(np.int32)
        return canc[i[..., 0] + nx * i[..., 1] + (nx * ny) * i[..., 2]]

    B = subtet_centroids(level).astype(np.float32)
    frac = np.empty(len(cells))
    for i in range(0, len(cells), 20000):            # chunks of elements x 64 points
        frac[i:i + 20000] = 1.0 - is_canc(B @ u[cells[i:i + 20000]]).mean(1)
    cen_cort = ~is_canc(u[cells].mean(1))
    vol = np.abs(signed_volume(points, cells))
    n_cort, n_canc = np.count_nonzero(arr == cortical), np.count_nonzero(canc)
    target = vol.sum() * n_cort / max(n_cort + n_canc, 1)
    order = np.lexsort((~cen_cort, -frac))
    cum = np.concatenate([[0.0], np.cumsum(vol[order])])
    k = int(np.argmin(np.abs(cum - target)))
    out = np.zeros(len(cells), bool)
    out[order[:k]] = True
    return out, {"cortical_fraction_label": float(target / max(vol.sum(), 1e-300)),
                 "cortical_threshold": float(frac[order[k - 1]]) if k else 1.0,
                 "cortical_sample_points": int(len(B))}


def signed_volume(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Signed volume of each tetrahedron (tet_quality's sign convention); 20x cheaper than tet_quality."""
    p0 = points[cells[:, 0]]
    return np.einsum("ij,ij->i", np.cross(points[cells[:, 1]] - p0, points[cells[:, 2]] - p0),
                     points[cells[:, 3]] - p0) / 6.0


def vol_min_dihedral(P: np.ndarray):
    """Signed volume and smallest dihedral angle (deg) of tetrahedra given as corner arrays (..., 4, 3);
    the part of tetmesh.tet_quality the node relocation needs, on any leading shape."""
    e1, e2, e3 = P[..., 1, :] - P[..., 0, :], P[..., 2, :] - P[..., 0, :], P[..., 3, :] - P[..., 0, :]
    vol = np.einsum("...i,...i->...", np.cross(e1, e2), e3) / 6.0
    # normals of the faces opposite corners 0..3, all outward for a positive element
    n = [np.cross(P[..., 2, :] - P[..., 1, :], P[..., 3, :] - P[..., 1, :]), np.cross(e3, e2), np.cross(e1, e3),
         np.cross(e2, e1)]
    n = [v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-300) for v in n]
    cmax = np.full(vol.shape, -1.0)
    for a in range(4):
        for b in range(a + 1, 4):   # interior dihedral = pi - angle between outward normals
            cmax = np.maximum(cmax, -np.einsum("...i,...i->...", n[a], n[b]))
    return vol, np.degrees(np.arccos(np.clip(cmax, -1.0, 1.0)))


def sliding_normals(points, surface_faces, face_group, max_deviation_deg: float = 35.0):
    """Unit normals of the surface nodes that may slide in their tangent plane, NaN elsewhere.

    A node may slide when all its surface faces belong to one group (one interface, or the free boundary
    of one tissue), form one closed fan (no triple line, no boundary of the patch) and deviate by at most
    `max_deviation_deg` from their mean normal (no crease or corner): a tangential move of length d then
    moves the surface by about d^2 / (2 R), R the curvature radius (0.04 mm for d = 1 mm, R = 12 mm)."""
    from needletissue.geometry.tetmesh import unique_rows

    n_pts = len(points)
    t = points[surface_faces]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nv = np.zeros((n_pts, 3))
    for k in range(3):
        np.add.at(nv, surface_faces[:, k], fn)
    ok = np.zeros(n_pts, bool)
    on = np.unique(surface_faces)
    ok[on] = True
    # one group per node
    g0 = np.full(n_pts, -1)
    for k in range(3):
        g0[surface_faces[:, k]] = face_group
    for k in range(3):
        ok[surface_faces[:, k][face_group != g0[surface_faces[:, k]]]] = False
    # closed fan: every surface edge at the node is shared by exactly two of its surface faces
    E = np.sort(np.concatenate([surface_faces[:, [0, 1]], surface_faces[:, [1, 2]], surface_faces[:, [2, 0]]]), 1)
    first, _, cnt = unique_rows(E)
    odd = E[first[cnt != 2]].ravel()
    ok[odd] = False
    nrm = nv / np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-300)
    fu = fn / np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    cmin = np.ones(n_pts)
    for k in range(3):
        np.minimum.at(cmin, surface_faces[:, k], np.einsum("ij,ij->i", fu, nrm[surface_faces[:, k]]))
    ok &= cmin >= np.cos(np.radians(max_deviation_deg))
    out = np.full((n_pts, 3), np.nan)
    out[ok] = nrm[ok]
    return out


def relocate_nodes(points, cells, fixed, target_deg: float = 12.0, rounds: int = 4, samples: int = 48,
                   seed: int = 0, slide=None):
    """Move the nodes of tetrahedra whose smallest dihedral angle is below `target_deg` to the best of a
    few candidate positions (the mean of their neighbours, random points around the current one),
    keeping a move only if it raises the smallest dihedral angle of the node's star and no element
    inverts. Nodes in `fixed` never move, except those with a finite normal in `slide` (n, 3): they move
    in their tangent plane only (sliding_normals). Deterministic (seeded; compiled loop in relocate_kernel).
    Returns (points, number of node moves)."""
    from needletissue.geometry.relocate_kernel import min_dihedral, relocate

    x = np.array(points, float, copy=True)
    cells = np.ascontiguousarray(cells, np.int64)
    flat = cells.ravel()
    order = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[order], np.arange(len(x) + 1))
    sliding = np.zeros(len(x), bool) if slide is None else np.asarray(fixed, bool) & np.isfinite(slide[:, 0])
    normal = np.zeros((len(x), 3)) if slide is None else np.where(sliding[:, None], slide, 0.0)
    movable = ~np.asarray(fixed, bool) | sliding
    md = min_dihedral(x, cells)                    # kept up to date star by star
    moved = relocate(x, cells, start, order // 4, movable, sliding, np.ascontiguousarray(normal), md,
                     float(target_deg), int(rounds), int(samples), int(seed))
    return x, int(moved)


def _faces_with(cell, w):
    """The three faces of a tetrahedron (4 node ids) that contain node w."""
    c = [int(v) for v in cell]
    return [[c[j] for j in range(4) if j != k] for k in range(4) if c[k] != w]


def _triangulations(n: int) -> list[list[tuple[int, int, int]]]:
    """All triangulations of the convex polygon 0..n-1 (triangles in ring order)."""
    def rec(i, j):
        if j - i < 2:
            return [[]]
        return [a + b + [(i, k, j)] for k in range(i + 1, j) for a in rec(i, k) for b in rec(k, j)]
    return rec(0, n - 1)


RING_TRIANGULATIONS = {n: _triangulations(n) for n in range(3, 8)}   # 1, 2, 5, 14, 42


def remove_slivers(points, cells, tag, target_deg: float = 12.0, max_shift: float = 0.0, passes: int = 8,
                   samples: int = 48, seed: int = 0, pinned=None, frozen=()):
    """Topological sliver removal on a multi-region mesh of positive tetrahedra; worst elements first,
    for every element whose smallest dihedral angle is below `target_deg`, the best of:
    - a 2-3 face flip or an edge removal (the n tetrahedra around an edge -> the best of the 2n - 4
      triangulations of its ring, n <= 7) among tetrahedra of one tag, so no interface / boundary face
      changes;
    - if the element is flat (height 3 V / largest face area <= `max_shift`): the same with the element
      given to a tissue across one of its faces (an interface edge flip: the interface moves by at most
      that height), or, with two faces on the free boundary, cutting it off (unless that pinches an edge);
    - if none of these improves: splitting an edge that has no interface / boundary face at a new node
      placed (mean of the edge, `samples` seeded random points) to maximise its star's worst angle;
    - else collapsing an edge no longer than `max_shift` (link condition checked; the nodes merge at one
      end or the middle, so an interface moves by at most that length).
    An operation is kept only if the worst new element beats the worst one it replaces (all positive),
    so the minimum angle never drops. Nodes in `pinned` are never collapsed and elements of a tag in `frozen`
    never change tag nor give theirs (exact solids keep their surfaces).
    Returns (points, cells, tag, number of operations), nodes compacted."""
    from itertools import combinations

    from needletissue.geometry.relocate_kernel import min_dihedral

    x = np.array(points, float)
    n_x = len(x)
    rng = np.random.default_rng(seed)
    n0 = len(cells)
    C = np.zeros((n0 + 64, 4), np.int64)
    C[:n0] = cells
    T = np.zeros(n0 + 64, np.asarray(tag).dtype)
    T[:n0] = tag
    alive = np.zeros(n0 + 64, bool)
    alive[:n0] = True
    md = np.full(n0 + 64, 180.0)
    md[:n0] = min_dihedral(x, np.ascontiguousarray(cells, np.int64))   # compiled: 0.2 s, not 1.5 s, on the CT
    size = n0
    flat = np.asarray(cells).ravel()
    order = np.argsort(flat, kind="stable")
    start = np.searchsorted(flat[order], np.arange(n_x + 1))
    stars = {}                                   # node -> set of live elements, built on demand

    def star(v):
        s = stars.get(v)
        if s is None:
            s = stars[v] = set((order[start[v]:start[v + 1]] // 4).tolist())
        return s

    def face_elems(f):
        return star(f[0]) & star(f[1]) & star(f[2])

    def remove(ids):
        for e in ids:
            alive[e] = False
            for v in C[e]:
                star(int(v)).discard(e)

    def add(new, tg, q):
        nonlocal size, C, T, alive, md
        k = len(new)
        if size + k > len(C):
            g = max(k, len(C) // 4)
            C, T = np.vstack([C, np.zeros((g, 4), np.int64)]), np.concatenate([T, np.zeros(g, T.dtype)])
            alive, md = np.concatenate([alive, np.zeros(g, bool)]), np.concatenate([md, np.full(g, 180.0)])
        C[size:size + k], T[size:size + k], alive[size:size + k], md[size:size + k] = new, tg, True, q
        for e in range(size, size + k):
            for v in C[e]:
                star(int(v)).add(e)
        size += k

    def closed_ring(t, u, v):
        """Elements around edge u-v and their other vertices as a cycle with (u, v, p_i, p_i+1) positive;
        None if a face around the edge is an interface or free (open ring or another tag)."""
        ring = list(star(u) & star(v))
        if len(ring) < 3 or np.any(T[ring] != T[t]):
            return None
        nxt = {}
        for r in ring:
            c = [int(w) for w in C[r]]
            p, q = (w for w in c if w != u and w != v)
            perm = [c.index(u), c.index(v), c.index(p), c.index(q)]
            if sum(perm[m] > perm[k] for m in range(4) for k in range(m + 1, 4)) % 2:
                p, q = q, p
            if p in nxt:
                return None
            nxt[p] = q
        cyc = [next(iter(nxt))]
        while len(cyc) < len(ring):
            q = nxt.get(cyc[-1])
            if q is None or q in cyc:
                return None
            cyc.append(q)
        return (ring, cyc) if nxt.get(cyc[-1]) == cyc[0] else None

    def flips(t):
        """(old elements, new cells) of every 2-3 flip and edge removal touching element t."""
        a = C[t]
        out = []
        for k in range(4):                       # 2-3 flip of the face opposite corner k
            f = [int(a[j]) for j in range(4) if j != k]
            other = face_elems(f) - {t}
            if len(other) != 1:
                continue
            u = other.pop()
            if T[u] != T[t]:
                continue
            e = int(np.setdiff1d(C[u], f)[0])
            new = np.repeat(a[None], 3, 0)
            new[np.arange(3), [j for j in range(4) if j != k]] = e
            out.append(([t, u], new))
        for i, j in combinations(range(4), 2):   # edge removal
            u, v = int(a[i]), int(a[j])
            rc = closed_ring(t, u, v)
            if rc is None or len(rc[0]) > 7:
                continue
            ring, cyc = rc
            for tri in RING_TRIANGULATIONS[len(ring)]:   # ring counter-clockwise seen from v
                new = ([[cyc[p], cyc[q], cyc[r], v] for p, q, r in tri]
                       + [[cyc[p], cyc[r], cyc[q], u] for p, q, r in tri])
                out.append((ring, np.array(new)))
        return out

    def split(t):
        """(gain, ring, new cells with -1 for the new node, its position, angles) of the best edge split."""
        a = C[t]
        best = (0.0, None)
        for i, j in combinations(range(4), 2):
            u, v = int(a[i]), int(a[j])
            rc = closed_ring(t, u, v)
            if rc is None:
                continue
            ring = rc[0]
            cu, cv = C[ring].copy(), C[ring].copy()
            cu[cu == u], cv[cv == v] = -1, -1
            new = np.vstack([cu, cv])
            h = np.linalg.norm(x[u] - x[v])
            cand = 0.5 * (x[u] + x[v]) + np.vstack([np.zeros(3), rng.normal(scale=0.3 * h, size=(samples, 3))])
            P = np.broadcast_to(x[np.where(new < 0, 0, new)], (len(cand),) + new.shape + (3,)).copy()
            P[:, new < 0] = cand[:, None, :]
            vol, q = vol_min_dihedral(P)
            score = np.where((vol > 0).all(1), q.min(1), -1.0)
            k = int(np.argmax(score))
            if score[k] - md[ring].min() > best[0]:
                best = (score[k] - md[ring].min(), ring, new, cand[k], q[k])
        return best

    def collapse(t):
        """(gain, old elements, new cells, kept node, its new position, angles, tags) of the best collapse of an edge
        of t no longer than max_shift (the two nodes merge at one end or the middle); the link condition
        keeps the complex's topology, and the free boundary may only be collapsed along its edges."""
        a = [int(w) for w in C[t]]
        best = (0.0, None)
        for u, v in combinations(a, 2):
            if np.linalg.norm(x[u] - x[v]) > max_shift or pin(u) or pin(v):
                continue
            su, sv = star(u), star(v)
            both = su & sv
            link_e = {frozenset(w for w in C[e] if w != u and w != v) for e in both}
            pu = {frozenset(w for w in f if w != u) for e in su - both for f in _faces_with(C[e], u)}
            pv = {frozenset(w for w in f if w != v) for e in sv - both for f in _faces_with(C[e], v)}
            nu = set(C[list(su)].ravel().tolist()) - {u, v}
            nv = set(C[list(sv)].ravel().tolist()) - {u, v}
            if (pu & pv) - link_e or (nu & nv) != set().union(*link_e):
                continue
            on_b = [any(len(face_elems(f)) == 1 for e in st for f in _faces_with(C[e], w))
                    for w, st in ((u, su), (v, sv))]
            if on_b[0] and on_b[1] and not any(len(face_elems([u, v, int(w)])) == 1
                                               for e in both for w in C[e] if w != u and w != v):
                continue
            old = list(su | sv)
            keep = [e for e in old if e not in both]
            new = C[keep].copy()
            new[new == v] = u
            for pos in (x[u], x[v], 0.5 * (x[u] + x[v])):
                P = x[new]
                P[new == u] = pos
                vol, q = vol_min_dihedral(P)
                g = (q.min() if (vol > 0).all() else -1.0) - md[old].min()
                if g > best[0]:
                    best = (g, old, new, u, pos, q, T[keep])
        return best

    pinned0 = np.zeros(n_x, bool) if pinned is None else np.asarray(pinned, bool)
    pin = lambda v: v < len(pinned0) and pinned0[v]  # noqa: E731  (new nodes are never pinned)
    frozen = set(frozen)
    n_ops = 0
    for _ in range(passes):
        bad = np.flatnonzero(alive[:size] & (md[:size] < target_deg))
        n_pass = 0
        for t in bad[np.argsort(md[bad])]:
            t = int(t)
            if not alive[t] or md[t] >= target_deg:
                continue
            own = T[t]
            cand = [(o, nw, own) for o, nw in flips(t)]
            tags = [own]
            P = x[C[t]]
            area = max(np.linalg.norm(np.cross(P[(k + 1) % 4] - P[k], P[(k + 2) % 4] - P[k])) for k in range(4)) / 2
            if max_shift > 0 and own not in frozen and 3 * abs(vol_min_dihedral(P)[0]) / area <= max_shift:
                a = [int(w) for w in C[t]]
                faces = [[a[j] for j in range(4) if j != k] for k in range(4)]
                free = [k for k in range(4) if len(face_elems(faces[k])) == 1]
                if len(free) == 2:               # a flat cap on the free boundary: cut it off
                    p, q = a[free[0]], a[free[1]]   # the exposed faces share edge p-q: must not be free yet
                    if not any(len(star(p) & star(q) & star(int(w))) == 1
                               for u in (star(p) & star(q)) - {t} for w in C[u] if w != p and w != q):
                        cand.append(([t], np.zeros((0, 4), np.int64), own))
                for f in faces:                  # give it to a neighbour tissue, then flip
                    for u in face_elems(f) - {t}:
                        if T[u] not in tags and T[u] not in frozen:
                            tags.append(T[u])
                            T[t] = T[u]
                            cand += [(o, nw, T[u]) for o, nw in flips(t)]
                            T[t] = own
            best, gain = None, 0.0
            if cand:
                vol, q = vol_min_dihedral(x[np.concatenate([c[1] for c in cand])])
                q = np.where(vol > 0, q, -1.0)
                pos = 0
                for old, new, tg in cand:
                    qn = q[pos:pos + len(new)]
                    pos += len(new)
                    g = (qn.min() if len(qn) else 90.0) - md[old].min()
                    if g > gain:
                        best, gain = (old, new, tg, qn), g
            if best is None:                     # split an edge, own tag first, then a neighbour's
                sp, tg = (0.0, None), None
                for tgi in tags:
                    T[t] = tgi
                    s_i = split(t)
                    if s_i[0] > sp[0]:
                        sp, tg = s_i, tgi
                T[t] = own
                if sp[1] is None:                # last resort: collapse a short edge
                    cl = collapse(t) if max_shift > 0 else (0.0, None)
                    if cl[1] is None:
                        continue
                    _, old, new, u, x[u], qn, tg = cl
                    remove(old)
                    add(new, tg, qn)
                    n_pass += 1
                    continue
                if n_x == len(x):
                    x = np.vstack([x, np.zeros((max(64, n_x // 50), 3))])
                x[n_x] = sp[3]
                stars[n_x] = set()
                best = (sp[1], np.where(sp[2] < 0, n_x, sp[2]), tg, sp[4])
                n_x += 1
            remove(best[0])
            add(best[1], best[2], best[3])
            n_pass += 1
        n_ops += n_pass
        if n_pass == 0:
            break
    c = C[:size][alive[:size]]
    used, inv = np.unique(c, return_inverse=True)
    return x[used], inv.reshape(c.shape), T[:size][alive[:size]], n_ops


OPT_MAX_DIHEDRAL = 165.0   # TetGen -O: flip/smooth away tetrahedra with a dihedral angle above this
OPT_ITERATIONS = 5
TETGEN_SMOOTHING = 2        # TetGen's vertex smoothing passes (default 7: half its time on the CT); steps 7-8 do the rest
OPTIMIZE_THRESHOLD = 0.5   # gmsh gamma below which tetrahedra are optimised (0: no gmsh pass)
OPTIMIZE_PASSES = 1         # a 2nd pass on the CT: 204 instead of 233 elements below 10 deg for ~2x the stage CPU
OPTIMIZE_METHODS = ("",)    # gmsh optimisers per pass ("": gmsh's own tetrahedron optimiser)
SLIDE = True               # interface nodes may slide in their tangent plane during relocation
SLIDE_MAX_DEVIATION = 35.0  # degrees; surface nodes whose faces deviate more from their mean normal stay put
RELOCATE_TARGET = 20.0      # degrees; relocation works on elements below this (goal: 1st percentile >= 20)
SLIVER_TARGET = 13.0        # degrees; remove_slivers works on elements below this (goal: 10; 12 left 9.49 on the whole CT)
POLISH_TARGET = 20.0        # degrees; relocation once more after the sliver removal (0: none)
SLIVER_SHIFT = 1 / 3        # x voxel: a flat element this thin may change tissue (its interface moves that much)
GRADED_SLIVER_SHIFT = 2 / 3  # the same on CGAL's interfaces (pelvis at 4.5 mm: 1/3 leaves 9.4 deg, 2/3 12.0)


def _pad_for_solids(seg, arr, start, f, solids):
    """Zero-pad the (cropped, coarsened) label array so that the solids and their corridor fit inside it
    (no more). Returns (arr, start, the crop's voxel index ranges (x, y, z) in it or None: its cut faces
    stay flat)."""
    D = np.asarray(seg.labels.GetDirection(), float).reshape(3, 3)
    sp0 = np.asarray(seg.labels.GetSpacing(), float)
    idx = (np.asarray(solids.points, float) - np.asarray(seg.labels.GetOrigin(), float)) @ D / sp0  # (x, y, z)
    m = solids.margin / (sp0 * f) + 0.5
    lo = np.floor((idx.min(0) - start) / f - (f - 1) / (2 * f) - m).astype(int)
    hi = np.ceil((idx.max(0) - start) / f + m).astype(int) + 1
    shape = np.asarray(arr.shape[::-1])
    pad_lo, pad_hi = np.maximum(-lo, 0), np.maximum(hi - shape, 0)
    if not (pad_lo.any() or pad_hi.any()):
        return arr, start, None
    arr = np.pad(arr, list(zip(pad_lo[::-1], pad_hi[::-1])))
    return arr, np.asarray(start) - pad_lo * f, (pad_lo, pad_lo + shape)


def _largest_body(cells, tag):
    """The face-connected component with the most elements (corridor elements labelled by centroid can
    leave a tissue element touching the rest at an edge only)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from needletissue.geometry.tetmesh import face_pairs

    *_, two = face_pairs(cells, tag, pairs=True)
    a, b = two[:, 0] % len(cells), two[:, 1] % len(cells)
    _, comp = connected_components(coo_matrix((np.ones(len(a)), (a, b)), shape=(len(cells),) * 2), directed=False)
    keep = comp == np.argmax(np.bincount(comp))
    return cells[keep], tag[keep]


def _grid_centres(arr, sp):
    """Grid coordinates (index * spacing, x y z) of every voxel of a (z, y, x) array, in array order."""
    k, j, i = np.meshgrid(*[np.arange(n) for n in arr.shape], indexing="ij")
    return np.stack([i.ravel(), j.ravel(), k.ravel()], 1) * sp


def _move_constraints(nodes, cells, tag, frozen):
    """(fixed, slide, pinned) for relocate_nodes / remove_slivers on positive cells: interface and free
    boundary nodes are fixed, those on a smooth patch of one interface may slide (sliding_normals), the
    surface nodes of the tags in `frozen` (exact solids) are pinned: never moved."""
    from needletissue.geometry.tetmesh import face_pairs

    inter, free, faces, two = face_pairs(cells, tag, pairs=True)
    bnd = np.concatenate([inter, free])
    fixed = np.zeros(len(nodes), bool)
    fixed[np.unique(faces[bnd])] = True
    # the worst elements have all four nodes on interfaces (measured): let smooth-patch nodes slide
    n_c = len(cells)
    partner = np.full(len(faces), -1)
    partner[two[:, 0]], partner[two[:, 1]] = two[:, 1], two[:, 0]
    ta = tag[bnd % n_c]
    tb = np.where(partner[bnd] >= 0, tag[partner[bnd] % n_c], -1)     # -1: free boundary
    group = np.minimum(ta, tb) * 1000 + np.maximum(ta, tb)             # one id per interface / boundary
    slide = sliding_normals(nodes, faces[bnd], group, SLIDE_MAX_DEVIATION) if SLIDE else None
    pinned = np.zeros(len(nodes), bool)
    pinned[np.unique(cells[np.isin(tag, frozen)])] = True
    pinned &= fixed                                   # the solids' surface nodes: exact, never moved
    if slide is not None:
        slide[pinned] = np.nan
    return fixed, slide, pinned


def polish_nodes(points, cells, tag, target_deg, frozen=()):
    """relocate_nodes on the stars of the nodes of the elements below `target_deg` only (the nodes outside
    stay put, so those stars are exact), with _move_constraints computed on that sub-mesh: a node whose
    star is whole in it has the same interface / boundary faces there. 0.7-0.9 s CPU on the CT crop where a
    whole-mesh relocation took ~7 s (face_pairs and sliding_normals of 1.2 M elements: 3.7 s of it).
    Returns (points, number of moves, smallest dihedral angle of the mesh after)."""
    from needletissue.geometry.relocate_kernel import min_dihedral

    md = min_dihedral(np.ascontiguousarray(points, float), np.ascontiguousarray(cells, np.int64))
    move = np.zeros(len(points), bool)
    move[cells[md < target_deg].ravel()] = True
    if not move.any():
        return points, 0, float(md.min())
    sub = np.flatnonzero(move[cells].any(1))
    used, inv = np.unique(cells[sub], return_inverse=True)
    sc = inv.reshape(-1, 4)
    fixed, slide, _ = _move_constraints(points[used], sc, np.asarray(tag)[sub], frozen)
    fixed |= ~move[used]
    if slide is not None:
        slide[~move[used]] = np.nan
    y, n = relocate_nodes(points[used], sc, fixed, target_deg=target_deg, slide=slide)
    x = np.array(points, float, copy=True)
    x[used] = y
    md[sub] = min_dihedral(y, sc)
    return x, n, float(md.min())


def smooth_tet_mesh(seg, cfg, solids: Solids | None = None):
    """TetMesh with smooth, conforming tissue interfaces (module docstring); cfg: tetmesh.MeshConfig.

    solids: closed solids (needles, clamp) meshed exactly: their triangles join the interface set inside a
    corridor cut from the label map, their elements form regions named after them, their surface nodes
    never move (Solids)."""
    import time

    from needletissue.geometry.tetmesh import (TetMesh, _crop_and_coarsen, _grid_frame, bone_surfaces_by_bone, face_pairs, interface_surfaces,
                                               regular_tet_volume)
    from needletissue.imaging.segment import material_for

    t0 = time.perf_counter()
    cpu = [time.process_time()]
    arr, start, f, names = _crop_and_coarsen(seg, cfg)
    flat = None
    if solids is not None:
        arr, start, flat = _pad_for_solids(seg, arr, start, f, solids)
    sp, to_phys = _grid_frame(seg, arr, start, f)
    bone_ids = [seg.tissues[n] for n in BONE if n in names]
    work = arr.copy()
    if len(bone_ids) > 1:
        work[np.isin(work, bone_ids)] = bone_ids[-1]   # one bone region: its outer surface is the interface
    tissue = work
    if solids is not None:
        tissue = work.copy()
        near = solids.label(to_phys(_grid_centres(work, sp)), solids.margin) >= 0
        work[near.reshape(work.shape)] = CORRIDOR
    if cfg.graded:   # CGAL's interfaces (geometry.graded); TetGen grades the volume from them
        from needletissue.geometry import graded

        if solids is None:
            raise InputError("far_size", "a graded mesh grows from the solids (needles): none were given")
        h = graded.size_field(work, sp, CORRIDOR, cfg.size, cfg.far_size, cfg.refine_radius)
        volumes = np.bincount(work.ravel(), minlength=256) * float(np.prod(sp))   # the label map's, kept
        work, n_dropped = graded.drop_small_components(work, sp, h, keep=(CORRIDOR,))
        surf = graded.graded_interfaces(work, sp, h, flat=flat, volumes=volumes, fixed_labels=(CORRIDOR,))
        surf.info["voxels_of_small_pieces_merged"] = n_dropped
    else:
        surf = smooth_interfaces(work, sp, iterations=cfg.smoothing_iterations, scale=cfg.smoothing_scale, flat=flat)
    plc_points, plc_faces = surf.points, surf.faces
    if solids is not None:   # the exact solid surfaces inside the corridor: same PLC, no Boolean needed
        plc_points = np.vstack([surf.points, to_phys.inverse(solids.points)])
        plc_faces = np.vstack([surf.faces, np.asarray(solids.faces, np.int64) + len(surf.points)])
        e, _ = edge_face_crossings(plc_points, plc_faces)
        if len(e):
            raise CorridorTooNarrow("solids", f"{len(e)} edge(s) of the solids cross the tissue interfaces: the "
                                    f"corridor margin ({solids.margin:g} mm) is too small for this voxel or element size")
    t1 = time.perf_counter()
    cpu.append(time.process_time())
    bound = cfg.max_volume
    if bound is None and cfg.size < 0.999 * sp.min() and not cfg.graded:
        bound = regular_tet_volume(cfg.size)
    nodes, elem, attr = _tetgen(plc_points, plc_faces, cfg, bound)
    t2 = time.perf_counter()
    cpu.append(time.process_time())
    # tissue per TetGen subdomain: volume-weighted majority of the labels at its tetrahedra's centroids
    vol = np.abs(signed_volume(nodes, elem))
    cen = nodes[elem].mean(1)
    shape = np.asarray(arr.shape[::-1])
    ijk = np.clip(np.floor(cen / sp + 0.5).astype(int), 0, shape - 1)
    lab_c = work[ijk[:, 2], ijk[:, 1], ijk[:, 0]].astype(np.int64)
    sub_ids, sub = np.unique(attr, return_inverse=True)
    votes = np.zeros((len(sub_ids), 256))
    np.add.at(votes, (sub, lab_c), vol)
    sub_label = votes.argmax(1)
    purity = votes.max(1).sum() / votes.sum()
    if solids is not None:   # a subdomain mostly inside a solid is that solid
        sid = solids.label(to_phys(cen), 0.0)
        inside_vol = np.zeros((len(sub_ids), len(solids.names) + 1))
        np.add.at(inside_vol, (sub, sid + 1), vol)
        k = inside_vol.argmax(1)
        is_solid = (k > 0) & (inside_vol.max(1) > 0.5 * inside_vol.sum(1))
        sub_label[is_solid] = SOLID0 + k[is_solid] - 1
        missing = [n for i, n in enumerate(solids.names) if not np.any(sub_label == SOLID0 + i)]
        if missing:
            raise InputError("solids", f"no subdomain for {', '.join(missing)}: not closed or outside the crop")
    tag = sub_label[sub]
    inside = tag > 0
    elem, tag = elem[inside], tag[inside]
    used, inv = np.unique(elem, return_inverse=True)
    cells = inv.reshape(elem.shape).astype(np.int64)
    nodes = nodes[used]
    shift = (GRADED_SLIVER_SHIFT if cfg.graded else SLIVER_SHIFT) * float(sp.min())
    t3 = time.perf_counter()
    cpu.append(time.process_time())
    if OPTIMIZE_THRESHOLD > 0:
        nodes, cells, tag = gmsh_optimize(nodes, cells, tag, OPTIMIZE_THRESHOLD)
    t4 = time.perf_counter()
    cpu.append(time.process_time())
    frozen = [SOLID0 + i for i in range(len(solids.names))] if solids is not None else []
    v = signed_volume(nodes, cells)
    cells[v < 0] = cells[v < 0][:, [0, 2, 1, 3]]  # positive orientation (in grid coordinates)
    fixed, slide, pinned = _move_constraints(nodes, cells, tag, frozen)
    nodes, n_moved = relocate_nodes(nodes, cells, fixed, target_deg=RELOCATE_TARGET, slide=slide)
    t5 = time.perf_counter()
    cpu.append(time.process_time())
    # what relocation leaves below the goal sits on interfaces (caps at an interface edge): flips, splits
    nodes, cells, tag, n_ops = remove_slivers(nodes, cells, tag, SLIVER_TARGET, shift,
                                              pinned=pinned, frozen=frozen)
    t5b = time.perf_counter()
    cpu.append(time.process_time())
    n_polish = 0
    if POLISH_TARGET > 0:   # the flips and splits leave new elements next to the old worst: relocate again,
        nodes, n_polish, worst = polish_nodes(nodes, cells, tag, POLISH_TARGET, frozen)
        if worst < SLIVER_TARGET:   # and what that frees, flip / split once more (measured: 9.72 -> 13.03)
            pinned = _move_constraints(nodes, cells, tag, frozen)[2]
            nodes, cells, tag, n2 = remove_slivers(nodes, cells, tag, SLIVER_TARGET, shift,
                                                   pinned=pinned, frozen=frozen)
            nodes, n3, _ = polish_nodes(nodes, cells, tag, POLISH_TARGET, frozen)
            n_ops, n_polish = n_ops + n2, n_polish + n3
    t5c = time.perf_counter()
    cpu.append(time.process_time())
    if solids is not None:   # corridor elements outside the solids: the tissue at the centroid; air dropped
        cor = np.flatnonzero(tag == CORRIDOR)
        ijk = np.clip(np.floor(nodes[cells[cor]].mean(1) / sp + 0.5).astype(int), 0, shape - 1)
        tag[cor] = tissue[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        cells, tag = _largest_body(cells[tag > 0], tag[tag > 0])
        used, inv = np.unique(cells, return_inverse=True)
        nodes, cells = nodes[used], inv.reshape(cells.shape)
    split_info = {}
    if len(bone_ids) > 1:
        # cortical / cancellous per tetrahedron, after the optimisation: the split is a rule, no interface,
        # so its element-staircase nodes must stay free to move
        bone = np.flatnonzero(tag == bone_ids[-1])
        cort, split_info = split_cortex(nodes, cells[bone], arr, sp, seg.tissues["cortical_bone"], bone_ids[-1])
        tag[bone[cort]] = seg.tissues["cortical_bone"]
    t6 = time.perf_counter()
    cpu.append(time.process_time())
    points = to_phys(nodes)
    if to_phys.flips:
        cells = cells[:, [0, 2, 1, 3]]
    regions = {n: np.flatnonzero(tag == seg.tissues[n]) for n in names}
    regions = {n: ids for n, ids in regions.items() if len(ids)}
    lost = [n for n in names if n not in regions]
    for i, n in enumerate(solids.names if solids is not None else []):
        regions[n] = np.flatnonzero(tag == SOLID0 + i)
    if lost and cfg.regions is not None:
        raise InputError("regions", f"tissue(s) lost by the smooth mesh: {', '.join(lost)}")
    mesh = TetMesh(points=points, cells=cells, regions=regions,
                   materials={n: material_for(n) for n in regions})
    mesh.surfaces = interface_surfaces(mesh)
    if seg.bones is not None and "bone_surface" in mesh.surfaces:
        mesh.surfaces.update(bone_surfaces_by_bone(mesh, seg.bones, 0.5 * float(sp.min())))
    mesh.info = {"method": "smooth", **surf.info, "subdomains": int(len(sub_ids)),
                 "subdomain_label_purity": float(purity), "lost_tissues": lost, "nodes_relocated": int(n_moved),
                 "sliver_operations": int(n_ops), "nodes_relocated_after_slivers": int(n_polish), **split_info,
                 "time_s": {"surfaces": t1 - t0, "tetgen": t2 - t1, "gmsh_optimize": t4 - t3, "relocate": t5 - t4,
                            "slivers": t5b - t5, "polish": t5c - t5b, "split": t6 - t5c, "total": time.perf_counter() - t0},
                 "cpu_s": {"surfaces": cpu[1] - cpu[0], "tetgen": cpu[2] - cpu[1], "label": cpu[3] - cpu[2],
                           "gmsh_optimize": cpu[4] - cpu[3], "relocate": cpu[5] - cpu[4],
                           "slivers": cpu[6] - cpu[5], "polish": cpu[7] - cpu[6],
                           "split": cpu[8] - cpu[7], "total": time.process_time() - cpu[0]}}
    return mesh
