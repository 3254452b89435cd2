"""The reference paper's published numbers: the reference column of the report's comparison table.

Source: "Study on the interactive deformation of bone needles and circum-pelvic soft tissue"
(docs: ../shared/reference/paper.md). Each value carries where it is printed.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class PaperValue:
    value: float
    unit: str
    source: str


PAPER = {
    "ritz_tip_deflection_300N_mm": PaperValue(17.63, "mm", "Sec. 2.3 and Conclusion (1): Ritz, 300 N"),
    "ritz_increase_300_vs_100N_percent": PaperValue(
        250.08, "%", "Sec. 2.3: 300 N deflection 'increased by 250.08 %' over 100 N"),
    "fe_max_needle_deformation_100N_mm": PaperValue(5.8152, "mm", "Sec. 3.3: FE, 100 N"),
    "fe_max_needle_deformation_200N_mm": PaperValue(10.8990, "mm", "Sec. 3.3: FE, 200 N"),
    "fe_max_needle_deformation_300N_mm": PaperValue(18.0620, "mm", "Sec. 3.3: FE, 300 N"),
    "theory_fe_difference_300N_mm": PaperValue(0.432, "mm", "Abstract, Sec. 3.3, Conclusion (3): 300 N"),
    "adipose_max_deformation_300N_mm": PaperValue(7.45, "mm", "Conclusion (2): anatomical FE, 300 N"),
    "traction_rmse_muscle_MPa": PaperValue(0.0131, "MPa", "Sec. 3.2, Eq. (16): iliacus muscle"),
    "traction_rmse_adipose_MPa": PaperValue(0.0105, "MPa", "Sec. 3.2, Eq. (16): adipose"),
    "soft_tissue_thickness_mean_mm": PaperValue(31.82, "mm", "Sec. 2.3: 10 patients (Song, its Ref. [15])"),
    "soft_tissue_thickness_std_mm": PaperValue(5.43, "mm", "Sec. 2.3: 10 patients (Song, its Ref. [15])"),
}

# Sec. 3.3: "adipose tissue > iliacus muscle > gluteus medius > gluteus maximus" (300 N).
PAPER_RANKING = ("adipose", "iliacus", "gluteus_medius", "gluteus_maximus")


def fe_key(force: float) -> str | None:
    key = f"fe_max_needle_deformation_{force:g}N_mm"
    return key if key in PAPER else None
