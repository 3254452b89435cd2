"""The paper's anatomical model: hemipelvis with soft tissues, two needles, a clamp, 100/200/300 N.

config (PelvisConfig) -> geometry.pelvis (labels, site, mesh) -> FEModel + BCs -> solve -> PelvisResult.

Boundary conditions (paper Sec. 3.1, "fixed proximal femoral section, superior surface of the sacrum and
the sacroiliac joint"):
  femur_fixed       all components fixed on the femur's section at the crop's bottom plane
  sacrum_fixed      all components fixed on the superior sacral surface (boundary within 6 mm of its top)
  sacroiliac_joint  `si_joint="fixed"` (paper): the ilium's auricular surface (hip-bone faces touching or
                    within 1.5 voxels of the sacrum) is fixed; `"bonded"`: only the shared nodes of
                    touching hip/sacrum elements tie the bones (gaps stay open)
  midline           u_x = 0 on the medial crop plane (mirror symmetry of the other hemipelvis)
  gripper           the reduction force, spread uniformly over the clamp bar's two side faces (the robot's
                    jaws; same convention as the `needle` branch), resultant at the clamp's mid-height
Everything else is bonded (one conforming mesh) unless `interfaces`/`friction` make the needle,
muscle and bone interfaces frictional contacts (needletissue.fem.contact; docs/contact.md).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from needletissue.errors import InputError, check_force, check_number
from needletissue.fem.solvelog import SOLVE_LOG
from needletissue.geometry.tetmesh import FAR_SIZE_MAX
from needletissue.materials import tissue_bulk

PAPER = {
    "forces_N": [100.0, 200.0, 300.0],
    "max_needle_deformation_mm": [5.8152, 10.8990, 18.0620],
    "ritz_tip_deflection_mm_300N": 17.63,
    "theory_fe_difference_mm_300N": 0.432,
    "adipose_max_deformation_mm_300N": 7.45,
    "ranking_300N": ["adipose", "iliacus", "gluteus_medius", "gluteus_maximus"],
    "soft_tissue_thickness_mm": {"muscle": 22.0, "adipose": 10.0, "patients_mean": 31.82, "patients_sd": 5.43},
    "elements": 1329469,
}

SLIDING_RADIUS = 35.0
"""Default muscle-bone sliding radius, mm: beyond it the muscles stay bonded (origins and insertions)."""
FRAME = "patient RAS, mm (x right, y anterior, z superior), the CT's scanner coordinates"

MATERIALS = {
    "hip_cortical": "cortical_bone",
    "hip_cancellous": "cancellous_bone",
    "sacrum": "cancellous_bone",  # mostly trabecular; fixed on two faces, so it barely matters
    "femur": "cortical_bone",  # the proximal shaft section carrying the fixed boundary is cortical
    "gluteus_maximus": "muscle",
    "gluteus_medius": "muscle",
    "gluteus_minimus": "muscle",
    "iliopsoas": "muscle",
    "body_wall": "muscle",
    "adipose": "adipose",
    "needle_1": "needle",
    "needle_2": "needle",
    "clamp": "clamp",
}


# Default soft-tissue size at the needles per mesher (mm). Smooth (graded to 4x): 4.5 mm is 1.6-2.0 % softer
# than its 3.6 and 2.88 mm levels (which agree to 0.4 %), and its contact solve fits 2 cores and ~10 GB (3.6 mm's
# does not); the box is 3 mm (the paper's size), 5.8 % stiff against its limit (docs/pelvis_model.md).
DEFAULT_MESH_SIZE = {"smooth": 4.5, "box": 3.0}


@dataclass
class PelvisConfig:
    """Inputs of the anatomical model. Lengths mm, forces N.

    source          "ct" (ct + labels NIfTI; default the example CT) or "ssm" (mean SSM bone surfaces)
    side            hemipelvis carrying the needles: "right" (default) or "left"
    site            "supra_acetabular" (default) or "iliac_crest" (geometry.pelvis.standard_site)
    entries         optional (2,3) needle entry points (snapped along the axis to the bone surface)
    direction       optional (3,) needle direction into the bone
    needle_diameter, depth_in_bone, clamp_gap   mm
    forces          reduction forces on the clamp, N
    force_direction (3,) direction of the reduction force (patient RAS; default inferior = traction);
                    with project_force=True its component along the needle axis is removed
    mesh_size       soft-tissue element size next to the needles, mm (None: DEFAULT_MESH_SIZE of the mesher,
                    4.5 smooth, 3 box (the paper's); docs/pelvis_model.md "Default mesh")
    needle_size     needle element size, mm (default 2*mesh_size/3; quadratic tets)
    far_size        element size far (refine_radius) from the needles, mm (default 4*mesh_size)
    mesher          "smooth" (the default) or "box" (gmsh box fragmented with the needles and the clamp, tissue
                    per element by its smoothed centroid label; graded around the needles). "smooth": the `segment` +
                    `mesh` reconstruction, geometry.smooth, of the CT's segmentation or of the SSM's label
                    volume, with the needles and the clamp inserted exactly; graded like the box from
                    mesh_size to far_size by CGAL's interfaces, geometry.graded, which needs CGAL's headers;
                    far_size = mesh_size: one size, surface nets, the label map coarsened to it; needle_size
                    on the solids. With "smooth" the site, paths and crop come from the same segmentation
                    (smooth_label_map)
    segmentation    folder written by `needletissue segment` (tissues.nii.gz, bones.nii.gz): the label map of
                    the smooth mesher instead of segmenting ct + labels again
    order           2 (tetra10, curved needle surfaces; the default) or 1 (linear tets: the paper's element
                    type, for the paper-scale run of benchmarks/paper_scale_pelvis.py; stiffer in bending,
                    so it needs fine needles, and the needles stay inscribed polygons)
    si_joint        "fixed" (paper) or "bonded"
    interfaces      "bonded" (one conforming mesh) or "paper" (frictional contact: needle-muscle 0.3,
                    muscle-bone 0.3, bone-needle 0.9; docs/contact.md)
    friction        {"needle-muscle": 0.3, ...} per-pair friction coefficients (>= 0); each becomes a contact
    sliding_radius  muscle-bone contact only within this distance of a needle axis, mm; beyond it the muscle
                    elements stay bonded (standing in for the muscles' origins and insertions: gluteals on the
                    outer ilium and the trochanters, iliacus in the iliac fossa; docs/contact.md). A radius
                    larger than the model (e.g. 1000) lets every muscle-bone face slide: friction alone then
                    holds the soft tissue on the skeleton (None: SLIDING_RADIUS, 35 mm)
    contact_dhat    contact barrier distance = largest interpenetration, mm
    contact_eps_v   friction smoothing: slip per load increment below which an interface sticks, mm
    """

    source: str = "ct"
    ct: str | None = None
    labels: str | None = None
    segmentation: str | None = None  # a `needletissue segment` folder (mesher "smooth"): instead of ct + labels
    side: str = "right"
    site: str = "supra_acetabular"
    entries: list | None = None
    direction: list | None = None
    needle_diameter: float = 5.0
    depth_in_bone: float = 40.0
    clamp_gap: float = 20.0
    forces: list = field(default_factory=lambda: [100.0, 200.0, 300.0])
    force_direction: list = field(default_factory=lambda: [0.0, 0.0, -1.0])
    project_force: bool = True
    mesh_size: float | None = None   # None: DEFAULT_MESH_SIZE[mesher]
    needle_size: float | None = None
    far_size: float | None = None
    refine_radius: float = 35.0
    cortical_thickness: float = 1.5
    ssm_spacing: float = 2.0
    mesher: str = "smooth"
    order: int = 2
    formulation: str = "mixed"
    tissue_bulk_ratio: float | None = None  # K/mu0 of the tissue; None: the materials' K
    si_joint: str = "fixed"
    interfaces: str = "bonded"
    friction: dict = field(default_factory=dict)
    sliding_radius: float | None = None  # None: SLIDING_RADIUS
    contact_dhat: float | None = None  # None: needle_settings (models.contact)
    contact_eps_v: float | None = None
    solver: str = "auto"
    out: str | None = None
    figures: bool = True
    progress: bool = False
    crosscheck_thickness: bool = True  # CT only: thickness again with the img branch's segmentation

    def __post_init__(self):
        if self.source not in ("ct", "ssm"):
            raise InputError("source", f"must be 'ct' or 'ssm', got {self.source!r}")
        if self.si_joint not in ("fixed", "bonded"):
            raise InputError("si_joint", f"must be 'fixed' or 'bonded', got {self.si_joint!r}")
        if self.mesher not in ("box", "smooth"):
            raise InputError("mesher", f"must be 'box' or 'smooth', got {self.mesher!r}")
        if self.segmentation is not None and self.source != "ct":
            raise InputError("segmentation", "a `segment` folder is a CT's segmentation: it cannot be meshed with "
                                             "the SSM source (--ssm); give one of them")
        if self.segmentation is not None and (self.mesher != "smooth" or self.ct or self.labels):
            raise InputError("segmentation", "a `segment` folder is meshed by mesher 'smooth', instead of ct/labels")
        if self.interfaces not in ("bonded", "paper"):
            raise InputError("interfaces", f"must be 'bonded' or 'paper', got {self.interfaces!r}")
        for name, mu in self.friction.items():
            check_number(f"friction {name}", mu, ge=0)
            check_interface_name(name)
        if self.sliding_radius is None:
            self.sliding_radius = SLIDING_RADIUS
        check_number("sliding_radius", self.sliding_radius, gt=0)
        for name in ("contact_dhat", "contact_eps_v"):
            if getattr(self, name) is not None:
                check_number(name, getattr(self, name), gt=0)
        if not self.forces:
            raise InputError("force", "give at least one force (N), e.g. --force 100 --force 200 --force 300")
        self.forces = sorted(check_force("force", f) for f in self.forces)
        if len(set(self.forces)) != len(self.forces):
            raise InputError("force", f"forces must be distinct, got {self.forces}")
        defaulted = self.mesh_size is None
        if defaulted:
            self.mesh_size = DEFAULT_MESH_SIZE[self.mesher]
        check_number("mesh_size", self.mesh_size, ge=0.5, le=20)
        d = np.asarray(self.force_direction, float)
        if d.shape != (3,) or not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
            raise InputError("force_direction", f"must be a non-zero 3-vector, got {self.force_direction}")
        if self.order not in (1, 2) or isinstance(self.order, bool):
            raise InputError("order", f"must be 1 (linear tets) or 2 (tetra10), got {self.order!r}")
        if self.needle_size is not None:
            check_number("needle_size", self.needle_size, ge=0.2, le=10)
        if self.far_size is not None:
            check_number("far_size", self.far_size)   # a number first: the hint compares it
            try:
                check_number("far_size", self.far_size, ge=self.mesh_size, le=FAR_SIZE_MAX)
            except InputError as exc:
                if not defaulted or self.far_size > self.mesh_size:   # the hint is for a far_size below it
                    raise
                raise InputError("far_size", f"{exc.message} (the {self.mesher} mesher's default "
                                             f"mesh_size is {self.mesh_size} mm; give a smaller mesh_size)") from None
        if self.formulation not in ("displacement", "mixed"):
            raise InputError("formulation", f"must be 'displacement' or 'mixed', got {self.formulation!r}")
        tissue_bulk(MATERIALS, self.tissue_bulk_ratio)  # checks the ratio


def check_interface_name(name: str) -> None:
    """InputError naming `friction` unless `name` is 'groupA-groupB' with groups of this model's regions
    (material families such as muscle, bone, needle, adipose, clamp, or region names): before meshing."""
    from needletissue.fem.contact.mesh import group_regions, material_groups, parse_interface_name

    groups = material_groups(MATERIALS)
    regions = SimpleNamespace(regions=MATERIALS)  # group_regions reads mesh.regions
    try:
        ga, gb = parse_interface_name(name)
    except InputError as exc:
        raise InputError("friction", exc.message) from None
    for g in (ga, gb):
        if not group_regions(regions, g, groups):
            raise InputError("friction", f"interface {name!r}: no region or material {g!r}; allowed: "
                                         f"{', '.join(sorted(set(groups) | set(MATERIALS)))}")


# relative residual (free dofs / reactions) of a contact solve: with muscle-bone in contact Newton's residual
# floors at 4e-8..1e-7 near the solution (the full step repeats; docs/contact.md), so 1e-8 cut back at the same
# state until it failed; 1e-6 of the reactions is < 3e-4 N at 300 N (coarse mesh: 300 N, no cut-back)
CONTACT_TOL = 1e-6
# Newton iterations of a contact increment before it is cut back (fem.solve's default 25): converged
# increments take 4-6 on the coarse mesh (up to 17 with main's softer barriers); the two that failed cycled
# at 1-3e-6 for 25 each, half of the run's iterations (docs/contact.md)
CONTACT_MAXITER = 15
ATTACHED = "@attached"  # suffix of the muscle cells kept bonded to bone while the interfaces are split


def _axis_distance(x: np.ndarray, needle_axes) -> np.ndarray:
    """Distance (mm) of points x (n, 3) to the nearest needle axis segment (bottom in bone, top in clamp)."""
    out = []
    for a, b in needle_axes:
        a, d = np.asarray(a, float), np.asarray(b, float) - np.asarray(a, float)
        t = np.clip((x - a) @ d / (d @ d), 0.0, 1.0)
        out.append(np.linalg.norm(x - a - t[:, None] * d, axis=1))
    return np.min(out, axis=0)


def split_contact(contact, mesh, needle_axes, sliding_radius: float):
    """Split the contact interfaces of `mesh` (NeedleContact.prepare), keeping the muscle elements farther
    than `sliding_radius` from the needle axes bonded to their neighbours (muscle attachments to bone).

    Those elements are set aside in regions "<muscle>@attached" (in no contact group) during the split, so
    their faces stay conforming; the nodes where sliding and attached muscle meet stay tied (split_interfaces).
    Returns the split mesh and the muscle-bone faces (count and area mm2): total, bonded (corners still shared
    after the split, including contact faces whose corners are all tied) and sliding (in contact, a corner
    split); the rest (total - bonded - sliding) touch a node split for another interface (the needle rings)
    and are neither."""
    from needletissue.fem.contact.mesh import interface_faces

    muscles = [r for r in mesh.regions if MATERIALS.get(r) == "muscle"]
    bones = [r for r in mesh.regions if MATERIALS.get(r, "").endswith("_bone")]
    regions = dict(mesh.regions)
    for r in muscles:
        ids = mesh.regions[r]
        far = _axis_distance(mesh.points[mesh.cells[ids][:, :4]].mean(axis=1), needle_axes) > sliding_radius
        regions[r], regions[r + ATTACHED] = ids[~far], ids[far]
    regions = {r: ids for r, ids in regions.items() if len(ids)}
    split = contact.prepare(replace(mesh, regions=regions))
    none = np.zeros(0, int)
    merged = replace(split, regions={r: np.sort(np.concatenate([split.regions.get(r, none),
                                                                split.regions.get(r + ATTACHED, none)]))
                                     for r in mesh.regions})

    def area(faces):
        p = merged.points[faces[:, :3]]
        return float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())

    no = np.zeros((0, 3), int)
    faces = {"total": interface_faces(mesh, muscles, bones)[0] if muscles and bones else no,
             "bonded": interface_faces(merged, muscles, bones)[0] if muscles and bones else no,
             "sliding": next((s.faces_a[np.isin(s.faces_a[:, :3], s.nodes_a).any(axis=1)]
                              for s in contact._split if s.name == "muscle-bone"), no)}
    info = {"sliding_radius_mm": sliding_radius, **{f"muscle_bone_faces_{k}": len(f) for k, f in faces.items()},
            **{f"muscle_bone_area_{k}_mm2": area(f) for k, f in faces.items()}}
    return merged, info


@dataclass
class LoadResult:
    force_N: float
    max_needle_deformation_mm: float
    clamp_displacement_mm: float
    max_deformation_mm: dict
    ritz_tip_deflection_mm: float | None
    theory_fe_difference_mm: float | None
    needle_max_deformation_mm: dict
    newton_iterations: int
    reactions_N: dict = field(default_factory=dict)
    vtu: str | None = None
    # per region: volume fraction beyond the tissue law's Drucker-stable range (fem FEResult.check_drucker)
    drucker_unstable_volume_fraction: dict = field(default_factory=dict)
    strength: dict = field(default_factory=dict)  # models.strength.strength_check: utilisations, warnings


@dataclass
class PelvisResult:
    mesh: dict
    wall_time_s: float
    results: list
    ranking: list
    thickness: list
    site: dict
    force_vector_unit: list
    boundary_conditions: dict
    notes: list
    comparison: list
    timing_s: dict
    ritz: dict
    thickness_img: list = field(default_factory=list)
    figures: dict = field(default_factory=dict)
    contact: dict | None = None  # interfaces, settings, per force the gap opening (mm)

    def to_dict(self) -> dict:
        from needletissue.runinfo import to_jsonable

        return to_jsonable(asdict(self))


def smooth_label_map(config: PelvisConfig):
    """(Segmentation, LabelVolume) the smooth mesher meshes: a `segment` folder, the SSM's label volume as a
    segmentation, or the CT (default the example CT) segmented; the label volume (RAS, one hemipelvis) comes
    back from the segmentation (the SSM's is already one hemipelvis, the same labels: it is kept as it is), so
    that site, paths and mesh are made from one label map."""
    from needletissue.geometry import pelvis as gp
    from needletissue.imaging.segment import Segmentation, SegmentationConfig, segment

    if config.segmentation:
        seg = Segmentation.load(config.segmentation)
    elif config.source == "ssm":   # no CT: the SSM's label volume as a segmentation
        vol = gp.ssm_label_volume(side=config.side, spacing=config.ssm_spacing)
        return gp.label_volume_segmentation(vol, config.cortical_thickness), vol
    else:
        d = None if config.ct else gp.data_dir() / "pelvis_ct"
        seg = segment(config.ct or d / "example_ct.nii.gz", config.labels or d / "example_seg_fast_force_split.nii.gz",
                      SegmentationConfig(cortical_thickness=config.cortical_thickness))
    return seg, gp.segmentation_label_volume(seg, side=config.side)


def build(config: PelvisConfig):
    """Labels, needle site and the linear conforming mesh for `config` (geometry.pelvis.PelvisMesh)."""
    from needletissue.geometry import pelvis as gp

    seg = None
    far = min(4 * config.mesh_size, FAR_SIZE_MAX) if config.far_size is None else config.far_size
    if config.mesher == "smooth":
        if far > config.mesh_size:   # the CGAL helper first: a missing CGAL is named before any work
            from needletissue.geometry.graded import helper

            helper()
        seg, vol = smooth_label_map(config)
    elif config.source == "ct":
        vol = gp.ct_label_volume(config.ct, config.labels, side=config.side)
    else:
        vol = gp.ssm_label_volume(side=config.side, spacing=config.ssm_spacing)
    kw = dict(diameter=config.needle_diameter, depth_in_bone=config.depth_in_bone, clamp_gap=config.clamp_gap)
    if config.entries is not None or config.direction is not None:
        base = gp.standard_site(vol, config.site, **kw)
        site = gp.NeedleSite(
            entries=base.entries if config.entries is None else np.asarray(config.entries, float),
            direction=base.direction if config.direction is None else np.asarray(config.direction, float),
            name="custom", **kw)
        site = gp.snap_entries(vol, site)
    else:
        site = gp.standard_site(vol, config.site, **kw)
    vol = gp.crop_to_site(vol, site)
    if seg is not None:
        return vol, gp.build_mesh_smooth(seg, vol, site, mesh_size=config.mesh_size, needle_size=config.needle_size,
                                         far_size=far, refine_radius=config.refine_radius)
    mesh = gp.build_mesh(vol, site, mesh_size=config.mesh_size, needle_size=config.needle_size,
                         far_size=config.far_size, cortical_thickness=config.cortical_thickness,
                         refine_radius=config.refine_radius, cache=True)   # $NEEDLETISSUE_MESH_CACHE=0: off
    return vol, mesh


def mesh_quality(pm, vol) -> dict:
    """Quality and fidelity of the linear mesh that is solved (its tetra10 has the same corners): dihedral
    angles (min, 1st percentile of the per-element minimum), and each tissue's mesh volume against its
    voxel volume in the label map the mesh was made from (pm.label_volumes: the segmentation for the smooth
    route; else the cropped label volume; hip cortical + cancellous against hip_bone; needles and clamp
    replace the tissue they occupy, so the soft tissue they cross reads a little low)."""
    from needletissue.geometry.pelvis import TISSUES
    from needletissue.geometry.tetmesh import tet_quality

    q = tet_quality(pm.points, pm.cells)
    vols = {n: float(q["volume"][ids].sum()) for n, ids in pm.regions.items()}
    vols["hip_bone"] = vols.pop("hip_cortical", 0.0) + vols.pop("hip_cancellous", 0.0)
    counts = np.bincount(vol.labels.ravel(), minlength=len(TISSUES) + 1)
    label = dict(pm.label_volumes or {n: float(counts[i] * vol.spacing ** 3) for i, n in TISSUES.items() if counts[i]})
    bones = ("hip_bone", "sacrum", "femur")   # all bone: the split between bones is per element
    vols["bone"], label["bone"] = (sum(d.get(b, 0.0) for b in bones) for d in (vols, label))
    return {"min_dihedral_deg": float(q["min_dihedral"].min()),
            "p01_dihedral_deg": float(np.percentile(q["min_dihedral"], 1)),
            "below_10_deg": int(np.count_nonzero(q["min_dihedral"] < 10.0)),
            "inverted": int(np.count_nonzero(q["volume"] <= 0)),
            "volume_mm3": {n: vols[n] for n in label if n in vols},
            "label_volume_mm3": label,
            "volume_error_vs_labels": {n: vols[n] / v - 1.0 for n, v in label.items() if n in vols}}


def force_unit(config: PelvisConfig, site) -> np.ndarray:
    d = np.asarray(config.force_direction, float)
    d = d / np.linalg.norm(d)
    if config.project_force:
        a = site.direction
        d = d - (d @ a) * a
        if np.linalg.norm(d) < 1e-6:
            raise InputError("force_direction", "is parallel to the needles; give a transverse direction")
        d = d / np.linalg.norm(d)
    return d


def ritz_prediction(config: PelvisConfig, paths, free_length: list, load_point: list, forces) -> dict:
    """Rayleigh-Ritz (paper Eqs. 8-15, `needletissue.ritz`) for each needle with its measured layers:
    muscle-like tissue (k = 0.048) next to the bone, adipose (k = 0.023) outside it, as in the paper's
    two-layer model (Table 1 stiffnesses); l = bone entry to the needle's end in the clamp, z3 = clamp
    mid-height (where the resultant of the uniform clamp load acts)."""
    from needletissue import ritz

    out = {"model": "two-layer Rayleigh-Ritz, cubic trial function (paper Eq. 13); the whole force F on "
                    "each needle as in the paper's comparison, and F/2 for reference", "per_needle": []}
    for p, l, z3 in zip(paths, free_length, load_point):
        layers = [ritz.Layer(n, t, k) for n, t, k in (("muscle", p.muscle_mm, 0.048), ("adipose", p.adipose_mm, 0.023))
                  if t > 0]
        model = ritz.RitzModel(diameter_mm=config.needle_diameter, free_length_mm=l, layers=tuple(layers),
                               load_point_mm=z3)
        res = ritz.solve_forces(forces, model)
        half = ritz.solve_forces([f / 2 for f in forces], model)  # if the two needles share F equally
        out["per_needle"].append({"model": model.to_dict(), "tip_deflection_mm": [r.tip_deflection_mm for r in res],
                                  "max_deflection_mm": [r.max_deflection_mm for r in res],
                                  "max_deflection_half_force_mm": [r.max_deflection_mm for r in half]})
    return out


def thickness_crosscheck(config: PelvisConfig, pm) -> list:
    """Soft-tissue thickness along each needle from the `img` branch's own segmentation and path walk
    (needletissue.imaging.segment + geometry.thickness.thickness_along, LPS frame): an independent
    check of geometry.pelvis.needle_paths. The path enters 10 mm outside our skin exit."""
    from needletissue.geometry.pelvis import RAS_LPS, data_dir
    from needletissue.geometry.thickness import thickness_along
    from needletissue.imaging.segment import SegmentationConfig, segment

    d = None if config.ct else data_dir() / "pelvis_ct"
    ct = config.ct or d / "example_ct.nii.gz"
    labels = config.labels or d / "example_seg_fast_force_split.nii.gz"
    # split on the CT grid itself: the thickness needs bone vs soft tissue only, and the 0.75 mm split
    # grid took ~4 GB more memory
    seg = segment(ct, labels, SegmentationConfig(split_spacing=3.0))
    out = []
    for i, p in enumerate(pm.paths):
        r = thickness_along(seg, (p.skin_exit - 10.0 * pm.site.direction) * RAS_LPS,
                            pm.site.direction * RAS_LPS)
        bone = None if r.bone_point is None else np.asarray(r.bone_point) * RAS_LPS
        out.append({"needle": f"needle_{i + 1}", "total_mm": r.soft_tissue_thickness_mm,
                    "by_tissue_mm": r.thickness_by_tissue,
                    "bone_point_distance_mm": None if bone is None else float(np.linalg.norm(bone - p.entry)),
                    "ours_total_mm": p.total_mm})
    return out


def run_pelvis_model(config: PelvisConfig | dict | None = None) -> PelvisResult:
    """Build, solve and report the anatomical model; writes VTU, figures and run files to config.out.

    The files are written into a hidden folder inside config.out and moved in when all are written
    (runinfo.staged_output): a run stopped or failed meanwhile leaves config.out as it was; the
    pelvis_<F>N files of an earlier run's other forces are removed."""
    if config is None:
        config = PelvisConfig()
    elif isinstance(config, dict):
        config = PelvisConfig(**config)
    if not config.out:
        return _run_pelvis_model(config, None)
    from needletissue.runinfo import staged_output

    out_dir = Path(config.out).absolute()
    with staged_output(out_dir, replaces=r"pelvis_[0-9]+N(\.vtu|\.vtm)?") as stage:
        res = _run_pelvis_model(config, stage)
    for x in res.results:  # where the files are now
        x.vtu = str(out_dir / Path(x.vtu).name) if x.vtu else x.vtu
    if res.figures.get("files"):
        res.figures["files"] = [str(out_dir / Path(f).name) for f in res.figures["files"]]
    return res


def _run_pelvis_model(config: PelvisConfig, out_dir: Path | None) -> PelvisResult:
    from contextlib import nullcontext

    from needletissue.fem import FEModel, Fixed, PrescribedDisplacement, SurfaceForce, TaggedMesh, solve
    from needletissue.fem.solvelog import SolveLog

    t0 = time.perf_counter()
    c0 = time.process_time()
    vol, pm = build(config)
    t_mesh = time.perf_counter() - t0
    tm = TaggedMesh(pm.points, pm.cells, pm.regions, pm.surfaces)
    tm.check(regions=["needle_1", "needle_2", "clamp", "hip_cortical"],
             surfaces=["femur_fixed", "sacrum_fixed", "sacroiliac_joint", "gripper", "midline"])
    if config.order == 2:
        from needletissue.geometry.pelvis import curve_needles

        q = tm.to_quadratic()
        q.points = curve_needles(q.points, q.cells, q.regions, pm.needle_axes, pm.site.diameter / 2)
        tm_solve = q
    else:
        tm_solve = tm
    contact = None
    if config.interfaces != "bonded" or config.friction:
        from needletissue.models.contact import NeedleContact, needle_settings

        # the needle model's settings (barrier per interface, virtual gap, friction smoothing): one rule
        contact = NeedleContact(config.interfaces, dict(config.friction),
                                needle_settings(**{k: v for k, v in (("dhat", config.contact_dhat),
                                                                     ("eps_v", config.contact_eps_v)) if v is not None}),
                                materials=MATERIALS)
        # split the contact interfaces (duplicate their nodes); muscle attachments stay bonded
        tm_solve, attachments = split_contact(contact, tm_solve, pm.needle_axes, config.sliding_radius)
    mats = {r: MATERIALS[r] for r in tm.regions}
    model = FEModel(tm_solve, mats, order=config.order, formulation=config.formulation,
                    bulk=tissue_bulk(mats, config.tissue_bulk_ratio))
    items = contact.items(model) if contact is not None else ()
    t_model = time.perf_counter() - t0 - t_mesh
    fdir = force_unit(config, pm.site)
    fmax = config.forces[-1]
    bcs = [PrescribedDisplacement("midline", value=(0.0, None, None))]
    bcs += [Fixed("femur_fixed"), Fixed("sacrum_fixed")]
    if config.si_joint == "fixed":
        bcs.append(Fixed("sacroiliac_joint"))
    bcs.append(SurfaceForce("gripper", total=tuple(fmax * fdir)))
    factors = [f / fmax for f in config.forces]
    # the solve's progress, line by line as it happens, in --out itself (not the staged folder: it stays
    # when the run fails or is stopped, and says the load reached)
    log = None if config.out is None else SolveLog(
        Path(config.out) / SOLVE_LOG, scale=fmax, load_key="force_N", forces_N=config.forces,
        tetrahedra=len(model.mesh.cells), dofs=int(model.ndof),
        interfaces=dict(contact.friction) if contact is not None else "bonded")
    with log or nullcontext():
        fe = solve(model, bcs, load_factors=factors, solver=config.solver, progress=config.progress, items=items,
                   # contact: from the second increment on, shortened to what CCD admits, as the needle model
                   predictor=2 if items else config.formulation == "mixed",
                   log=log, **({"tol": CONTACT_TOL, "maxiter": CONTACT_MAXITER} if items else {}))
    t_solve = time.perf_counter() - t0 - t_mesh - t_model

    qm = model.mesh
    # exposed needle length: bone entry to the clamp's mid-height (where the resultant acts)
    h_clamp = pm.site.clamp_size[0]
    a_out = -pm.site.direction
    exposed = [float((top - e) @ a_out) for e, (_, top) in zip(pm.site.entries, pm.needle_axes)]
    ritz = ritz_prediction(config, pm.paths, exposed, [x - h_clamp / 2 for x in exposed], config.forces)
    # the FE reports the larger of the two needles' maxima: compare with the larger Ritz deflection
    ritz_tip = [max(n["max_deflection_mm"][i] for n in ritz["per_needle"]) for i in range(len(config.forces))]

    loads = []
    gripper_nodes = np.unique(qm.surfaces["gripper"])  # |mean u| over the gripper, as `fe needle`
    from needletissue.models.strength import strength_check

    for f, r, rt in zip(config.forces, fe, ritz_tip):
        by = {k: float(v) for k, v in r.max_displacement_by_region.items()}
        needles = {k: by[k] for k in ("needle_1", "needle_2")}
        nmax = max(needles.values())
        clamp_u = float(np.linalg.norm(r.displacement[gripper_nodes].mean(axis=0)))
        vtu = None
        if out_dir is not None:
            vtu = str(r.write_vtu(out_dir / f"pelvis_{int(round(f))}N.vtu", frame=FRAME, force_N=f))
        loads.append(LoadResult(f, nmax, clamp_u, by, rt, None if rt is None else abs(rt - nmax), needles,
                                r.newton_iterations, {k: np.asarray(v).tolist() for k, v in r.reaction_forces.items()},
                                vtu, dict(r.drucker_unstable_fraction), strength_check(r, MATERIALS)))
    from needletissue.geometry.pelvis import SOFT_TISSUES

    last = loads[-1].max_deformation_mm
    ranking = sorted((t for t in SOFT_TISSUES if t in last), key=lambda t: -last[t])
    thickness = [dict(needle=f"needle_{i + 1}", entry_mm=p.entry, skin_exit_mm=p.skin_exit, muscle_mm=p.muscle_mm,
                      adipose_mm=p.adipose_mm, total_mm=p.total_mm, exposed_length_mm=exposed[i],
                      layers=[dict(tissue=n, from_mm=a, to_mm=b) for n, a, b in p.layers])
                 for i, p in enumerate(pm.paths)]
    res = PelvisResult(
        mesh={"nodes": int(len(qm.points)), "tetrahedra": int(len(qm.cells)), "order": config.order,
              "linear_nodes": int(len(pm.points)),
              "cells_by_region": {k: int(len(v)) for k, v in qm.regions.items()},
              "dofs": int(model.ndof), "min_quality": float(tm.quality().min()),
              "region_tags": {k: int(v) for k, v in fe[-1].region_tags.items()},
              "quality": mesh_quality(pm, vol), "mesher": config.mesher, "mesh_info": pm.info,
              "cached": pm.cached},
        wall_time_s=time.perf_counter() - t0,
        results=loads,
        ranking=ranking,
        thickness=thickness,
        site={"name": pm.site.name, "entries_mm": pm.site.entries, "direction": pm.site.direction,
              "needle_diameter_mm": pm.site.diameter, "depth_in_bone_mm": pm.site.depth_in_bone,
              "clamp_gap_mm": pm.site.clamp_gap, "clamp_size_mm": pm.site.clamp_size,
              "needle_axes_mm": pm.needle_axes, "source": vol.source, "side": vol.side},
        force_vector_unit=fdir,
        boundary_conditions={"femur_fixed": "fixed", "sacrum_fixed": "fixed",
                             "sacroiliac_joint": config.si_joint, "midline": "u_x = 0 (symmetry)",
                             "gripper": "uniform surface force on the clamp's side faces (dead load)",
                             "interfaces": "bonded (one conforming mesh)" if contact is None else
                             {"contact": dict(contact.friction), "bonded": "every other interface"}},
        notes=pm.notes,
        comparison=[],
        timing_s={"mesh": t_mesh, "model": t_model, "solve": t_solve, "cpu_s": time.process_time() - c0,
                  # solve = Newton (assembly + linear solves) + stress/VTU evaluation
                  "newton": fe[-1].timing_s.get("newton"), "linear_solve": fe[-1].timing_s.get("linear_solve"),
                  "linear_solver": fe[-1].linear_solver, "linear_factor": fe[-1].linear_factor,
                  "linear_counts": fe[-1].linear_counts},
        ritz=ritz,
    )
    if contact is not None:
        res.contact = {**contact.summary(config.forces, [r.displacement for r in fe]), "attachments": attachments,
                       "newton_tol": CONTACT_TOL}
        for x, load in zip(res.contact["per_force"], loads):  # the supports carry the clamp force
            reaction = np.sum([np.asarray(v) for v in load.reactions_N.values()], axis=0)
            x["equilibrium_error"] = float(np.linalg.norm(reaction + load.force_N * fdir) / load.force_N)
            x["newton_iterations"] = load.newton_iterations
    if config.source == "ct" and config.crosscheck_thickness and not config.segmentation:
        res.thickness_img = thickness_crosscheck(config, pm)
    res.comparison = comparison_table(res)
    if out_dir is not None:
        from needletissue.runinfo import write_json, write_run_files

        pm_m = pm.to_meshio()
        import meshio

        from needletissue.fem.result import write_series

        # the same region numbers as the results' VTU ("region"; -1 on the boundary triangles)
        tags = fe[-1].region_tags
        pm_m.cell_data["region"] = [np.concatenate([np.full(len(ids), tags.get(n, -1), np.int32)
                                                    for n, ids in pm.regions.items()]),
                                    np.full(len(pm_m.cells[1].data), -1, np.int32)]
        out_dir.mkdir(parents=True, exist_ok=True)
        meshio.write(out_dir / "pelvis_mesh.vtu", pm_m)
        write_series(out_dir / "pelvis.pvd", [(x.force_N, Path(x.vtu).with_suffix(".vtm").name) for x in loads if x.vtu])
        res.wall_time_s = time.perf_counter() - t0
        from needletissue.models.pelvis.report import comparison_markdown, render_in_subprocess
        from needletissue.runinfo import write_atomic

        write_atomic(out_dir / "pelvis_comparison.md", comparison_markdown(res))
        # `out` is where the files are, not an input: --out chooses it when the config is run again
        write_run_files(out_dir, {k: v for k, v in asdict(config).items() if k != "out"}, res.to_dict())
        write_json(out_dir / "pelvis_results.json", res.to_dict())
        if config.figures:  # after the results are safe: a VTK crash must not lose them
            res.figures = render_in_subprocess(out_dir)
            write_json(out_dir / "pelvis_results.json", res.to_dict())
    return res


def comparison_table(res: PelvisResult) -> list:
    """Our numbers beside the paper's, one row per quantity, with the reason for the difference."""
    rows = []
    by_force = {r.force_N: r for r in res.results}
    for f, p in zip(PAPER["forces_N"], PAPER["max_needle_deformation_mm"]):
        if f in by_force:
            v = by_force[f].max_needle_deformation_mm
            rows.append(dict(quantity=f"max needle deformation at {f:.0f} N (mm)", ours=v, paper=p,
                             difference=v - p, relative=(v - p) / p))
    r300 = by_force.get(300.0)
    if r300 is not None:
        if r300.ritz_tip_deflection_mm is not None:
            rows.append(dict(quantity="Ritz tip deflection at 300 N (mm)", ours=r300.ritz_tip_deflection_mm,
                             paper=PAPER["ritz_tip_deflection_mm_300N"],
                             difference=r300.ritz_tip_deflection_mm - PAPER["ritz_tip_deflection_mm_300N"]))
            rows.append(dict(quantity="theory-FE difference at 300 N (mm)", ours=r300.theory_fe_difference_mm,
                             paper=PAPER["theory_fe_difference_mm_300N"],
                             difference=r300.theory_fe_difference_mm - PAPER["theory_fe_difference_mm_300N"]))
        a = r300.max_deformation_mm.get("adipose")
        if a is not None:
            rows.append(dict(quantity="adipose max deformation at 300 N (mm)", ours=a,
                             paper=PAPER["adipose_max_deformation_mm_300N"],
                             difference=a - PAPER["adipose_max_deformation_mm_300N"]))
    paper_names = {"iliacus": "iliopsoas"}
    ours_rank = [t for t in res.ranking if t in ("adipose", "iliopsoas", "gluteus_medius", "gluteus_maximus")]
    rows.append(dict(quantity="ranking of the paper's four tissues (largest first)", ours=ours_rank,
                     paper=[paper_names.get(t, t) for t in PAPER["ranking_300N"]],
                     difference="same order" if ours_rank == [paper_names.get(t, t) for t in PAPER["ranking_300N"]]
                     else "different order"))
    for t in res.thickness:
        rows.append(dict(quantity=f"soft tissue along {t['needle']} (mm): muscle / adipose / total",
                         ours=[t["muscle_mm"], t["adipose_mm"], t["total_mm"]],
                         paper=[22.0, 10.0, PAPER["soft_tissue_thickness_mm"]["patients_mean"]],
                         difference=t["total_mm"] - PAPER["soft_tissue_thickness_mm"]["patients_mean"]))
    rows.append(dict(quantity="tetrahedra", ours=res.mesh["tetrahedra"], paper=PAPER["elements"],
                     difference=res.mesh["tetrahedra"] - PAPER["elements"]))
    return rows
