"""Parametric needle-tissue-bone geometry and conforming multi-region tetrahedral mesh (gmsh, OCC).

Coordinates in mm: z is the needle axis direction, z = 0 the bone surface (bone below, tissue above);
the needles stand at x = -s/2 and x = +s/2 (one needle: x = 0), y = 0. Layers from the bone up:
muscle 0..t_m, adipose t_m..t_m+t_a (skin surface on top). Each needle runs from z = -h (tip in bone)
to z = l (free length from the bone surface); a steel clamp bar holds the needle ends over its grip
length L_g, and the robot's force acts uniformly on the clamp's two gripper faces (y = +-w/2).

Config -> `NeedleGeometry` (validated before gmsh starts) -> `mesh_needle_model` -> `.msh` file with
named physical volumes (REGIONS) and surfaces (SURFACES) that `needletissue.fem.TaggedMesh.read` reads.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from needletissue.errors import InputError, NeedleTissueError, check_number
from needletissue.cache import cache_key, mesh_cache_dir, read_entry, write_entry

REGIONS = ("cortical_bone", "cancellous_bone", "muscle", "adipose", "needle_1", "needle_2", "clamp")

# Physical surfaces: name -> (region A, region B or None for an outer face, extra rule).
SURFACES = (
    "bone_fixed",      # bone bottom and lateral far faces (fixed)
    "tissue_far",      # muscle and adipose lateral far faces
    "skin",            # adipose top surface (traction-free)
    "gripper",         # clamp faces y = +-w/2 where the reduction force acts
    "needle_muscle",   # interfaces that the contact model turns into frictional pairs
    "needle_bone",
    "muscle_bone",
    "needle_adipose",
    "muscle_adipose",
    "needle_clamp",
)


# Above the paper-scale run (benchmarks/paper_scale_needle.py: 1.33 M tetrahedra, estimated 2.1 M) and
# far below what runs for ever (--mesh-size 0.02: ~3e10): a finer mesh needs max_tetrahedra raised.
DEFAULT_MAX_TETRAHEDRA = 3_000_000


class MeshError(NeedleTissueError):
    """gmsh could not build a valid mesh (failed meshing, inverted or degenerate elements)."""


@dataclass(frozen=True)
class NeedleGeometry:
    """Needle-tissue-bone model dimensions and mesh sizes. All lengths in mm.

    Defaults (docs/needle_model.md gives the sources): layer thicknesses from the paper (muscle
    22 mm, adipose 10 mm); cortical thickness 1.5 mm, within the 0.4-4 mm measured over the human
    pelvis (Anderson et al. 2005, J Biomech Eng 127:364); 5 mm Schanz pins (usual 5-6 mm in pelvic
    reduction); the rest are documented choices the paper leaves open.
    """

    needles: int = 2                 # 1 or 2 needles
    diameter: float = 5.0            # needle diameter d, mm
    spacing: float = 40.0            # needle axis spacing s, mm (two needles)
    depth: float = 30.0              # insertion depth h into bone, mm
    free_length: float = 100.0       # needle length l from the bone surface to its end, mm
    muscle_thickness: float = 22.0   # mm (paper)
    adipose_thickness: float = 10.0  # mm (paper)
    bone_thickness: float = 40.0     # bone plate thickness, mm
    cortical_thickness: float = 1.5  # cortical shell thickness t_c, mm
    half_width: float = 40.0         # lateral extent beyond the outer needle axis, each side, mm
    grip_length: float = 20.0        # clamp height along the needles (gripper length), mm
    clamp_width: float = 20.0        # clamp bar size in y, mm
    clamp_overhang: float = 10.0     # clamp bar beyond the outer needle axis in x, mm
    needle_mesh_size: float = 2.0    # element size on the needles, mm
    mesh_size: float = 4.0           # element size in tissue, bone and clamp near the needles, mm
    far_mesh_size: float = 20.0      # element size at the far boundary (graded from mesh_size), mm
    axis_points: bool = True         # embed each needle axis in the mesh (exact deflection curve)
    max_tetrahedra: int = DEFAULT_MAX_TETRAHEDRA  # refuse before meshing when the estimate is above

    def __post_init__(self):
        if self.needles not in (1, 2) or isinstance(self.needles, bool):
            raise InputError("needles", f"must be 1 or 2, got {self.needles!r}")
        for name in ("diameter", "depth", "free_length", "muscle_thickness", "adipose_thickness",
                     "bone_thickness", "cortical_thickness", "half_width", "grip_length", "clamp_width",
                     "clamp_overhang", "needle_mesh_size", "mesh_size", "far_mesh_size"):
            check_number(name, getattr(self, name), gt=0)
        d = self.diameter
        if self.needles == 2:
            check_number("spacing", self.spacing, gt=d)
        if self.depth >= self.bone_thickness:
            raise InputError("depth", f"needle depth in bone must be < bone_thickness "
                                      f"({self.bone_thickness} mm), got {self.depth}")
        if 2 * self.cortical_thickness >= self.bone_thickness:
            raise InputError("cortical_thickness", f"must be < bone_thickness/2 "
                                                   f"({self.bone_thickness / 2} mm), got {self.cortical_thickness}")
        clamp_bottom = self.free_length - self.grip_length
        if clamp_bottom <= self.tissue_thickness:
            raise InputError("free_length", f"the clamp (grip_length {self.grip_length} mm) must sit above the "
                                            f"skin at {self.tissue_thickness} mm: free_length must be > "
                                            f"{self.tissue_thickness + self.grip_length}, got {self.free_length}")
        if self.clamp_width <= d or self.clamp_overhang <= d / 2:
            field_ = "clamp_width" if self.clamp_width <= d else "clamp_overhang"
            raise InputError(field_, f"the clamp must enclose the needle (diameter {d} mm)")
        if self.half_width <= 2 * d:
            raise InputError("half_width", f"must be > 2*diameter ({2 * d} mm), got {self.half_width}")
        if self.needle_mesh_size > d:
            raise InputError("needle_mesh_size", f"must be <= diameter ({d} mm), got {self.needle_mesh_size}")
        if self.far_mesh_size < self.mesh_size:
            raise InputError("far_mesh_size", f"must be >= mesh_size ({self.mesh_size}), got {self.far_mesh_size}")
        if isinstance(self.max_tetrahedra, bool) or not isinstance(self.max_tetrahedra, int) or self.max_tetrahedra < 1:
            raise InputError("max_tetrahedra", f"must be a positive integer, got {self.max_tetrahedra!r}")
        needle_part, rest = self._tetrahedra_parts()
        n = int(round(needle_part + rest))
        if n > self.max_tetrahedra:
            name = "needle_mesh_size" if needle_part > rest else "mesh_size"
            raise InputError(name, f"about {n:,} tetrahedra estimated for these element sizes (needle "
                                   f"{self.needle_mesh_size:g}, near {self.mesh_size:g}, far {self.far_mesh_size:g} "
                                   f"mm), above the limit of {self.max_tetrahedra:,}: coarsen the mesh, or raise "
                                   "the limit (max_tetrahedra, --max-tetrahedra)")

    # Derived dimensions -------------------------------------------------------------------------
    @property
    def tissue_thickness(self) -> float:
        return self.muscle_thickness + self.adipose_thickness

    @property
    def needle_x(self) -> tuple[float, ...]:
        """x of each needle axis (y = 0)."""
        return (0.0,) if self.needles == 1 else (-self.spacing / 2, self.spacing / 2)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """Model box in the plane: (x0, x1, y0, y1)."""
        xm = max(abs(x) for x in self.needle_x) + self.half_width
        return (-xm, xm, -self.half_width, self.half_width)

    @property
    def clamp_box(self) -> tuple[float, float, float, float, float, float]:
        xm = max(abs(x) for x in self.needle_x) + self.clamp_overhang
        return (-xm, xm, -self.clamp_width / 2, self.clamp_width / 2,
                self.free_length - self.grip_length, self.free_length)

    @property
    def gripper_centre(self) -> float:
        """z3: height of the resultant of the uniform gripper load, mm."""
        return self.free_length - self.grip_length / 2

    @property
    def gripper_area(self) -> float:
        x0, x1, _, _, z0, z1 = self.clamp_box
        return 2 * (x1 - x0) * (z1 - z0)

    def analytic_volumes(self) -> dict[str, float]:
        """Exact region volumes (mm^3), needles as true cylinders."""
        x0, x1, y0, y1 = self.extent
        A = (x1 - x0) * (y1 - y0)
        tc, T, n = self.cortical_thickness, self.bone_thickness, self.needles
        r2 = math.pi * (self.diameter / 2) ** 2
        core = (x1 - x0 - 2 * tc) * (y1 - y0 - 2 * tc) * (T - 2 * tc)
        h_in_core = max(0.0, self.depth - tc)
        cx0, cx1, cy0, cy1, cz0, cz1 = self.clamp_box
        vols = {
            "cortical_bone": A * T - core - n * r2 * (self.depth - h_in_core),
            "cancellous_bone": core - n * r2 * h_in_core,
            "muscle": A * self.muscle_thickness - n * r2 * self.muscle_thickness,
            "adipose": A * self.adipose_thickness - n * r2 * self.adipose_thickness,
            "clamp": (cx1 - cx0) * (cy1 - cy0) * (cz1 - cz0) - n * r2 * self.grip_length,
        }
        for i in range(n):
            vols[f"needle_{i + 1}"] = r2 * (self.depth + self.free_length)
        return vols

    def estimate_tetrahedra(self) -> int:
        return int(round(sum(self._tetrahedra_parts())))

    def _tetrahedra_parts(self) -> tuple[float, float]:
        """(in the needles, elsewhere) of `estimate_tetrahedra`: tetrahedra the mesh will have, estimated from the size field before meshing (milliseconds).

        The mesh's size field (`_size_fields`): needle size inside the needles; mesh_size within one
        diameter of them, graded linearly to far_mesh_size at half_width. A regular tetrahedron of edge
        h has volume h^3 / (6 sqrt 2): the estimate is the integral of 6 sqrt(2) / h(x)^3 over the solid,
        needles exactly, the rest on a 1 mm grid (tests/geometry compares it with gmsh's counts)."""
        c = 6.0 * math.sqrt(2.0)
        vols = self.analytic_volumes()
        n_needle = sum(v for k, v in vols.items() if k.startswith("needle")) * c / self.needle_mesh_size ** 3
        x0, x1, y0, y1 = self.extent
        step = min(1.0, self.diameter / 5)
        R, D, hw = self.diameter / 2, self.diameter, self.half_width
        hm, hf = self.mesh_size, self.far_mesh_size
        cx0, cx1, cy0, cy1, cz0, cz1 = self.clamp_box
        total = 0.0
        for za, zb in ((-self.bone_thickness, self.tissue_thickness), (cz0, cz1)):  # bone + tissue, clamp
            xa, xb, ya, yb = (x0, x1, y0, y1) if za < 0 else (cx0, cx1, cy0, cy1)
            nx, ny, nz = (min(200, max(2, int(math.ceil((b - a) / step)))) for a, b in ((xa, xb), (ya, yb), (za, zb)))
            x = xa + (np.arange(nx) + 0.5) * (xb - xa) / nx
            y = ya + (np.arange(ny) + 0.5) * (yb - ya) / ny
            z = za + (np.arange(nz) + 0.5) * (zb - za) / nz
            X, Y = np.meshgrid(x, y, indexing="ij")
            r = np.min([np.hypot(X - xn, Y) for xn in self.needle_x], axis=0)   # to the nearest axis
            radial = np.maximum(r - R, 0.0)
            for zz in z:
                below = max(0.0, -self.depth - zz)  # under the needle tip: distance to the tip too
                d = np.hypot(radial, below)
                h = np.clip(hm + (hf - hm) * (d - D) / (hw - D), hm, hf) if hw > D else np.full_like(d, hm)
                solid = (r >= R) | (below > 0)
                total += float(np.sum(c / h[solid] ** 3)) * (xb - xa) * (yb - ya) * (zb - za) / (nx * ny * nz)
        return n_needle, total

    def regions(self) -> tuple[str, ...]:
        return tuple(r for r in REGIONS if r != "needle_2" or self.needles == 2)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class NeedleMeshInfo:
    """What `mesh_needle_model` built: the .msh path and facts the solver and the tests need."""

    path: Path
    geometry: NeedleGeometry
    nodes: int
    tetrahedra: int
    region_tetrahedra: dict[str, int] = field(default_factory=dict)
    min_quality: float = float("nan")   # gmsh minSICN (> 0: no inverted element)
    mesh_time_s: float = 0.0
    cached: bool = False                 # read from the mesh cache (mesh_cache_dir), gmsh not run


def _cache_key(geometry: NeedleGeometry, order: int) -> str:
    """Every input of the mesh: the geometry, the order (and gmsh's version), this module and the gmsh set-up."""
    from importlib.metadata import version

    return cache_key({"geometry": geometry.to_dict(), "order": order, "gmsh": version("gmsh")},
                     tuple(Path(__file__).parent / f for f in ("needle.py", "gmsh_init.py")))


def mesh_needle_model(geometry: NeedleGeometry, path: str | Path, *, order: int = 1,
                      verbose: bool = False, isolate: bool = True, cache: bool = False) -> NeedleMeshInfo:
    """Build the OCC geometry, mesh it conformingly, check it, write `path` (.msh, named groups).

    order=1: linear tets (the FE core converts to quadratic with the VTK node order it expects).
    Raises MeshError when gmsh fails, crashes or produces inverted/degenerate elements. With isolate
    (the default) gmsh runs in a child process (~1 s more), so a native crash is a MeshError too.
    With cache, a mesh made before from the same inputs (_cache_key) is copied from mesh_cache_dir()
    instead (the default `fe needle` mesh: ~5 s of gmsh saved); a new one is stored there.
    """
    folder = mesh_cache_dir() if cache else None
    if folder is not None:
        key = _cache_key(geometry, order)
        info = _from_cache(folder, key, geometry, path)
        if info is not None:
            return info
    info = _mesh(geometry, path, order=order, verbose=verbose, isolate=isolate)
    if folder is not None:
        _to_cache(folder, key, info)
    return info


def _from_cache(folder: Path, key: str, geometry: NeedleGeometry, path: str | Path) -> NeedleMeshInfo | None:
    entry = read_entry(folder, key, ".msh")
    if entry is None:
        return None
    data, facts = entry
    try:
        info = NeedleMeshInfo(path=Path(path), geometry=geometry, nodes=facts["nodes"], tetrahedra=facts["tetrahedra"],
                              region_tetrahedra=facts["region_tetrahedra"], min_quality=facts["min_quality"],
                              mesh_time_s=0.0, cached=True)
    except KeyError:
        return None
    info.path.parent.mkdir(parents=True, exist_ok=True)
    info.path.write_bytes(data)
    return info


def _to_cache(folder: Path, key: str, info: NeedleMeshInfo) -> None:
    facts = {"nodes": info.nodes, "tetrahedra": info.tetrahedra, "region_tetrahedra": info.region_tetrahedra,
             "min_quality": info.min_quality, "geometry": info.geometry.to_dict()}
    write_entry(folder, key, ".msh", Path(info.path).read_bytes(), facts)


def _mesh(geometry: NeedleGeometry, path: str | Path, *, order: int, verbose: bool, isolate: bool) -> NeedleMeshInfo:
    if isolate:
        from needletissue.geometry.child import ChildCrash, call_in_child

        try:
            reply = call_in_child("needletissue.geometry.needle:_mesh_for_child",
                                  {"geometry": geometry.to_dict(), "path": str(path), "order": order,
                                   "verbose": verbose}, what="gmsh (needle model)")
        except ChildCrash as exc:
            raise MeshError(f"{exc} (mesh_size {geometry.mesh_size:g}, needle_mesh_size "
                            f"{geometry.needle_mesh_size:g} mm)") from None
        return NeedleMeshInfo(path=Path(path), geometry=geometry, nodes=reply["nodes"],
                              tetrahedra=reply["tetrahedra"], region_tetrahedra=reply["region_tetrahedra"],
                              min_quality=reply["min_quality"], mesh_time_s=reply["mesh_time_s"])
    return _mesh_here(geometry, path, order=order, verbose=verbose)


def _mesh_for_child(geometry: dict, path: str, order: int, verbose: bool) -> dict:
    info = _mesh_here(NeedleGeometry(**geometry), path, order=order, verbose=verbose)
    return {"nodes": info.nodes, "tetrahedra": info.tetrahedra, "region_tetrahedra": info.region_tetrahedra,
            "min_quality": info.min_quality, "mesh_time_s": info.mesh_time_s}


def _mesh_here(geometry: NeedleGeometry, path: str | Path, *, order: int, verbose: bool) -> NeedleMeshInfo:
    import time

    import gmsh

    g = geometry
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    own = not gmsh.isInitialized()
    if own:
        from needletissue.geometry.gmsh_init import initialize  # keeps the SIGTERM handler

        initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 1 if verbose else 0)
        gmsh.clear()
        gmsh.option.setNumber("General.NumThreads", 1)   # reproducible node counts
        gmsh.option.setNumber("Mesh.MaxNumThreads3D", 1)
        gmsh.option.setNumber("Mesh.RandomFactor", 1e-9)
        gmsh.model.add("needle_tissue_bone")
        _build(g)
        _size_fields(g)
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:  # gmsh raises bare Exception with its log message
            raise MeshError(f"gmsh failed to mesh the needle model: {exc} "
                            f"(try a different mesh_size/needle_mesh_size)") from exc
        if order != 1:
            # curved (CAD-conforming) midside nodes; untangle the few that curving inverts
            gmsh.model.mesh.setOrder(order)
            gmsh.model.mesh.optimize("HighOrderElastic")
            gmsh.model.mesh.optimize("HighOrder")
        info = _check_and_count(g, path)
        gmsh.write(str(path))
        info.mesh_time_s = time.perf_counter() - t0
        return info
    finally:
        if own:
            gmsh.finalize()


# --- gmsh internals --------------------------------------------------------------------------------

def _build(g: NeedleGeometry) -> None:
    import gmsh

    occ = gmsh.model.occ
    x0, x1, y0, y1 = g.extent
    T, tc, tm, ta = g.bone_thickness, g.cortical_thickness, g.muscle_thickness, g.adipose_thickness
    r = g.diameter / 2
    bone = occ.addBox(x0, y0, -T, x1 - x0, y1 - y0, T)
    core = occ.addBox(x0 + tc, y0 + tc, -T + tc, x1 - x0 - 2 * tc, y1 - y0 - 2 * tc, T - 2 * tc)
    muscle = occ.addBox(x0, y0, 0, x1 - x0, y1 - y0, tm)
    adipose = occ.addBox(x0, y0, tm, x1 - x0, y1 - y0, ta)
    cx0, cx1, cy0, cy1, cz0, cz1 = g.clamp_box
    clamp = occ.addBox(cx0, cy0, cz0, cx1 - cx0, cy1 - cy0, cz1 - cz0)
    needles = [occ.addCylinder(x, 0, -g.depth, 0, 0, g.depth + g.free_length, r) for x in g.needle_x]
    axes = []
    if g.axis_points:
        for x in g.needle_x:
            p0 = occ.addPoint(x, 0, -g.depth)
            p1 = occ.addPoint(x, 0, g.free_length)
            axes.append(occ.addLine(p0, p1))
    inputs = [(3, t) for t in (bone, core, muscle, adipose, clamp, *needles)]
    # Priority when pieces overlap: needle > clamp > cancellous > cortical > muscle > adipose.
    owner_of_input = ["cortical_bone", "cancellous_bone", "muscle", "adipose", "clamp",
                      *[f"needle_{i + 1}" for i in range(len(needles))]]
    priority = [f"needle_{i + 1}" for i in range(len(needles))] + [
        "clamp", "cancellous_bone", "cortical_bone", "muscle", "adipose"]
    _, out_map = occ.fragment(inputs, [(1, a) for a in axes])
    occ.synchronize()
    owners: dict[int, set[str]] = {}
    for name, pieces in zip(owner_of_input, out_map[: len(inputs)]):
        for dim, tag in pieces:
            if dim == 3:
                owners.setdefault(tag, set()).add(name)
    region_vols: dict[str, list[int]] = {r_: [] for r_ in g.regions()}
    for tag, names in owners.items():
        region_vols[next(p for p in priority if p in names)].append(tag)
    for name, tags in region_vols.items():
        if not tags:
            raise MeshError(f"geometry has no volume for region {name!r}")
        gmsh.model.addPhysicalGroup(3, sorted(tags), name=name)
    _surface_groups(g, region_vols)


def _surface_groups(g: NeedleGeometry, region_vols: dict[str, list[int]]) -> None:
    import gmsh

    vol_region = {t: name for name, tags in region_vols.items() for t in tags}
    faces: dict[int, list[str]] = {}
    for vtag, name in vol_region.items():
        _, down = gmsh.model.getAdjacencies(3, vtag)
        for s in down:
            faces.setdefault(int(s), []).append(name)

    def kind(name):
        if name.startswith("needle"):
            return "needle"
        if name.endswith("bone"):
            return "bone"
        return name

    x0, x1, y0, y1 = g.extent
    eps = 1e-6 * max(x1 - x0, 1.0)
    groups: dict[str, list[int]] = {s: [] for s in SURFACES}
    for s, names in faces.items():
        kinds = sorted({kind(n) for n in names})
        bx = gmsh.model.getBoundingBox(2, s)
        if len(names) == 1:
            k = kinds[0]
            on_far = (abs(bx[0] - x0) < eps and abs(bx[3] - x0) < eps) or (
                abs(bx[0] - x1) < eps and abs(bx[3] - x1) < eps) or (
                abs(bx[1] - y0) < eps and abs(bx[4] - y0) < eps) or (
                abs(bx[1] - y1) < eps and abs(bx[4] - y1) < eps)
            if k == "bone" and (on_far or abs(bx[5] + g.bone_thickness) < eps):
                groups["bone_fixed"].append(s)
            elif k in ("muscle", "adipose") and on_far:
                groups["tissue_far"].append(s)
            elif k == "adipose" and abs(bx[2] - g.tissue_thickness) < eps:
                groups["skin"].append(s)
            elif k == "clamp" and abs(bx[1] - bx[4]) < eps and abs(abs(bx[1]) - g.clamp_width / 2) < eps:
                groups["gripper"].append(s)
        elif len(kinds) == 2:
            key = "_".join(kinds) if kinds[0] != "adipose" else f"{kinds[1]}_{kinds[0]}"
            key = {"bone_muscle": "muscle_bone", "bone_needle": "needle_bone", "clamp_needle": "needle_clamp",
                   "adipose_muscle": "muscle_adipose", "needle_adipose": "needle_adipose",
                   "muscle_needle": "needle_muscle"}.get(key, key)
            if key in groups:
                groups[key].append(s)
    for name, tags in groups.items():
        if not tags:
            raise MeshError(f"geometry has no surface for group {name!r}")
        gmsh.model.addPhysicalGroup(2, sorted(tags), name=name)


def _size_fields(g: NeedleGeometry) -> None:
    """Needle size on and near the needles, mesh_size nearby, graded to far_mesh_size far away."""
    import gmsh

    fld = gmsh.model.mesh.field
    needle_surfs = []
    for name in g.regions():
        if name.startswith("needle"):
            tag = next(t for d_, t in gmsh.model.getPhysicalGroups(3) if gmsh.model.getPhysicalName(3, t) == name)
            for v in gmsh.model.getEntitiesForPhysicalGroup(3, tag):
                _, down = gmsh.model.getAdjacencies(3, int(v))
                needle_surfs.extend(int(s) for s in down)
    dist = fld.add("Distance")
    fld.setNumbers(dist, "SurfacesList", sorted(set(needle_surfs)))
    fld.setNumber(dist, "Sampling", 40)
    near = fld.add("Threshold")   # needle size at the needle, mesh_size one diameter away
    fld.setNumber(near, "InField", dist)
    fld.setNumber(near, "SizeMin", g.needle_mesh_size)
    fld.setNumber(near, "SizeMax", g.mesh_size)
    fld.setNumber(near, "DistMin", 0.0)
    fld.setNumber(near, "DistMax", g.diameter)
    far = fld.add("Threshold")    # mesh_size within 1 diameter, graded to the far size at the boundary
    fld.setNumber(far, "InField", dist)
    fld.setNumber(far, "SizeMin", g.mesh_size)
    fld.setNumber(far, "SizeMax", g.far_mesh_size)
    fld.setNumber(far, "DistMin", g.diameter)
    fld.setNumber(far, "DistMax", g.half_width)
    fields = [near, far]
    tags_needle = [t for d_, t in gmsh.model.getPhysicalGroups(3)
                   if gmsh.model.getPhysicalName(3, t).startswith("needle")]
    needle_vols = [int(v) for t in tags_needle for v in gmsh.model.getEntitiesForPhysicalGroup(3, t)]
    inside = fld.add("Constant")  # the whole needle volume at needle size
    fld.setNumber(inside, "VIn", g.needle_mesh_size)
    fld.setNumber(inside, "VOut", 1e22)
    fld.setNumbers(inside, "VolumesList", needle_vols)
    fields.append(inside)
    combo = fld.add("Max")
    fld.setNumbers(combo, "FieldsList", [near, far])
    final = fld.add("Min")
    fld.setNumbers(final, "FieldsList", [combo, inside])
    fld.setAsBackgroundMesh(final)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    # The cortical shell is thinner than the tissue size: no stricter size, but keep elements sane.
    gmsh.option.setNumber("Mesh.MeshSizeMax", g.far_mesh_size)


def _check_and_count(g: NeedleGeometry, path: Path) -> NeedleMeshInfo:
    import gmsh

    node_tags, _, _ = gmsh.model.mesh.getNodes()
    region_counts = {}
    all_tets = []
    for dim, tag in gmsh.model.getPhysicalGroups(3):
        name = gmsh.model.getPhysicalName(3, tag)
        n = 0
        for v in gmsh.model.getEntitiesForPhysicalGroup(3, tag):
            types, etags, _ = gmsh.model.mesh.getElements(3, int(v))
            for t, e in zip(types, etags):
                n += len(e)
                all_tets.append(e)
        if n == 0:
            raise MeshError(f"region {name!r} has no elements")
        region_counts[name] = n
    tets = np.concatenate(all_tets) if all_tets else np.array([], dtype=np.int64)
    if tets.size == 0:
        raise MeshError("the mesh has no tetrahedra")
    q = gmsh.model.mesh.getElementQualities(tets, "minSICN")
    qmin = float(q.min())
    if qmin <= 0:
        raise MeshError(f"{int((q <= 0).sum())} inverted or degenerate tetrahedra (min SICN {qmin:.3g}); "
                        f"change mesh_size/needle_mesh_size")
    return NeedleMeshInfo(path=path, geometry=g, nodes=int(len(node_tags)), tetrahedra=int(tets.size),
                          region_tetrahedra=region_counts, min_quality=qmin)
