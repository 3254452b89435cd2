"""How well a tissue tetrahedral mesh matches its label map: quality, volumes, Dice, Hausdorff 95 %.

Measured on the grid the mesh was built from (the same crop / coarsening / region selection, see
tetmesh._crop_and_coarsen), so that the voxel route scores volume error 0 and Dice 1 by construction.
- volume: each region's mesh volume against its voxel count x voxel volume;
- Dice: the mesh voxelised at the voxel centres (the tissue of the tetrahedron holding each centre)
  against the label map; `bone` is cortical + cancellous (their split is a rule, not a boundary);
- Hausdorff 95 %: the mesh's tissue interfaces (faces between different tissues and the free
  boundary, bone merged) against the label boundaries (the voxel faces between different labels),
  95th percentile of the point-to-surface distances, taken both ways and the larger reported;
- sliver: a tetrahedron whose smallest dihedral angle is below SLIVER_DEG; inverted: volume <= 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SLIVER_DEG = 5.0
BONE = ("cortical_bone", "cancellous_bone")


@dataclass
class MeshFidelity:
    n_tetrahedra: int
    min_dihedral_deg: float
    p01_dihedral_deg: float
    n_inverted: int
    n_slivers: int                       # smallest dihedral angle < SLIVER_DEG
    n_below_10deg: int
    volume_error: dict[str, float]       # region -> mesh / label volume - 1
    dice: dict[str, float]               # region (and `bone`) -> Dice of the voxelised mesh
    hausdorff95_mm: float
    hausdorff95_voxels: float
    voxel_mm: float

    def worst_volume_error(self, names=None) -> float:
        v = self.volume_error if names is None else {k: self.volume_error[k] for k in names}
        return float(max(abs(x) for x in v.values()))


def _raw_boundaries(arr, sp):
    import pyvista as pv

    grid = pv.ImageData(dimensions=arr.shape[::-1], spacing=sp)
    grid.point_data["labels"] = np.ascontiguousarray(arr).ravel()
    return grid, grid.contour_labels("all", smoothing=False, output_mesh_type="triangles",
                                     pad_background=True, scalars="labels")


def mesh_fidelity(seg, mesh, config, solids=()) -> MeshFidelity:
    """Measure `mesh` (a TetMesh from tet_mesh(seg, config=config)) against its label map. solids: regions
    that are not in the label map (needles, clamp): no volume or Dice of their own, outside in the Dice of
    the tissues, and their surfaces left out of the Hausdorff distance."""
    import pyvista as pv

    from needletissue.geometry.tetmesh import _crop_and_coarsen, _row_groups, _sub_image, tet_quality

    arr, start, f, names = _crop_and_coarsen(seg, config)
    sub = _sub_image(seg, arr, start, f)
    sp = np.asarray(sub.GetSpacing(), float)
    d = np.asarray(sub.GetDirection(), float).reshape(3, 3)
    o = np.asarray(sub.GetOrigin(), float)
    x = (mesh.points - o) @ d                       # physical -> grid coordinates (index * spacing)
    q = tet_quality(mesh.points, mesh.cells)
    vol = q["volume"]
    vox = float(np.prod(sp))
    volume_error = {}
    regions = {n: ids for n, ids in mesh.regions.items() if n not in solids}
    for n, ids in regions.items():
        nv = int(np.count_nonzero(arr == seg.tissues[n]))
        volume_error[n] = float(vol[ids].sum() / (nv * vox) - 1.0) if nv else float("inf")
    bones_present = [n for n in BONE if n in mesh.regions]
    if len(bones_present) > 1:   # the outer bone surface is the interface; the split inside is a rule
        nv = int(np.count_nonzero(np.isin(arr, [seg.tissues[n] for n in bones_present])))
        volume_error["bone"] = float(sum(vol[mesh.regions[n]].sum() for n in bones_present) / (nv * vox) - 1.0)
    # voxelise the mesh: region tag (1-based, 0 outside) at every voxel centre
    tag = np.zeros(len(mesh.cells), np.int32)
    ids_of = {}
    for i, (n, ids) in enumerate(regions.items(), start=1):
        tag[ids] = i
        ids_of[n] = i
    cells = np.hstack([np.full((len(mesh.cells), 1), 4), mesh.cells]).ravel()
    ug = pv.UnstructuredGrid(cells, np.full(len(mesh.cells), 10, np.uint8), x)
    ug.cell_data["tag"] = tag
    ug = ug.cell_data_to_point_data() if False else ug
    ug.point_data["one"] = np.ones(len(x), np.float32)   # vtkProbeFilter needs point scalars on the source
    grid = pv.ImageData(dimensions=arr.shape[::-1], spacing=sp)
    grid.point_data["labels"] = np.ascontiguousarray(arr).ravel()  # vtkProbeFilter wants input scalars
    smp = grid.sample(ug, categorical=True, locator="static_cell")
    got = np.asarray(smp.point_data["tag"]).reshape(arr.shape)
    valid = np.asarray(smp.point_data["vtkValidPointMask"]).reshape(arr.shape).astype(bool)
    got = np.where(valid, got, 0)
    dice = {}
    groups = {n: [n] for n in regions}
    bones = [n for n in BONE if n in mesh.regions]
    if bones:
        groups["bone"] = bones
    for g, members in groups.items():
        a = np.isin(arr, [seg.tissues[n] for n in members])
        b = np.isin(got, [ids_of[n] for n in members])
        dice[g] = float(2 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1))
    # Hausdorff 95 % between the tissue interfaces (bone merged) and the label boundaries
    merged = arr.copy()
    bone_ids = [seg.tissues[n] for n in BONE if n in seg.tissues]
    if bone_ids:
        merged[np.isin(merged, bone_ids)] = bone_ids[0]
    _, raw = _raw_boundaries(merged, sp)
    mtag = tag.copy()
    for n in bones:
        mtag[mesh.regions[n]] = ids_of[bones[0]]
    loc = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    faces = np.concatenate([mesh.cells[:, fl] for fl in loc])
    owner = np.tile(np.arange(len(mesh.cells)), 4)
    key = np.sort(faces, axis=1)
    order, inv, cnt = _row_groups(key)                 # order = argsort(inv, kind="stable")
    pair = order[cnt[inv[order]] == 2].reshape(-1, 2)
    # faces of a solid's elements are no tissue boundary of the label map
    solid = np.zeros(len(mesh.cells), bool)
    for n in solids:
        solid[mesh.regions.get(n, [])] = True
    a, b = owner[pair[:, 0]], owner[pair[:, 1]]
    inter = pair[(mtag[a] != mtag[b]) & ~solid[a] & ~solid[b], 0]
    free = np.flatnonzero(cnt[inv] == 1)
    free = free[~solid[owner[free]]]
    sf = faces[np.concatenate([inter, free])]
    surf = pv.PolyData(x, np.hstack([np.full((len(sf), 1), 3), sf]).ravel()).clean()
    a2b = np.abs(pv.PolyData(np.asarray(surf.points)).compute_implicit_distance(raw)["implicit_distance"])
    b2a = np.abs(pv.PolyData(np.asarray(raw.points)).compute_implicit_distance(surf)["implicit_distance"])
    hd = float(max(np.percentile(a2b, 95), np.percentile(b2a, 95)))
    md = q["min_dihedral"]
    return MeshFidelity(
        n_tetrahedra=int(len(mesh.cells)), min_dihedral_deg=float(md.min()),
        p01_dihedral_deg=float(np.percentile(md, 1)), n_inverted=int(np.count_nonzero(vol <= 0)),
        n_slivers=int(np.count_nonzero(md < SLIVER_DEG)), n_below_10deg=int(np.count_nonzero(md < 10.0)),
        volume_error=volume_error, dice=dice, hausdorff95_mm=hd, hausdorff95_voxels=hd / float(sp.max()),
        voxel_mm=float(sp.max()))
