"""Write a synthetic uniaxial data set for `needletissue materials fit`: the paper's adipose Ogden law
(mu = 1.1667e-3 MPa, alpha = 16.2) at 25 stretches from 1.0 to 1.4, plus 2 % Gaussian noise (seed 0).
Not measured data: it exists to show the fitting workflow on a curve of known origin.

    python examples/materials/make_adipose_csv.py examples/materials/adipose_uniaxial_synthetic.csv
"""

import sys

import numpy as np

from needletissue.materials import closed_form as cf

lam = np.linspace(1.0, 1.4, 25)
P = cf.nominal_stress("ogden", {"mu": [1.1667e-3], "alpha": [16.2]}, "uniaxial", lam)
P = P * (1 + 0.02 * np.random.default_rng(0).standard_normal(lam.size))
lines = ["# synthetic: paper's adipose Ogden law + 2 % noise (examples/materials/make_adipose_csv.py)",
         "stretch,nominal_stress_MPa"] + [f"{a:.4f},{b:.6e}" for a, b in zip(lam, P)]
open(sys.argv[1], "w").write("\n".join(lines) + "\n")
