"""Turn bonded (conforming) interfaces of a tetrahedral TaggedMesh into contact pairs.

A conforming mesh shares nodes across every interface, so the bodies are glued. For contact to act,
the nodes of a named interface must be duplicated: the cells of one side (side ``b``) get copies of
the interface nodes, the other side keeps the originals. Interfaces are named by the two region
groups they separate, e.g. ``needle-muscle``; a group matches a region of the same name or a region
whose name starts with ``group_`` or ends with ``_group`` (``needle`` -> ``needle_1``, ``needle_2``;
``bone`` -> ``cortical_bone``, ``cancellous_bone``). Several interfaces are split one after the other,
so a node on a line where three contact interfaces meet ends up with one copy per body.

Works for linear (4-node) and quadratic (10-node, VTK order) tetrahedra.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from needletissue.errors import InputError

# corner faces of a tetrahedron (orientation is fixed later from the opposite vertex)
_TET_FACES = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]])
_OPPOSITE = np.array([3, 2, 0, 1])
# VTK tetra10 mid-edge node of each corner edge
_TET10_EDGE = {(0, 1): 4, (1, 2): 5, (0, 2): 6, (0, 3): 7, (1, 3): 8, (2, 3): 9}


@dataclass(frozen=True)
class SplitInterface:
    """One interface after splitting.

    faces_a, faces_b: (k, 3|6) node ids of the interface faces, oriented outward of side a / b
    (VTK triangle / triangle6 order). nodes_a, nodes_b: the originally coincident node pairs
    (nodes_b are the new copies owned by side b).
    """

    name: str
    regions_a: tuple[str, ...]
    regions_b: tuple[str, ...]
    faces_a: np.ndarray
    faces_b: np.ndarray
    nodes_a: np.ndarray
    nodes_b: np.ndarray
    # side a's faces bonded to a rim region next to the split line (split_interfaces' rim): collision
    # faces only, so side b's rim meets side a's surface, not its boundary edge, when it slides past
    skirt_a: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), dtype=int))


def group_regions(mesh, group: str, groups: dict[str, tuple[str, ...]] | None = None) -> tuple[str, ...]:
    """Regions of ``mesh`` that belong to a region group name (see module docstring); ``groups``
    (group -> regions, e.g. from ``material_groups``) takes precedence over the name rule."""
    if groups and group in groups:
        return tuple(r for r in mesh.regions if r in groups[group])
    return tuple(
        r
        for r in mesh.regions
        if r == group or r.startswith(group + "_") or r.endswith("_" + group)
    )


def material_groups(materials: dict[str, str]) -> dict[str, tuple[str, ...]]:
    """Region groups by material, for meshes whose region names are anatomical: region -> material
    name (e.g. ``{"gluteus_medius": "muscle", "hip_cortical": "cortical_bone"}``) gives
    ``{"muscle": ("gluteus_medius",), "bone": ("hip_cortical",), ...}`` (a material ``x_bone`` is in
    group ``bone``)."""
    out: dict[str, list[str]] = {}
    for region, material in materials.items():
        family = material.rsplit("_", 1)[-1]
        out.setdefault(family, []).append(region)
        if family != material:
            out.setdefault(material, []).append(region)
    return {k: tuple(v) for k, v in out.items()}


def parse_interface_name(name: str) -> tuple[str, str]:
    parts = name.split("-")
    if len(parts) != 2 or not all(parts):
        raise InputError("interfaces", f"interface name {name!r} must be 'groupA-groupB', e.g. 'needle-muscle'")
    return parts[0], parts[1]


def _cell_faces(cells: np.ndarray, points: np.ndarray):
    """All faces of the cells: corner keys (sorted), oriented corner faces, full faces, cell ids."""
    m = len(cells)
    corner = cells[:, :4]
    faces = corner[:, _TET_FACES].reshape(-1, 3)  # (4m, 3)
    opp = corner[np.arange(m)[:, None], _OPPOSITE[None, :]].reshape(-1)
    p0, p1, p2 = points[faces[:, 0]], points[faces[:, 1]], points[faces[:, 2]]
    normal = np.cross(p1 - p0, p2 - p0)
    inward = np.einsum("ij,ij->i", normal, points[opp] - p0) > 0
    local = np.tile(_TET_FACES, (m, 1))
    local[inward] = local[inward][:, [0, 2, 1]]  # flip to point outward
    cell_ids = np.repeat(np.arange(m), 4)
    oriented = cells[cell_ids[:, None], local]
    if cells.shape[1] == 10:
        mids = np.empty((len(local), 3), dtype=int)
        for j, (a, b) in enumerate([(0, 1), (1, 2), (2, 0)]):
            la, lb = local[:, a], local[:, b]
            lo, hi = np.minimum(la, lb), np.maximum(la, lb)
            lut = np.zeros((4, 4), dtype=int)
            for (i, k), v in _TET10_EDGE.items():
                lut[i, k] = v
            mids[:, j] = cells[cell_ids, lut[lo, hi]]
        full = np.hstack([oriented, mids])
    else:
        full = oriented
    keys = np.sort(oriented, axis=1)
    return keys, full, cell_ids


def _as_void(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a.astype(np.int64))
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel()


def interface_faces(mesh, regions_a, regions_b, origin=None):
    """Faces shared by a cell of regions_a and a cell of regions_b: (faces_a, faces_b) oriented
    outward of each side. ``origin`` (node id -> id of the node it was copied from): match faces by
    their original corners, so faces already detached along a line by an earlier split still match."""
    cells = np.asarray(mesh.cells)
    ca = np.unique(np.concatenate([np.asarray(mesh.regions[r]) for r in regions_a]))
    cb = np.unique(np.concatenate([np.asarray(mesh.regions[r]) for r in regions_b]))
    ka, fa, _ = _cell_faces(cells[ca], mesh.points)
    kb, fb, _ = _cell_faces(cells[cb], mesh.points)
    if origin is not None:
        ka, kb = np.sort(origin[fa[:, :3]], axis=1), np.sort(origin[fb[:, :3]], axis=1)
    _, ia, ib = np.intersect1d(_as_void(ka), _as_void(kb), assume_unique=False, return_indices=True)
    return fa[ia], fb[ib]


def _bonded_nodes(mesh, ra, rb, pairs, skip=()) -> np.ndarray:
    """Nodes of faces between side a (regions ra) and regions other than rb (and `skip`) that are not
    in contact with side a (no pair of `pairs`, a list of (regions, regions), joins them)."""
    sa = set(ra)
    contact = set(rb) | set(skip)
    for p, q in pairs:
        contact |= q if p == sa else p if q == sa else set()
    others = [r for r in mesh.regions if r not in sa and r not in contact]
    if not others:
        return np.zeros(0, dtype=int)
    faces_a, _ = interface_faces(mesh, ra, others)
    return np.unique(faces_a)


def split_interfaces(mesh, names, groups: dict[str, tuple[str, ...]] | None = None,
                     rim: tuple[str, ...] = ()) -> tuple[object, list[SplitInterface]]:
    """Duplicate the nodes of each named interface on its side b (the second group).

    Where side a also touches a region it stays bonded to, the nodes of that line stay tied (not
    split), unless the region is in the groups ``rim``: then the line is split too and its copies
    belong to side b and to that region (the tissue rim stays in one piece and slides; the rim
    region's bond to side a loses only that line).

    Returns a new mesh of the same dataclass type (points appended, side-b cells and side-b faces of
    the named surfaces renumbered) and one SplitInterface per name. Raises InputError for a name that
    is malformed, names a group without regions, or two groups that share no face.
    """
    points = np.asarray(mesh.points, dtype=float).copy()
    cells = np.asarray(mesh.cells).copy()
    surfaces = {k: np.asarray(v).copy() for k, v in mesh.surfaces.items()}
    origin = np.arange(len(points))  # node id -> the conforming mesh's node it was copied from
    out: list[SplitInterface] = []
    seen = set()
    pairs = [tuple(set(group_regions(mesh, g, groups)) for g in parse_interface_name(n)) for n in names]
    for name in names:
        ga, gb = parse_interface_name(name)
        if name in seen:
            raise InputError("interfaces", f"interface {name!r} given twice")
        seen.add(name)
        ra, rb = group_regions(mesh, ga, groups), group_regions(mesh, gb, groups)
        for g, r in ((ga, ra), (gb, rb)):
            if not r:
                raise InputError(
                    "interfaces",
                    f"interface {name!r}: no region matches {g!r}; regions in the mesh: {sorted(mesh.regions)}",
                )
        if set(ra) & set(rb):
            raise InputError("interfaces", f"interface {name!r}: both sides contain {sorted(set(ra) & set(rb))}")
        current = dataclasses.replace(mesh, points=points, cells=cells)
        # matched by original node ids: where an earlier split already gave side b its own copy (the
        # ring where needle, muscle and bone meet) the faces touching it are still this interface's
        # (by current ids, 19 of 190 muscle-bone faces of the default needle mesh were neither
        # bonded nor in contact there, docs/contact.md)
        faces_a, faces_b = interface_faces(current, ra, rb, origin)
        if len(faces_a) == 0:
            raise InputError(
                "interfaces",
                f"interface {name!r} does not exist in the mesh: regions {ra} and {rb} share no face",
            )
        # coincident node pairs (side a, side b) of the matched faces, aligned by original id
        oa, ob = origin[faces_a], origin[faces_b]
        ia, ib = np.argsort(oa, axis=1), np.argsort(ob, axis=1)
        pa = np.take_along_axis(faces_a, ia, axis=1).ravel()
        pb = np.take_along_axis(faces_b, ib, axis=1).ravel()
        pair = np.unique(np.c_[pa, pb], axis=0)
        shared = pair[pair[:, 0] == pair[:, 1], 0]
        # nodes where side a also touches a region it stays bonded to (the ring where needle, muscle
        # and adipose meet) are not split: a point of that line belongs to the bond, so side b stays
        # tied to side a there (split, the muscle rim tore off the adipose and Newton failed, docs/contact.md)
        rr = tuple(r for g in rim for r in group_regions(mesh, g, groups) if r not in ra + rb)
        nodes = np.setdiff1d(shared, _bonded_nodes(current, ra, rb, pairs, skip=rr))
        # pinch points of a staircase interface stay tied too: no virtual gap separates them
        nodes = nodes[~virtual_gap_offsets(points, triangles(faces_a), nodes, 1.0)[1]]
        new = np.arange(len(points), len(points) + len(nodes))
        remap = np.arange(len(points))
        remap[nodes] = new
        points = np.vstack([points, points[nodes]])
        origin = np.concatenate([origin, origin[nodes]])
        # pairs split before (side b already has its own copy) + the new copies
        apart = pair[pair[:, 0] != pair[:, 1]]
        nodes_a, nodes_b = np.r_[apart[:, 0], nodes], np.r_[remap[apart[:, 1]], new]
        cb = np.unique(np.concatenate([np.asarray(mesh.regions[r]) for r in rb]))
        # named surfaces: faces that lie on a side-b cell (and not on side a) follow side b
        if surfaces:
            kb, _, _ = _cell_faces(cells[cb], points)
            ca = np.unique(np.concatenate([np.asarray(mesh.regions[r]) for r in ra]))
            ka, _, _ = _cell_faces(cells[ca], points)
            vb, va = _as_void(kb), _as_void(ka)
            for key, f in surfaces.items():
                if len(f) == 0:
                    continue
                fk = _as_void(np.sort(f[:, :3], axis=1))
                move = np.isin(fk, vb) & ~np.isin(fk, va)
                f[move] = remap[f[move]]
        cells[cb] = remap[cells[cb]]
        if rr:  # the rim region's cells at the split line follow side b (its other nodes are not in `nodes`)
            cr = np.unique(np.concatenate([np.asarray(mesh.regions[r]) for r in rr]))
            cells[cr] = remap[cells[cr]]
        # earlier interfaces whose side lies in these regions follow the new node ids
        for k, prev in enumerate(out):
            if set(prev.regions_a) <= set(rb):
                prev = dataclasses.replace(prev, faces_a=remap[prev.faces_a], nodes_a=remap[prev.nodes_a],
                                           skirt_a=remap[prev.skirt_a])
            if set(prev.regions_b) <= set(rb):
                prev = dataclasses.replace(prev, faces_b=remap[prev.faces_b], nodes_b=remap[prev.nodes_b])
            out[k] = prev
        skirt = np.zeros((0, faces_a.shape[1]), dtype=int)
        if rr:
            fr, _ = interface_faces(dataclasses.replace(mesh, points=points, cells=cells), ra, rr, origin)
            skirt = fr[np.isin(fr, nodes[np.isin(new, cells[cr])]).any(axis=1)]
        out.append(
            SplitInterface(
                name=name,
                regions_a=ra,
                regions_b=rb,
                faces_a=faces_a,
                faces_b=remap[faces_b],
                nodes_a=nodes_a,
                nodes_b=nodes_b,
                skirt_a=skirt,
            )
        )
    new_mesh = dataclasses.replace(mesh, points=points, cells=cells, surfaces=surfaces)
    return new_mesh, out


def triangles(faces: np.ndarray) -> np.ndarray:
    """Linear triangles of (k,3) or (k,6) faces (a triangle6 is cut into four)."""
    faces = np.asarray(faces)
    if faces.shape[1] == 3:
        return faces
    a, b, c, ab, bc, ca = faces.T
    return np.vstack(
        [np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]]
    )


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit area-weighted vertex normals (n, 3) and tributary areas (n,) of a face set, per mesh point
    (zero where a point is not on the faces)."""
    t = triangles(faces)
    fn = np.cross(points[t[:, 1]] - points[t[:, 0]], points[t[:, 2]] - points[t[:, 0]])  # 2 area n
    normal, area = np.zeros((len(points), 3)), np.zeros(len(points))
    for j in range(3):
        np.add.at(normal, t[:, j], fn)
        np.add.at(area, t[:, j], np.linalg.norm(fn, axis=1) / 6)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    return normal, area


GAP_CAP = 3.0
"""Largest virtual-gap offset of a side-b vertex, x the gap: a node that needs more is a pinch point."""


def virtual_gap_offsets(points, tri_a, nodes, gap: float):
    """Virtual-gap offsets (len(nodes), 3) for the side-b copies of side-a nodes `nodes`: the shortest
    vector that puts the copy at least `gap` from the plane of every side-a triangle (`tri_a`, linear,
    outward of side a) at that node; the area-weighted vertex normal x gap where that already holds
    (smooth surfaces, to 0.1 %). Why: at the right-angled edges of a voxel staircase the vertex normal
    left side b gap/sqrt(2) from side a's faces, and at points where side a's faces point every way ~0:
    rest barrier distances of 1e-5 mm, where the barrier is 1e2-1e4 x stiffer (docs/contact.md).
    Also returns the mask of pinch nodes: no offset up to GAP_CAP x gap separates them (there the
    vertex normal is kept); split_interfaces leaves them tied."""
    from scipy.optimize import minimize

    tri_a = np.asarray(tri_a)
    nodes = np.asarray(nodes, dtype=int)
    out = np.zeros((len(nodes), 3))
    bad = np.zeros(len(nodes), bool)
    if len(tri_a) == 0 or len(nodes) == 0:
        return out, bad
    fn = np.cross(points[tri_a[:, 1]] - points[tri_a[:, 0]], points[tri_a[:, 2]] - points[tri_a[:, 0]])
    unit = fn / np.linalg.norm(fn, axis=1, keepdims=True)
    flat = tri_a.ravel()
    order = np.argsort(flat, kind="stable")
    ids, start = np.unique(flat[order], return_index=True)
    stop = np.append(start[1:], len(order))
    where = np.minimum(np.searchsorted(ids, nodes), len(ids) - 1)
    for i, w in enumerate(where):
        if ids[w] != nodes[i]:
            continue
        f = order[start[w]:stop[w]] // 3
        N, a = unit[f], fn[f].sum(axis=0)
        o = gap * a / max(np.linalg.norm(a), 1e-300)
        out[i] = o
        if (N @ o).min() >= gap * (1 - 1e-3):
            continue
        N = np.unique(np.round(N, 9), axis=0)
        r = minimize(lambda x: x @ x, o / max((N @ o).min() / gap, 0.2), jac=lambda x: 2 * x, method="SLSQP",
                     constraints=[{"type": "ineq", "fun": lambda x: N @ x - gap, "jac": lambda x: N}])
        if r.success and (N @ r.x).min() >= gap * (1 - 1e-3) and np.linalg.norm(r.x) <= GAP_CAP * gap:
            out[i] = r.x
        else:
            bad[i] = True
    return out, bad
