"""Second source: bone surfaces (e.g. the mean pelvis of a statistical shape model) -> tissue layers.

The bones are voxelised on a regular grid; muscle and adipose are the shells 0 < d <= t_muscle and
t_muscle < d <= t_muscle + t_adipose at distance d outside the bone surface (as the paper built its
adipose layer by thickening); bone is split by the same inward offset rule as CT bone. The result is a
Segmentation, so surfaces(), tet_mesh() and thickness_along() apply unchanged.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from needletissue.errors import InputError, check_number


@dataclass
class LayerConfig:
    """Layer thicknesses (mm) and grid spacing (mm). Defaults: paper Table 1 (Z1 = 22, Z2 = 10 mm)."""

    muscle_thickness: float = 22.0
    adipose_thickness: float = 10.0
    cortical_thickness: float = 1.5
    spacing: float = 2.0
    split_spacing: float = 0.75

    def validate(self) -> "LayerConfig":
        check_number("muscle_thickness", self.muscle_thickness, ge=0, le=200)
        check_number("adipose_thickness", self.adipose_thickness, ge=0, le=200)
        check_number("cortical_thickness", self.cortical_thickness, gt=0, le=10)
        check_number("spacing", self.spacing, gt=0.2, le=10)
        check_number("split_spacing", self.split_spacing, gt=0.05, le=5)
        return self


def _read_surface(path):
    import pyvista as pv

    path = Path(path)
    if not path.is_file():
        raise InputError("surface", f"{path}: no such file")
    try:
        surf = pv.read(str(path))
    except Exception as exc:  # VTK readers raise assorted types
        raise InputError("surface", f"{path}: not a readable surface ({exc})") from None
    if not isinstance(surf, pv.PolyData):
        surf = surf.extract_surface()
    surf = surf.triangulate().clean()
    if surf.n_cells == 0:
        raise InputError("surface", f"{path}: no triangles")
    if surf.n_open_edges:
        raise InputError("surface", f"{path}: not watertight ({surf.n_open_edges} open edges)")
    return surf


def from_surfaces(paths, config: LayerConfig | None = None, names=None):
    """Segmentation (cortical/cancellous bone, muscle, adipose) around closed bone surfaces (mm).

    `names` (optional) are bone names from imaging.segment.BONE_IDS for bones.nii.gz, one per path.
    """
    import pyvista as pv
    import SimpleITK as sitk

    from needletissue.imaging.segment import BONE_IDS, TISSUE_IDS, Segmentation, split_bone

    cfg = (config or LayerConfig()).validate()
    surfs = [_read_surface(p) for p in paths]
    if not surfs:
        raise InputError("surface", "no bone surface given")
    bounds = np.array([s.bounds for s in surfs])
    lo = bounds[:, 0::2].min(0)
    hi = bounds[:, 1::2].max(0)
    h = cfg.spacing
    margin = cfg.muscle_thickness + cfg.adipose_thickness + 3 * h
    lo, hi = lo - margin, hi + margin
    dims = np.ceil((hi - lo) / h).astype(int) + 1
    grid = pv.ImageData(dimensions=dims, spacing=(h, h, h), origin=lo)
    bone_ids = np.zeros(dims[::-1], np.uint8)
    for i, s in enumerate(surfs):
        m = s.voxelize_binary_mask(reference_volume=grid)
        mask = np.asarray(m.point_data["mask"]).reshape(dims[::-1]).astype(bool)
        bone_ids[mask & (bone_ids == 0)] = i + 1
    bone = bone_ids > 0
    if not bone.any():
        raise InputError("surface", "surfaces enclose no voxel at this spacing")
    # distance outside the bone surface: EDT to the nearest bone voxel centre minus half a voxel
    d_out = ndi.distance_transform_edt(~bone, sampling=h) - 0.5 * h
    out = np.zeros(bone.shape, np.uint8)
    tm, ta = cfg.muscle_thickness, cfg.adipose_thickness
    out[(~bone) & (d_out <= tm)] = TISSUE_IDS["muscle"]
    out[(~bone) & (d_out > tm) & (d_out <= tm + ta)] = TISSUE_IDS["adipose"]
    cort, canc, info = split_bone(bone, (h, h, h), cfg.cortical_thickness, cfg.split_spacing)
    out[canc] = TISSUE_IDS["cancellous_bone"]
    out[cort] = TISSUE_IDS["cortical_bone"]
    tissues = {n: TISSUE_IDS[n] for n in ("cortical_bone", "cancellous_bone", "adipose", "muscle")
               if np.any(out == TISSUE_IDS[n])}
    img = sitk.GetImageFromArray(out)
    img.SetSpacing((h, h, h))
    img.SetOrigin(tuple(lo))
    seg = Segmentation(labels=img, tissues=tissues, source=", ".join(str(p) for p in paths),
                       stats={"source": "bone surfaces + offset layers", "bone_split": info,
                              "config": asdict(cfg)})
    if names is not None:
        if len(names) != len(paths):
            raise InputError("names", "one bone name per surface")
        bones = np.zeros_like(out)
        for i, n in enumerate(names):
            if n not in BONE_IDS:
                raise InputError("names", f"unknown bone {n!r}; known: {list(BONE_IDS)}")
            bones[bone_ids == i + 1] = BONE_IDS[n]
        seg.bones = sitk.GetImageFromArray(bones)
        seg.bones.CopyInformation(img)
    seg.stats["volumes_mm3"] = seg.volumes_mm3()
    return seg


def mean_pelvis(config: LayerConfig | None = None):
    """The packaged/shared mean pelvis (two hip bones + sacrum) with muscle and adipose layers."""
    from needletissue.imaging.data import SSM_NAMES, data_path

    paths = [data_path(n) for n in SSM_NAMES]
    return from_surfaces(paths, config, names=["hip_left", "hip_right", "sacrum"])
