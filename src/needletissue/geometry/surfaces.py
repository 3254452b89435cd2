"""Tissue surfaces from a label map: per-tissue closed surfaces and the conforming multi-label set.

Per tissue: discrete flying edges (marching cubes on the binary mask), windowed-sinc smoothing (a
low-pass filter that, unlike Laplacian smoothing, does not shrink the surface), quadric decimation
with volume preservation, then a check that the result is watertight and manifold.
The conforming multi-label surface for tetrahedral meshing comes from surface nets (VTK
SurfaceNets3D), see label_boundaries().
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, check_number


def image_to_pyvista(labels_img, array: np.ndarray | None = None):
    """SimpleITK label image -> pyvista ImageData in index*spacing coordinates (origin 0, no rotation).

    Returns (grid, to_physical) where to_physical(points) maps grid coordinates to LPS mm.
    """
    import pyvista as pv
    import SimpleITK as sitk

    arr = sitk.GetArrayFromImage(labels_img) if array is None else array
    sp = np.asarray(labels_img.GetSpacing(), float)
    grid = pv.ImageData(dimensions=arr.shape[::-1], spacing=sp)
    grid.point_data["labels"] = np.ascontiguousarray(arr).ravel()
    d = np.asarray(labels_img.GetDirection(), float).reshape(3, 3)
    o = np.asarray(labels_img.GetOrigin(), float)

    def to_physical(points: np.ndarray) -> np.ndarray:
        return o + np.asarray(points, float) @ d.T

    to_physical.flips = np.linalg.det(d) < 0  # orientation of triangles/tets must be flipped
    to_physical.inverse = lambda x: (np.asarray(x, float) - o) @ d  # LPS mm -> grid coordinates
    return grid, to_physical


@dataclass
class SurfaceReport:
    name: str
    label: int | list
    n_points: int
    n_triangles: int
    watertight: bool
    manifold: bool
    volume_mm3: float
    voxel_volume_mm3: float
    area_mm2: float

    @property
    def volume_change(self) -> float:
        return self.volume_mm3 / self.voxel_volume_mm3 - 1.0


@dataclass
class TissueSurfaces:
    surfaces: dict = field(default_factory=dict)   # name -> pyvista PolyData (LPS mm)
    reports: dict = field(default_factory=dict)    # name -> SurfaceReport

    def write(self, out_dir: str | Path, formats=("stl", "vtp")) -> list[Path]:
        from needletissue.runinfo import make_dir

        out_dir = make_dir(out_dir)
        paths = []
        for name, surf in self.surfaces.items():
            for ext in formats:
                path = out_dir / f"{name}.{ext}"
                tmp = out_dir / f".{name}.tmp.{ext}"
                surf.save(str(tmp), binary=True)
                tmp.replace(path)
                paths.append(path)
        return paths


def tissue_surface(labels_img, label, *, smoothing_iterations: int = 20, passband: float = 0.05,
                   target_edge_mm: float | None = None, array=None):
    """One closed, smoothed, decimated surface of the voxels whose label is `label` (an id or a tuple
    of ids, e.g. both bone labels for the outer bone surface), in LPS mm."""
    import pyvista as pv
    import vtk

    grid, to_phys = image_to_pyvista(labels_img, array)
    arr = np.asarray(grid.point_data["labels"]).reshape(grid.dimensions[::-1])
    mask = np.isin(arr, np.atleast_1d(label)).astype(np.uint8)
    if not mask.any():
        raise InputError("labels", f"empty tissue: label {label} has no voxel")
    padded = np.pad(mask, 1)  # closes surfaces that touch the image border
    sp = np.asarray(grid.spacing)
    g = pv.ImageData(dimensions=padded.shape[::-1], spacing=sp, origin=-sp)
    g.point_data["m"] = padded.ravel()
    fe = vtk.vtkDiscreteFlyingEdges3D()
    fe.SetInputData(g)
    fe.SetValue(0, 1)
    fe.ComputeNormalsOff()
    fe.Update()
    surf = pv.wrap(fe.GetOutput()).clean().triangulate()
    if smoothing_iterations > 0:
        sm = vtk.vtkWindowedSincPolyDataFilter()
        sm.SetInputData(surf)
        sm.SetNumberOfIterations(int(smoothing_iterations))
        sm.SetPassBand(float(passband))
        sm.NormalizeCoordinatesOn()
        sm.BoundarySmoothingOff()
        sm.FeatureEdgeSmoothingOff()
        sm.NonManifoldSmoothingOn()
        sm.Update()
        surf = pv.wrap(sm.GetOutput())
    if target_edge_mm is not None:
        check_number("target_edge_mm", target_edge_mm, gt=0)
        edge = float(np.mean(sp)) / np.sqrt(2.0) * 1.2  # typical flying-edges edge length
        reduction = 1.0 - min(1.0, (edge / target_edge_mm) ** 2)
        if reduction > 0.05:
            surf = surf.decimate(reduction, volume_preservation=True)
    surf = surf.clean()
    surf.points = to_phys(surf.points)
    if to_phys.flips:
        surf = surf.flip_faces()
    surf = surf.compute_normals(auto_orient_normals=True, cell_normals=False, split_vertices=False)
    return surf, float(mask.sum() * np.prod(sp))


def surfaces(seg, tissues: list[str] | None = None, *, smoothing_iterations: int = 20,
             target_edge_mm: float | None = None) -> TissueSurfaces:
    """Closed surfaces of each tissue of a Segmentation, with a watertight/manifold/volume report."""
    from needletissue.imaging.segment import NOT_MESHED

    names = [n for n in seg.tissues if n not in NOT_MESHED] if tissues is None else list(tissues)
    unknown = [n for n in names if n not in seg.tissues]
    if unknown:
        raise InputError("tissues", f"unknown tissue(s) {unknown}; known: {list(seg.tissues)}")
    arr = seg.array()
    out = TissueSurfaces()
    groups = {n: seg.tissues[n] for n in names}
    bones = tuple(seg.tissues[n] for n in ("cortical_bone", "cancellous_bone") if n in seg.tissues)
    if tissues is None and len(bones) > 1:
        groups["bone"] = bones  # the outer bone surface (the cortex alone is a thin shell)
    for name, lab in groups.items():
        surf, vvox = tissue_surface(seg.labels, lab, smoothing_iterations=smoothing_iterations,
                                    target_edge_mm=target_edge_mm, array=arr)
        out.surfaces[name] = surf
        out.reports[name] = SurfaceReport(
            name=name, label=lab if np.isscalar(lab) else list(lab), n_points=surf.n_points, n_triangles=surf.n_cells,
            watertight=surf.n_open_edges == 0, manifold=bool(surf.is_manifold),
            volume_mm3=float(abs(surf.volume)), voxel_volume_mm3=vvox, area_mm2=float(surf.area))
    return out


def write_surfaces(directory: str, regions: list[str] | None, out: str) -> dict:
    """`needletissue mesh`'s viewing surfaces of the segmentation in `directory`, written to `out`; returns
    the report per tissue as JSON-able dicts and the wall time. Run in a child process by the command, in
    parallel with the tetrahedral mesh (they are independent)."""
    import time
    from dataclasses import asdict

    from needletissue.imaging.segment import Segmentation

    t0 = time.perf_counter()
    ts = surfaces(Segmentation.load(directory), regions)
    ts.write(out)
    reports = {n: {**asdict(r), "volume_change": r.volume_change} for n, r in ts.reports.items()}
    return {"reports": reports, "wall_time_s": time.perf_counter() - t0}


def label_boundaries(grid, *, smoothing: bool = False):
    """All interfaces between different labels (incl. background 0) as one conforming triangle set.

    Surface nets without smoothing put every vertex on a voxel corner: the facets are exact voxel faces,
    meet only along shared edges, and never intersect, which is what a TetGen PLC needs. (Smoothed
    surface nets pull apart the sheets where regions touch only along a voxel edge and then overlap.)
    Returns PolyData with cell data 'boundary_labels' (n, 2).
    """
    surf = grid.contour_labels("all", output_mesh_type="triangles", smoothing=smoothing,
                               pad_background=True, scalars="labels")
    return surf.clean()
