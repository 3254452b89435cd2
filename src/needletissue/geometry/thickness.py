"""Soft-tissue thickness along a needle path, and standard pin sites found automatically.

Frame: physical LPS millimetres of the image header (SimpleITK/ITK convention: +x patient Left,
+y Posterior, +z Superior). The path starts at `entry` and runs along `direction`; counting starts at
the first voxel inside the body (the skin) and stops at the first bone voxel.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from needletissue.errors import InputError, check_number

BONE_NAMES = ("cortical_bone", "cancellous_bone")


@dataclass
class PathSegment:
    tissue: str
    start_mm: float  # distance from the entry point along the direction
    end_mm: float

    @property
    def length_mm(self) -> float:
        return self.end_mm - self.start_mm


@dataclass
class ThicknessResult:
    entry: list[float]
    direction: list[float]
    frame: str
    bone_hit: bool
    skin_mm: float | None                 # distance entry -> skin
    soft_tissue_thickness_mm: float | None  # skin -> bone
    thickness_by_tissue: dict[str, float]
    segments: list[PathSegment] = field(default_factory=list)
    bone_point: list[float] | None = None
    site: str | None = None


def _parse_vec(field_name: str, value) -> np.ndarray:
    if isinstance(value, str):
        try:
            value = [float(v) for v in value.split(",")]
        except ValueError:
            raise InputError(field_name, f"expected X,Y,Z numbers, got {value!r}") from None
    v = np.asarray(value, float).ravel()
    if v.size != 3 or not np.all(np.isfinite(v)):
        raise InputError(field_name, f"expected 3 finite numbers (mm), got {value!r}")
    return v


def thickness_along(seg, entry, direction, *, step_mm: float | None = None,
                    max_length_mm: float | None = None, site: str | None = None) -> ThicknessResult:
    """Tissues crossed from `entry` along `direction` (LPS mm) until the first bone voxel."""
    import SimpleITK as sitk

    p0 = _parse_vec("entry", entry)
    d = _parse_vec("direction", direction)
    n = np.linalg.norm(d)
    if n < 1e-9:
        raise InputError("direction", "must not be the zero vector")
    d = d / n
    img = seg.labels
    arr = sitk.GetArrayViewFromImage(img)
    sp = np.asarray(img.GetSpacing(), float)
    step = float(min(sp) / 10.0 if step_mm is None else check_number("step_mm", step_mm, gt=0))
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    o = np.asarray(img.GetOrigin(), float)
    size = np.asarray(img.GetSize())
    if max_length_mm is None:
        max_length_mm = float(np.linalg.norm(size * sp)) + float(np.linalg.norm(p0 - o)) + 10.0
    t = (np.arange(int(max_length_mm / step)) + 0.5) * step  # sample centres; boundaries at i*step
    pts = p0 + t[:, None] * d
    idx = np.floor((pts - o) @ D / sp + 0.5).astype(int)  # nearest voxel (i, j, k)
    inside = np.all((idx >= 0) & (idx < size), axis=1)
    lab = np.zeros(len(t), np.int32)
    lab[inside] = arr[idx[inside, 2], idx[inside, 1], idx[inside, 0]]
    names = {v: k for k, v in seg.tissues.items()}
    bone_ids = [seg.tissues[b] for b in BONE_NAMES if b in seg.tissues]
    is_bone = np.isin(lab, bone_ids)
    body = np.flatnonzero(lab > 0)
    res = ThicknessResult(entry=p0.tolist(), direction=d.tolist(), frame="LPS mm (image header)",
                          bone_hit=False, skin_mm=None, soft_tissue_thickness_mm=None,
                          thickness_by_tissue={}, site=site)
    if len(body) == 0:
        return res
    i_skin = body[0]
    bones = np.flatnonzero(is_bone[i_skin:])
    i_end = i_skin + bones[0] if len(bones) else int(body[-1]) + 1
    # boundaries sit halfway between the samples on either side (error <= step / 2)
    half = lambda i: float(t[i] - step / 2)  # noqa: E731
    res.skin_mm = half(i_skin)
    seg_lab = lab[i_skin:i_end]
    # run-length segments (boundaries halfway between samples)
    change = np.flatnonzero(np.diff(seg_lab)) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, len(seg_lab)]
    for a, b in zip(starts, ends):
        name = names.get(int(seg_lab[a]), "unlabelled")
        s0 = half(i_skin + a)
        s1 = half(i_skin + b) if i_skin + b < len(t) else float(t[-1])
        res.segments.append(PathSegment(name, float(s0), float(s1)))
        res.thickness_by_tissue[name] = res.thickness_by_tissue.get(name, 0.0) + float(s1 - s0)
    if len(bones):
        res.bone_hit = True
        res.soft_tissue_thickness_mm = half(i_end) - res.skin_mm
        res.bone_point = (p0 + half(i_end) * d).tolist()
    return res


# ---------------------------------------------------------------- standard sites
@dataclass
class SiteSummary:
    site: str
    n: int
    mean_mm: float
    sd_mm: float
    min_mm: float
    max_mm: float
    results: list[ThicknessResult]


def _bone_points(seg, name: str) -> np.ndarray:
    """Physical (LPS mm) centres of the voxels of one bone from bones.nii.gz."""
    import SimpleITK as sitk

    from needletissue.imaging.segment import BONE_IDS

    if seg.bones is None:
        raise InputError("site", "automatic sites need bones.nii.gz (segment with --labels)")
    b = sitk.GetArrayViewFromImage(seg.bones)
    kji = np.argwhere(np.asarray(b) == BONE_IDS[name])
    if len(kji) == 0:
        raise InputError("site", f"bone {name} is empty")
    return _to_phys(seg.labels, kji[:, ::-1].astype(float))


def _to_phys(img, ijk: np.ndarray) -> np.ndarray:
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    return np.asarray(img.GetOrigin(), float) + (ijk * np.asarray(img.GetSpacing(), float)) @ D.T


def _exit_point(seg, point, outward, margin_mm: float = 5.0, clear_mm: float = 30.0) -> np.ndarray:
    """Point just outside the body along `outward` from `point`: the start of the first gap of at
    least `clear_mm` without any tissue label (organs inside the body are unlabelled but short)."""
    import SimpleITK as sitk

    img = seg.labels
    arr = sitk.GetArrayViewFromImage(img)
    d = np.asarray(outward, float) / np.linalg.norm(outward)
    sp = np.asarray(img.GetSpacing(), float)
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    step = 0.5
    t = np.arange(0.0, float(np.linalg.norm(np.asarray(img.GetSize()) * sp)), step)
    idx = np.rint((np.asarray(point) + t[:, None] * d - np.asarray(img.GetOrigin())) @ D / sp).astype(int)
    ok = np.all((idx >= 0) & (idx < np.asarray(img.GetSize())), axis=1)
    lab = np.zeros(len(t), np.int32)
    lab[ok] = arr[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    empty = ndi.uniform_filter1d((lab == 0).astype(float), int(clear_mm / step), origin=-int(clear_mm / step) // 2)
    free = np.flatnonzero((empty > 0.999) | ~ok)
    t_out = t[free[0]] if len(free) else t[-1]
    return np.asarray(point) + (t_out + margin_mm) * d


def _head_centre(seg, side: str) -> np.ndarray:
    fem = _bone_points(seg, f"femur_{side}")
    top = fem[fem[:, 2] > fem[:, 2].max() - 40.0]  # femoral head (about 45 mm across)
    return top.mean(0)


def _nearest_skin(seg):
    """Index of the nearest voxel outside the body (label 0) for every voxel."""
    import SimpleITK as sitk

    arr = np.asarray(sitk.GetArrayViewFromImage(seg.labels))
    outside = arr == 0  # segment() labels every body voxel (other_body for organs etc.)
    sp = np.asarray(seg.labels.GetSpacing(), float)[::-1]
    _, ind = ndi.distance_transform_edt(~outside, sampling=sp, return_indices=True)
    return ind


def iliac_crest_sites(seg, side: str, posterior_mm=(20.0, 60.0)) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pin sites on the anterior iliac crest, `posterior_mm` behind the ASIS (gluteal pillar).

    ASIS: the most anterior hip-bone point more than 30 mm above the femoral-head centre. Crest: for
    each 1-voxel AP slab behind it the highest hip-bone point. Path: from the nearest point outside
    the body straight to the crest point (the shortest skin-to-crest distance, as measured on CT).
    Returns [(entry, direction)].
    """
    hip = _bone_points(seg, f"hip_{side}")
    head = _head_centre(seg, side)
    upper = hip[hip[:, 2] > head[2] + 30.0]
    asis_y = upper[:, 1].min()  # LPS: anterior is -y
    img = seg.labels
    sp = np.asarray(img.GetSpacing(), float)
    D = np.asarray(img.GetDirection(), float).reshape(3, 3)
    ind = _nearest_skin(seg)
    out = []
    for y in np.arange(asis_y + posterior_mm[0], asis_y + posterior_mm[1] + 1e-9, sp[1]):
        slab = upper[np.abs(upper[:, 1] - y) <= sp[1] / 2]
        if len(slab) == 0:
            continue
        crest = slab[np.argmax(slab[:, 2])]
        i, j, k = np.rint((crest - np.asarray(img.GetOrigin())) @ D / sp).astype(int)
        skin = _to_phys(img, ind[:, k, j, i][::-1].astype(float)[None])[0]
        d = crest - skin
        d /= np.linalg.norm(d)
        out.append((skin - 5.0 * d, d))
    if not out:
        raise InputError("site", f"no iliac crest found on the {side} side")
    return out


def supra_acetabular_sites(seg, side: str, heights_mm=(15.0, 45.0)) -> list[tuple[np.ndarray, np.ndarray]]:
    """Supra-acetabular (AIIS) pin sites: the most anterior hip-bone point of each axial slab
    `heights_mm` above the femoral-head centre, directed at the PSIS (the standard AIIS->PSIS corridor).
    """
    hip = _bone_points(seg, f"hip_{side}")
    head = _head_centre(seg, side)
    psis = hip[hip[:, 2] > head[2] + 40.0]
    psis = psis[np.argmax(psis[:, 1])]  # most posterior point of the upper ilium
    sz = float(seg.labels.GetSpacing()[2])
    out = []
    for z in np.arange(head[2] + heights_mm[0], head[2] + heights_mm[1] + 1e-9, sz):
        slab = hip[np.abs(hip[:, 2] - z) <= sz / 2]
        if len(slab) == 0:
            continue
        aiis = slab[np.argmin(slab[:, 1])]
        d = psis - aiis
        d /= np.linalg.norm(d)
        out.append((_exit_point(seg, aiis, -d), d))
    if not out:
        raise InputError("site", f"no supra-acetabular site found on the {side} side")
    return out


SITES = {"iliac_crest": iliac_crest_sites, "supra_acetabular": supra_acetabular_sites}


def site_thickness(seg, site: str, sides=("left", "right")) -> SiteSummary:
    """Soft-tissue thickness at a standard site over its set of entry points: mean +- SD (sample SD)."""
    if site not in SITES:
        raise InputError("site", f"unknown site {site!r}; known: {', '.join(SITES)}")
    results = []
    for side in sides:
        for entry, d in SITES[site](seg, side):
            r = thickness_along(seg, entry, d, site=f"{site}_{side}")
            if r.bone_hit:
                results.append(r)
    if not results:
        raise InputError("site", f"no path at {site} reached bone")
    v = np.array([r.soft_tissue_thickness_mm for r in results])
    return SiteSummary(site=site, n=len(v), mean_mm=float(v.mean()),
                       sd_mm=float(v.std(ddof=1)) if len(v) > 1 else 0.0,
                       min_mm=float(v.min()), max_mm=float(v.max()), results=results)
