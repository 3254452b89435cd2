"""Hyperelastic and elastic materials of the needle-tissue-bone model (MPa, g/cm^3)."""

from needletissue.materials.laws import mooney_rivlin_5
from needletissue.materials.registry import (
    HYPERELASTIC_MODELS, MODELS, TISSUE_BULK_RATIO, Material, get, load_toml, names, register,
)

__all__ = [
    "HYPERELASTIC_MODELS", "MODELS", "TISSUE_BULK_RATIO", "Material", "get", "load_toml", "names",
    "register", "mooney_rivlin_5",
]
