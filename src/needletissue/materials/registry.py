"""Named materials with the reference study's values, and their FElupe constitutive models.

Units: stresses and moduli in MPa, density in g/cm^3.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import felupe as fem

from needletissue.errors import InputError, check_number
from needletissue.materials.laws import InvariantPolynomial, Ogden, mooney_rivlin_5
from needletissue.runinfo import read_toml

# Isochoric laws: name -> (strain energy, parameter names).
HYPERELASTIC_MODELS = {
    "neo_hooke": (fem.neo_hooke, ("mu",)),
    "mooney_rivlin": (fem.mooney_rivlin, ("C10", "C01")),
    "mooney_rivlin_5": (mooney_rivlin_5, ("C10", "C01", "C20", "C11", "C02")),
    "yeoh": (fem.yeoh, ("C10", "C20", "C30")),
    "ogden": (fem.ogden, ("mu", "alpha")),
}
MODELS = (*HYPERELASTIC_MODELS, "elastic")
# Hand-coded stress and elasticity of the same laws (laws.py; equal to the AD ones to round-off, Ogden's
# to tensortrax's eigenvalue perturbation): 5-25x faster than tensortrax (docs/bench.md, "Tissue laws").
CLOSED_FORM = {
    "neo_hooke": lambda p: InvariantPolynomial({(1, 0): p["mu"] / 2}),
    "mooney_rivlin": lambda p: InvariantPolynomial({(1, 0): p["C10"], (0, 1): p["C01"]}),
    "mooney_rivlin_5": lambda p: InvariantPolynomial({(1, 0): p["C10"], (0, 1): p["C01"], (2, 0): p["C20"],
                                                      (1, 1): p["C11"], (0, 2): p["C02"]}),
    "yeoh": lambda p: InvariantPolynomial({(1, 0): p["C10"], (2, 0): p["C20"], (3, 0): p["C30"]}),
    "ogden": lambda p: Ogden(_as_list(p["mu"]), _as_list(p["alpha"])),
}

# Bulk modulus of nearly incompressible tissue: K = max(TISSUE_BULK_MODULUS, TISSUE_BULK_RATIO * mu0).
# 10 MPa keeps muscle (MR5) and adipose (Ogden, alpha 16.2) within 2 % of their incompressible laws up
# to stretch 1.5: their stiffening, not mu0, sets the K they need (7.98 and 8.97 MPa; docs/materials.md).
# 100 mu0 was the default before issue 16 (the FEBio comparison and the frame sweep were measured at
# it); it stays the floor for stiffer user tissue. Needs the mixed P2/P0 formulation (docs/fem.md).
TISSUE_BULK_MODULUS = 10.0
TISSUE_BULK_RATIO = 100.0


@dataclass(frozen=True)
class Material:
    """A named material. `model` is one of MODELS; `parameters` in MPa (alpha dimensionless)."""

    name: str
    model: str
    parameters: dict = field(default_factory=dict)
    density: float = 1.0  # g/cm^3
    source: str = ""
    bulk_modulus: float | None = None  # MPa; None -> documented default
    # Stress (MPa) beyond which the elastic law stops describing the material: yield for metals,
    # strength for bone; compared with the FE's von Mises stress. None: not defined (soft tissue).
    strength: float | None = None
    strength_source: str = ""

    def __post_init__(self):
        if self.strength is not None:
            check_number(f"{self.name}.strength", self.strength, gt=0)
        if self.model not in MODELS:
            raise InputError(f"{self.name}.model", f"unknown model {self.model!r}; known: {', '.join(MODELS)}")
        check_number(f"{self.name}.density", self.density, gt=0)
        if self.model == "elastic":
            check_number(f"{self.name}.E", self.parameters.get("E"), gt=0)
            check_number(f"{self.name}.nu", self.parameters.get("nu"), gt=-1, lt=0.5)
        else:
            names = HYPERELASTIC_MODELS[self.model][1]
            missing = [n for n in names if n not in self.parameters]
            if missing:
                raise InputError(f"{self.name}.parameters", f"missing {', '.join(missing)} for model {self.model}")
            extra = sorted(set(self.parameters) - set(names))
            if extra:
                raise InputError(f"{self.name}.parameters", f"unknown {', '.join(extra)} for model {self.model}; "
                                 f"expected {', '.join(names)}")
            for n in names:
                values = self.parameters[n]
                if self.model == "ogden":
                    if not isinstance(values, (list, tuple)):
                        values = [values]
                    if n == "alpha" and len(values) != len(_as_list_checked(self.name, "mu", self.parameters["mu"])):
                        raise InputError(f"{self.name}.parameters", "mu and alpha need the same number of terms")
                    _as_list_checked(self.name, n, values)
                    if n == "alpha" and any(a == 0 for a in values):
                        raise InputError(f"{self.name}.parameters.alpha", "every alpha must be non-zero")
                else:
                    check_number(f"{self.name}.parameters.{n}", values)
            if self.initial_shear_modulus <= 0:
                raise InputError(f"{self.name}.parameters", "initial shear modulus must be > 0")

    @property
    def initial_shear_modulus(self) -> float:
        """mu0 in MPa (small-strain shear modulus)."""
        p = self.parameters
        if self.model == "elastic":
            return p["E"] / (2 * (1 + p["nu"]))
        from needletissue.materials import closed_form

        return closed_form.initial_shear_modulus(self.model, p)

    @property
    def bulk(self) -> float:
        """Bulk modulus K in MPa: explicit, from E and nu, or max(TISSUE_BULK_MODULUS, TISSUE_BULK_RATIO * mu0)."""
        if self.bulk_modulus is not None:
            return self.bulk_modulus
        if self.model == "elastic":
            E, nu = self.parameters["E"], self.parameters["nu"]
            return E / (3 * (1 - 2 * nu))
        return max(TISSUE_BULK_MODULUS, TISSUE_BULK_RATIO * self.initial_shear_modulus)

    def nominal_stress(self, mode: str, stretch):
        """Incompressible closed-form nominal stress (MPa) in a homogeneous load case (tissue laws)."""
        from needletissue.materials import closed_form

        return closed_form.nominal_stress(self.model, self.parameters, mode, stretch)

    def stable_range(self, mode: str) -> tuple[float, float]:
        """Drucker-stable stretch range (lo, hi) in a homogeneous incompressible load case (tissue laws)."""
        from needletissue.materials import stability

        return stability.stable_range(self.model, self.parameters, mode)

    def isochoric(self, ad: bool = False):
        """FElupe isochoric hyperelastic material (tissue laws only): the hand-coded one where the law has
        one, else (or with `ad`) FElupe's Hyperelastic on the strain energy (tensortrax AD)."""
        if not ad and self.model in CLOSED_FORM:
            return CLOSED_FORM[self.model]({n: self.parameters[n] for n in HYPERELASTIC_MODELS[self.model][1]})
        fun, names = HYPERELASTIC_MODELS[self.model]
        kwargs = {n: self.parameters[n] for n in names}
        if self.model == "ogden":
            kwargs = {n: _as_list(v) for n, v in kwargs.items()}
        return fem.Hyperelastic(fun, **kwargs)

    def umat(self, bulk: float | None = None):
        """FElupe material for a displacement-based solid: isochoric part plus volumetric part.

        Stiff parts (bone, needle, clamp) are compressible Neo-Hooke with mu, K from E and nu:
        identical to linear elasticity at small strain, and objective under the needle's large rotations.
        """
        K = self.bulk if bulk is None else bulk
        if self.model == "elastic":
            return fem.NeoHooke(mu=self.initial_shear_modulus, bulk=K)
        return self.isochoric() & fem.Volumetric(bulk=K)


def _as_list_checked(name, field_name, values):
    values = values if isinstance(values, (list, tuple)) else [values]
    return [check_number(f"{name}.parameters.{field_name}[{i}]", v) for i, v in enumerate(values)]


def _as_list(v):
    return [float(x) for x in v] if isinstance(v, (list, tuple)) else [float(v)]


_BUILTIN = {
    m.name: m
    for m in (
        Material(
            "muscle", "mooney_rivlin_5",
            dict(C10=0.08556, C01=-0.05841, C20=0.03900, C11=-0.02320, C02=0.00851),
            density=1.06,
            source="Paper Sec. 1.2.1 (its Ref. [12]); density: typical skeletal muscle (not given by the paper)",
        ),
        Material(
            "adipose", "ogden", dict(mu=[1.1667e-3], alpha=[16.2]), density=0.92,
            source="Paper Sec. 1.2.2 (Al-Dirini et al., its Ref. [14]); W = 2mu/alpha^2 convention (Eq. 7)",
        ),
        Material("cortical_bone", "elastic", dict(E=17000.0, nu=0.30), density=2.00, source="Paper Table 2",
                 strength=133.0,
                 strength_source="ultimate tensile strength of human femoral cortical bone, longitudinal "
                                 "(Reilly & Burstein 1975, J Biomech 8:393; compressive 193 MPa): the lower, "
                                 "tensile value, compared with von Mises"),
        Material("cancellous_bone", "elastic", dict(E=150.0, nu=0.20), density=2.00, source="Paper Table 2",
                 strength=0.93,
                 strength_source="tensile yield strain 0.62 % of human trabecular bone (Morgan & Keaveny "
                                 "2001, J Biomech 34:569; compressive 0.70 %) x this model's E = 150 MPa"),
        Material("needle", "elastic", dict(E=110000.0, nu=0.30), density=2.77,
                 source="Paper Table 2 (titanium alloy bone needle)",
                 strength=880.0,
                 strength_source="tensile yield (0.2 % proof) of annealed Ti-6Al-4V, Grade 5 (ASM Aerospace "
                                 "Specification Metals data sheet; ASTM F136 ELI implant grade: >= 795 MPa)"),
        Material("clamp", "elastic", dict(E=200000.0, nu=0.30), density=7.85,
                 source="Paper Table 2 (structural steel clamper)",
                 strength=250.0,
                 strength_source="tensile yield of structural steel (ANSYS Engineering Data 'Structural "
                                 "Steel', the paper's material library)"),
    )
}
_USER: dict[str, Material] = {}


def names() -> list[str]:
    return [*_BUILTIN, *_USER]


def get(name: str) -> Material:
    """A named material; unknown names raise InputError listing the known ones."""
    if isinstance(name, Material):
        return name
    try:
        return _USER.get(name) or _BUILTIN[name]
    except KeyError:
        raise InputError("material", f"unknown material {name!r}; known: {', '.join(names())}") from None


def tissue_bulk(materials: dict, ratio: float | None) -> dict:
    """{region: ratio * mu0} for the tissue (hyperelastic) regions of {region: material}; {} for ratio None.
    Pins K/mu0, e.g. TISSUE_BULK_RATIO for like-for-like comparisons with figures measured at 100 mu0."""
    if ratio is None:
        return {}
    check_number("tissue_bulk_ratio", ratio, ge=1, le=1e6)
    mats = {r: get(m) for r, m in materials.items()}
    return {r: ratio * m.initial_shear_modulus for r, m in mats.items() if m.model != "elastic"}


def register(material: Material) -> Material:
    _USER[material.name] = material
    return material


def load_toml(path: str | Path) -> list[Material]:
    """Register user materials from a TOML file of tables:

    [my_fat]
    model = "ogden"
    parameters = { mu = [0.001], alpha = [18.0] }
    density = 0.92
    source = "my lab"
    """
    path = Path(path)
    data = read_toml(path, field="materials TOML")
    out = []
    for name, table in data.items():
        if not isinstance(table, dict) or "model" not in table:
            raise InputError(f"{path}:{name}", "each material is a table with at least 'model' and 'parameters'")
        unknown = set(table) - {"model", "parameters", "density", "source", "bulk_modulus", "strength",
                                "strength_source"}
        if unknown:
            raise InputError(f"{path}:{name}", f"unknown fields {sorted(unknown)}")
        out.append(register(Material(name=name, **table)))
    return out
