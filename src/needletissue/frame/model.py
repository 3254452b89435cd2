"""Needle-frame model parameters: n Schanz pins from their tips in the bone to a clamp, a wrench.

Units: mm, N, MPa. Coordinates as in `fe needle` (needletissue.geometry.needle): z along the needles,
z = 0 the bone surface (bone below, tissue above), needle i at (x_i, y_i); each needle runs from its
tip z = -depth through the cortex (-cortex..0), the tissue layers (0..T), free above the skin and is
built into the clamp over its grip (clamp_length) below its end z = free_length.

Defaults equal `fe needle`'s (NeedleGeometry and the materials registry; tests/frame/test_defaults.py
checks that they still do). They are copied, not imported: frame sits beside ritz, below models and
geometry, and must not pull in gmsh or FElupe (the control loop imports it).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from needletissue.errors import InputError, check_number
from needletissue.ritz.model import DEFAULT_LAYERS, NEEDLE_E_MPA, Layer

# `fe needle` geometry defaults (NeedleGeometry): mm
DEFAULT_NEEDLES = 2
DEFAULT_DIAMETER_MM = 5.0
DEFAULT_SPACING_MM = 40.0
DEFAULT_DEPTH_MM = 30.0
DEFAULT_FREE_LENGTH_MM = 100.0
DEFAULT_CORTEX_MM = 1.5
DEFAULT_CLAMP_LENGTH_MM = 20.0   # NeedleGeometry.grip_length
DEFAULT_CLAMP_WIDTH_MM = 20.0    # NeedleGeometry.clamp_width (y)
DEFAULT_CLAMP_OVERHANG_MM = 10.0  # NeedleGeometry.clamp_overhang (x beyond the outer needle)
# Radius b where the bone's displacement field has died out (the foundation formulas' outer radius): the
# distance to where the bone is held. 60 mm = 1.5 x the 40 mm lateral extent of fe needle's bone plate
# beyond the pin (its far faces are fixed), and equal to Randolph & Wroth's 2.5 h (1 - nu) at the default
# depth h = 30 mm. On the FE sweep neither b is clearly better (docs/frame.md: leave one configuration out,
# medians 1.4/1.9 % fixed vs 2.0/1.7 % depth-proportional, max 7.6 % vs 11.3 %).
DEFAULT_BONE_RADIUS_MM = 60.0
DEFAULT_BONE_THICKNESS_MM = 40.0  # NeedleGeometry.bone_thickness: the bone's far side (held), below the surface
BONE_LAWS = ("plate", "winkler")
CANCELLOUS_SUBSEGMENTS = 4   # the confined cancellous modulus varies with depth: piecewise constant over these
# materials registry (paper Table 2), MPa
NEEDLE_NU = 0.30
CORTICAL_E_MPA, CORTICAL_NU = 17000.0, 0.30
CANCELLOUS_E_MPA, CANCELLOUS_NU = 150.0, 0.20
# The clamp bar of `fe needle` (materials registry "clamp": structural steel, paper Table 2), MPa. Its section is
# the bar's: clamp_width_mm (y) x clamp_length_mm (z, the grip length), NeedleGeometry.clamp_box.
CLAMP_E_MPA, CLAMP_NU = 200000.0, 0.30
CLAMPS = ("rigid", "elastic")

# Strengths (validity checks, not model inputs), MPa.
# Ti-6Al-4V annealed: tensile yield 880 MPa (ASM Aerospace Specification Metals, Ti-6Al-4V Grade 5
# data sheet; ASTM F136 ELI implant grade requires >= 795 MPa).
NEEDLE_YIELD_MPA = 880.0
# Cortical bone, transverse compressive strength 131 MPa (Reilly & Burstein 1975, J Biomech 8:393).
CORTICAL_STRENGTH_MPA = 131.0
# Cancellous bone compressive strength: of order 1-10 MPa (Keaveny et al. 2001, Annu Rev Biomed Eng 3:307);
# 5 MPa taken as a representative value for pelvic cancellous bone.
CANCELLOUS_STRENGTH_MPA = 5.0
# Linear hardening of Ti-6Al-4V between yield (880 MPa at 0.8 % strain) and ultimate strength (950 MPa at
# the 14 % elongation at break, same data sheet): H = (950 - 880) / (0.14 - 0.008) ~ 530 MPa.
NEEDLE_HARDENING_MPA = 530.0

# Shear correction factor of a solid circular section (Timoshenko; Cowper 1966: 6(1+nu)/(7+6nu)).
ROOTS = ("bone", "rigid")
# Factors fitted to the FE needle model (benchmarks/frame_vs_fe.py --calibrate on the complete FE sweep of
# benchmarks/frame_sweep, 124 points of 31 configurations, residuals in units of max(0.432 mm, 2.4 %);
# docs/frame.md gives the errors, in sample and leave-one-configuration-out). Not the defaults: the defaults
# stay physical. With the plate bone law the bone needs no factor (fitted beside the tissue factor,
# cortex_factor 0.967 (95 % 0.950-0.984) and axial_factor 0.86 (0.74-1.00), and leaving one configuration out
# the one-factor fit already meets the goal): only the tissue springs' factor is fitted, 0.284 (95 %
# 0.233-0.346): the FE's continuum tissue resists the pins' large excursions far less than the paper's
# cubic spring law.
FE_CALIBRATION = {"foundation_factor": 1.0, "axial_factor": 1.0, "tissue_factor": 0.2837, "cortex_factor": 1.0,
                  "confinement_factor": 1.0}
MAX_FACTOR = 10.0


def shear_factor(nu: float) -> float:
    return 6.0 * (1.0 + nu) / (7.0 + 6.0 * nu)


def lateral_foundation_k(E: float, nu: float, radius: float, outer_radius: float) -> float:
    """Lateral stiffness per unit length (N/mm^2) of a rigid disc of radius a translating in a plane-strain
    elastic annulus fixed at r = b: K = 8 pi G (1 - nu) / ((3 - 4 nu) ln(b/a) - (b^2 - a^2)/(b^2 + a^2))
    (the form of Baguelin, Frank & Said 1977, Geotechnique 27:405, for laterally loaded piles)."""
    G = E / (2.0 * (1.0 + nu))
    beta = outer_radius / radius
    return 8.0 * math.pi * G * (1.0 - nu) / ((3.0 - 4.0 * nu) * math.log(beta) - (beta**2 - 1) / (beta**2 + 1))


def axial_foundation_k(E: float, nu: float, radius: float, outer_radius: float) -> float:
    """Axial (shaft) stiffness per unit length (N/mm^2): concentric shear cylinders, tau = G w / (r ln(b/a))
    (Randolph & Wroth 1978, J Geotech Eng Div 104:1465): K = 2 pi G / ln(b/a)."""
    G = E / (2.0 * (1.0 + nu))
    return 2.0 * math.pi * G / math.log(outer_radius / radius)


def plate_rigidity(E: float, nu: float, t: float) -> float:
    """Bending stiffness D = E t^3 / (12 (1 - nu^2)) of a thin plate (N mm)."""
    return E * t**3 / (12.0 * (1.0 - nu**2))


def plate_rocking_k(D: float, radius: float, outer_radius: float) -> float:
    """Moment per unit tilt (N mm/rad) of a rigid circular inclusion of radius a bonded in a Kirchhoff plate
    clamped at r = b: K = 4 pi D / (ln(b/a) - (b^2 - a^2)/(b^2 + a^2)). Derived from w = f(r) cos(theta),
    f = A r + B r^3 + C/r + E r ln r with f = theta a, f' = theta at r = a, f = f' = 0 at r = b; K = 2U/theta^2
    (tests/frame checks it against the energy integral). Independent of nu: with both edges clamped the
    Gaussian-curvature term integrates to zero."""
    beta = outer_radius / radius
    return 4.0 * math.pi * D / (math.log(beta) - (beta**2 - 1) / (beta**2 + 1))


def plate_axial_k(D: float, radius: float, outer_radius: float) -> float:
    """Force per unit axial displacement (N/mm) of a rigid circular inclusion (radius a) pushed through a
    Kirchhoff plate clamped at r = b (annular plate, both edges clamped; Roark, Table 11.2, case 2L):
    K = 16 pi D / (a^2 [(beta^2 - 1) - 4 beta^2 ln(beta)^2 / (beta^2 - 1)]), beta = b/a."""
    beta = outer_radius / radius
    L = math.log(beta)
    return 16.0 * math.pi * D / (radius**2 * ((beta**2 - 1) - 4 * beta**2 * L**2 / (beta**2 - 1)))


# Equivalent clamped radius of a plate on a Winkler foundation (characteristic length l = (D/k_s)^(1/4)): the
# exact rigid-inclusion solutions (Kelvin functions, w = Re/Im K_n(r e^(i pi/4) / l), n = 1 tilt, 0 push)
# equal the clamped-annulus closed forms with b / l = c0 + c1 (a/l) + c2 (a/l)^2, least squares over
# a/l = 0.1..1 (the sweep spans 0.2..0.7): the stiffness within 0.3 % (tilt) and 1 % (push) of the exact one
# (tests/frame/test_bone_law.py computes the exact solutions and checks it).
PLATE_ROCKING_RADIUS, PLATE_AXIAL_RADIUS = (3.04, 0.12, 0.33), (2.47, 0.47, 0.255)


def plate_equivalent_radius(coeffs, radius: float, length: float) -> float:
    """Clamped radius b (mm) equivalent to a plate on a foundation of characteristic length l, for an
    inclusion of radius a: b = l (c0 + c1 a/l + c2 (a/l)^2)."""
    x = radius / length
    return length * (coeffs[0] + coeffs[1] * x + coeffs[2] * x * x)


def subgrade_modulus(E: float, nu: float, thickness: float) -> float:
    """Winkler modulus (N/mm^3) of an elastic layer of the given thickness held at its base, loaded on top: the
    oedometric column, k_s = E (1 - nu) / ((1 + nu) (1 - 2 nu)) / thickness."""
    return E * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / thickness


def confined_radius(radius: float, d_top: float, d_bottom: float, outer_radius: float, factor: float = 1.0) -> float:
    """Radius b at which the displacement field around a pin section in the cancellous bone dies out, when
    the cancellous bone is held above by the (much stiffer, bonded) cortex at distance d_top and below by the
    bone's far side at d_bottom: the field cannot reach further than the nearest held face, so
    1/(b - a) = 1/(c d_top) + 1/(c d_bottom) + 1/(b_far - a), c = `factor` (1 physical: the field reaches
    as far as the face), b_far the bone's lateral size. Deep in thick bone b -> b_far (the old Winkler law)."""
    inv = 1.0 / (factor * d_top) + 1.0 / (factor * max(d_bottom, 1e-9)) + 1.0 / (outer_radius - radius)
    return radius + 1.0 / inv


def magic_radius(depth: float, nu: float) -> float:
    """Radius b at which the bone's displacement field dies out: r_m = 2.5 L (1 - nu) with L the embedded
    length (Randolph & Wroth 1978), and never less than 2 pin radii."""
    return 2.5 * depth * (1.0 - nu)


@dataclass(frozen=True)
class FrameModel:
    """Parameters of the needle-frame model. Lengths mm, moduli MPa, k of the layers N/mm^2.

    needle_xy: positions (x, y) of the needles in mm; None = `needles` pins on the x axis at
    `spacing_mm`, centred on x = 0 (one needle: x = 0), as `fe needle` places them.
    load_point_mm: where the wrench acts (a point of the clamp); None = the centre of the clamp's
    gripper faces (x centre, y = 0, z = free_length - clamp_length/2), `fe needle`'s load resultant.
    foundation_factor, axial_factor, tissue_factor: multiply the derived bone foundation (lateral and
    torsion; axial shaft and tip bearing) and the layers' k (1 = the physical values; calibrate() fits
    them to FE or measurements).
    clamp: "rigid" (default: a rigid body) or "elastic": a straight Timoshenko bar along the line of the pins
    (x for one pin) at the clamp's centre height, condensed to a compliance at the pins' ends
    (`clamp_compliance`). Its defaults are `fe needle`'s clamp bar: clamp_E_MPa 200,000 MPa and clamp_nu 0.30
    (materials registry "clamp", structural steel, paper Table 2), section clamp_section_mm = None ->
    (clamp_width_mm, clamp_length_mm) = 20 x 20 mm (width along y, height along z; NeedleGeometry.clamp_width
    and grip_length, the bar of NeedleGeometry.clamp_box). The pins must lie on one line.
    """

    needles: int = DEFAULT_NEEDLES
    spacing_mm: float = DEFAULT_SPACING_MM
    diameter_mm: float = DEFAULT_DIAMETER_MM
    free_length_mm: float = DEFAULT_FREE_LENGTH_MM
    depth_mm: float = DEFAULT_DEPTH_MM
    cortex_mm: float = DEFAULT_CORTEX_MM
    clamp_length_mm: float = DEFAULT_CLAMP_LENGTH_MM
    layers: tuple[Layer, ...] = field(default=DEFAULT_LAYERS)
    tissue: bool = True
    root: str = "bone"
    needle_xy: tuple | None = None
    load_point_mm: tuple | None = None
    youngs_modulus_MPa: float = NEEDLE_E_MPA
    poisson: float = NEEDLE_NU
    cortical_E_MPa: float = CORTICAL_E_MPA
    cortical_nu: float = CORTICAL_NU
    cancellous_E_MPa: float = CANCELLOUS_E_MPA
    cancellous_nu: float = CANCELLOUS_NU
    foundation_factor: float = 1.0
    tissue_factor: float = 1.0
    axial_factor: float = 1.0   # on the bone's axial (shaft and tip) stiffness, separate from the lateral
    shear: bool = True          # Timoshenko shear and axial strain (False: Kirchhoff, inextensible)
    clamp_width_mm: float = DEFAULT_CLAMP_WIDTH_MM
    clamp_overhang_mm: float = DEFAULT_CLAMP_OVERHANG_MM
    step_mm: float = 8.0        # integration step (RK4) target; doubled in the error estimate
    yield_MPa: float = NEEDLE_YIELD_MPA
    bone_radius_mm: float | None = DEFAULT_BONE_RADIUS_MM  # where the bone's displacement field ends; None:
    #                                     Randolph & Wroth's 2.5 depth (1 - nu)
    plastic: bool = False       # elastic-plastic pin section (bilinear, hardening_MPa), monotonic loading
    hardening_MPa: float = NEEDLE_HARDENING_MPA
    # bone law: "plate" = the cortex as a plate (in-plane lateral, bending for the pin's tilt and axial push)
    # on a cancellous core confined between the cortex and the bone's far side; "winkler" = the earlier
    # uniform foundation (cortex and cancellous as thick media, docs/frame.md)
    bone_law: str = "plate"
    bone_thickness_mm: float = DEFAULT_BONE_THICKNESS_MM  # the bone's far side (held) at z = -bone_thickness
    cortex_factor: float = 1.0       # on the cortex plate's rocking and axial springs (plate law)
    confinement_factor: float = 1.0  # c in confined_radius: how far the field reaches, per distance to a face
    # clamp: "rigid" (a rigid body) or "elastic" (a straight Timoshenko bar along the line of the pins, through
    # their attachment points and the load point; `clamp_compliance`, docs/frame.md)
    clamp: str = "rigid"
    clamp_E_MPa: float = CLAMP_E_MPA   # Young's modulus of the clamp bar, MPa (fe needle: steel, paper Table 2)
    clamp_nu: float = CLAMP_NU         # Poisson's ratio of the clamp bar (fe needle: 0.30)
    # (width along y, height along z) of the clamp bar's rectangular section, mm; None = (clamp_width_mm,
    # clamp_length_mm): fe needle's bar, clamp_width wide and the grip length tall
    clamp_section_mm: tuple | None = None

    def __post_init__(self):
        if isinstance(self.needles, bool) or not isinstance(self.needles, (int, np.integer)) \
                or not 1 <= self.needles <= 4:
            raise InputError("needles", f"must be an integer 1..4, got {self.needles!r}")
        object.__setattr__(self, "needles", int(self.needles))
        for name in ("diameter_mm", "free_length_mm", "depth_mm", "cortex_mm", "youngs_modulus_MPa",
                     "cortical_E_MPa", "cancellous_E_MPa", "foundation_factor", "tissue_factor", "axial_factor",
                     "cortex_factor", "confinement_factor", "bone_thickness_mm", "clamp_width_mm", "clamp_overhang_mm", "step_mm", "yield_MPa"):
            check_number(name, getattr(self, name), gt=0)
        check_number("clamp_length_mm", self.clamp_length_mm, ge=0)
        # shooting through the bone stays well conditioned while the foundation's decay lengths are not
        # far below the depth (docs/frame.md): factors up to MAX_FACTOR
        check_number("foundation_factor", self.foundation_factor, le=MAX_FACTOR)
        check_number("tissue_factor", self.tissue_factor, le=MAX_FACTOR)
        check_number("axial_factor", self.axial_factor, le=MAX_FACTOR)
        check_number("cortex_factor", self.cortex_factor, le=MAX_FACTOR)
        check_number("confinement_factor", self.confinement_factor, le=MAX_FACTOR)
        if self.clamp not in CLAMPS:
            raise InputError("clamp", f"must be one of {CLAMPS}, got {self.clamp!r}")
        check_number("clamp_E_MPa", self.clamp_E_MPa, gt=0)
        check_number("clamp_nu", self.clamp_nu, gt=-1, lt=0.5)
        if self.clamp_section_mm is not None:
            try:
                sec = tuple(float(check_number("clamp_section_mm", v, gt=0)) for v in self.clamp_section_mm)
            except TypeError:
                raise InputError("clamp_section_mm", f"expected (width, height) in mm, got "
                                 f"{self.clamp_section_mm!r}") from None
            if len(sec) != 2:
                raise InputError("clamp_section_mm", f"expected (width, height) in mm, got {self.clamp_section_mm!r}")
            object.__setattr__(self, "clamp_section_mm", sec)
        elif self.clamp == "elastic" and not self.clamp_length_mm > 0:
            raise InputError("clamp_section_mm", "the elastic clamp needs a section: clamp_length_mm is 0 (no bar "
                             "to take the height from); give clamp_section_mm = (width, height) in mm")
        if self.bone_law not in BONE_LAWS:
            raise InputError("bone_law", f"must be one of {BONE_LAWS}, got {self.bone_law!r}")
        for name in ("poisson", "cortical_nu", "cancellous_nu"):
            check_number(name, getattr(self, name), gt=-1, lt=0.5)
        if self.root not in ROOTS:
            raise InputError("root", f"must be one of {ROOTS}, got {self.root!r}")
        check_number("hardening_MPa", self.hardening_MPa, gt=0, lt=self.youngs_modulus_MPa)
        if self.bone_radius_mm is not None:
            check_number("bone_radius_mm", self.bone_radius_mm, gt=self.diameter_mm)
        for name in ("tissue", "shear", "plastic"):
            if not isinstance(getattr(self, name), bool):
                raise InputError(name, f"must be true or false, got {getattr(self, name)!r}")
        layers = tuple(self.layers)
        for la in layers:
            if not isinstance(la, Layer):
                raise InputError("layers", f"expected Layer objects, got {la!r}")
        object.__setattr__(self, "layers", layers)
        d = self.diameter_mm
        if self.root == "bone" and self.depth_mm <= self.cortex_mm:
            raise InputError("depth_mm", f"the pin must reach the cancellous bone: depth must be > cortex "
                             f"({self.cortex_mm} mm), got {self.depth_mm}")
        if self.root == "bone" and self.bone_law == "plate" and self.depth_mm >= self.bone_thickness_mm:
            raise InputError("depth_mm", f"the pin tip must stay inside the bone: depth must be < bone_thickness_mm "
                             f"({self.bone_thickness_mm} mm), got {self.depth_mm}")
        if self.clamp_length_mm >= self.free_length_mm:
            raise InputError("clamp_length_mm", f"must be < free_length_mm ({self.free_length_mm}), "
                             f"got {self.clamp_length_mm}")
        T = self.tissue_thickness_mm
        if T > self.clamp_bottom_mm:
            raise InputError("free_length_mm", f"the clamp must sit above the skin at {T} mm: free_length - "
                             f"clamp_length must be >= {T}, got {self.clamp_bottom_mm}")
        given_xy = self.needle_xy is not None
        if not given_xy:
            if self.needles > 1:
                check_number("spacing_mm", self.spacing_mm, gt=0)
            xy = tuple(((i - (self.needles - 1) / 2) * float(self.spacing_mm), 0.0) for i in range(self.needles))
        else:
            try:
                xy = tuple((float(p[0]), float(p[1])) for p in self.needle_xy)
            except (TypeError, ValueError, IndexError):
                raise InputError("needle_xy", f"expected (x, y) pairs in mm, got {self.needle_xy!r}") from None
            if len(xy) != self.needles or any(len(p) != 2 for p in self.needle_xy):
                raise InputError("needle_xy", f"need {self.needles} (x, y) pairs, got {self.needle_xy!r}")
            for i, (x, y) in enumerate(xy):
                check_number(f"needle_xy[{i}].x", x)
                check_number(f"needle_xy[{i}].y", y)
        object.__setattr__(self, "needle_xy", xy)
        for i in range(len(xy)):
            for j in range(i):
                dist = math.hypot(xy[i][0] - xy[j][0], xy[i][1] - xy[j][1])
                if dist <= d:
                    raise InputError("needle_xy" if given_xy else "spacing_mm",
                                     f"needles {j + 1} and {i + 1} are {dist:g} mm apart, closer than their "
                                     f"diameter {d} mm")
        if self.clamp == "elastic" and len(xy) > 2:
            # the bar runs along the line of the pins; a pin off its axis is held by the bar's section through a
            # rigid arm, as long as it lies inside the section's width
            e = clamp_bar_direction(xy)
            o = np.mean(xy, axis=0)
            off = [abs(-e[1] * (x - o[0]) + e[0] * (y - o[1])) for x, y in xy]
            width = (self.clamp_section_mm or (self.clamp_width_mm,))[0]
            if max(off) > width / 2:
                i = int(np.argmax(off))
                raise InputError("needle_xy", f"the elastic clamp is a straight bar {width:g} mm wide along the line "
                                 f"of the pins: pin {i + 1} is {off[i]:.3g} mm off its axis, more than half its width")
        if self.load_point_mm is None:
            lp = (self.centre_xy[0], self.centre_xy[1], self.free_length_mm - self.clamp_length_mm / 2)
        else:
            try:
                lp = tuple(float(v) for v in self.load_point_mm)
            except (TypeError, ValueError):
                raise InputError("load_point_mm", f"expected X,Y,Z in mm, got {self.load_point_mm!r}") from None
            if len(lp) != 3:
                raise InputError("load_point_mm", f"expected 3 coordinates, got {self.load_point_mm!r}")
            for v in lp:
                check_number("load_point_mm", v)
            lo, hi = self.clamp_box_mm
            tol = 1e-9 * self.free_length_mm
            if any(p < a - tol or p > b + tol for p, a, b in zip(lp, lo, hi)):
                raise InputError("load_point_mm", f"must lie in the clamp {tuple(lo)}..{tuple(hi)} mm, got {lp}")
        object.__setattr__(self, "load_point_mm", lp)

    # derived ------------------------------------------------------------------------------------
    @property
    def tissue_thickness_mm(self) -> float:
        return sum(la.thickness_mm for la in self.layers) if self.tissue else 0.0

    @property
    def clamp_bottom_mm(self) -> float:
        """z where the needles enter the clamp (built in above)."""
        return self.free_length_mm - self.clamp_length_mm

    @property
    def centre_xy(self) -> tuple[float, float]:
        xy = np.asarray(self.needle_xy)
        return (0.5 * (xy[:, 0].min() + xy[:, 0].max()), 0.5 * (xy[:, 1].min() + xy[:, 1].max()))

    @property
    def clamp_centre_mm(self) -> tuple[float, float, float]:
        """Centre of the gripper faces (where `fe needle` measures the clamp displacement)."""
        return (*self.centre_xy, self.free_length_mm - self.clamp_length_mm / 2)

    @property
    def clamp_box_mm(self):
        xy = np.asarray(self.needle_xy)
        o, w = self.clamp_overhang_mm, self.clamp_width_mm / 2
        lo = (xy[:, 0].min() - o, min(xy[:, 1].min() - w, -w), self.clamp_bottom_mm)
        hi = (xy[:, 0].max() + o, max(xy[:, 1].max() + w, w), self.free_length_mm)
        return lo, hi

    @property
    def area_mm2(self) -> float:
        return math.pi * self.diameter_mm**2 / 4

    @property
    def second_moment_mm4(self) -> float:
        return math.pi * self.diameter_mm**4 / 64

    @property
    def bending_stiffness_Nmm2(self) -> float:
        return self.youngs_modulus_MPa * self.second_moment_mm4

    @property
    def shear_modulus_MPa(self) -> float:
        return self.youngs_modulus_MPa / (2 * (1 + self.poisson))

    @property
    def foundation(self) -> dict:
        """Bone foundation, derived (before the factors): per unit length N/mm^2 (rocking and torsion
        N mm/rad per mm), tip spring N/mm. Plate law: `cortex_rocking` and `cortex_axial` are the plate's
        concentrated springs (`cortex_rocking_Nmm_per_rad`, `cortex_axial_N_per_mm`) spread over its
        thickness; `cancellous_lateral` is the length-average of `cancellous_profile`."""
        a = self.diameter_mm / 2
        b = (magic_radius(self.depth_mm, self.cancellous_nu) if self.bone_radius_mm is None
             else self.bone_radius_mm)
        b = max(b, 2 * a)
        out = {"outer_radius_mm": b}
        # The cortex loaded in its plane (the pin pushed sideways): plane stress, nu' = nu / (1 + nu) in the
        # plane-strain formula.
        nu_c = self.cortical_nu / (1 + self.cortical_nu)
        G_c = self.cortical_E_MPa / (2 * (1 + self.cortical_nu))  # G is the same in both
        out["cortex_lateral"] = lateral_foundation_k(2 * G_c * (1 + nu_c), nu_c, a, b)
        out["cancellous_lateral"] = lateral_foundation_k(self.cancellous_E_MPa, self.cancellous_nu, a, b)
        out["cancellous_axial"] = axial_foundation_k(self.cancellous_E_MPa, self.cancellous_nu, a, b)
        # twist: a rigid cylinder turning in an elastic medium, tau(a) = 2 G psi: T = 4 pi G a^2 psi per length
        for name, E, nu in (("cortex", self.cortical_E_MPa, self.cortical_nu),
                            ("cancellous", self.cancellous_E_MPa, self.cancellous_nu)):
            out[f"{name}_torsion"] = 4 * math.pi * E / (2 * (1 + nu)) * a**2
        if self.bone_law == "plate":
            # the cortex loaded across its plane (the pin tilted or pushed along its axis) bends as a plate
            # ... resting on the cancellous bone, which confines its bending to a few characteristic lengths
            # l = (D / k_s)^(1/4) (plate on a Winkler foundation; the clamped-annulus forms with the
            # equivalent radii of the exact solution, never beyond the bone's radius b)
            t = self.cortex_mm
            D = plate_rigidity(self.cortical_E_MPa, self.cortical_nu, t)
            ks = subgrade_modulus(self.cancellous_E_MPa, self.cancellous_nu, self.bone_thickness_mm - t)
            lp = (D / ks) ** 0.25
            out["cortex_plate_length_mm"] = lp
            out["cortex_rocking_Nmm_per_rad"] = plate_rocking_k(
                D, a, max(min(plate_equivalent_radius(PLATE_ROCKING_RADIUS, a, lp), b), 1.5 * a))
            out["cortex_axial_N_per_mm"] = plate_axial_k(
                D, a, max(min(plate_equivalent_radius(PLATE_AXIAL_RADIUS, a, lp), b), 1.5 * a))
            out["cortex_rocking"] = out["cortex_rocking_Nmm_per_rad"] / t
            out["cortex_axial"] = out["cortex_axial_N_per_mm"] / t
            prof = self.cancellous_profile
            out["cancellous_lateral"] = float(sum((z1 - z0) * k for z0, z1, k in prof) / (prof[-1][1] - prof[0][0]))
        else:
            out["cortex_rocking"] = 0.0
            out["cortex_axial"] = axial_foundation_k(self.cortical_E_MPa, self.cortical_nu, a, b)
        # end bearing of the tip: rigid punch on a half-space, F = 2 a E / (1 - nu^2) w (Boussinesq)
        out["tip_axial_N_per_mm"] = 2 * a * self.cancellous_E_MPa / (1 - self.cancellous_nu**2)
        return out

    @property
    def cancellous_profile(self) -> list:
        """Plate law: [(z0, z1, k_h)] for the cancellous sub-segments from the tip up to the cortex, k_h (N/mm^2)
        the mean over the sub-segment (8-point Gauss) of the plane-strain disc formula with the confined outer
        radius (`confined_radius`: the cortex mid-plane above, the bone's far side below)."""
        a = self.diameter_mm / 2
        b = self.bone_radius_mm if self.bone_radius_mm is not None else magic_radius(self.depth_mm, self.cancellous_nu)
        b = max(b, 2 * a)
        z_tip, z_top = -self.depth_mm, -self.cortex_mm
        n = CANCELLOUS_SUBSEGMENTS
        # sub-segments crowd towards both ends, where the modulus changes fastest
        edges = z_tip + (z_top - z_tip) * (1 - np.cos(np.pi * np.arange(n + 1) / n)) / 2
        xg, wg = np.polynomial.legendre.leggauss(8)
        out = []
        for z0, z1 in zip(edges[:-1], edges[1:]):
            zs = 0.5 * (z0 + z1) + 0.5 * (z1 - z0) * xg
            ks = [lateral_foundation_k(self.cancellous_E_MPa, self.cancellous_nu, a,
                                       confined_radius(a, -z - self.cortex_mm / 2, self.bone_thickness_mm + z, b,
                                                       self.confinement_factor)) for z in zs]
            out.append((float(z0), float(z1), float(np.dot(wg, ks) / 2)))
        return out

    @property
    def clamp_section(self) -> dict:
        """The clamp bar's section (rectangle, width b along y, height h along z; mm, mm^2, mm^4) and moduli
        (MPa): A = b h, I_y = b h^3 / 12 (bending in the pins' plane: the portal frame), I_z = h b^3 / 12
        (bending across it), the torsion constant of a rectangle J = a c^3 (1/3 - 0.21 (c/a) (1 - c^4 /
        (12 a^4))), a >= c its sides (Roark, Table 10.7 case 4; 0.1 % of the exact series for a square), and
        Cowper's (1966) shear factor of a rectangle k = 10 (1 + nu) / (12 + 11 nu)."""
        b, h = self.clamp_section_mm if self.clamp_section_mm is not None else (self.clamp_width_mm,
                                                                              self.clamp_length_mm)
        a, c = max(b, h), min(b, h)
        E, nu = self.clamp_E_MPa, self.clamp_nu
        return {"width_mm": b, "height_mm": h, "area_mm2": b * h, "Iy_mm4": b * h**3 / 12, "Iz_mm4": h * b**3 / 12,
                "J_mm4": a * c**3 * (1 / 3 - 0.21 * (c / a) * (1 - c**4 / (12 * a**4))) if c > 0 else 0.0,
                "shear_factor": 10 * (1 + nu) / (12 + 11 * nu), "E_MPa": E, "G_MPa": E / (2 * (1 + nu)),
                "axis_z_mm": self.free_length_mm - self.clamp_length_mm / 2}

    def replace(self, **changes) -> "FrameModel":
        if "needles" in changes and "needle_xy" not in changes:
            changes["needle_xy"] = None
        if ("needle_xy" in changes or "free_length_mm" in changes or "clamp_length_mm" in changes
                or "spacing_mm" in changes) and "load_point_mm" not in changes:
            changes["load_point_mm"] = None
        return replace(self, **changes)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["layers"] = [asdict(la) for la in self.layers]
        d["needle_xy"] = [list(p) for p in self.needle_xy]
        d["load_point_mm"] = list(self.load_point_mm)
        d["bending_stiffness_Nmm2"] = self.bending_stiffness_Nmm2
        d["foundation_N_per_mm2"] = self.foundation
        d["clamp_centre_mm"] = list(self.clamp_centre_mm)
        if self.clamp_section_mm is not None:
            d["clamp_section_mm"] = list(self.clamp_section_mm)
        if self.clamp == "elastic":
            d["clamp_bar"] = self.clamp_section
        return d


def clamp_bar_direction(xy) -> np.ndarray:
    """Unit direction (x, y) of the clamp bar in plan: the line of the pins (principal direction of their
    positions); one pin: x, like fe needle's bar."""
    xy = np.asarray(xy, float)
    if len(xy) < 2:
        return np.array([1.0, 0.0])
    d = xy - xy.mean(0)
    e = np.linalg.svd(d)[2][0]
    if e[0] < 0 or (e[0] == 0 and e[1] < 0):
        e = -e
    return e


def clamp_compliance(model: FrameModel, points) -> np.ndarray:
    """Compliance (6p x 6p) of the elastic clamp bar between points rigid with it: block (a, b) maps a force (N)
    and a moment (N mm, about point b) applied at point b to the displacement (mm) and rotation (rad) of point a,
    with the bar's section through the load point held (the clamp's reference: it carries the applied wrench,
    so the pins' end wrenches load the bar against it). Axes: the clamp's (global at rest).

    The bar: a straight prismatic Timoshenko beam (`clamp_section`) along the line of the pins in plan (x for one
    pin), at the height of the clamp's centre (z = free_length - clamp_length / 2). A point X belongs to the bar
    section at its projection xi(X) on the axis. Unit-load method: a wrench (f, m) at X_b is carried between the
    reference section xi_L and xi(X_b) by the stress resultant F = f, M(xi) = m + (X_b - p(xi)) x f, so

        C_ab = int_overlap R_a(xi)^T D^-1 R_b(xi) dxi,   D = diag(EA, kGA, kGA, GJ, EI_y, EI_z)

    in the bar's axes (axial, across in plan, vertical), the overlap the part of the axis between xi_L and both
    points (zero for points on opposite sides of the reference). R is linear in xi, so 2-point Gauss is exact."""
    pts = np.atleast_2d(np.asarray(points, float))
    p = len(pts)
    sec = model.clamp_section
    e2 = clamp_bar_direction(model.needle_xy)
    E3 = np.array([[e2[0], -e2[1], 0.0], [e2[1], e2[0], 0.0], [0.0, 0.0, 1.0]])  # columns: axis, across, up
    o = np.array([*np.mean(np.asarray(model.needle_xy, float), 0), sec["axis_z_mm"]])
    E, G, A, k = sec["E_MPa"], sec["G_MPa"], sec["area_mm2"], sec["shear_factor"]
    Dinv = 1.0 / np.array([E * A, k * G * A, k * G * A, G * sec["J_mm4"], E * sec["Iy_mm4"], E * sec["Iz_mm4"]])
    xi = (pts - o) @ E3[:, 0]
    xiL = (np.asarray(model.load_point_mm, float) - o) @ E3[:, 0]
    s = xi - xiL
    gx = np.array([0.5 - 0.5 / math.sqrt(3), 0.5 + 0.5 / math.sqrt(3)])

    def R(X, x):  # resultant in bar axes per unit (f, m) at X, at the section x
        d = X - (o + x * E3[:, 0])
        cross = np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]])
        out = np.zeros((6, 6))
        out[:3, :3] = E3.T
        out[3:, :3] = E3.T @ cross
        out[3:, 3:] = E3.T
        return out

    C = np.zeros((6 * p, 6 * p))
    for a in range(p):
        for b in range(p):
            if s[a] * s[b] <= 0:
                continue
            ell = min(abs(s[a]), abs(s[b]))
            blk = np.zeros((6, 6))
            for g in gx:
                x = xiL + math.copysign(g * ell, s[a])
                blk += 0.5 * ell * R(pts[a], x).T @ (Dinv[:, None] * R(pts[b], x))
            C[6 * a: 6 * a + 6, 6 * b: 6 * b + 6] = blk
    return C


def moment_curvature(model: FrameModel, points: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """M(kappa) of the solid circular pin section with a bilinear material (E up to the yield stress,
    then the hardening modulus H), M = int sigma(kappa y) y dA; kappa from 0 to 60 x the first-yield
    curvature (surface strain ~ 50 %, far past any use). Gauss-Legendre in y on [-r, r] with the chord
    width 2 sqrt(r^2 - y^2): converged to 1e-6 (tested against the closed forms: M_y = sigma_y pi d^3/32
    at first yield, M -> M_p = sigma_y d^3/6 for H -> 0)."""
    E, sy, H = model.youngs_modulus_MPa, model.yield_MPa, model.hardening_MPa
    r = model.diameter_mm / 2
    ky = sy / (E * r)
    kap = np.concatenate([[0.0, ky], ky * np.geomspace(1.0005, 60.0, points - 2)])
    # y = r sin(t): dA-weighted integral int_{-pi/2}^{pi/2} sigma(kappa r sin t) r sin t 2 r cos t r cos t dt
    t, w = np.polynomial.legendre.leggauss(400)
    t = t * np.pi / 2
    w = w * np.pi / 2
    y = r * np.sin(t)
    dA = 2 * r * np.cos(t) * r * np.cos(t)
    eps = kap[:, None] * y[None, :]
    ey = sy / E
    sig = np.where(np.abs(eps) <= ey, E * eps, np.sign(eps) * (sy + H * (np.abs(eps) - ey)))
    M = (sig * y * dA * w).sum(1)
    M[1] = sy * np.pi * model.diameter_mm**3 / 32  # exact at first yield (the quadrature's kink)
    return kap, M


def section_tangent(model: FrameModel, kap: np.ndarray) -> np.ndarray:
    """dM/dkappa of the same section at the curvatures kap: E_t = E in the elastic core |y| <= c = sigma_y/(E kappa)
    and H outside, so dM/dkappa = H I + (E - H) I_c with the core's second moment (closed form, exact)
    I_c = (c/2)(2c^2 - r^2) sqrt(r^2 - c^2) + (r^4/2) asin(c/r) (= I at c = r). It is continuous at first yield
    (the plastic zone starts with zero area: EI on both sides), so kappa(M), interpolated as a cubic Hermite with
    these slopes, is continuously differentiable: what Newton needs (a piecewise-linear table kinks at every
    node, and Newton on it stalled to linear convergence; docs/frame.md)."""
    E, sy, H = model.youngs_modulus_MPa, model.yield_MPa, model.hardening_MPa
    r = model.diameter_mm / 2
    kap = np.asarray(kap, float)
    c = np.minimum(r, sy / (E * np.maximum(kap, 1e-300)))
    Ic = 0.5 * c * (2 * c**2 - r**2) * np.sqrt(np.maximum(r**2 - c**2, 0.0)) + 0.5 * r**4 * np.arcsin(c / r)
    return H * model.second_moment_mm4 + (E - H) * Ic
