"""Extra solids (needles, clamp) inserted into a tissue label map before tetrahedral meshing.

The label-map route keeps every region conforming for free: a solid painted into the map becomes one
more label, and tet_mesh() meshes its interfaces with the tissues like any other. A 5 mm needle needs
voxels of about 1 mm: resample() the map (nearest neighbour, optionally cropped to a box around the
pins) first, paint, then mesh with MeshConfig(coarsen=False).
"""

from __future__ import annotations

import numpy as np

from needletissue.errors import InputError, check_number

SOLID_ID_START = 40  # label ids of added solids: 40, 41, ...


def resample(seg, spacing: float, crop=None):
    """The Segmentation on an isotropic grid of `spacing` mm (nearest neighbour), optionally cropped
    to crop = (xmin, xmax, ymin, ymax, zmin, zmax) in LPS mm."""
    import SimpleITK as sitk

    from needletissue.imaging.segment import Segmentation

    h = check_number("spacing", spacing, gt=0.1, le=20)
    img = seg.labels
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    sp = np.asarray(img.GetSpacing(), float)
    size = np.asarray(img.GetSize())
    # physical extent in the image axes (voxel edges)
    lo_idx, hi_idx = -0.5 * np.ones(3), size - 0.5
    if crop is not None:
        c = np.asarray(crop, float).reshape(3, 2)
        corners = np.array([[c[0, a], c[1, b], c[2, g]] for a in (0, 1) for b in (0, 1) for g in (0, 1)])
        idx = (corners - np.asarray(img.GetOrigin())) @ D / sp
        lo_idx = np.maximum(lo_idx, idx.min(0))
        hi_idx = np.minimum(hi_idx, idx.max(0))
        if np.any(hi_idx <= lo_idx):
            raise InputError("crop", f"box {crop} (LPS mm) does not overlap the image")
    n = np.maximum(1, np.round((hi_idx - lo_idx) * sp / h).astype(int))
    first = lo_idx + 0.5 * h / sp  # continuous index of the first new voxel centre
    origin = np.asarray(img.GetOrigin()) + D @ (first * sp)
    ref = sitk.Image([int(v) for v in n], img.GetPixelID())
    ref.SetSpacing((h, h, h))
    ref.SetDirection(img.GetDirection())
    ref.SetOrigin(tuple(origin))
    out = sitk.Resample(img, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    bones = None
    if seg.bones is not None:
        bones = sitk.Resample(seg.bones, ref, sitk.Transform(), sitk.sitkNearestNeighbor, 0)
    return Segmentation(labels=out, tissues=dict(seg.tissues), source=seg.source,
                        stats=dict(seg.stats), bones=bones)


def _voxel_centres(img, box_lo, box_hi):
    """Index ranges and physical centres of the voxels whose centres may lie in a physical box."""
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    sp = np.asarray(img.GetSpacing(), float)
    o = np.asarray(img.GetOrigin(), float)
    corners = np.array([[x, y, z] for x in (box_lo[0], box_hi[0]) for y in (box_lo[1], box_hi[1])
                        for z in (box_lo[2], box_hi[2])])
    idx = (corners - o) @ D / sp
    lo = np.maximum(np.floor(idx.min(0)).astype(int), 0)
    hi = np.minimum(np.ceil(idx.max(0)).astype(int) + 1, np.asarray(img.GetSize()))
    if np.any(hi <= lo):
        return None, None
    ii, jj, kk = np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij")
    ijk = np.stack([ii.ravel(), jj.ravel(), kk.ravel()], 1)
    return ijk, o + (ijk * sp) @ D.T


def _paint(seg, name: str, inside_fn, box_lo, box_hi):
    import SimpleITK as sitk

    if name in seg.tissues:
        raise InputError("name", f"region {name!r} already exists")
    arr = sitk.GetArrayFromImage(seg.labels)
    ijk, pts = _voxel_centres(seg.labels, box_lo, box_hi)
    if ijk is None:
        raise InputError(name, "solid lies outside the image")
    hit = inside_fn(pts)
    if not hit.any():
        raise InputError(name, "solid covers no voxel centre: resample to a finer spacing first")
    lab = max([SOLID_ID_START - 1] + [v for v in seg.tissues.values() if v >= SOLID_ID_START]) + 1
    if lab > 255:
        raise InputError(name, "too many regions for a uint8 label map")
    h = ijk[hit]
    arr[h[:, 2], h[:, 1], h[:, 0]] = lab
    img = sitk.GetImageFromArray(arr)
    img.CopyInformation(seg.labels)
    seg.labels = img
    seg.tissues[name] = lab
    return seg


def paint_cylinder(seg, name: str, p0, p1, radius: float):
    """Paint a solid cylinder (axis p0 -> p1, LPS mm) as a new region `name` (in place; returns seg)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    r = check_number("radius", radius, gt=0)
    axis = p1 - p0
    L = np.linalg.norm(axis)
    if L <= 0:
        raise InputError("p1", "cylinder axis has zero length")
    a = axis / L

    def inside(x):
        t = (x - p0) @ a
        rad = np.linalg.norm((x - p0) - t[:, None] * a, axis=1)
        return (t >= 0) & (t <= L) & (rad <= r)

    lo = np.minimum(p0, p1) - r
    hi = np.maximum(p0, p1) + r
    return _paint(seg, name, inside, lo, hi)


def paint_box(seg, name: str, centre, axes, half_sizes):
    """Paint an oriented box (centre, 3 orthonormal axes as rows, half sizes in mm) as region `name`."""
    c = np.asarray(centre, float)
    ax = np.asarray(axes, float).reshape(3, 3)
    hs = np.asarray(half_sizes, float)
    if not np.allclose(ax @ ax.T, np.eye(3), atol=1e-6):
        raise InputError("axes", "box axes must be orthonormal")
    if np.any(hs <= 0):
        raise InputError("half_sizes", "must be > 0 mm")

    def inside(x):
        return np.all(np.abs((x - c) @ ax.T) <= hs, axis=1)

    ext = np.abs(ax.T) @ hs
    return _paint(seg, name, inside, c - ext, c + ext)
