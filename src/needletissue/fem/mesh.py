"""Tetrahedral meshes with named regions (physical volumes) and surfaces (physical surfaces).

Node order is VTK's (and FElupe's): tetra10 midpoints on edges 01, 12, 02, 03, 13, 23;
triangle6 midpoints on edges 01, 12, 20. Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.cells import GMSH_TO_VTK_TET10, TET10_EDGES
from needletissue.errors import InputError


@dataclass
class TaggedMesh:
    """A tetrahedral mesh with named regions and boundary surfaces.

    points   : (n, 3) float, mm
    cells    : (m, 4) tetra or (m, 10) tetra10, VTK node order
    regions  : name -> (k,) cell ids (physical volumes, e.g. "muscle", "needle_1")
    surfaces : name -> (k, 3) triangle or (k, 6) triangle6 node ids (physical surfaces, e.g. "top")
    """

    points: np.ndarray
    cells: np.ndarray
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    surfaces: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=float)
        self.cells = np.ascontiguousarray(self.cells, dtype=np.int64)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise InputError("mesh.points", f"expected shape (n, 3), got {self.points.shape}")
        if self.cells.ndim != 2 or self.cells.shape[1] not in (4, 10):
            raise InputError("mesh.cells", f"expected shape (m, 4) or (m, 10), got {self.cells.shape}")
        self.regions = {str(k): np.asarray(v, dtype=np.int64).ravel() for k, v in self.regions.items()}
        self.surfaces = {str(k): np.asarray(v, dtype=np.int64).reshape(len(v), -1)
                         for k, v in self.surfaces.items()}
        if not self.regions:
            self.regions = {"solid": np.arange(len(self.cells))}

    # ------------------------------------------------------------------ properties
    @property
    def order(self) -> int:
        """1 for tetra, 2 for tetra10."""
        return 1 if self.cells.shape[1] == 4 else 2

    @property
    def cell_type(self) -> str:
        return "tetra" if self.order == 1 else "tetra10"

    def region_of_cells(self) -> np.ndarray:
        """(m,) int tag per cell: index into list(regions) (-1 when untagged)."""
        tag = np.full(len(self.cells), -1, dtype=np.int64)
        for i, ids in enumerate(self.regions.values()):
            tag[ids] = i
        return tag

    def surface_nodes(self, name: str) -> np.ndarray:
        """Sorted unique node ids of a named surface (InputError when unknown)."""
        if name not in self.surfaces:
            raise InputError("surface", f"unknown surface {name!r}; known: {', '.join(self.surfaces) or 'none'}")
        return np.unique(self.surfaces[name])

    def surface_area(self, name: str) -> float:
        """Reference area of a named surface, mm^2."""
        return float(_triangle_areas(self.points, self.surfaces[name]).sum())

    def nodal_area_weights(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(nodes, weights): consistent nodal shares of a uniform unit traction, summing to the area.

        Flat triangles: area/3 per corner; flat 6-node triangles: 0 per corner, area/3 per midside
        node (the exact integrals of the quadratic shape functions).
        """
        tris = self.surfaces[name]
        area = _triangle_areas(self.points, tris)
        w = np.zeros(len(self.points))
        if tris.shape[1] == 3:
            np.add.at(w, tris.ravel(), np.repeat(area / 3, 3))
        else:
            np.add.at(w, tris[:, 3:].ravel(), np.repeat(area / 3, 3))
        nodes = np.unique(tris)
        return nodes, w[nodes]

    # ------------------------------------------------------------------ I/O
    @classmethod
    def read(cls, source) -> "TaggedMesh":
        """From a file any meshio can read (gmsh .msh first) or a meshio.Mesh.

        Physical volumes name regions and physical surfaces name surfaces (gmsh's field_data);
        without physical names every tetrahedron goes to region "solid". Unused points are dropped.
        """
        import meshio

        if isinstance(source, (str, Path)):
            path = Path(source)
            if not path.exists():
                raise InputError("mesh", f"file not found: {path}")
            try:
                source = meshio.read(path)
            except Exception as exc:  # meshio raises many types
                raise InputError("mesh", f"cannot read {path}: {exc}") from None
        m = source
        names = {}  # (dim, tag) -> name
        for name, (tag, dim) in getattr(m, "field_data", {}).items():
            names[(int(dim), int(tag))] = name
        phys = m.cell_data.get("gmsh:physical")
        vol_type = "tetra10" if any(b.type == "tetra10" for b in m.cells) else "tetra"
        tri_type = "triangle6" if vol_type == "tetra10" else "triangle"
        cells, vol_tags, tris, tri_tags = [], [], [], []
        for i, block in enumerate(m.cells):
            tags = np.asarray(phys[i]) if phys is not None else np.zeros(len(block.data), int)
            if block.type == vol_type:
                cells.append(block.data)
                vol_tags.append(tags)
            elif block.type == tri_type:
                tris.append(block.data)
                tri_tags.append(tags)
        if not cells:
            raise InputError("mesh", f"no tetrahedra in mesh (cell types: {[b.type for b in m.cells]})")
        cells = np.concatenate(cells)
        vol_tags = np.concatenate(vol_tags)
        regions = {}
        for t in np.unique(vol_tags):
            regions[names.get((3, int(t)), "solid" if len(names) == 0 else f"volume_{t}")] = np.flatnonzero(vol_tags == t)
        surfaces = {}
        if tris:
            tris = np.concatenate(tris)
            tri_tags = np.concatenate(tri_tags)
            for t in np.unique(tri_tags):
                if (2, int(t)) in names:
                    surfaces[names[(2, int(t))]] = tris[tri_tags == t]
        return cls(np.asarray(m.points)[:, :3], cells, regions, surfaces).pruned()

    @classmethod
    def from_gmsh(cls) -> "TaggedMesh":
        """From the live gmsh model (after gmsh.model.mesh.generate(3)), by physical groups."""
        import gmsh

        tags, coords, _ = gmsh.model.mesh.getNodes()
        index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
        index[tags.astype(np.int64)] = np.arange(len(tags))
        points = coords.reshape(-1, 3)
        cells, regions, surfaces = [], {}, {}
        ncell = 0
        for dim, ptag in gmsh.model.getPhysicalGroups():
            name = gmsh.model.getPhysicalName(dim, ptag) or f"{'volume' if dim == 3 else 'surface'}_{ptag}"
            blocks = []
            for ent in gmsh.model.getEntitiesForPhysicalGroup(dim, ptag):
                etypes, _, enodes = gmsh.model.mesh.getElements(dim, ent)
                for et, en in zip(etypes, enodes):
                    nn = {4: 4, 11: 10, 2: 3, 9: 6}.get(int(et))
                    if nn is None:
                        raise InputError("mesh", f"unsupported gmsh element type {et} in group {name!r}")
                    blocks.append(index[en.astype(np.int64)].reshape(-1, nn))
            if not blocks:
                continue
            conn = np.concatenate(blocks)
            if dim == 3:
                if conn.shape[1] == 10:
                    conn = conn[:, GMSH_TO_VTK_TET10]
                cells.append(conn)
                regions[name] = np.arange(ncell, ncell + len(conn))
                ncell += len(conn)
            elif dim == 2:
                surfaces[name] = conn
        if not cells:
            raise InputError("mesh", "the gmsh model has no physical volume with tetrahedra")
        return cls(points, np.concatenate(cells), regions, surfaces).pruned()

    def write(self, path) -> Path:
        """Write as any meshio format (VTU/XDMF/msh) with a cell_data 'region' tag."""
        import meshio

        from needletissue.runinfo import write_atomic

        path = Path(path)
        m = meshio.Mesh(self.points, [(self.cell_type, self.cells)],
                        cell_data={"region": [self.region_of_cells()]})
        tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
        meshio.write(tmp, m)
        write_atomic(path, tmp.read_bytes())
        tmp.unlink()
        return path

    # ------------------------------------------------------------------ transforms
    def pruned(self) -> "TaggedMesh":
        """Drop points used by no tetrahedron (surfaces are renumbered)."""
        used = np.zeros(len(self.points), bool)
        used[self.cells] = True
        if used.all():
            return self
        new = np.full(len(self.points), -1, dtype=np.int64)
        new[used] = np.arange(used.sum())
        surfaces = {}
        for k, tri in self.surfaces.items():
            if (new[tri] < 0).any():
                raise InputError(f"surface {k!r}", "has nodes that belong to no tetrahedron")
            surfaces[k] = new[tri]
        return TaggedMesh(self.points[used], new[self.cells], self.regions, surfaces)

    def to_quadratic(self) -> "TaggedMesh":
        """tetra -> tetra10 by edge midpoints on the merged mesh (FElupe's add_midpoints_edges);
        regions keep their cell ids, surfaces become triangle6 sharing the same midpoint nodes."""
        import felupe as fem

        if self.order == 2:
            return self
        m = fem.Mesh(self.points, self.cells, "tetra").add_midpoints_edges()
        cells = np.asarray(m.cells)
        # edge (i, j) sorted -> midpoint node id, from the tetra10 connectivity
        a = cells[:, TET10_EDGES[:, 0]].ravel()
        b = cells[:, TET10_EDGES[:, 1]].ravel()
        mid = cells[:, 4:].ravel()
        n = len(m.points)
        key = np.minimum(a, b) * n + np.maximum(a, b)
        order = np.argsort(key)
        key, mid = key[order], mid[order]
        surfaces = {}
        for k, tri in self.surfaces.items():
            e = np.stack([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]], axis=1)  # (k,3,2)
            q = np.minimum(e[..., 0], e[..., 1]) * n + np.maximum(e[..., 0], e[..., 1])
            pos = np.searchsorted(key, q)
            if (pos >= len(key)).any() or (key[np.minimum(pos, len(key) - 1)] != q).any():
                raise InputError(f"surface {k!r}", "has edges that are not tetrahedron edges")
            surfaces[k] = np.hstack([tri, mid[pos]])
        return TaggedMesh(np.asarray(m.points), cells, dict(self.regions), surfaces)

    def submesh_cells(self, region: str) -> np.ndarray:
        return self.cells[self.regions[region]]

    # ------------------------------------------------------------------ quality
    def volumes(self) -> np.ndarray:
        """Signed volume of each tetrahedron from its corners, mm^3 (negative = inverted)."""
        p = self.points[self.cells[:, :4]]
        return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6

    def quality(self) -> np.ndarray:
        """Mean-ratio quality of each tetrahedron's corners, 1 = regular, 0 = degenerate, < 0 inverted:
        q = 12 (3 V)^(2/3) / sum of squared edge lengths."""
        p = self.points[self.cells[:, :4]]
        v = self.volumes()
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        l2 = sum(((p[:, i] - p[:, j]) ** 2).sum(1) for i, j in pairs)
        return np.sign(v) * 12 * np.cbrt(3 * np.abs(v)) ** 2 / np.where(l2 > 0, l2, np.inf)

    def stats(self) -> dict:
        """Nodes, tetrahedra, cells per region, surface triangles, min quality, size of the box (mm)."""
        q = self.quality()
        return {
            "nodes": int(len(self.points)),
            "tetrahedra": int(len(self.cells)),
            "cell_type": self.cell_type,
            "cells_by_region": {k: int(len(v)) for k, v in self.regions.items()},
            "triangles_by_surface": {k: int(len(v)) for k, v in self.surfaces.items()},
            "min_quality": float(q.min()) if len(q) else float("nan"),
            "mean_quality": float(q.mean()) if len(q) else float("nan"),
            "bounding_box_mm": [self.points.min(0).tolist(), self.points.max(0).tolist()],
        }

    def check(self, regions=(), surfaces=(), min_quality: float = 1e-4) -> "TaggedMesh":
        """Raise InputError on inverted/degenerate tetrahedra, cells outside every region, node ids
        out of range, or a missing named region/surface. Returns self."""
        n = len(self.points)
        if self.cells.min(initial=0) < 0 or self.cells.max(initial=0) >= n:
            raise InputError("mesh.cells", f"node ids must be in [0, {n - 1}]")
        for k, tri in self.surfaces.items():
            if tri.size and (tri.min() < 0 or tri.max() >= n):
                raise InputError(f"surface {k!r}", f"node ids must be in [0, {n - 1}]")
        for k, ids in self.regions.items():
            if ids.size == 0:
                raise InputError(f"region {k!r}", "has no tetrahedra; every region needs >= 1 cell")
            if ids.min() < 0 or ids.max() >= len(self.cells):
                raise InputError(f"region {k!r}", f"cell ids must be in [0, {len(self.cells) - 1}]")
        tag = self.region_of_cells()
        if (tag < 0).any():
            raise InputError("mesh.regions", f"{int((tag < 0).sum())} tetrahedra belong to no region")
        q = self.quality()
        bad = np.flatnonzero(q < min_quality)
        if bad.size:
            kind = "inverted" if (q[bad] < 0).any() else "degenerate"
            raise InputError("mesh.cells", f"{bad.size} {kind} tetrahedra (quality < {min_quality}), "
                             f"first cell {int(bad[0])} with quality {q[bad[0]]:.3g}; allowed: quality >= {min_quality}")
        for name in regions:
            if name not in self.regions:
                raise InputError("mesh.regions", f"missing region {name!r}; present: {', '.join(self.regions)}")
        for name in surfaces:
            if name not in self.surfaces:
                raise InputError("mesh.surfaces", f"missing surface {name!r}; present: {', '.join(self.surfaces) or 'none'}")
        return self

    # ------------------------------------------------------------------ simple geometry
    @classmethod
    def box(cls, size=(1.0, 1.0, 1.0), n=(2, 2, 2), origin=(0.0, 0.0, 0.0), region: str = "solid",
            layers: dict[str, tuple[float, float]] | None = None) -> "TaggedMesh":
        """Structured tetrahedral box (FElupe Cube, 6 tets per hexahedron), size in mm, n nodes per axis.

        Surfaces: xmin, xmax, ymin, ymax, zmin, zmax. `layers` = {name: (z_lo, z_hi)} splits the
        cells into regions by centroid height (mm); otherwise all cells are `region`.
        """
        import felupe as fem

        for i, k in enumerate(n):
            if int(k) < 2:
                raise InputError("box.n", f"need >= 2 nodes per axis, got {n}")
        a = np.asarray(origin, float)
        b = a + np.asarray(size, float)
        m = fem.Cube(a=tuple(a), b=tuple(b), n=tuple(int(k) for k in n)).triangulate()
        points, cells = np.asarray(m.points), np.asarray(m.cells)
        # orient all tets positively
        p = points[cells]
        v = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
        cells[v < 0] = cells[v < 0][:, [0, 2, 1, 3]]
        if layers:
            zc = points[cells, 2].mean(1)
            regions = {k: np.flatnonzero((zc >= lo) & (zc < hi)) for k, (lo, hi) in layers.items()}
        else:
            regions = {region: np.arange(len(cells))}
        surfaces = {}
        faces = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
        tri = cells[:, faces].reshape(-1, 3)
        tol = 1e-9 * max(size)
        for axis, ax in enumerate("xyz"):
            for side, val in (("min", a[axis]), ("max", b[axis])):
                on = np.abs(points[tri, axis] - val).max(1) < tol
                surfaces[f"{ax}{side}"] = tri[on]
        return cls(points, cells, regions, surfaces)


def _triangle_areas(points, tris) -> np.ndarray:
    p = points[tris[:, :3]]
    return 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
