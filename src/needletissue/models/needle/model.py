"""The needle-tissue-bone FE model: geometry -> mesh -> FElupe solve (needletissue.fem) -> results.

Bonded interfaces (one conforming mesh); bone far faces (bottom and sides) fixed; tissue far faces
(the muscle and adipose sides) fixed, because the tissue continues there and is tethered to the pelvis
(the far boundary is far enough that this choice changes the needle result by less than the mesh error,
docs/needle_model.md); skin free. The reduction force is a dead load spread uniformly over the
gripper faces of the clamp, optionally with a moment (`load_offset`: the force acts at an offset from
the gripper centre, a statically equivalent force + moment r x F at the centre). Needle, clamp, bone: compressible Neo-Hooke from E, nu (paper Table 2);
muscle MR5 and adipose Ogden nearly incompressible (P2/P0 mixed elements on quadratic tets).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, check_force, check_number
from needletissue.geometry.needle import NeedleGeometry, mesh_needle_model
from needletissue.materials import tissue_bulk

MATERIALS = {
    "cortical_bone": "cortical_bone", "cancellous_bone": "cancellous_bone", "muscle": "muscle",
    "adipose": "adipose", "needle_1": "needle", "needle_2": "needle", "clamp": "clamp",
}
TISSUE_FAR = ("fixed", "free")
# first contact increment, a fraction of the first force: on the default mesh the tissue rim's needle-muscle
# barrier closes in larger ones (100 N and 50 N failed after 25 iterations each, 1 and 2 needles; from 5 N
# with growth it reaches 300 N), where the coarse mesh and the anatomical model converge from the full first
# force (docs/contact.md, "Contact increments")
CONTACT_FIRST_INCREMENT = 1 / 20
FRAME = ("needle model, mm: z along the needles (0 at the bone surface, tissue above), x across the needles, "
         "y lateral (the default force direction)")


@dataclass(frozen=True)
class NeedleModelConfig:
    """Inputs of one needle model run. Forces in N, direction a unit-free vector (normalised)."""

    geometry: NeedleGeometry = field(default_factory=NeedleGeometry)
    forces: tuple[float, ...] = (100.0, 200.0, 300.0)   # N, solved as one load path
    direction: tuple[float, float, float] = (0.0, 1.0, 0.0)  # default lateral: perpendicular to the
    #                                                  needles and to their plane (y)
    load_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # mm: load point - gripper centre; the
    #                           FE applies F at the centre plus the moment load_offset x F (N mm)
    order: int = 2                                     # 2: quadratic tets (linear ones lock in bending)
    formulation: str = "mixed"                         # tissue P2/P0 (nearly incompressible)
    tissue_far: str = "fixed"                          # "fixed" | "free": muscle/adipose far faces
    tissue_bulk_ratio: float | None = None             # K/mu0 of the tissue; None: the materials' K
    solver: str = "auto"
    ritz: bool = True                                  # compare with the Rayleigh-Ritz model
    progress: bool = False

    def __post_init__(self):
        if not isinstance(self.geometry, NeedleGeometry):
            raise InputError("geometry", "must be a NeedleGeometry")
        if len(self.forces) == 0:
            raise InputError("forces", "give at least one force (N)")
        f = [check_force("forces", v) for v in self.forces]
        if any(b <= a for a, b in zip(f, f[1:])):
            # one load path: the solver needs strictly increasing load factors
            object.__setattr__(self, "forces", tuple(sorted(set(f))))
        else:
            object.__setattr__(self, "forces", tuple(f))
        d = np.asarray([check_number("direction", v) for v in self.direction], dtype=float)
        if d.shape != (3,) or np.linalg.norm(d) == 0:
            raise InputError("direction", f"must be a non-zero 3-vector, got {self.direction!r}")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / np.linalg.norm(d)))
        r = [check_number("load_offset", v) for v in self.load_offset]
        if len(r) != 3:
            raise InputError("load_offset", f"must be a 3-vector (mm), got {self.load_offset!r}")
        object.__setattr__(self, "load_offset", tuple(r))

    @property
    def load_point(self) -> np.ndarray:
        """Where the force acts (mm): the gripper centre (0, 0, z3) plus load_offset."""
        return np.array([0.0, 0.0, self.geometry.gripper_centre]) + np.asarray(self.load_offset)

    def moment(self, force: float) -> np.ndarray:
        """Moment (N mm) about the gripper centre of the force `force` (N) at the load point."""
        return np.cross(np.asarray(self.load_offset), force * np.asarray(self.direction))
        if self.order not in (1, 2):
            raise InputError("order", f"must be 1 or 2, got {self.order!r}")
        if self.formulation not in ("displacement", "mixed"):
            raise InputError("formulation", f"must be 'displacement' or 'mixed', got {self.formulation!r}")
        tissue_bulk(MATERIALS, self.tissue_bulk_ratio)  # checks the ratio
        if self.tissue_far not in TISSUE_FAR:
            raise InputError("tissue_far", f"must be one of {TISSUE_FAR}, got {self.tissue_far!r}")


@dataclass
class DeflectionCurve:
    """Needle axis in the reference configuration and its displacement (mm)."""

    z_mm: np.ndarray               # axial position, 0 = bone surface, from -depth to free_length
    deflection_mm: np.ndarray      # displacement along the force direction
    displacement_mm: np.ndarray    # (k, 3) full displacement


@dataclass
class NeedleLoadResult:
    force_N: float
    max_needle_deformation_mm: float   # max |u| over the needle nodes (the paper's "maximum deformation")
    clamp_displacement_mm: float       # |mean u| over the gripper faces (where the robot holds)
    max_deformation_mm: dict[str, float]
    needle_end_deflection_mm: dict[str, float]   # axis end (z = l), along the force direction
    curves: dict[str, DeflectionCurve]
    newton_iterations: int
    steps: int
    ritz_tip_deflection_mm: float | None = None
    theory_fe_difference_mm: float | None = None
    ritz_force_per_needle_tip_deflection_mm: float | None = None
    fe: object = field(default=None, repr=False)   # the FEResult (displacements, stresses)
    ritz: tuple = field(default=(), repr=False)    # RitzResult at the full force and per needle
    # the wrench and the clamp's rigid motion (for reduced-order models: issue 14)
    force_vector_N: list = field(default_factory=list)
    moment_Nmm: list = field(default_factory=list)              # about the gripper centre
    load_point_mm: list = field(default_factory=list)
    clamp_displacement_vector_mm: list = field(default_factory=list)   # mean u over the gripper nodes
    clamp_rotation_rad: list = field(default_factory=list)      # rotation vector, rigid fit to the clamp
    clamp_fit: dict = field(default_factory=dict)               # centre displacement, fit residual
    root_slope: dict = field(default_factory=dict)              # needle -> [du_x/dz, du_y/dz] at z = 0
    root_displacement_mm: dict = field(default_factory=dict)    # needle -> u at z = 0
    strength: dict = field(default_factory=dict)                # models.strength.strength_check

    def to_dict(self) -> dict:
        return {
            "force_N": self.force_N,
            "max_needle_deformation_mm": self.max_needle_deformation_mm,
            "clamp_displacement_mm": self.clamp_displacement_mm,
            "max_deformation_mm": self.max_deformation_mm,
            "ritz_tip_deflection_mm": self.ritz_tip_deflection_mm,
            "theory_fe_difference_mm": self.theory_fe_difference_mm,
            "ritz_force_per_needle_tip_deflection_mm": self.ritz_force_per_needle_tip_deflection_mm,
            "needle_end_deflection_mm": self.needle_end_deflection_mm,
            "newton_iterations": self.newton_iterations,
            "steps": self.steps,
            "drucker_unstable_volume_fraction": self.fe.drucker_unstable_fraction if self.fe is not None else {},
            "reaction_forces_N": {k: np.asarray(v).tolist() for k, v in self.fe.reaction_forces.items()}
            if self.fe is not None else {},
            "deflection_curves": {k: {"z_mm": c.z_mm.tolist(), "deflection_mm": c.deflection_mm.tolist()}
                                  for k, c in self.curves.items()},
            "force_vector_N": self.force_vector_N,
            "moment_Nmm": self.moment_Nmm,
            "load_point_mm": self.load_point_mm,
            "clamp_displacement_vector_mm": self.clamp_displacement_vector_mm,
            "clamp_rotation_rad": self.clamp_rotation_rad,
            "clamp_fit": self.clamp_fit,
            "root_slope": self.root_slope,
            "root_displacement_mm": self.root_displacement_mm,
            **self.strength,
        }


@dataclass
class NeedleModelResult:
    config: NeedleModelConfig
    mesh: dict                     # nodes, tetrahedra (+ quadratic nodes, per-region counts, quality)
    wall_time_s: float
    results: list[NeedleLoadResult]
    timing_s: dict = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    extra: dict = field(default_factory=dict)     # e.g. "contact": interfaces, settings, gap per force

    def to_dict(self) -> dict:
        return {
            "mesh": self.mesh,
            "wall_time_s": self.wall_time_s,
            "timing_s": self.timing_s,
            "results": [r.to_dict() for r in self.results],
            "files": self.files,
            **self.extra,
        }


def run_needle_model(config: NeedleModelConfig | None = None, out_dir: str | Path | None = None, *,
                     mesh_path: str | Path | None = None, items=(), mesh_hook=None,
                     report=None) -> NeedleModelResult:
    """Mesh, solve every force of `config.forces` on one load path, post-process; with `out_dir`
    write the mesh, one VTU per force, results.json, config.toml, versions.json and the figures.

    Hooks for the frictional-contact model: `mesh_hook(TaggedMesh) -> TaggedMesh` runs on the mesh
    before the FE model is built (e.g. to split the interface surfaces); `items` is a sequence of
    extra FElupe items or a callable `items(FEModel) -> sequence` (built once the model exists);
    `report(NeedleModelResult) -> dict` adds fields to the results (and results.json).
    """
    import tempfile

    from contextlib import nullcontext

    from needletissue.fem import Fixed, FEModel, SurfaceForce, TaggedMesh, solve
    from needletissue.fem.solvelog import SOLVE_LOG, SolveLog

    cfg = config or NeedleModelConfig()
    g = cfg.geometry
    t0 = time.perf_counter()
    ritz = _ritz_tips(cfg) if cfg.ritz else {}   # first: cheap, and fails fast on bad input
    with tempfile.TemporaryDirectory() as tmp:
        # not into out_dir: an interrupted or failed run leaves no mesh there (write_outputs adds it)
        msh = Path(mesh_path) if mesh_path else Path(tmp) / "needle_model.msh"
        # order 2: midside nodes on the true cylinder; cached per geometry ($NEEDLETISSUE_MESH_CACHE=0: off)
        info = mesh_needle_model(g, msh, order=cfg.order, cache=True)
        mesh = TaggedMesh.read(msh)
        mesh_file = msh.read_bytes() if out_dir is not None else None
    t_mesh = time.perf_counter() - t0
    if mesh_hook is not None:
        mesh = mesh_hook(mesh)
    mesh.check(regions=g.regions(), surfaces=("bone_fixed", "tissue_far", "gripper"))
    mats = {r: MATERIALS[r] for r in mesh.regions}
    model = FEModel(mesh, mats, order=cfg.order, formulation=cfg.formulation,
                    bulk=tissue_bulk(mats, cfg.tissue_bulk_ratio))
    fmax = max(cfg.forces)
    bcs = [Fixed("bone_fixed")]
    if cfg.tissue_far == "fixed":
        bcs.append(Fixed("tissue_far"))
    bcs.append(SurfaceForce("gripper", total=tuple(fmax * np.asarray(cfg.direction)),
                            moment=tuple(cfg.moment(fmax))))
    extra = tuple(items(model) if callable(items) else items)
    # the solve's progress as it happens, in out_dir itself (not the staged folder): it stays when the run
    # fails or is stopped, and says the load reached
    log = None if out_dir is None else SolveLog(
        Path(out_dir) / SOLVE_LOG, scale=fmax, load_key="force_N", forces_N=list(cfg.forces),
        tetrahedra=len(model.mesh.cells), dofs=int(model.ndof), needles=g.needles,
        interfaces=[x.name for i in extra if hasattr(i, "surface") for x in i.surface.interfaces] or "bonded")
    with log or nullcontext():
        # the linear predictor with mixed tissue (at K = 10 MPa the displacement formulation's extrapolated
        # start diverges, docs/bench.md) and in contact runs (small increments that extrapolate well and
        # start with the contact loaded), there from the second converged increment on: the first closes
        # the gaps to the barrier's working distance, not in proportion to the load (docs/contact.md)
        factors = [f / fmax for f in cfg.forces]
        fe_results = solve(model, bcs, load_factors=factors, solver=cfg.solver, items=extra, progress=cfg.progress,
                           predictor=2 if extra else cfg.formulation == "mixed", log=log,
                           initial_step=CONTACT_FIRST_INCREMENT * factors[0] if extra else None)
    t_solve = time.perf_counter() - t0 - t_mesh

    used = model.mesh                         # tetra10 when order=2
    axes = _axis_nodes(used.points, g)
    gripper_nodes = used.surface_nodes("gripper")
    clamp_nodes = np.unique(used.cells[used.regions["clamp"]])
    centre = np.array([0.0, 0.0, g.gripper_centre])
    from needletissue.models.strength import strength_check

    results = []
    for f, r in zip(cfg.forces, fe_results):
        u = r.displacement
        needle_max = max(r.max_displacement_by_region[k] for k in r.max_displacement_by_region
                         if k.startswith("needle"))
        curves = {name: DeflectionCurve(z, u[idx] @ np.asarray(cfg.direction), u[idx])
                  for name, (idx, z) in axes.items()}
        res = NeedleLoadResult(
            force_N=f, max_needle_deformation_mm=float(needle_max),
            clamp_displacement_mm=float(np.linalg.norm(u[gripper_nodes].mean(axis=0))),
            max_deformation_mm={k: float(v) for k, v in r.max_displacement_by_region.items()},
            needle_end_deflection_mm={k: float(c.deflection_mm[-1]) for k, c in curves.items()},
            curves=curves, newton_iterations=r.newton_iterations, steps=r.steps, fe=r)
        res.force_vector_N = (f * np.asarray(cfg.direction)).tolist()
        res.moment_Nmm = cfg.moment(f).tolist()
        res.load_point_mm = cfg.load_point.tolist()
        res.clamp_displacement_vector_mm = u[gripper_nodes].mean(axis=0).tolist()
        rot, centre_u, rms = rigid_fit(used.points[clamp_nodes], u[clamp_nodes], centre)
        res.clamp_rotation_rad = rot.tolist()
        res.clamp_fit = {"centre_mm": centre.tolist(), "centre_displacement_mm": centre_u.tolist(),
                         "rms_residual_mm": rms, "nodes": int(len(clamp_nodes))}
        for name, c in curves.items():
            slope, u0 = root_slope(c.z_mm, c.displacement_mm, half_window=g.diameter)
            res.root_slope[name] = slope.tolist()
            res.root_displacement_mm[name] = u0.tolist()
        res.strength = strength_check(r, {k: MATERIALS[k] for k in mesh.regions})
        if f in ritz:
            res.ritz_tip_deflection_mm = ritz[f]["full"]
            res.ritz_force_per_needle_tip_deflection_mm = ritz[f]["per_needle"]
            res.theory_fe_difference_mm = float(needle_max - ritz[f]["full"])
            res.ritz = (ritz[f]["full_result"], ritz[f]["per_needle_result"])
        results.append(res)
    stats = mesh.stats()
    mesh_summary = {"nodes": int(info.nodes), "tetrahedra": int(info.tetrahedra),
                    "quadratic_nodes": int(len(used.points)), "order": cfg.order, "dofs": int(model.ndof),
                    "tetrahedra_by_region": info.region_tetrahedra,
                    "min_quality_sicn": info.min_quality, "min_quality_mean_ratio": stats.get("min_quality"),
                    "cached": info.cached}
    out = NeedleModelResult(cfg, mesh_summary, time.perf_counter() - t0, results,
                            timing_s={"mesh": t_mesh, "solve": t_solve})
    if report is not None:
        out.extra.update(report(out))
    if out_dir is not None:
        write_outputs(out, Path(out_dir), mesh=mesh_file)
    return out


def _axis_nodes(points: np.ndarray, g: NeedleGeometry) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Mesh nodes on each needle axis (embedded in the mesh), sorted by z."""
    if not g.axis_points:
        raise InputError("axis_points", "the deflection curve needs the needle axes embedded (axis_points=True)")
    tol = 1e-6 * g.diameter
    out = {}
    for i, x in enumerate(g.needle_x):
        idx = np.flatnonzero((np.abs(points[:, 0] - x) < tol) & (np.abs(points[:, 1]) < tol)
                             & (points[:, 2] >= -g.depth - tol) & (points[:, 2] <= g.free_length + tol))
        idx = idx[np.argsort(points[idx, 2])]
        out[f"needle_{i + 1}"] = (idx, points[idx, 2].copy())
    return out


def rigid_fit(x: np.ndarray, u: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Best rigid motion of points x (k, 3) displaced by u (least squares, Kabsch/SVD, finite
    rotations): (rotation vector in rad, displacement of the point `centre` under that motion in mm,
    rms distance of the points from the rigid motion in mm: how rigid the body moved)."""
    from scipy.spatial.transform import Rotation

    y = x + u
    xm, ym = x.mean(axis=0), y.mean(axis=0)
    h = (x - xm).T @ (y - ym)
    a, _, bt = np.linalg.svd(h)
    sign = np.sign(np.linalg.det(bt.T @ a.T))
    rot = bt.T @ np.diag([1.0, 1.0, sign]) @ a.T
    moved = (x - xm) @ rot.T + ym
    rms = float(np.sqrt(np.mean(np.sum((moved - y) ** 2, axis=1))))
    centre_u = rot @ (centre - xm) + ym - centre
    return Rotation.from_matrix(rot).as_rotvec(), centre_u, rms


def root_slope(z: np.ndarray, disp: np.ndarray, half_window: float) -> tuple[np.ndarray, np.ndarray]:
    """Slope (du_x/dz, du_y/dz) and displacement u (3) of a needle axis at the bone surface z = 0,
    from a cubic least-squares fit of the axis nodes within |z| <= half_window (mm); the slope and
    the bending moment are continuous there, so one cubic spans the bone and the tissue side."""
    near = np.abs(z) <= half_window
    if near.sum() < 5:  # too coarse an axis for a cubic: no estimate rather than a wrong one
        return np.full(2, np.nan), np.full(3, np.nan)
    coef = np.polynomial.polynomial.polyfit(z[near], disp[near], 3)   # (4, 3)
    return coef[1, :2].copy(), coef[0].copy()


def ritz_model(g: NeedleGeometry):
    """The Rayleigh-Ritz model with the FE model's needle and layers: needle clamped at the bone
    surface, free length l = geometry.free_length, force at the gripper centre z3, paper Table 1 k."""
    from needletissue.ritz import DEFAULT_LAYERS, RitzModel

    k = {la.name: la.k_N_per_mm2 for la in DEFAULT_LAYERS}
    layers = tuple(type(DEFAULT_LAYERS[0])(n, t, k[n]) for n, t in
                   (("muscle", g.muscle_thickness), ("adipose", g.adipose_thickness)))
    return RitzModel(diameter_mm=g.diameter, free_length_mm=g.free_length, layers=layers,
                     load_point_mm=g.gripper_centre)


def _ritz_tips(cfg: NeedleModelConfig) -> dict[float, dict[str, object]]:
    """Ritz solutions at the full force (the paper's comparison) and at the force per needle."""
    from needletissue.ritz import solve

    model = ritz_model(cfg.geometry)
    out = {}
    for f in cfg.forces:
        full = solve(f, model)
        per = solve(f / cfg.geometry.needles, model)
        out[f] = {"full": float(full.tip_deflection_mm), "per_needle": float(per.tip_deflection_mm),
                  "full_result": full, "per_needle_result": per}
    return out


def write_outputs(result: NeedleModelResult, out_dir: Path, mesh: bytes | None = None) -> None:
    """VTU (+ .vtm and its region pieces) per force, needle.pvd, results.json + config.toml +
    versions.json, figures (deformed model, curves), and the gmsh mesh `mesh` as needle_model.msh.

    All are written into a hidden folder inside out_dir and moved in when complete, so a run stopped
    meanwhile (SIGTERM, Ctrl-C, a failed render) leaves out_dir as it was, not half a set of files. The
    per-force files of an earlier run into the same folder that this run did not write (other forces)
    are removed: listed in no needle.pvd or results.json, they passed for this run's."""
    from needletissue.runinfo import staged_output, write_atomic

    with staged_output(out_dir, replaces=r"needle_[-+0-9.e]+N(\.vtu|\.vtm)?|needle_model\.msh") as stage:
        # needle_<force:g>N.vtu / .vtm / pieces folder of an earlier run's other forces; its mesh
        if mesh is not None:
            write_atomic(stage / "needle_model.msh", mesh)
        _write_outputs(result, stage, with_mesh=mesh is not None)


def _write_outputs(result: NeedleModelResult, out_dir: Path, with_mesh: bool) -> None:
    from needletissue.fem.result import write_series
    from needletissue.runinfo import write_run_files

    files = {"mesh": "needle_model.msh"} if with_mesh else {}  # results.json names no mesh it lacks
    names = {r.force_N: f"needle_{r.force_N:g}N.vtu" for r in result.results}
    for r in result.results:
        files[f"vtu_{r.force_N:g}N"] = names[r.force_N]
        files[f"vtm_{r.force_N:g}N"] = Path(names[r.force_N]).with_suffix(".vtm").name  # the same, one block per region
    from needletissue.models.needle.plot import plot_deflection_curves, scene
    from needletissue.models.render import Isolated, render_vtu

    last = result.results[-1]
    last.fe.write_vtu(out_dir / names[last.force_N], frame=FRAME, force_N=last.force_N)
    # rendered from that VTU in a child process (a VTK crash costs the picture, not the run), beside the
    # other files: its start-up and render overlap them
    with Isolated(render_vtu, out_dir / names[last.force_N], out_dir / "needle_deformed.png", scene(result)) as job:
        for r in result.results[:-1]:
            r.fe.write_vtu(out_dir / names[r.force_N], frame=FRAME, force_N=r.force_N)
        files["series"] = write_series(out_dir / "needle.pvd", [(r.force_N, files[f"vtm_{r.force_N:g}N"])
                                                              for r in result.results]).name
        files["figure_deflection"] = plot_deflection_curves(result, out_dir / "needle_deflection.png").name
        try:
            files["figure_deformed"] = Path(job.result()).name
        except Exception as exc:  # the numbers stand without the picture
            import warnings

            warnings.warn(f"needle_deformed.png not written: {type(exc).__name__}: {exc}", stacklevel=2)
    result.files = files
    record = {"needle_model": _config_dict(result.config)}
    contact = result.extra.get("contact")
    if contact:  # the frictional interfaces, in the form `fe needle --config` reads back
        s = next(iter(contact["settings"].values()), {})
        record["contact"] = {"friction": contact["interfaces"], "dhat_mm": s.get("dhat_mm"),
                             "eps_v_mm": s.get("eps_v_mm")}
    write_run_files(out_dir, record, result.to_dict())


def _config_dict(cfg: NeedleModelConfig) -> dict:
    from dataclasses import asdict

    return asdict(cfg)


def with_geometry(cfg: NeedleModelConfig, **changes) -> NeedleModelConfig:
    """A copy of cfg with geometry fields changed (validated)."""
    return replace(cfg, geometry=replace(cfg.geometry, **changes))
