"""Is the elastic model still valid? The FE's von Mises stress per region against the strength of its
material (`needletissue.materials` registry: `Material.strength`, MPa, with its source).

The FE models are elastic (Neo-Hooke from E, nu): past the needle's yield the pin would bend for good
and past the bone's strength the bone around it would crush or crack, neither of which the model
represents. Every FE result reports the ratios and a warning where one exceeds 1 (issue 14, item 6).

Stress measure: the cell's von Mises Cauchy stress averaged over its quadrature points (`FEResult
cell_data["von_mises_MPa"]`), maximum over the region's cells. Bone is compared with its tensile
strength, the lower of tension and compression, so the check errs towards a warning.
"""

from __future__ import annotations

import math

import numpy as np

from needletissue import materials


def strength_check(fe_result, region_materials: dict[str, str]) -> dict:
    """Max von Mises (MPa) per region, utilisation = max stress / strength per region whose material
    has a strength, the needle's yield utilisation (max over the needle regions), the bone's (max over
    regions whose material name ends in "bone") and a warning text per utilisation > 1.

    Empty when the result carries no stresses (solve(..., results=False))."""
    vm = fe_result.cell_data.get("von_mises_MPa")
    if vm is None:
        return {}
    tags = fe_result.cell_data["region"]
    max_vm, util, strength = {}, {}, {}
    for region, i in fe_result.region_tags.items():
        cells = tags == i
        if not cells.any():
            continue
        s = float(np.max(vm[cells]))
        max_vm[region] = s
        mat = materials.get(region_materials.get(region, region))
        if mat.strength is not None:
            strength[region] = float(mat.strength)
            util[region] = s / mat.strength

    def worst(pred):
        vals = [u for r, u in util.items() if pred(region_materials.get(r, r))]
        return max(vals) if vals else math.nan

    needle = worst(lambda m: m == "needle")
    bone = worst(lambda m: m.endswith("bone"))
    warnings = [f"{r}: von Mises {max_vm[r]:.0f} MPa exceeds its strength {strength[r]:g} MPa "
                f"(utilisation {u:.2f}): the elastic model is not valid there"
                for r, u in util.items() if u > 1]
    return {"max_von_mises_MPa": max_vm, "strength_MPa": strength, "strength_utilisation": util,
            "needle_yield_utilisation": needle, "bone_strength_utilisation": bone,
            "validity_warnings": warnings}
