"""needletissue: bone needles (Schanz pins) and pelvic soft tissue deforming together.

Units everywhere: mm, N, MPa (= N/mm^2), s; densities in t/mm^3 internally, g/cm^3 in tables.
"""

__version__ = "0.1.0"
