"""Anatomical pelvis geometry: tissue label volumes, a standard needle site, and a conforming tet mesh.

Pipeline (units mm):
  source (CT + label map, or SSM bone surfaces)  -> LabelVolume (tissue id per voxel, cropped hemipelvis)
  LabelVolume + NeedleSite                       -> gmsh: crop box fragmented with two needle cylinders
                                                    and a clamp bar (OCC), graded mesh around the needles
  tets of the box                                -> tissue per tet from smoothed label indicators at the
                                                    centroid; void tets dropped; one face-connected body kept
  -> PelvisMesh (points, tets, regions, boundary/load surfaces), conforming by construction (one mesh).

Region boundaries inside the anatomy follow element faces (the CT is 3 mm isotropic, so the anatomy is
not known more finely than the tissue elements); needles and clamp are exact OCC solids.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, check_number
from needletissue.cache import cache_key, mesh_cache_dir, read_entry, sha256, write_entry
from needletissue.geometry.tetmesh import FAR_SIZE_MAX, unique_rows

# Tissue ids of a LabelVolume (0 = void: air, viscera, anything not modelled).
TISSUES = {
    1: "hip_bone",
    2: "sacrum",
    3: "femur",
    4: "gluteus_maximus",
    5: "gluteus_medius",
    6: "gluteus_minimus",
    7: "iliopsoas",
    8: "adipose",
    9: "body_wall",
}
RAS_LPS = np.array([-1.0, -1.0, 1.0])  # RAS <-> LPS: x and y negated (a rotation by pi about z: orientation kept)
SOFT_TISSUES = ("adipose", "iliopsoas", "gluteus_medius", "gluteus_maximus", "gluteus_minimus", "body_wall")
# body_wall (skin and the unlabelled muscles of the trunk and thigh wall: obliques, sartorius, tensor
# fasciae latae) is muscle-like tissue: it counts as muscle in the thickness along a needle.
MUSCLES = ("iliopsoas", "gluteus_medius", "gluteus_maximus", "gluteus_minimus", "body_wall")

# TotalSegmentator "fast, force split" class ids (data README) per side.
CT_LABELS = {
    "right": {"hip_bone": 78, "sacrum": 25, "femur": 76, "gluteus_maximus": 81, "gluteus_medius": 83,
              "gluteus_minimus": 85, "iliopsoas": 89},
    "left": {"hip_bone": 77, "sacrum": 25, "femur": 75, "gluteus_maximus": 80, "gluteus_medius": 82,
             "gluteus_minimus": 84, "iliopsoas": 88},
}
FAT_HU = (-190.0, -30.0)  # subcutaneous/intermuscular fat window (data README)
SOFT_HU = (-30.0, 150.0)  # unlabelled non-fat soft tissue (muscle, skin, viscera)
BODY_WALL_MM = 25.0  # unlabelled soft tissue this close to the skin is body wall; deeper = viscera (void)


def data_dir() -> Path:
    """`$NEEDLETISSUE_DATA` or <repo root>/../shared/data; InputError when absent."""
    from needletissue.imaging.data import shared_data_dir

    path = shared_data_dir()
    if path is None or not path.is_dir():
        raise InputError("data", f"data folder not found at {path or '<repo>/../shared/data'}: "
                         "set NEEDLETISSUE_DATA or provide ../shared/data")
    return path.resolve()


@dataclass
class LabelVolume:
    """Tissue ids (TISSUES) on a regular grid: point of voxel (i,j,k) = origin + spacing*(i,j,k), mm.

    Axes are patient RAS (x right, y anterior, z superior) for both sources.
    """

    labels: np.ndarray
    origin: np.ndarray
    spacing: float
    side: str
    source: str
    notes: list = field(default_factory=list)

    def world(self, ijk):
        return self.origin + self.spacing * np.asarray(ijk, float)

    def index(self, xyz):
        return (np.asarray(xyz, float) - self.origin) / self.spacing

    @property
    def bounds(self):
        lo = self.origin - 0.5 * self.spacing
        return lo, lo + self.spacing * np.array(self.labels.shape)

    def sample(self, xyz):
        """Nearest-voxel tissue id at points (n,3); 0 outside the grid."""
        ijk = np.rint(self.index(np.atleast_2d(xyz))).astype(int)
        ok = np.all((ijk >= 0) & (ijk < np.array(self.labels.shape)), axis=1)
        out = np.zeros(len(ijk), int)
        out[ok] = self.labels[tuple(ijk[ok].T)]
        return out


def _crop_hemipelvis(lab: np.ndarray, origin, spacing, side, margin_mm=1e9, femur_mm=45.0):
    """Keep one hemipelvis: from the sacrum's mid-sagittal plane to the lateral skin, from the proximal
    femur (femur_mm below the femoral head top) up; all of y. `crop_to_site` trims the top."""
    sac = np.argwhere(lab == 2)
    hip = np.argwhere(lab == 1)
    fem = np.argwhere(lab == 3)
    if len(sac) == 0 or len(hip) == 0 or len(fem) == 0:
        raise InputError("labels", "label map lacks sacrum, hip bone or femur on the chosen side")
    imid = int(round(np.median(sac[:, 0])))
    m = int(np.ceil(margin_mm / spacing))
    k_top = min(lab.shape[2], hip[:, 2].max() + 1 + m)
    k_bot = max(0, fem[:, 2].max() - int(round(femur_mm / spacing)))
    if side == "right":
        i0, i1 = imid, lab.shape[0]
    else:
        i0, i1 = 0, imid + 1
    sl = (slice(i0, i1), slice(0, lab.shape[1]), slice(k_bot, k_top))
    return lab[sl], origin + spacing * np.array([i0, 0, k_bot], float), sl


def ct_label_volume(ct: str | Path | None = None, labels: str | Path | None = None, side: str = "right",
                    fat_hu=FAT_HU) -> LabelVolume:
    """Tissue labels from the example CT: bones and muscles from the label map, adipose from HU.

    Adipose = voxels in the body with HU in `fat_hu` and no label; everything else unlabelled (skin,
    viscera, other muscles, air) is void. Side 'right' by default: the lowest slices of the left femur
    carry streak artefact (data README).
    """
    import nibabel as nib

    if side not in CT_LABELS:
        raise InputError("side", f"must be 'right' or 'left', got {side!r}")
    d = None
    if ct is None or labels is None:
        d = data_dir() / "pelvis_ct"
    ct = Path(ct) if ct is not None else d / "example_ct.nii.gz"
    labels = Path(labels) if labels is not None else d / "example_seg_fast_force_split.nii.gz"
    from needletissue.imaging.io import check_complete

    for name, p in (("ct", ct), ("labels", labels)):
        if not p.is_file():
            raise InputError(name, f"file not found: {p}")
        check_complete(p, name)  # whole gzip stream, every voxel, no NaN: before nibabel reads it
    img_ct, img_lab = nib.as_closest_canonical(nib.load(ct)), nib.as_closest_canonical(nib.load(labels))
    hu = np.asarray(img_ct.dataobj, dtype=np.float32)
    seg = np.asarray(img_lab.dataobj).astype(np.int32)
    if hu.shape != seg.shape:
        raise InputError("labels", f"label map grid {seg.shape} does not match the CT grid {hu.shape}")
    if not np.allclose(img_ct.affine, img_lab.affine, atol=1e-3):
        shift = float(np.abs(img_ct.affine - img_lab.affine).max())
        raise InputError("labels", f"label map is not on the CT's grid: their voxel-to-mm affines differ by up to "
                                   f"{shift:.3g} mm (same shape {hu.shape}); resample the labels onto the CT")
    present = set(np.unique(seg).tolist())
    missing = [f"{name} (id {i})" for name, i in CT_LABELS[side].items() if i not in present]
    if missing:
        raise InputError("labels", f"label map has no {', '.join(missing)} for the {side} side; the model "
                                   f"needs every tissue of {sorted(CT_LABELS[side])} (TotalSegmentator ids)")
    A = img_ct.affine
    sp = np.abs(np.diag(A[:3, :3]))
    if not np.allclose(sp, sp[0], rtol=1e-3) or not np.allclose(A[:3, :3], np.diag(np.diag(A[:3, :3]))):
        raise InputError("ct", f"needs an axis-aligned isotropic grid, got spacing {sp}")
    spacing = float(sp[0])
    lab = np.zeros(seg.shape, np.uint8)
    for tid, name in TISSUES.items():
        if name in CT_LABELS[side]:
            lab[seg == CT_LABELS[side][name]] = tid
    free = (lab == 0) & (seg == 0)
    lab[free & (hu >= fat_hu[0]) & (hu <= fat_hu[1])] = 8
    from scipy import ndimage

    body = np.zeros(hu.shape, bool)
    for k in range(hu.shape[2]):  # body outline per axial slice (bowel gas inside is body)
        body[:, :, k] = ndimage.binary_fill_holes(hu[:, :, k] > -400)
    skin_depth = ndimage.distance_transform_edt(body, sampling=spacing)
    lab[free & (hu > SOFT_HU[0]) & (hu <= SOFT_HU[1]) & (skin_depth <= BODY_WALL_MM)] = 9
    lab, origin, _ = _crop_hemipelvis(lab, A[:3, 3].astype(float), spacing, side)
    vol = LabelVolume(lab, origin, spacing, side, f"ct:{ct.name}+{labels.name}")
    vol.notes += [
        f"adipose = unlabelled body voxels with {fat_hu[0]} <= HU <= {fat_hu[1]} (subcutaneous, "
        "intermuscular and visceral fat)",
        f"body_wall = unlabelled voxels with {SOFT_HU[0]} < HU <= {SOFT_HU[1]} within {BODY_WALL_MM} mm of the "
        "skin (skin, oblique abdominal muscles, sartorius, tensor fasciae latae); deeper unlabelled tissue "
        "(viscera) and air are void",
    ]
    return vol


def segmentation_label_volume(seg, side: str = "right") -> LabelVolume:
    """The model's LabelVolume (RAS, one hemipelvis) from a `needletissue segment` result (imaging.segment.
    Segmentation with bones.nii.gz): hip / sacrum / femur of the chosen side from the bones image, the
    side's four muscles, adipose, and other_soft_tissue as body_wall (all of it: the segmentation already
    leaves organs out). The same label map the smooth mesher meshes, so site, paths and mesh agree."""
    import SimpleITK as sitk

    from needletissue.imaging.segment import BONE_IDS

    if side not in CT_LABELS:
        raise InputError("side", f"must be 'right' or 'left', got {side!r}")
    if seg.bones is None:
        raise InputError("segmentation", "has no bones.nii.gz: run `needletissue segment` with --labels (the model "
                                         "needs hip bone, sacrum and femur apart)")
    D = np.asarray(seg.labels.GetDirection(), float).reshape(3, 3)
    sp = np.asarray(seg.labels.GetSpacing(), float)
    if not np.allclose(np.abs(D), np.eye(3)) or not np.allclose(sp, sp[0], rtol=1e-3):
        raise InputError("segmentation", f"needs an axis-aligned isotropic grid, got spacing {sp}")
    flip = np.diag(D) * RAS_LPS < 0           # index axes along which RAS decreases: reversed
    view = lambda img: np.flip(sitk.GetArrayFromImage(img).transpose(2, 1, 0), tuple(np.flatnonzero(flip)))  # noqa: E731
    tis, bones = view(seg.labels), view(seg.bones)
    lab = np.zeros(tis.shape, np.uint8)
    ids = {n: i for i, n in TISSUES.items()}
    for name, tid in (("hip_bone", f"hip_{side}"), ("sacrum", "sacrum"), ("femur", f"femur_{side}")):
        lab[bones == BONE_IDS[tid]] = ids[name]
    for name in ("gluteus_maximus", "gluteus_medius", "gluteus_minimus", "iliopsoas"):
        for n in (f"{name}_{side}", name):
            if n in seg.tissues:
                lab[(tis == seg.tissues[n]) & (lab == 0)] = ids[name]
    for n, name in (("adipose", "adipose"), ("other_soft_tissue", "body_wall")):
        if n in seg.tissues:
            lab[(tis == seg.tissues[n]) & (lab == 0)] = ids[name]
    missing = [n for n in ("hip_bone", "sacrum", "femur", "gluteus_maximus", "gluteus_medius", "gluteus_minimus",
                           "iliopsoas", "adipose") if not np.any(lab == ids[n])]
    if missing:
        raise InputError("segmentation", f"has no {', '.join(missing)} on the {side} side; the model needs every "
                                         "one of them")
    first = np.where(flip, np.array(tis.shape) - 1, 0)
    origin = np.asarray(seg.labels.TransformContinuousIndexToPhysicalPoint(first.astype(float).tolist())) * RAS_LPS
    lab, origin, _ = _crop_hemipelvis(lab, origin, float(sp[0]), side)
    vol = LabelVolume(lab, origin, float(sp[0]), side, f"segmentation:{seg.source or 'in memory'}")
    vol.notes.append("labels from the segmentation (imaging.segment): body_wall = its other_soft_tissue")
    return vol


def label_volume_segmentation(vol: LabelVolume, cortical_thickness: float = 1.5):
    """The Segmentation (imaging.segment, LPS image) of a LabelVolume that has no CT (the SSM's): what the
    smooth mesher meshes. Bone split into cortical / cancellous as `segment` splits it, muscles by name,
    body_wall as other_soft_tissue, and bones.nii.gz with hip / sacrum / femur of vol.side, so that
    segmentation_label_volume gives the same labels back."""
    import SimpleITK as sitk

    from needletissue.imaging.segment import BONE_IDS, TISSUE_IDS, Segmentation, SegmentationConfig, split_bone

    cfg = SegmentationConfig(cortical_thickness=cortical_thickness).validate()
    lab = vol.labels.transpose(2, 1, 0)          # (z, y, x) index order of a SimpleITK array
    sp = np.full(3, vol.spacing)
    cortical, cancellous, split = split_bone(np.isin(lab, (1, 2, 3)), sp, cfg.cortical_thickness, cfg.split_spacing)
    out = np.zeros(lab.shape, np.uint8)
    bones = np.zeros(lab.shape, np.uint8)
    names = {"hip_bone": f"hip_{vol.side}", "sacrum": "sacrum", "femur": f"femur_{vol.side}"}
    tissues = {}
    for i, name in TISSUES.items():
        m = lab == i
        if not m.any():
            continue
        if name in names:
            bones[m] = BONE_IDS[names[name]]
            continue
        tname = {"body_wall": "other_soft_tissue"}.get(name, name)
        out[m] = TISSUE_IDS[tname]
        tissues[tname] = TISSUE_IDS[tname]
    out[cancellous], out[cortical] = TISSUE_IDS["cancellous_bone"], TISSUE_IDS["cortical_bone"]
    tissues.update({n: TISSUE_IDS[n] for n, m in (("cortical_bone", cortical), ("cancellous_bone", cancellous))
                    if m.any()})

    def image(a):   # RAS index axes x, y -> LPS: the same voxels with x and y pointing the other way
        img = sitk.GetImageFromArray(a)
        img.SetSpacing(sp.tolist())
        img.SetOrigin((vol.origin * RAS_LPS).tolist())
        img.SetDirection(np.diag(RAS_LPS).ravel().tolist())
        return img

    seg = Segmentation(labels=image(out), tissues=dict(sorted(tissues.items(), key=lambda kv: kv[1])),
                       source=vol.source, stats={"bone_split": split}, bones=image(bones))
    seg.stats["volumes_mm3"] = seg.volumes_mm3()
    return seg


def ssm_label_volume(side: str = "right", spacing: float = 2.0, muscle_mm: float = 22.0,
                     adipose_mm: float = 10.0) -> LabelVolume:
    """Tissue labels around the mean SSM hip bone and sacrum (bone surfaces only).

    Soft tissue is built by offsetting, as the paper built its adipose layer: a muscle layer of
    `muscle_mm` around the hip bone (medial side of the wing -> iliopsoas, lateral side -> gluteus
    minimus, medius, maximus by depth thirds), then an adipose layer of `adipose_mm` (the paper's
    Table 1 thicknesses). There is no femur in the SSM: a femoral-head proxy (sphere fitted into the
    acetabulum) carries the femoral boundary condition.
    """
    import pyvista as pv
    from scipy import ndimage

    check_number("spacing", spacing, gt=0.5, le=6)
    d = data_dir() / "pelvis_ssm"
    # The SSM frame is LPS-like (+y posterior: the sacrum lies at larger y than the hips; +z superior),
    # so the "xpos" hip is the left one. Rotate 180 deg about z into RAS.
    def load(name):
        m = pv.read(d / f"LLP26_mean_{name}.stl")
        m.points = m.points * RAS_LPS
        return m

    hip = load("hip_xneg" if side == "right" else "hip_xpos")
    sac = load("sacrum")
    lateral = 1.0 if side == "right" else -1.0
    pad = muscle_mm + adipose_mm + 3 * spacing
    lo = np.minimum(hip.bounds[::2], sac.bounds[::2]) - pad
    hi = np.maximum(hip.bounds[1::2], sac.bounds[1::2]) + pad
    cx = sac.center[0]
    if side == "right":
        lo[0] = cx
    else:
        hi[0] = cx
    shape = np.ceil((hi - lo) / spacing).astype(int) + 1
    grid = np.stack(np.meshgrid(*[lo[a] + spacing * np.arange(shape[a]) for a in range(3)], indexing="ij"), -1)
    pts = pv.PolyData(grid.reshape(-1, 3))

    def inside(surf):
        import warnings

        with warnings.catch_warnings():  # renamed in newer PyVista; same VTK filter
            warnings.simplefilter("ignore")
            sel = pts.select_enclosed_points(surf, tolerance=1e-6, check_surface=False)
        return np.asarray(sel["SelectedPoints"], bool).reshape(shape)

    hipm, sacm = inside(hip), inside(sac)
    lab = np.zeros(shape, np.uint8)
    lab[hipm] = 1
    lab[sacm & ~hipm] = 2
    bone = hipm | sacm
    dist = ndimage.distance_transform_edt(~bone, sampling=spacing)
    dhip = ndimage.distance_transform_edt(~hipm, sampling=spacing)
    # Femoral head proxy: close the hip bone with a 26 mm ball (EDT dilation then erosion); of the
    # concavities this fills, the acetabulum is the most lateral one.
    closed = ndimage.distance_transform_edt(dhip <= 26.0, sampling=spacing) > 26.0
    socket = closed & ~bone
    cc, n = ndimage.label(socket)
    if n == 0:
        raise InputError("ssm", "no acetabulum found on the SSM hip bone")
    sizes = ndimage.sum(socket, cc, range(1, n + 1))
    xs = ndimage.mean(grid[..., 0], cc, range(1, n + 1)) * lateral
    big = np.nonzero(sizes * spacing**3 > 4000.0)[0]  # > 4 cm^3: the socket, not surface creases
    if len(big) == 0:
        raise InputError("ssm", "no acetabulum found on the SSM hip bone")
    head = cc == (1 + big[np.argmax(xs[big])])
    lab[head] = 3
    soft = (dist > 0) & (dist <= muscle_mm) & (lab == 0)
    # Medial vs lateral side of the wing from the hip bone's distance gradient along x.
    gx = np.gradient(dhip, axis=0) * lateral
    medial = gx < 0
    depth = dhip / muscle_mm
    post = grid[..., 1] < np.median(grid[hipm][:, 1])
    lab[soft & medial] = 7
    lat = soft & ~medial
    lab[lat & (depth <= 1 / 3)] = 6
    lab[lat & (depth > 1 / 3) & (depth <= 2 / 3)] = 5
    lab[lat & (depth > 2 / 3)] = 4
    lab[lat & post & (depth > 1 / 3)] = 4  # gluteus maximus covers the posterior ilium
    lab[(dist > muscle_mm) & (dist <= muscle_mm + adipose_mm) & (lab == 0)] = 8
    vol = LabelVolume(lab, lo.astype(float), float(spacing), side, "ssm:LLP26_mean")
    vol.notes += [
        f"muscle layer {muscle_mm} mm and adipose layer {adipose_mm} mm offset from the bone surfaces",
        "femoral head proxy: the acetabular socket filled by morphological closing (no femur in the SSM)",
    ]
    return vol


def _ball(r):
    r = max(int(r), 1)
    g = np.mgrid[-r:r + 1, -r:r + 1, -r:r + 1]
    return (g ** 2).sum(0) <= r * r


# ---------------------------------------------------------------------------------------------- needles

@dataclass
class NeedleSite:
    """Two parallel needles and a clamp. Points in mm (RAS), directions unit vectors.

    `entries` are the points where each needle axis enters the hip bone; `direction` points from the
    entry into the bone; the needle runs `depth_in_bone` into the bone and out through the soft tissue
    to the clamp, whose bottom face lies `clamp_gap` beyond the farthest skin exit along the axis.
    """

    entries: np.ndarray  # (2,3)
    direction: np.ndarray  # (3,) into the bone
    name: str = "iliac_crest"
    diameter: float = 5.0
    depth_in_bone: float = 40.0
    clamp_gap: float = 20.0
    clamp_size: tuple = (20.0, 20.0)  # clamp bar height along the needle, width; mm
    clamp_overhang: float = 15.0  # bar length beyond each needle axis, mm

    def __post_init__(self):
        self.entries = np.asarray(self.entries, float).reshape(2, 3)
        d = np.asarray(self.direction, float)
        n = np.linalg.norm(d)
        if not np.isfinite(n) or n == 0:
            raise InputError("needle.direction", "must be a non-zero 3-vector")
        self.direction = d / n
        check_number("needle.diameter", self.diameter, gt=0.5, le=12)
        check_number("needle.depth_in_bone", self.depth_in_bone, gt=0, le=120)
        check_number("needle.clamp_gap", self.clamp_gap, ge=1, le=200)
        if np.linalg.norm(self.entries[1] - self.entries[0]) < 2 * self.diameter:
            raise InputError("needle.entries", "needle entry points must be at least two diameters apart")


def standard_site(vol: LabelVolume, site: str = "supra_acetabular", spacing_mm: float | None = None,
                  **kw) -> NeedleSite:
    """A documented standard insertion site found on the hip bone of `vol`.

    iliac_crest: the gluteal pillar. The first entry is the top of the crest 40 mm posterior to the
      anterior superior iliac spine (ASIS = most anterior hip-bone voxel in the top 30 mm of the bone),
      the second `spacing_mm` (default 25) further posterior on the crest; both needles aim at the
      acetabular roof (top of the femoral head) - the usual crest pin path between the inner and outer
      tables. On this CT the crest lies deep under the flank: the path to the skin is > 150 mm.
    supra_acetabular (default): entry at the anterior inferior iliac spine (most anterior hip voxel
      10-30 mm above the femoral head top), aiming at the posterior superior iliac spine (most
      posterior hip voxel) - the supra-acetabular corridor of anterior pelvic frames; the second pin
      parallel, `spacing_mm` (default 12) lateral (the corridor is narrow; superior to the AIIS the
      axis leaves the bone into the iliac fossa).
    """
    lab = vol.labels
    hip = vol.world(np.argwhere(lab == 1))
    fem = vol.world(np.argwhere(lab == 3))
    if len(hip) == 0:
        raise InputError("labels", "no hip bone in the label volume")
    head_top = fem[np.argmax(fem[:, 2])] if len(fem) else hip[np.argmin(hip[:, 2])]
    if site == "iliac_crest":
        top = hip[hip[:, 2] > hip[:, 2].max() - 30.0]
        asis = top[np.argmax(top[:, 1])]
        entries = []
        for dy in (40.0, 40.0 + (25.0 if spacing_mm is None else spacing_mm)):
            band = hip[np.abs(hip[:, 1] - (asis[1] - dy)) <= vol.spacing]
            if len(band) == 0:
                raise InputError("needle.site", "iliac crest not found 40 mm posterior to the ASIS")
            zmax = band[:, 2].max()
            crest = band[band[:, 2] >= zmax - 0.5 * vol.spacing]
            p = crest.mean(axis=0)
            p[2] = zmax + 0.5 * vol.spacing  # surface of the top voxel
            entries.append(p)
        entries = np.array(entries)
        direction = head_top - entries.mean(axis=0)
    elif site == "supra_acetabular":
        band = hip[(hip[:, 2] > head_top[2] + 10) & (hip[:, 2] < head_top[2] + 30)]
        aiis = band[np.argmax(band[:, 1])]
        psis = hip[np.argmin(hip[:, 1])]
        direction = psis - aiis
        lateral = np.array([1.0 if vol.side == "right" else -1.0, 0, 0])
        entries = np.array([aiis, aiis + (12.0 if spacing_mm is None else spacing_mm) * lateral])
    else:
        raise InputError("needle.site", f"must be 'iliac_crest' or 'supra_acetabular', got {site!r}")
    out = NeedleSite(entries=entries, direction=direction, name=site, **kw)
    return snap_entries(vol, out)


def snap_entries(vol: LabelVolume, site: NeedleSite, search_mm: float = 60.0) -> NeedleSite:
    """Move each entry along its axis to where the needle first meets the hip bone coming from
    outside: walk inwards from `search_mm` outside the given point; InputError if no bone is hit
    within `search_mm` inside it."""
    s = np.arange(-search_mm, search_mm, 0.25)
    new = []
    for i, e in enumerate(site.entries):
        ids = vol.sample(e[None, :] + s[:, None] * site.direction[None, :])
        hit = np.nonzero(ids == 1)[0]
        if len(hit) == 0:
            raise InputError(f"needle.entries[{i}]", f"the axis through {e.round(1)} misses the hip bone "
                             f"within {search_mm} mm")
        new.append(e + s[hit[0]] * site.direction)
    site.entries = np.array(new)
    return site


@dataclass
class NeedlePath:
    """Tissue layers along one needle from the bone entry outwards to the skin (mm)."""

    entry: np.ndarray
    skin_exit: np.ndarray
    layers: list  # [(tissue name, start, end)] distances from the bone entry
    muscle_mm: float
    adipose_mm: float
    total_mm: float


def needle_paths(vol: LabelVolume, site: NeedleSite, step: float = 0.25) -> list[NeedlePath]:
    """Soft-tissue thickness along each needle: walk outwards (against `direction`) from the bone
    entry until the last non-void sample; muscle = any of MUSCLES, adipose = adipose; bone re-entries
    and void gaps inside the body are reported as layers but counted in neither."""
    out = []
    lo, hi = vol.bounds
    reach = float(np.linalg.norm(hi - lo))
    s = np.arange(0.0, reach, step)
    for e in site.entries:
        pts = e[None, :] - s[:, None] * site.direction[None, :]
        ids = vol.sample(pts)
        # start past the bone at the entry
        start = int(np.argmax(ids != 1)) if ids[0] == 1 else 0
        body = np.nonzero(ids[start:] != 0)[0]
        if len(body) == 0:
            raise InputError("needle.entries", f"no soft tissue outward from the entry {e.round(1)}")
        last = start + body[-1]
        layers = []
        cur, c0 = ids[start], s[start]
        for i in range(start + 1, last + 2):
            v = ids[i] if i <= last else -1
            if v != cur:
                layers.append((TISSUES.get(int(cur), "void"), float(c0), float(s[i - 1] + step)))
                cur, c0 = v, s[i] if i <= last else 0
        muscle = sum(b - a for n, a, b in layers if n in MUSCLES)
        fat = sum(b - a for n, a, b in layers if n == "adipose")
        out.append(NeedlePath(e, pts[last], layers, muscle, fat, float(s[last] + step - s[start])))
    return out


def crop_to_site(vol: LabelVolume, site: NeedleSite, margin_mm: float = 30.0) -> LabelVolume:
    """Trim the volume's top to `margin_mm` above the higher of the iliac crest and the needles' skin
    exits, so that every needle's whole soft-tissue path stays inside the model."""
    paths = needle_paths(vol, site)
    hip = np.argwhere(vol.labels == 1)
    ztop = max(vol.world(hip)[:, 2].max(), *(p.skin_exit[2] for p in paths)) + margin_mm
    k1 = int(min(vol.labels.shape[2], np.ceil(vol.index([0, 0, ztop])[2]) + 1))
    out = LabelVolume(vol.labels[:, :, :k1].copy(), vol.origin.copy(), vol.spacing, vol.side, vol.source,
                      list(vol.notes))
    out.notes.append(f"cropped at z = {vol.world([0, 0, k1 - 1])[2]:.1f} mm ({margin_mm} mm above the crest/skin exits)")
    return out


# ------------------------------------------------------------------------------------------------- mesh

@dataclass
class PelvisMesh:
    """Linear tet mesh of the model: regions -> tet ids, surfaces -> (k,3) node ids (fem contract)."""

    points: np.ndarray
    cells: np.ndarray
    regions: dict
    surfaces: dict
    site: NeedleSite
    paths: list
    clamp_frame: np.ndarray  # rows e1 (along the bar), e2, e3 (needle axis, outwards); mm
    needle_axes: list  # [(bottom point in bone, top point in clamp)]
    notes: list = field(default_factory=list)
    info: dict = field(default_factory=dict)  # how the mesh was built (smooth route: mesh_info)
    label_volumes: dict | None = None  # region -> voxel volume (mm^3) of the label map it was meshed from
    cached: bool = False  # read from the mesh cache (needletissue.cache), not meshed

    def to_meshio(self):
        """meshio mesh with gmsh physical groups named as the regions and surfaces."""
        import meshio

        names = list(self.regions) + list(self.surfaces)
        tag = {n: i + 1 for i, n in enumerate(names)}
        tets, tet_tags = [], []
        for n, ids in self.regions.items():
            tets.append(self.cells[ids])
            tet_tags.append(np.full(len(ids), tag[n]))
        tris, tri_tags = [], []
        for n, f in self.surfaces.items():
            tris.append(f)
            tri_tags.append(np.full(len(f), tag[n]))
        cells = [("tetra", np.vstack(tets)), ("triangle", np.vstack(tris))]
        phys = [np.concatenate(tet_tags), np.concatenate(tri_tags)]
        return meshio.Mesh(
            self.points, cells,
            cell_data={"gmsh:physical": phys, "gmsh:geometrical": phys},
            field_data={n: np.array([tag[n], 3 if n in self.regions else 2]) for n in names},
        )


def _frame(axis, across):
    e3 = axis / np.linalg.norm(axis)
    e1 = across - (across @ e3) * e3
    if np.linalg.norm(e1) < 1e-9:
        raise InputError("needle.entries", "the line between the needles must not be parallel to them")
    e1 /= np.linalg.norm(e1)
    return np.array([e1, np.cross(e3, e1), e3])


def _needles_and_clamp(site: NeedleSite, paths):
    """(clamp frame, centre of the clamp's bottom face, needle axes [(bottom in bone, top in the clamp)], bar
    length): the clamp bottom lies clamp_gap beyond the farthest skin exit along the axis (measured from the
    first entry); the needles run depth_in_bone into the bone and through the clamp bar."""
    a = -site.direction  # outwards
    reach = max(float((p.skin_exit - site.entries[0]) @ a) for p in paths)
    frame = _frame(a, site.entries[1] - site.entries[0])
    mid = site.entries.mean(axis=0)
    c_bottom = mid + (reach + site.clamp_gap - float((mid - site.entries[0]) @ a)) * a
    axes = []
    for e in site.entries:
        top_t = float((c_bottom - e) @ a) + site.clamp_size[0]
        axes.append((e - site.depth_in_bone * a, e + top_t * a))
    span = float(abs((site.entries[1] - site.entries[0]) @ frame[0]))
    return frame, c_bottom, axes, span + 2 * site.clamp_overhang


def build_mesh(vol: LabelVolume, site: NeedleSite, mesh_size: float = 3.0, needle_size: float | None = None,
               far_size: float | None = None, cortical_thickness: float = 1.5, refine_radius: float = 35.0,
               sacroiliac_gap: float | None = None, smoothing: float = 0.7, threads: int = 1,
               cache: bool = False) -> PelvisMesh:
    """Conforming linear tet mesh of the cropped anatomy with two needles and the clamp.

    mesh_size: soft-tissue element size next to the needles, mm (the paper: 3 mm); needle_size default
    2*mesh_size/3 (quadratic elements are used for the solve); far_size default 4*mesh_size, reached at
    `refine_radius` mm from the needles. Hip-bone tets whose centroid lies less than
    max(cortical_thickness, half the tet's longest edge) below the bone surface are cortical bone
    (the 3 mm CT does not resolve the cortex; a one-element shell where elements are coarse).
    With cache, a mesh made before from the same label volume, site and sizes is read from
    needletissue.cache.mesh_cache_dir() instead of meshing again (paper scale: ~85 s of gmsh and labelling).
    """
    check_number("mesh_size", mesh_size, ge=0.5, le=20)
    needle_size = 2 * mesh_size / 3 if needle_size is None else check_number("needle_size", needle_size, ge=0.2, le=10)
    far_size = 4 * mesh_size if far_size is None else check_number("far_size", far_size, ge=mesh_size, le=FAR_SIZE_MAX)
    check_number("cortical_thickness", cortical_thickness, gt=0, le=10)
    sacroiliac_gap = 1.5 * vol.spacing if sacroiliac_gap is None else sacroiliac_gap
    paths = needle_paths(vol, site)
    frame, c_bottom, axes, bar_len = _needles_and_clamp(site, paths)
    notes = list(vol.notes) + [
        f"tissue tets: argmax of Gaussian-smoothed (sigma {smoothing} voxel) label indicators at the centroid",
        f"hip cortical shell: centroid depth < max({cortical_thickness} mm, half the longest edge)",
    ]
    args = (vol, site, frame, c_bottom, axes, bar_len, mesh_size, needle_size, far_size, cortical_thickness,
            refine_radius, sacroiliac_gap, smoothing, threads)
    folder = mesh_cache_dir() if cache else None
    key = _cache_key(*args) if folder is not None else None
    arrays = _from_cache(folder, key) if folder is not None else None
    cached = arrays is not None
    if not cached:
        arrays = _box_mesh(*args)
        if folder is not None:
            _to_cache(folder, key, *arrays)
    return PelvisMesh(*arrays, site, paths, frame, axes, notes, cached=cached)


def _cache_key(vol, site, *rest) -> str:
    """Every input of the box mesh: the label volume's voxels and grid, the site, the sizes and options,
    and the meshing code (this module, the gmsh set-up, tetmesh's helpers)."""
    from importlib.metadata import version

    labels = vol.labels
    inputs = {"labels": sha256(labels), "shape": labels.shape, "dtype": str(labels.dtype),
              "origin": np.asarray(vol.origin, float).tolist(), "spacing": float(vol.spacing),
              "site": [np.asarray(getattr(site, k), float).tolist() for k in
                       ("entries", "direction", "diameter", "depth_in_bone", "clamp_gap", "clamp_size", "clamp_overhang")],
              "options": [np.asarray(x, float).tolist() for x in rest],
              "scipy": version("scipy"), "gmsh": version("gmsh")}
    here = Path(__file__).parent
    return cache_key(inputs, (here / "pelvis.py", here / "gmsh_init.py", here / "tetmesh.py"))


def _to_cache(folder: Path, key: str, pts, tets, regions: dict, surfaces: dict) -> None:
    import io

    buf = io.BytesIO()
    np.savez(buf, points=pts, cells=tets, **{f"region {k}": v for k, v in regions.items()},
             **{f"surface {k}": v for k, v in surfaces.items()})
    write_entry(folder, key, ".npz", buf.getvalue(),
                {"regions": list(regions), "surfaces": list(surfaces), "tetrahedra": int(len(tets))})


def _from_cache(folder: Path, key: str):
    """(points, tets, regions, surfaces) of a cached box mesh, or None (a miss)."""
    import io

    entry = read_entry(folder, key, ".npz")
    if entry is None:
        return None
    data, facts = entry
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            return (z["points"], z["cells"], {k: z[f"region {k}"] for k in facts["regions"]},
                    {k: z[f"surface {k}"] for k in facts["surfaces"]})
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _box_mesh(vol, site, frame, c_bottom, axes, bar_len, mesh_size, needle_size, far_size, cortical_thickness,
              refine_radius, sacroiliac_gap, smoothing, threads):
    """gmsh's mesh of the crop box with the needles and the clamp, tissue by label, the hip cortex, the
    largest body and its surfaces: (points, tets, regions, surfaces)."""
    import gmsh
    from scipy import ndimage

    r = site.diameter / 2
    h_clamp, w_clamp = site.clamp_size
    lo, hi = vol.bounds
    from needletissue.geometry.gmsh_init import initialize  # keeps the SIGTERM handler

    initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", threads)
        gmsh.model.add("pelvis")
        occ = gmsh.model.occ
        box = occ.addBox(*lo, *(hi - lo))
        needles = [occ.addCylinder(*b, *(t - b), r) for b, t in axes]
        clamp = occ.addBox(-bar_len / 2, -w_clamp / 2, 0.0, bar_len, w_clamp, h_clamp)
        M = np.column_stack([frame[0], frame[1], frame[2], c_bottom])  # x = R x' + c
        occ.affineTransform([(3, clamp)], list(M.ravel()))
        out, out_map = occ.fragment([(3, box)], [(3, n) for n in needles] + [(3, clamp)])
        occ.synchronize()
        parents = {"box": out_map[0], "needle_1": out_map[1], "needle_2": out_map[2], "clamp": out_map[3]}
        owner = {}
        for name in ("box", "clamp", "needle_2", "needle_1"):  # later names win: needle > clamp > box
            for dim, tag in parents[name]:
                owner[tag] = name
        needle_surfs = [t for dim, t in gmsh.model.getBoundary(
            [(3, t) for t, n in owner.items() if n.startswith("needle")], oriented=False, combined=False)]
        f_dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(f_dist, "SurfacesList", sorted(set(abs(s) for s in needle_surfs)))
        gmsh.model.mesh.field.setNumber(f_dist, "Sampling", 40)
        f_thr = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(f_thr, "InField", f_dist)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMin", mesh_size)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMax", far_size)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMin", 2 * mesh_size)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMax", refine_radius)
        f_ndl = gmsh.model.mesh.field.add("Constant")
        gmsh.model.mesh.field.setNumber(f_ndl, "VIn", needle_size)
        gmsh.model.mesh.field.setNumber(f_ndl, "VOut", 1e3)
        gmsh.model.mesh.field.setNumbers(f_ndl, "VolumesList", [t for t, n in owner.items() if n.startswith("needle")])
        f_min = gmsh.model.mesh.field.add("Min")
        gmsh.model.mesh.field.setNumbers(f_min, "FieldsList", [f_thr, f_ndl])
        gmsh.model.mesh.field.setAsBackgroundMesh(f_min)
        for opt in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
            gmsh.option.setNumber(f"Mesh.{opt}", 0)
        gmsh.option.setNumber("Mesh.Algorithm3D", 10)  # HXT
        gmsh.option.setNumber("Mesh.Optimize", 1)
        gmsh.model.mesh.generate(3)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        pts = coords.reshape(-1, 3)
        index = np.zeros(int(node_tags.max()) + 1, int)
        index[node_tags.astype(int)] = np.arange(len(node_tags))
        tets, owners = [], []
        for tag, name in owner.items():
            types, _, enodes = gmsh.model.mesh.getElements(3, tag)
            for et, en in zip(types, enodes):
                if et == 4:
                    t = index[en.astype(int)].reshape(-1, 4)
                    tets.append(t)
                    owners += [name] * len(t)
    finally:
        gmsh.finalize()
    tets = np.vstack(tets)
    owners = np.array(owners)

    # Tissue per box tet: argmax of smoothed one-hot label indicators at the centroid.
    cent = pts[tets].mean(axis=1)
    is_box = owners == "box"
    coords_ijk = vol.index(cent[is_box]).T
    ids = sorted(TISSUES)
    scores = []
    for tid in [0, *ids]:
        ind = ndimage.gaussian_filter((vol.labels == tid).astype(np.float32), smoothing, mode="nearest")
        scores.append(ndimage.map_coordinates(ind, coords_ijk, order=1, mode="nearest"))
    tissue = np.array([0, *ids])[np.argmax(np.array(scores), axis=0)]
    names = np.array(owners, dtype=object)
    names[is_box] = [TISSUES.get(int(t), "void") for t in tissue]

    # Cortical shell of the hip bone.
    hipm = vol.labels == 1
    sd = (ndimage.distance_transform_edt(hipm, sampling=vol.spacing)
          - ndimage.distance_transform_edt(~hipm, sampling=vol.spacing)) - 0.5 * vol.spacing
    hip_ids = np.nonzero(names == "hip_bone")[0]
    depth = ndimage.map_coordinates(sd, vol.index(cent[hip_ids]).T, order=1, mode="nearest")
    edges = pts[tets[hip_ids]]
    longest = np.max([np.linalg.norm(edges[:, i] - edges[:, j], axis=1)
                      for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))], axis=0)
    cort = depth < np.maximum(cortical_thickness, 0.5 * longest)
    names[hip_ids[cort]] = "hip_cortical"
    names[hip_ids[~cort]] = "hip_cancellous"

    keep = names != "void"
    tets, names = tets[keep], names[keep]
    tets, names = _largest_face_component(tets, names)
    for n in ("needle_1", "needle_2", "clamp"):
        if not np.any(names == n):
            raise InputError("needle.entries", f"{n} is not attached to the anatomy: check the site")
    used, inv = np.unique(tets, return_inverse=True)
    pts, tets = pts[used], inv.reshape(-1, 4)
    vol_sign = np.einsum("ij,ij->i", np.cross(pts[tets[:, 1]] - pts[tets[:, 0]], pts[tets[:, 2]] - pts[tets[:, 0]]),
                         pts[tets[:, 3]] - pts[tets[:, 0]])
    tets[vol_sign < 0] = tets[vol_sign < 0][:, [0, 2, 1, 3]]
    order = ["hip_cortical", "hip_cancellous", "sacrum", "femur", "gluteus_maximus", "gluteus_medius",
             "gluteus_minimus", "iliopsoas", "body_wall", "adipose", "needle_1", "needle_2", "clamp"]
    assert set(names) <= set(order), set(names) - set(order)
    regions = {n: np.nonzero(names == n)[0] for n in order if np.any(names == n)}

    surfaces = _surfaces(pts, tets, names, vol, frame, c_bottom, w_clamp, sacroiliac_gap)
    return pts, tets, regions, surfaces


_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def _faces(tets):
    f = tets[:, _FACES].reshape(-1, 3)
    key = np.sort(f, axis=1)
    return f, key


def _largest_face_component(tets, names):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f, key = _faces(tets)
    _, inv, cnt = unique_rows(key)  # np.unique(axis=0): 15 s of the paper-scale mesh
    owner = np.repeat(np.arange(len(tets)), 4)
    order = np.argsort(inv, kind="stable")
    s = inv[order]
    pair = np.nonzero(s[1:] == s[:-1])[0]
    a, b = owner[order][pair], owner[order][pair + 1]
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tets),) * 2)
    n, comp = connected_components(g, directed=False)
    big = np.argmax(np.bincount(comp))
    k = comp == big
    return tets[k], names[k]


def _surfaces(pts, tets, names, vol, frame, c_bottom, w_clamp, si_gap):
    """Boundary sets: femur_fixed (CT: femur faces on the crop's bottom plane; SSM: the femoral-head
    proxy's faces), sacrum_fixed (superior
    sacral surface: sacrum boundary faces within 6 mm of the sacrum's top), sacroiliac_joint (hip-bone
    faces shared with the sacrum or within si_gap of it), midline (all boundary faces on the medial crop
    plane), gripper (the clamp bar's two side faces at +-width/2, where the robot's jaws hold it and the
    uniform load acts, as in the `needle` branch's model: resultant at the clamp's mid-height)."""
    from scipy import ndimage

    f, key = _faces(tets)
    owner = np.repeat(np.arange(len(tets)), 4)
    _, inv, cnt = unique_rows(key)  # np.unique(axis=0): 15 s of the paper-scale mesh
    bnd = cnt[inv] == 1
    fo = names[owner]
    pf = pts[f]  # (faces, 3, 3): gathered once (5.4 M faces at paper scale, 0.4 GB)
    fc = pf.mean(axis=1)
    lo, hi = vol.bounds
    tol = 1e-6 * np.abs(hi - lo).max() + 1e-9
    on = lambda axis, val: np.all(np.abs(pf[:, :, axis] - val) < tol, axis=1)
    # interface faces (count 2) between hip and sacrum: keep once, from the hip side
    other = np.zeros(len(f), object)
    order = np.argsort(inv, kind="stable")
    s = inv[order]
    pair = np.nonzero(s[1:] == s[:-1])[0]
    other[order[pair]] = fo[order[pair + 1]]
    other[order[pair + 1]] = fo[order[pair]]
    out = {}
    if vol.source.startswith("ssm"):  # femoral-head proxy: its whole surface is the fixed hip joint
        out["femur_fixed"] = (fo == "femur") & (bnd | np.isin(other, ("hip_cortical", "hip_cancellous")))
    else:
        out["femur_fixed"] = bnd & (fo == "femur") & on(2, lo[2])
    sac_top = fc[fo == "sacrum", 2].max()
    # outer faces of the sacrum (free, or against soft tissue as in the SSM's offset layers)
    sac_outer = (fo == "sacrum") & (bnd | ((other != "sacrum") & (other != 0)))
    out["sacrum_fixed"] = sac_outer & (fc[:, 2] > sac_top - 6.0)
    sacm = vol.labels == 2
    dsac = ndimage.distance_transform_edt(~sacm, sampling=vol.spacing) - 0.5 * vol.spacing
    hipf = np.isin(fo, ("hip_cortical", "hip_cancellous"))
    d = np.full(len(f), np.inf)
    d[hipf] = ndimage.map_coordinates(dsac, vol.index(fc[hipf]).T, order=1, mode="nearest")
    out["sacroiliac_joint"] = hipf & ((bnd & (d < si_gap)) | (other == "sacrum"))
    medial_x = lo[0] if vol.side == "right" else hi[0]
    out["midline"] = bnd & on(0, medial_x)
    rel = np.abs((pf - c_bottom) @ frame[1])
    out["gripper"] = bnd & (fo == "clamp") & np.all(np.abs(rel - w_clamp / 2) < 1e-6 * w_clamp + 1e-6, axis=1)
    # Disjoint node sets (reactions per support then add up to the total): a face touching a node of an
    # earlier support set is left to that set.
    taken = np.zeros(len(pts), bool)
    for n in ("femur_fixed", "sacrum_fixed", "sacroiliac_joint", "midline", "gripper"):
        out[n] = out[n] & ~taken[f].any(axis=1)
        taken[f[out[n]].ravel()] = True
    surfaces = {}
    for n, m in out.items():
        if not m.any():
            raise InputError("mesh", f"boundary set {n!r} is empty: the crop or the site does not fit this anatomy")
        surfaces[n] = f[m]
    return surfaces


def curve_needles(qpoints: np.ndarray, qcells: np.ndarray, regions: dict, needle_axes, radius: float,
                  tol: float = 1e-3) -> np.ndarray:
    """Quadratic (tetra10, VTK order) points with the needles' lateral surfaces made exactly cylindrical.

    gmsh puts the corner nodes on the cylinder, but straight-edge midpoints cut its chords: with 2 mm
    elements on a 5 mm pin the polygonal cross-section loses ~10 % of its area and ~20 % of its second
    moment. Each midside node of an edge on a needle's lateral surface (both corners at `radius` from
    the axis, edge on a boundary face of the needle region) is moved radially onto the cylinder.
    Returns a new points array; the tissue and bone elements sharing the nodes follow the curved face.
    """
    from needletissue.cells import TET10_EDGES

    pts = np.array(qpoints, float)
    face_edges = np.array([[0, 1], [1, 2], [0, 2]])
    faces10 = np.array([[0, 1, 2, 4, 5, 6], [0, 1, 3, 4, 8, 7], [0, 2, 3, 6, 9, 7], [1, 2, 3, 5, 9, 8]])
    for i, (b, t) in enumerate(needle_axes):
        cells = qcells[regions[f"needle_{i + 1}"]]
        f = cells[:, faces10].reshape(-1, 6)
        key = np.sort(f[:, :3], axis=1)
        _, inv, cnt = unique_rows(key)
        f = f[cnt[inv] == 1]  # boundary faces of this needle
        axis = (t - b) / np.linalg.norm(t - b)

        def radial(p):
            d = p - b
            return d - (d @ axis)[:, None] * axis

        corner_r = np.linalg.norm(radial(pts[f[:, :3]].reshape(-1, 3)), axis=1).reshape(-1, 3)
        on = np.abs(corner_r - radius) < tol * radius
        # face edge k joins corners face_edges[k]; its midside node is column 3 + k
        for k, (a, c) in enumerate(face_edges):
            sel = on[:, a] & on[:, c]
            mids = np.unique(f[sel, 3 + k])
            rv = radial(pts[mids])
            rn = np.linalg.norm(rv, axis=1)
            pts[mids] += rv * (radius / rn - 1.0)[:, None]
    assert TET10_EDGES.shape == (6, 2)
    return _straighten_inverted(pts, np.asarray(qpoints, float), qcells)


def _straighten_inverted(pts: np.ndarray, straight: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Undo curving where it inverts an element (a thin tissue sliver beside the pin): its Jacobian
    must stay positive at the corners and the quadrature points, or the element integrates negative volume."""
    import felupe as fem

    element = fem.QuadraticTetra()
    r = np.vstack([fem.TetrahedronQuadrature(order=2).points, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]])
    dNdr = np.stack([element.gradient(ri) for ri in r])  # (q, 10, 3)
    moved = np.any(pts != straight, axis=1)
    for _ in range(10):
        check = cells[moved[cells].any(axis=1)]
        if not len(check):
            break
        J = np.einsum("cai,qaj->cqij", pts[check], dNdr)
        bad = check[(np.linalg.det(J) <= 0).any(axis=1)]
        if not len(bad):
            break
        nodes = np.unique(bad)
        pts[nodes] = straight[nodes]
        moved[nodes] = False
    return pts


def needle_solids(axes, radius: float, clamp_frame, clamp_bottom, clamp_size, bar_len: float,
                  size: float, names=("needle_1", "needle_2", "clamp"), margin: float | None = None):
    """The needles (cylinders of `radius` along `axes` [(bottom, top)]) and the clamp bar (rows of
    `clamp_frame`: along the bar, across, along the needles; bottom face centred at `clamp_bottom`, height x
    width `clamp_size`, length `bar_len`) as one conforming triangle set (gmsh OCC fragment: the needles
    run through the bar and share its faces) with triangles of about `size` mm: smooth.Solids for the
    smooth route. Coordinates in whatever frame the inputs are in. The needles win where they overlap the
    bar (a pin through a hole)."""
    import gmsh

    from needletissue.geometry.smooth import Solids

    axes = [(np.asarray(b, float), np.asarray(t, float)) for b, t in axes]
    frame, c0 = np.asarray(clamp_frame, float), np.asarray(clamp_bottom, float)
    h, w = clamp_size
    from needletissue.geometry.gmsh_init import initialize  # keeps the SIGTERM handler

    initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("needle_solids")
        occ = gmsh.model.occ
        cyl = [occ.addCylinder(*b, *(t - b), radius) for b, t in axes]
        clamp = occ.addBox(-bar_len / 2, -w / 2, 0.0, bar_len, w, h)
        occ.affineTransform([(3, clamp)], list(np.column_stack([*frame, c0]).ravel()))
        occ.fragment([(3, c) for c in cyl], [(3, clamp)])
        occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.25 * size)
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 12)   # >= 12 sides around a pin
        gmsh.model.mesh.generate(2)
        tags, xyz, _ = gmsh.model.mesh.getNodes()
        _, tri = gmsh.model.mesh.getElementsByType(2)
    finally:
        gmsh.finalize()
    index = np.zeros(int(tags.max()) + 1, np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    faces = index[tri.astype(np.int64)].reshape(-1, 3)
    used, inv = np.unique(faces, return_inverse=True)
    points = xyz.reshape(-1, 3)[used]
    faces = inv.reshape(-1, 3)

    def label(p, grow=0.0):
        p = np.asarray(p, float)
        out = np.full(len(p), -1)
        q = (p - c0) @ frame.T   # clamp frame coordinates
        box = (np.abs(q[:, 0]) <= bar_len / 2 + grow) & (np.abs(q[:, 1]) <= w / 2 + grow) \
            & (q[:, 2] >= -grow) & (q[:, 2] <= h + grow)
        out[box] = len(axes)
        for i, (b, t) in enumerate(axes):   # the pins win inside the bar
            L = np.linalg.norm(t - b)
            a = (t - b) / L
            s = (p - b) @ a
            r = np.linalg.norm((p - b) - s[:, None] * a, axis=1)
            out[(r <= radius + grow) & (s >= -grow) & (s <= L + grow)] = i
        return out

    return Solids(names=list(names), points=points, faces=faces, label=label,
                  margin=float(margin if margin is not None else radius))


# the segmentation's tissues (imaging.segment) -> the model's regions; bone is split by bone below
SEG_REGIONS = {"adipose": "adipose", "other_soft_tissue": "body_wall"}


# The corridor's margin is margin_voxels voxels; a coarse graded mesh's interfaces can deviate from it by more (the
# example CT at 5.625-11 mm: edges of the needles crossed them; 12 mm and above: no widening helps), so it widens a
# voxel at a time (docs/imaging.md, "The corridor at coarse graded sizes").
CORRIDOR_WIDENINGS = 4


def build_mesh_smooth(seg, vol: LabelVolume, site: NeedleSite, mesh_size: float = 3.0,
                      needle_size: float | None = None, sacroiliac_gap: float | None = None,
                      margin_voxels: float = 1.5, far_size: float | None = None,
                      refine_radius: float = 35.0) -> PelvisMesh:
    """The model's mesh through the `segment` + `mesh` reconstruction (geometry.smooth: smooth shared tissue
    interfaces, TetGen, optimised elements, cortex by volume) with the needles and the clamp inserted exactly.

    seg: imaging.segment.Segmentation of the same CT (LPS); vol: the cropped LabelVolume (RAS) that gives
    the crop box, the needle site and paths and the bone of each bone element (hip / sacrum / femur).
    mesh_size: the smooth route's element size (label maps finer than it are coarsened); needle_size:
    triangles on the needles and clamp (default 2*mesh_size/3); far_size: the size at refine_radius mm from
    the needles and beyond, graded from mesh_size at them by CGAL's interfaces (geometry.graded; None or
    mesh_size: one size everywhere, surface nets). Tissue regions are the mesh's own region
    tags; within margin_voxels (coarse) voxels of the needles and the clamp the tissue is the voxel at the
    element's centroid (the corridor in which the exact solids are inserted)."""
    from scipy import ndimage

    from needletissue.geometry.smooth import CorridorTooNarrow
    from needletissue.geometry.tetmesh import MeshConfig, _crop_and_coarsen, tet_mesh

    check_number("mesh_size", mesh_size, ge=0.5, le=20)
    needle_size = 2 * mesh_size / 3 if needle_size is None else check_number("needle_size", needle_size, ge=0.2, le=10)
    sacroiliac_gap = 1.5 * vol.spacing if sacroiliac_gap is None else sacroiliac_gap
    paths = needle_paths(vol, site)
    frame, c_bottom, axes, bar_len = _needles_and_clamp(site, paths)
    r = site.diameter / 2
    lo, hi = vol.bounds
    inset = 0.6 * vol.spacing  # inside the first / last voxel: the crop takes exactly the volume's voxels
    box = (-(hi[0] - inset), -(lo[0] + inset), -(hi[1] - inset), -(lo[1] + inset), lo[2] + inset, hi[2] - inset)
    cfg = MeshConfig(size=mesh_size, crop=box, method="smooth", far_size=far_size, refine_radius=refine_radius)
    cfg.coarsen = not cfg.graded   # CGAL meshes the label map at any size: as it is
    coarse = vol.spacing * (1 if cfg.graded else max(1, int(np.floor(mesh_size / vol.spacing + 1e-9))))
    solids = needle_solids([(b * RAS_LPS, t * RAS_LPS) for b, t in axes], r, frame * RAS_LPS, c_bottom * RAS_LPS,
                           site.clamp_size, bar_len, needle_size, margin=r + margin_voxels * coarse)
    margin = solids.margin
    for widened in range(CORRIDOR_WIDENINGS + 1):
        try:
            tm = tet_mesh(seg, config=cfg, solids=replace(solids, margin=margin))   # the same triangles
            break
        except CorridorTooNarrow:
            if widened == CORRIDOR_WIDENINGS:
                raise InputError("mesh_size", f"{mesh_size:g} mm is too coarse at the needles for the smooth mesher: "
                                 "its tissue interfaces cross the needles even with the corridor around them widened "
                                 f"to {margin - r:g} mm; give a smaller mesh_size, or the box mesher") from None
            margin += coarse
    pts = tm.points * RAS_LPS
    names = np.empty(len(tm.cells), object)
    for n, ids in tm.regions.items():
        base = n.removesuffix("_left").removesuffix("_right")
        names[ids] = SEG_REGIONS.get(base, base)
    # bone elements: the bone of the nearest bone voxel of the label volume at the centroid
    isbone = np.isin(vol.labels, (1, 2, 3))
    near = ndimage.distance_transform_edt(~isbone, return_distances=False, return_indices=True)
    bone = np.flatnonzero(np.isin(names, ("cortical_bone", "cancellous_bone")))
    ijk = np.clip(np.rint(vol.index(pts[tm.cells[bone]].mean(1))).astype(int), 0, np.array(vol.labels.shape) - 1)
    which = vol.labels[tuple(near[:, ijk[:, 0], ijk[:, 1], ijk[:, 2]])]
    hip = which == 1
    names[bone[hip]] = np.where(names[bone[hip]] == "cortical_bone", "hip_cortical", "hip_cancellous")
    names[bone[which == 2]] = "sacrum"
    names[bone[which == 3]] = "femur"
    order = ["hip_cortical", "hip_cancellous", "sacrum", "femur", "gluteus_maximus", "gluteus_medius",
             "gluteus_minimus", "iliopsoas", "body_wall", "adipose", "needle_1", "needle_2", "clamp"]
    other = sorted(set(names) - set(order))
    if other:
        raise InputError("labels", f"tissue(s) the model has no material for: {', '.join(other)}")
    regions = {n: np.flatnonzero(names == n) for n in order if np.any(names == n)}
    surfaces = _surfaces(pts, tm.cells, names, vol, frame, c_bottom, site.clamp_size[1], sacroiliac_gap)
    notes = list(vol.notes) + [
        f"mesh: the `segment` + `mesh` route (smooth shared interfaces, TetGen, cortex by volume) at size "
        f"{mesh_size} mm" + (f" graded to {far_size} mm at {refine_radius} mm (CGAL's interfaces)" if cfg.graded else "")
        + f" with the needles and the clamp inserted exactly (triangles {needle_size:.2f} mm); tissue "
        f"within {margin - r:g} mm ({(margin - r) / coarse:g} voxels) of them by the voxel at the element centroid"
        + (f" (the corridor widened {widened} time(s) by a voxel: the interfaces crossed the solids)" if widened else ""),
        "segmentation: imaging.segment (other_soft_tissue -> body_wall; bone elements hip / sacrum / femur by "
        "the nearest bone voxel of the label map)",
    ]
    # the label map's volumes in the model's names: soft tissue from the segmentation (the same crop, not
    # coarsened), bones from the label volume (both are the label map's bone voxels)
    seg_arr = _crop_and_coarsen(seg, MeshConfig(size=vol.spacing, crop=box, coarsen=False))[0]
    counts = np.bincount(seg_arr.ravel(), minlength=256) * vol.spacing ** 3
    label = {}
    for n, i in seg.tissues.items():
        base = n.removesuffix("_left").removesuffix("_right")
        if base in SEG_REGIONS or base in regions:
            label[SEG_REGIONS.get(base, base)] = label.get(SEG_REGIONS.get(base, base), 0.0) + float(counts[i])
    bones = np.bincount(vol.labels.ravel(), minlength=4) * vol.spacing ** 3
    label.update({"hip_bone": float(bones[1]), "sacrum": float(bones[2]), "femur": float(bones[3])})
    tm.info.update(corridor_margin_mm=margin - r, corridor_widenings=widened)
    out = PelvisMesh(pts, tm.cells, regions, surfaces, site, paths, frame, axes, notes, tm.info,
                     {k: v for k, v in label.items() if v > 0})
    return out
