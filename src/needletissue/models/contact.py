"""The needle model with the paper's frictional interfaces beside the bonded one.

``NeedleContact`` plugs into ``run_needle_model(config, **contact.hooks())`` (the needle model's
``mesh_hook``/``items`` hooks): it splits the chosen interfaces of the (conforming) needle mesh before
the FE model is built and adds one ``FrictionalContact`` item per interface. ``compare_interfaces`` runs the bonded and the contact model on the
same mesh and reports, per force, the needle and tissue deformation, the gap that opens at each
interface (behind the needle) and the change in the theory-FE (Rayleigh-Ritz) difference.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from needletissue.fem.contact import ContactSettings, ContactSurface, FrictionalContact, resolve_interfaces
from needletissue.fem.contact.mesh import split_interfaces


NEEDLE_EPS_V = 0.01
"""The needle model's friction smoothing (mm of slip per load increment): with ContactSettings' 0.001
Newton chattered between stick and slip from the second increment on (docs/contact.md)."""
NEEDLE_GAP_FRACTION = 0.95
"""The split sides' virtual gap (x dhat): the rest prestress of the stiffer bone-needle barrier stays
near 1 % of the bone's E (0.9: 5 %)."""
NEEDLE_RIM = ("adipose",)
"""Where the needle leaves the muscle into the adipose, the muscle rim's nodes are split from the needle
and shared with the adipose (split_interfaces' rim): tied to the needle there, the needle's rotation
pressed the muscle under the ring into the barrier (distances 2e-4..5e-4 mm, Newton stalled at 206 N on
the default mesh, docs/contact.md)."""
PRESSURE_FRACTION = {"bone-needle": 1.0, "needle-muscle": 1.0}
"""Barrier pressure at dhat/2 per interface (x E of the softer side; others 0.1): the pin presses the
bone with ~30 MPa at 300 N (beam on an elastic foundation, 30 mm deep), and with 0.1 E the cortical
rim squeezed the barrier to 1e-5 mm of dhat 0.1, where Newton stagnated; the muscle under the adipose
squeezed the needle-muscle barrier to 2e-4 mm by 160 N the same way (docs/contact.md)."""


def needle_settings(**given) -> ContactSettings:
    """The needle model's contact settings: NEEDLE_EPS_V and NEEDLE_GAP_FRACTION unless `given`."""
    return ContactSettings(**{"eps_v": NEEDLE_EPS_V, "gap_fraction": NEEDLE_GAP_FRACTION, **given})


@dataclass
class NeedleContact:
    """Interfaces of the needle model as contact pairs.

    interfaces: "paper" (needle-muscle 0.3, muscle-bone 0.3, bone-needle 0.9 where present) or
    "bonded"; overrides: {"needle-muscle": 0.5, ...} friction coefficients (>= 0) per pair.
    settings: ContactSettings (dhat mm, barrier stiffness MPa/mm, eps_v mm); its youngs_modulus
    defaults to the muscle's small-strain modulus 3 mu0 (the softest body in contact).
    """

    interfaces: str = "paper"
    overrides: dict[str, float] = field(default_factory=dict)
    settings: ContactSettings | None = None
    materials: dict[str, str] | None = None  # region -> material; None: the needle model's regions
    friction: dict[str, float] = field(default_factory=dict, init=False)
    item: FrictionalContact | None = field(default=None, init=False)
    item_list: list = field(default_factory=list, init=False)
    _split: list = field(default_factory=list, init=False, repr=False)

    def __post_init__(self):
        from needletissue.errors import InputError, check_number

        if self.interfaces not in ("bonded", "paper"):  # fail before meshing
            raise InputError("interfaces", f"must be 'bonded' or 'paper', got {self.interfaces!r}")
        for name, mu in self.overrides.items():
            check_number(f"interfaces.{name}", mu, ge=0)

    def hooks(self) -> dict:
        """Keyword arguments for run_needle_model."""
        return {"mesh_hook": self.prepare, "items": self.items, "report": self.report}

    def gaps(self, displacement) -> tuple[dict[str, float], float]:
        """Largest normal opening per interface (mm, > 0 = separated, e.g. behind the needle) and the
        largest interpenetration (mm) over all interfaces for a displacement field."""
        return _gaps(self.state(displacement))

    def state(self, displacement) -> dict[str, dict]:
        """Per interface: gaps, slip, contact pressure, interpenetration (`interface_state`)."""
        return {k: v for i in self.item_list for k, v in interface_state(i, displacement).items()}

    def settings_dict(self) -> dict:
        return {i.surface.interfaces[0].name: {
            "dhat_mm": i.settings.dhat, "stiffness_MPa_per_mm": i.settings.kappa,
            "eps_v_mm": i.settings.eps_v, "lag": i.settings.lag} for i in self.item_list}

    def summary(self, forces, displacements) -> dict:
        """Interfaces, settings and per force the gap opening per interface and the interpenetration
        (mm), for the displacement fields solved at `forces` (N); "interfaces": per interface the
        gaps, slip, contact pressure and interpenetration (`interface_state`); "rest": the pressure and
        normal force of the undeformed state (the barrier's prestress before the sides relax against it)."""
        per_force = []
        for force, u in zip(forces, displacements):
            state = self.state(u)
            gaps, penetration = _gaps(state)
            per_force.append({"force_N": force, "max_gap_opening_mm": gaps, "max_interpenetration_mm": penetration,
                              "interfaces": state})
        # the virtual gap's prestress: the pressure and normal force at zero displacement
        rest = self.state(np.zeros_like(displacements[0])) if per_force else {}
        return {"interfaces": dict(self.friction), "settings": self.settings_dict(), "per_force": per_force,
                "rest": {k: {"mean_pressure_MPa": v["mean_pressure_MPa"], "normal_force_N": v["normal_force_N"]}
                         for k, v in rest.items()}}

    def report(self, result) -> dict:
        """The "contact" field of the needle model's results (see `summary`)."""
        return {"contact": self.summary([r.force_N for r in result.results],
                                        [r.fe.displacement for r in result.results])}

    def _materials(self) -> dict[str, str]:
        from needletissue.models.needle.model import MATERIALS

        return MATERIALS if self.materials is None else self.materials

    def prepare(self, mesh):
        from needletissue.fem.contact.mesh import material_groups

        groups = material_groups(self._materials()) if self.materials is not None else None
        self.friction = resolve_interfaces(mesh, self.interfaces, self.overrides, groups)
        if not self.friction:
            return mesh
        mesh, self._split = split_interfaces(mesh, list(self.friction), groups,
                                             rim=NEEDLE_RIM if self.materials is None else ())
        return mesh

    def items(self, model) -> list:
        """One contact item per interface: the barrier stiffness follows the softer side's modulus
        (3 mu0 of the region's material), so needle-bone is not as soft as needle-muscle."""
        from needletissue import materials

        names = self._materials()
        self.item_list = []
        for itf in self._split:
            modulus = min(3.0 * materials.get(names.get(r, r)).initial_shear_modulus
                          for r in itf.regions_a + itf.regions_b)
            settings = self.settings or needle_settings()
            if settings.stiffness is None:  # PRESSURE_FRACTION: the pin's interfaces, both models
                fraction = PRESSURE_FRACTION.get(itf.name)
                settings = replace(settings, youngs_modulus=modulus,
                                   pressure_fraction=fraction or settings.pressure_fraction)
            surface = ContactSurface.build(model.mesh.points, [itf], self.friction, gap=settings.gap)
            self.item_list.append(FrictionalContact(model.field, surface, settings))
        self.item = self.item_list[0] if self.item_list else None
        return list(self.item_list)


def _gaps(state: dict) -> tuple[dict[str, float], float]:
    return ({k: v["max_gap_opening_mm"] for k, v in state.items()},
            max((v["max_interpenetration_mm"] for v in state.values()), default=0.0))


def interface_state(item, displacement) -> dict[str, dict]:
    """Per interface of a FrictionalContact item at a displacement field (all mesh nodes, mm):

    max_gap_opening_mm / max_pair_interpenetration_mm: largest normal separation / overlap of the
      originally coincident node pairs (normal of side a);
    max_slip_mm, mean_slip_mm: tangential relative displacement of those pairs (nodes tied at a
      bonded ring are not pairs: they cannot slip);
    max_pressure_MPa, mean_pressure_MPa, normal_force_N: the barrier's normal force on side a's
      vertices over their tributary area (mean = total force / interface area); it includes the
      rest prestress of the virtual gap (docs/contact.md);
    min_barrier_distance_mm, max_interpenetration_mm: smallest distance of the collision surfaces
      and the virtual gap minus it (< dhat by construction of the barrier);
    area_mm2, pairs: side a's interface area and the number of split node pairs.
    Assumes an interface per item or items whose interfaces share no vertex (NeedleContact's)."""
    from needletissue.fem.contact.item import _collisions
    from needletissue.fem.contact.mesh import triangles, vertex_normals

    s = item.surface
    points = np.asarray(item.field.region.mesh.points, dtype=float)
    V = item.positions(displacement[s.vertices])
    collisions = _collisions()
    collisions.build(item.cmesh, V, item.settings.dhat)
    force = -item.barrier.gradient(collisions, item.cmesh, V).reshape(-1, 3)
    dmin = float(np.sqrt(collisions.compute_minimum_distance(item.cmesh, V))) if len(collisions) else item.settings.dhat
    out = {}
    for itf in s.interfaces:
        ta = triangles(itf.faces_a)
        normal, area = vertex_normals(points, itf.faces_a)
        nodes = np.unique(ta)
        # side b lies along side a's outward normal: the barrier pushes side a against it
        pressing = np.maximum(-np.einsum("ij,ij->i", force[np.searchsorted(s.vertices, nodes)], normal[nodes]), 0)
        jump = displacement[itf.nodes_b] - displacement[itf.nodes_a]
        opening = np.einsum("ij,ij->i", jump, normal[itf.nodes_a])
        slip = np.linalg.norm(jump - opening[:, None] * normal[itf.nodes_a], axis=1)
        out[itf.name] = {
            "max_gap_opening_mm": float(max(0.0, opening.max(initial=0.0))),
            "max_pair_interpenetration_mm": float(max(0.0, -opening.min(initial=0.0))),
            "max_slip_mm": float(slip.max(initial=0.0)), "mean_slip_mm": float(slip.mean()) if len(slip) else 0.0,
            "max_pressure_MPa": float((pressing / area[nodes]).max(initial=0.0)),
            "mean_pressure_MPa": float(pressing.sum() / area[nodes].sum()),
            "normal_force_N": float(pressing.sum()),
            "min_barrier_distance_mm": dmin, "max_interpenetration_mm": float(max(0.0, item.settings.gap - dmin)),
            "area_mm2": float(area[nodes].sum()), "pairs": int(len(itf.nodes_a))}
    return out


@dataclass
class InterfaceComparison:
    """Bonded vs contact at one force (mm)."""

    force_N: float
    needle_max_bonded_mm: float
    needle_max_contact_mm: float
    tissue_max_bonded_mm: dict[str, float]
    tissue_max_contact_mm: dict[str, float]
    max_gap_opening_mm: dict[str, float]  # per interface: largest normal separation of node pairs
    max_interpenetration_mm: float
    theory_fe_difference_bonded_mm: float | None
    theory_fe_difference_contact_mm: float | None


@dataclass
class ComparisonResult:
    interfaces: dict[str, float]
    settings: dict
    rows: list[InterfaceComparison]
    wall_time_bonded_s: float
    wall_time_contact_s: float

    @property
    def cost_ratio(self) -> float:
        return self.wall_time_contact_s / self.wall_time_bonded_s


TISSUE = ("muscle", "adipose", "cortical_bone", "cancellous_bone")


def compare_interfaces(config=None, interfaces: str = "paper", overrides=None,
                       settings: ContactSettings | None = None) -> ComparisonResult:
    """Run the needle model bonded and with contact on the same mesh (see module docstring)."""
    from needletissue.models.needle import NeedleModelConfig, run_needle_model

    cfg = config or NeedleModelConfig()
    t0 = time.perf_counter()
    bonded = run_needle_model(cfg)
    t_bonded = time.perf_counter() - t0
    contact = NeedleContact(interfaces, dict(overrides or {}), settings)
    t0 = time.perf_counter()
    with_contact = run_needle_model(cfg, **contact.hooks())
    t_contact = time.perf_counter() - t0
    rows = []
    for b, c in zip(bonded.results, with_contact.results):
        gaps, penetration = contact.gaps(c.fe.displacement)
        rows.append(InterfaceComparison(
            force_N=b.force_N,
            needle_max_bonded_mm=b.max_needle_deformation_mm,
            needle_max_contact_mm=c.max_needle_deformation_mm,
            tissue_max_bonded_mm={k: v for k, v in b.max_deformation_mm.items() if k in TISSUE},
            tissue_max_contact_mm={k: v for k, v in c.max_deformation_mm.items() if k in TISSUE},
            max_gap_opening_mm=gaps,
            max_interpenetration_mm=penetration,
            theory_fe_difference_bonded_mm=b.theory_fe_difference_mm,
            theory_fe_difference_contact_mm=c.theory_fe_difference_mm,
        ))
    return ComparisonResult(contact.friction, contact.settings_dict(), rows, t_bonded, t_contact)
