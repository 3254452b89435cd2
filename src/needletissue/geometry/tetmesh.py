"""Conforming multi-region tetrahedral meshes from a tissue label map (TetGen), written as gmsh .msh.

Route: the label map (optionally cropped and coarsened to the element size) -> every interface between
two labels as one conforming triangle set (surface nets, voxel faces) -> TetGen on that piecewise linear
complex with a maximum volume (size control) and a radius-edge/dihedral quality bound -> each tetrahedron
tagged with the label of the voxel holding its centroid (exact: facets are voxel faces, so no tetrahedron
straddles two labels) -> tetrahedra of label 0 (outside the body, organs not meshed) dropped.
Why TetGen: it meshes a non-manifold multi-region PLC in one pass (every region shares its interface
nodes with its neighbours), is fast (1.35 M tetrahedra of the example CT in about 30 s of CPU), and the
`tetgen` wheel installs everywhere. See docs/imaging.md for the alternatives.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, check_number


def regular_tet_volume(edge: float) -> float:
    return edge ** 3 / (6.0 * np.sqrt(2.0))


FAR_SIZE_MAX = 60   # mm: the largest graded far-field element size (MeshConfig.far_size and the models')


@dataclass
class MeshConfig:
    """Meshing parameters; lengths in mm."""

    size: float = 3.0                      # mm, target tetrahedron edge (paper: 3 mm tissue)
    # TetGen quality bounds (-q ratio/dihedral); None: the route's own (TETGEN_BOUNDS)
    min_dihedral: float | None = None      # degrees
    max_radius_edge: float | None = None
    regions: list[str] | None = None       # tissues to mesh (default: all but other_body)
    crop: tuple[float, ...] | None = None  # (xmin, xmax, ymin, ymax, zmin, zmax) LPS mm
    coarsen: bool = True                   # block-majority coarsening of voxels finer than size
    max_volume: float | None = None        # mm^3; None: bound only when size < voxel spacing
    method: str = "voxel"                  # "voxel": voxel-face interfaces; "smooth": geometry.smooth
    smoothing_iterations: int = 16         # smooth: surface-nets constrained smoothing passes
    smoothing_scale: float = 0.3           # smooth: max vertex move / voxel diagonal (1 = VTK default)
    # smooth with solids: element size (mm) at refine_radius mm from the solids and beyond, `size` at them
    # (CGAL's interfaces, geometry.graded); None or `size`: one size everywhere (surface nets)
    far_size: float | None = None
    refine_radius: float = 35.0            # mm: where the graded size reaches far_size

    def validate(self) -> "MeshConfig":
        check_number("size", self.size, gt=0.2, le=50)
        if self.min_dihedral is not None:
            check_number("min_dihedral", self.min_dihedral, ge=0, lt=30)
        if self.max_radius_edge is not None:
            check_number("max_radius_edge", self.max_radius_edge, ge=1.1, le=10)
        if self.method not in ("voxel", "smooth"):
            raise InputError("method", f"unknown meshing method {self.method!r}; known: voxel, smooth")
        check_number("smoothing_iterations", self.smoothing_iterations, ge=0, le=500)
        check_number("smoothing_scale", self.smoothing_scale, ge=0, le=2)
        if self.far_size is not None:
            check_number("far_size", self.far_size, ge=self.size, le=FAR_SIZE_MAX)
            if self.method != "smooth":
                raise InputError("far_size", "a graded size needs method='smooth'")
        check_number("refine_radius", self.refine_radius, gt=0, le=500)
        if self.max_volume is not None:
            check_number("max_volume", self.max_volume, gt=0)
        if self.crop is not None:
            c = [check_number(f"crop[{i}]", v) for i, v in enumerate(self.crop)]
            if len(c) != 6 or c[0] >= c[1] or c[2] >= c[3] or c[4] >= c[5]:
                raise InputError("crop", f"expected xmin<xmax, ymin<ymax, zmin<zmax (LPS mm), got {self.crop}")
        return self

    @property
    def graded(self) -> bool:
        """Sizes grow from `size` at the solids to `far_size` (CGAL's interfaces, geometry.graded)."""
        return self.far_size is not None and self.far_size > self.size

    def tetgen_bounds(self) -> tuple[float, float]:
        """(radius-edge ratio, min dihedral deg) for TetGen: the fields, else the route's defaults."""
        ratio, dihedral = TETGEN_BOUNDS[self.method]
        return (ratio if self.max_radius_edge is None else self.max_radius_edge,
                dihedral if self.min_dihedral is None else self.min_dihedral)


# smooth: no dihedral bound but a tighter ratio; the optimisation after TetGen does the angles (CT pelvis:
# TetGen 21.5 s CPU instead of 24.4 at 2/10, min / 1st pct 12.59 / 21.72 deg; docs/imaging.md)
TETGEN_BOUNDS = {"voxel": (2.0, 10.0), "smooth": (1.6, 0.0)}


@dataclass
class QualityReport:
    n_nodes: int
    n_tetrahedra: int
    tetrahedra_by_region: dict[str, int]
    volume_mm3_by_region: dict[str, float]
    min_dihedral_deg: float
    p01_dihedral_deg: float          # 1st percentile over all elements' smallest dihedral angle
    max_dihedral_deg: float
    min_radius_ratio: float          # 3 r_in / R_circ, 1 for the regular tetrahedron
    mean_radius_ratio: float
    mean_edge_mm: float


def tet_quality(points: np.ndarray, cells: np.ndarray) -> dict[str, np.ndarray]:
    """Per element: signed volume, smallest/largest dihedral angle (deg), radius ratio 3 r_in / R."""
    # per coordinate (m, 4) arrays: 1-D arithmetic instead of np.cross / einsum on (m, 3), 3x faster
    X = [points[:, k][cells] for k in range(3)]
    sub = lambda j, i: [X[k][:, j] - X[k][:, i] for k in range(3)]  # noqa: E731
    dot = lambda u, v: u[0] * v[0] + u[1] * v[1] + u[2] * v[2]  # noqa: E731

    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    vol = dot(cross(sub(1, 0), sub(2, 0)), sub(3, 0)) / 6.0
    # outward unit normals and areas of the faces opposite each vertex
    nh, area2 = [], []
    for i in range(4):
        a, b, c = [j for j in range(4) if j != i]
        n = cross(sub(b, a), sub(c, a))
        s = np.sign(dot(n, sub(a, i)))
        ln = np.sqrt(dot(n, n))
        area2.append(ln)
        nh.append([v * (s / np.maximum(ln, 1e-300)) for v in n])
    cos = np.stack([dot(nh[i], nh[j]) for i in range(4) for j in range(i + 1, 4)], 1)
    # dihedral = pi - arccos(cos) grows with cos: two arccos per element instead of six
    min_dih = np.degrees(np.pi - np.arccos(np.clip(cos.min(1), -1, 1)))
    max_dih = np.degrees(np.pi - np.arccos(np.clip(cos.max(1), -1, 1)))
    av = np.abs(vol)
    r_in = 3 * av / np.maximum(sum(area2) / 2.0, 1e-300)
    # circumradius from products of opposite edge lengths
    L = {(i, j): np.sqrt((lambda d: dot(d, d))(sub(j, i))) for i in range(4) for j in range(i + 1, 4)}
    aA, bB, cC = L[0, 1] * L[2, 3], L[0, 2] * L[1, 3], L[0, 3] * L[1, 2]
    prod = (aA + bB + cC) * (aA + bB - cC) * (aA - bB + cC) * (-aA + bB + cC)
    R = np.sqrt(np.maximum(prod, 0)) / np.maximum(24 * av, 1e-300)
    return {"volume": vol, "min_dihedral": min_dih, "max_dihedral": max_dih,
            "radius_ratio": 3 * r_in / np.maximum(R, 1e-300), "mean_edge": sum(L.values()) / 6.0}


@dataclass
class TetMesh:
    """Linear tetrahedra in LPS mm with named regions (cell ids) and named surfaces (node triples)."""

    points: np.ndarray
    cells: np.ndarray
    regions: dict[str, np.ndarray]
    surfaces: dict[str, np.ndarray] = field(default_factory=dict)
    materials: dict[str, str] = field(default_factory=dict)   # region -> material name
    info: dict = field(default_factory=dict)                  # how it was built (method, timings)

    def quality(self) -> QualityReport:
        q = tet_quality(self.points, self.cells)
        return QualityReport(
            n_nodes=len(self.points), n_tetrahedra=len(self.cells),
            tetrahedra_by_region={k: int(len(v)) for k, v in self.regions.items()},
            volume_mm3_by_region={k: float(q["volume"][v].sum()) for k, v in self.regions.items()},
            min_dihedral_deg=float(q["min_dihedral"].min()),
            p01_dihedral_deg=float(np.percentile(q["min_dihedral"], 1)),
            max_dihedral_deg=float(q["max_dihedral"].max()),
            min_radius_ratio=float(q["radius_ratio"].min()),
            mean_radius_ratio=float(q["radius_ratio"].mean()),
            mean_edge_mm=float(q["mean_edge"].mean()))

    def region_ids(self) -> np.ndarray:
        tag = np.zeros(len(self.cells), np.int32)
        for i, ids in enumerate(self.regions.values(), start=1):
            tag[ids] = i
        return tag

    def write_msh(self, path: str | Path) -> Path:
        """gmsh MSH 4.1: one discrete volume + NAMED physical volume per region, named physical surfaces."""
        import gmsh

        from needletissue.runinfo import make_dir

        path = Path(path)
        make_dir(path.parent)
        tmp = path.with_name(f".{path.stem}.tmp.msh")
        was_init = gmsh.isInitialized()
        if not was_init:
            from needletissue.geometry.gmsh_init import initialize  # keeps the SIGTERM handler

            initialize()
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(f"needletissue_{path.stem}")
        try:
            n = len(self.points)
            first = None
            tag = 1
            for i, (name, ids) in enumerate(self.regions.items(), start=1):
                gmsh.model.addDiscreteEntity(3, i)
                if first is None:
                    gmsh.model.mesh.addNodes(3, i, np.arange(1, n + 1), self.points.ravel())
                    first = i
                gmsh.model.mesh.addElementsByType(i, 4, np.arange(tag, tag + len(ids)),
                                                  (self.cells[ids] + 1).ravel())
                tag += len(ids)
                gmsh.model.addPhysicalGroup(3, [i], tag=i, name=name)
            for j, (name, faces) in enumerate(self.surfaces.items(), start=1):
                gmsh.model.addDiscreteEntity(2, j)
                gmsh.model.mesh.addElementsByType(j, 2, np.arange(tag, tag + len(faces)),
                                                  (faces + 1).ravel())
                tag += len(faces)
                gmsh.model.addPhysicalGroup(2, [j], tag=j, name=name)
            gmsh.option.setNumber("Mesh.MshFileVersion", 4.1)
            gmsh.option.setNumber("Mesh.Binary", 1)
            gmsh.write(str(tmp))
            tmp.replace(path)
        finally:
            gmsh.model.remove()
            if not was_init:
                gmsh.finalize()
        return path

    def to_meshio(self):
        import meshio

        return meshio.Mesh(self.points, [("tetra", self.cells)],
                           cell_data={"region": [self.region_ids()]})

    def write_vtu(self, path: str | Path) -> Path:
        """VTU with cell data `region` (1-based, in `regions` order), by VTK's writer at zlib level 1
        (runinfo.write_vtu): 1.1 s CPU for the 1.2 M-tetrahedron CT mesh instead of meshio's 3.9 s (level 6),
        24 instead of 23 MB, the same inline base64 blocks, so meshio reads it as fast."""
        from needletissue.runinfo import write_vtu

        return write_vtu(path, self.points, self.cells, cell_data={"region": self.region_ids()})


def _crop_and_coarsen(seg, cfg: MeshConfig):
    """Label array restricted to cfg.regions, cropped to cfg.crop, and the index offset/spacing used."""
    from needletissue.imaging.segment import NOT_MESHED

    arr = seg.array()
    names = ([n for n in seg.tissues if n not in NOT_MESHED] if cfg.regions is None
             else list(cfg.regions))
    unknown = [n for n in names if n not in seg.tissues]
    if unknown:
        raise InputError("regions", f"unknown region(s) {unknown}; known: {list(seg.tissues)}")
    keep = np.isin(arr, [seg.tissues[n] for n in names])
    arr = np.where(keep, arr, 0).astype(np.uint8)
    sp = np.asarray(seg.labels.GetSpacing(), float)  # (x, y, z)
    start = np.zeros(3, int)  # (x, y, z) index of the first voxel kept
    if cfg.crop is not None:
        d = np.asarray(seg.labels.GetDirection(), float).reshape(3, 3)
        o = np.asarray(seg.labels.GetOrigin(), float)
        c = np.asarray(cfg.crop, float).reshape(3, 2)
        corners = np.array([[c[0, a], c[1, b], c[2, g]] for a in (0, 1) for b in (0, 1) for g in (0, 1)])
        idx = (corners - o) @ d / sp  # physical -> continuous index
        lo = np.maximum(np.floor(idx.min(0)).astype(int), 0)
        hi = np.minimum(np.ceil(idx.max(0)).astype(int) + 1, arr.shape[::-1])
        if np.any(hi <= lo):
            raise InputError("crop", f"box {cfg.crop} (LPS mm) does not overlap the image")
        arr = arr[lo[2]:hi[2], lo[1]:hi[1], lo[0]:hi[0]]
        start = lo
    # coarsen to the element size by a block majority when voxels are much smaller than elements
    f = np.maximum(1, np.floor(cfg.size / sp + 1e-9).astype(int))  # (x, y, z)
    if not cfg.coarsen:
        f[:] = 1
    if np.any(f > 1):
        fz, fy, fx = f[::-1]
        nz, ny, nx = (np.asarray(arr.shape) // (fz, fy, fx))
        blocks = arr[:nz * fz, :ny * fy, :nx * fx].reshape(nz, fz, ny, fy, nx, fx)
        labs = np.unique(arr)
        counts = np.stack([(blocks == lab).sum(axis=(1, 3, 5)) for lab in labs])
        arr = labs[np.argmax(counts, 0)].astype(np.uint8)
    if not np.any(arr):
        raise InputError("regions", "nothing to mesh: the selected regions are empty in the crop box")
    present = set(np.unique(arr).tolist())
    if cfg.regions is None:  # default: whatever the crop holds
        names = [n for n in names if seg.tissues[n] in present]
    empty = [n for n in names if seg.tissues[n] not in present]
    if empty:
        raise InputError("regions", f"empty tissue(s) after crop/coarsening: {', '.join(empty)}")
    return arr, start, f, names


def _sub_image(seg, arr, start, f):
    """The (cropped, coarsened) label array as an image with its own origin in the physical frame."""
    import SimpleITK as sitk

    sub = sitk.GetImageFromArray(arr)
    sub.SetSpacing(tuple(np.asarray(seg.labels.GetSpacing(), float) * f))
    sub.SetDirection(seg.labels.GetDirection())
    # centre of the first coarse voxel: block of f voxels starting at `start`
    first_centre = np.asarray(start, float) + (f - 1) / 2.0
    sub.SetOrigin(seg.labels.TransformContinuousIndexToPhysicalPoint(first_centre.tolist()))
    return sub


def _grid_frame(seg, arr, start, f):
    """Spacing (x, y, z) of the meshed grid and the map grid coordinates (index * spacing) -> LPS mm."""
    from needletissue.geometry.surfaces import image_to_pyvista

    _, to_phys = image_to_pyvista(_sub_image(seg, arr, start, f), arr)
    return np.asarray(seg.labels.GetSpacing(), float) * f, to_phys


def tet_mesh(seg, size: float = 3.0, config: MeshConfig | None = None, solids=None, **kw) -> TetMesh:
    """Conforming multi-region tetrahedral mesh of a Segmentation (tissues -> named regions).

    Size control: label maps finer than `size` (mm) are coarsened by a block majority, so interface
    triangles have edges of about `size`; inside, TetGen grades the elements under its quality bound.
    When `size` is below the voxel spacing (or `max_volume` is given) the tetrahedron volume is bounded
    by that of a regular tetrahedron of edge `size` (mean edge then about 0.9 `size`). Extra solids
    (needles, clamp) enter exactly as `solids` (smooth.Solids, method "smooth"), or painted into the label
    map first (geometry.solids; voxel staircases).
    """
    import tetgen

    from needletissue.geometry.surfaces import image_to_pyvista, label_boundaries
    from needletissue.imaging.segment import material_for

    cfg = config or MeshConfig(size=size, **kw)
    cfg.validate()
    if cfg.method == "smooth":
        from needletissue.geometry.smooth import smooth_tet_mesh

        return smooth_tet_mesh(seg, cfg, solids)
    if solids is not None:
        raise InputError("method", "exact solids (needles, clamp) need method 'smooth'")
    arr, start, f, names = _crop_and_coarsen(seg, cfg)
    sp, to_phys = _grid_frame(seg, arr, start, f)
    grid, _ = image_to_pyvista(_sub_image(seg, arr, start, f), arr)
    plc = label_boundaries(grid)
    if plc.n_cells == 0:
        raise InputError("regions", "no interface to mesh")
    bound = cfg.max_volume
    if bound is None and cfg.size < 0.999 * sp.min():
        bound = regular_tet_volume(cfg.size)
    ratio, dihedral = cfg.tetgen_bounds()
    tg = tetgen.TetGen(np.asarray(plc.points, float), np.asarray(plc.regular_faces, np.int32))
    try:
        nodes, elem, _, _ = tg.tetrahedralize(
            plc=True, quality=True, minratio=ratio, mindihedral=dihedral,
            fixedvolume=bound is not None, maxvolume=-1.0 if bound is None else float(bound),
            quiet=True, nowarning=True)
    except RuntimeError as exc:
        raise InputError("mesh", f"TetGen failed on the tissue interfaces: {exc}") from None
    nodes = np.asarray(nodes, float)
    elem = np.asarray(elem, np.int64)[:, :4]
    centroids = nodes[elem].mean(1)
    ijk = np.floor(centroids / sp + 0.5).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(arr.shape[::-1]) - 1)
    tag = arr[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    inside = tag > 0
    elem, tag = elem[inside], tag[inside]
    used, inv = np.unique(elem, return_inverse=True)
    cells = inv.reshape(elem.shape).astype(np.int64)
    points = to_phys(nodes[used])
    vol = tet_quality(points, cells)["volume"]
    cells[vol < 0] = cells[vol < 0][:, [0, 2, 1, 3]]  # positive orientation
    regions = {n: np.flatnonzero(tag == seg.tissues[n]) for n in names}
    regions = {n: ids for n, ids in regions.items() if len(ids)}
    mesh = TetMesh(points=points, cells=cells, regions=regions,
                   materials={n: material_for(n) for n in regions})
    mesh.surfaces = interface_surfaces(mesh)
    if seg.bones is not None and "bone_surface" in mesh.surfaces:
        mesh.surfaces.update(bone_surfaces_by_bone(mesh, seg.bones, 0.5 * float(sp.min())))
    return mesh


def bone_surfaces_by_bone(mesh: TetMesh, bones_img, depth: float) -> dict[str, np.ndarray]:
    """Split `bone_surface` by bone (bones.nii.gz): `bone_surface_sacrum`, `bone_surface_hip_left`, ...
    for boundary conditions (fixed sacrum, femoral sections) and fragments. Each face is assigned the
    bone found `depth` mm inside it."""
    import SimpleITK as sitk

    from needletissue.imaging.segment import BONE_IDS

    faces = mesh.surfaces["bone_surface"]
    p = mesh.points[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    x = p.mean(1) - depth * n  # faces point out of the bone
    D = np.asarray(bones_img.GetDirection(), float).reshape(3, 3)
    sp = np.asarray(bones_img.GetSpacing(), float)
    ijk = np.floor((x - np.asarray(bones_img.GetOrigin())) @ D / sp + 0.5).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(bones_img.GetSize()) - 1)
    arr = sitk.GetArrayViewFromImage(bones_img)
    bid = np.asarray(arr)[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    return {f"bone_surface_{name}": faces[bid == i] for name, i in BONE_IDS.items() if np.any(bid == i)}


def unique_rows(rows: np.ndarray):
    """np.unique(rows, axis=0, return_index, return_inverse, return_counts) for an integer (n, k) array,
    same groups in the same (lexicographic) order; by lexsort, because np.unique(axis=0) sorts a void
    view and took 15-40 s on the 4.7 M faces of a 1.2 M-tetrahedron mesh. Returns (first, inverse, counts)."""
    order, inv, cnt = _row_groups(rows)
    return order[np.cumsum(cnt) - cnt], inv, cnt


def _row_groups(rows: np.ndarray):
    """(stable order of the rows sorted lexicographically, group id per row, group sizes)."""
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo, m = int(rows.min()), int(rows.max()) - int(rows.min()) + 1
    if m ** rows.shape[1] < 2 ** 62:   # one int64 key per row, same order: one argsort, 4x faster than lexsort
        key = np.zeros(len(rows), np.int64)
        for j in range(rows.shape[1]):
            key = key * m + (rows[:, j] - lo)
        order = np.argsort(key, kind="stable")
        s = key[order]
        new = np.concatenate([[True], s[1:] != s[:-1]])
    else:
        order = np.lexsort(rows.T[::-1])
        s = rows[order]
        new = np.concatenate([[True], np.any(s[1:] != s[:-1], axis=1)])
    gid = np.cumsum(new) - 1
    inv = np.empty(len(rows), np.int64)
    inv[order] = gid
    return order, inv, np.bincount(gid)


def face_pairs(cells: np.ndarray, tag: np.ndarray, pairs: bool = False):
    """Faces of positive tetrahedra: (ids of faces between different tags, ids of free faces, faces), and
    with `pairs` the (k, 2) ids of every face shared by two cells.

    Face k belongs to cell k % len(cells); an interface face is listed once, oriented out of one owner."""
    loc = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    faces = np.concatenate([cells[:, f] for f in loc])
    owner = np.tile(np.arange(len(cells)), 4)
    order, inv, cnt = _row_groups(np.sort(faces, axis=1))   # order = argsort(inv, kind="stable")
    pair = order[cnt[inv[order]] == 2].reshape(-1, 2)
    inter = pair[tag[owner[pair[:, 0]]] != tag[owner[pair[:, 1]]], 0]
    out = inter, np.flatnonzero(cnt[inv] == 1), faces
    return out + (pair,) if pairs else out


def interface_surfaces(mesh: TetMesh) -> dict[str, np.ndarray]:
    """Named triangle sets: `boundary` (free faces), `bone_surface` (bone / non-bone interface)."""
    tag = mesh.region_ids()
    names = list(mesh.regions)
    is_bone = np.array([False] + [n in ("cortical_bone", "cancellous_bone") for n in names])
    loc = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]  # outward faces of a positive tetrahedron
    faces = np.concatenate([mesh.cells[:, f] for f in loc])
    owner = np.tile(np.arange(len(mesh.cells)), 4)
    order, inv, cnt = _row_groups(np.sort(faces, axis=1))   # order = argsort(inv, kind="stable")
    out = {"boundary": faces[cnt[inv] == 1]}
    # interior faces: pair the two owners
    shared = cnt[inv[order]] == 2
    o = order[shared].reshape(-1, 2)
    ta, tb = tag[owner[o[:, 0]]], tag[owner[o[:, 1]]]
    bone_face = is_bone[ta] != is_bone[tb]
    # orient outward from the bone
    pick = np.where(is_bone[ta[bone_face]], o[bone_face, 0], o[bone_face, 1])
    if len(pick):
        out["bone_surface"] = faces[pick]
    return out
