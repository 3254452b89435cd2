"""Hyperelastic and elastic materials of the needle-tissue-bone model (MPa, g/cm^3).

- registry: named materials and their FElupe constitutive models (`get`, `load_toml`, `Material.umat`)
- closed_form: incompressible uniaxial / equibiaxial / planar nominal stress, independent of FElupe
- stability: Drucker stability, stable stretch ranges, UnstableMaterialWarning
- fitting: least-squares fits to CSV stretch-stress data
- curves, plot: curves of named materials; `plot.plot_curves` draws the muscle and adipose uniaxial
  curves with the Drucker-stable range shaded (docs/img/materials_uniaxial.png)
"""

from needletissue.materials.laws import mooney_rivlin_5
from needletissue.materials.registry import (
    HYPERELASTIC_MODELS, MODELS, TISSUE_BULK_MODULUS, TISSUE_BULK_RATIO, Material, get, load_toml, names,
    register, tissue_bulk,
)
from needletissue.materials.stability import UnstableMaterialWarning

__all__ = [
    "HYPERELASTIC_MODELS", "MODELS", "TISSUE_BULK_MODULUS", "TISSUE_BULK_RATIO", "Material", "get",
    "load_toml", "names", "register", "tissue_bulk", "mooney_rivlin_5", "UnstableMaterialWarning",
]
