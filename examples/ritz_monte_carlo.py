"""Monte Carlo of the needle tip deflection at 300 N over uncertain pin, length and tissue: one call.

    python examples/ritz_monte_carlo.py [N_SAMPLES]      (default 1,000,000)

Samples d ~ U(5, 6) mm, l ~ N(84, 5) mm (>= 40), E ~ N(110, 5) GPa, muscle/adipose thickness from the
paper's 31.82 +- 5.43 mm total soft tissue (split 22:10), k lognormal around Table 1 (30 %).
Prints the wall time, the deflection quantiles and how many answers met the error tolerance.
"""

import sys
import time

import numpy as np

from needletissue import ritz

n = int(sys.argv[1]) if len(sys.argv) > 1 else 1_000_000
rng = np.random.default_rng(0)
d = rng.uniform(5.0, 6.0, n)
l = np.maximum(rng.normal(84.0, 5.0, n), 40.0)
E = rng.normal(110_000.0, 5_000.0, n)
total = np.clip(rng.normal(31.82, 5.43, n), 10.0, 39.0)
T = total[:, None] * np.array([22.0, 10.0]) / 32.0
K = np.array([0.048, 0.023]) * rng.lognormal(0.0, 0.3, (n, 2))
t0 = time.perf_counter()
cpu0 = time.process_time()
b = ritz.solve_batch(np.full(n, 300.0), diameter_mm=d, free_length_mm=l, youngs_modulus_MPa=E,
                     thickness_mm=T, k_N_per_mm2=K)
wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
q = np.percentile(b.tip_deflection_mm, [2.5, 50, 97.5])
print(f"{n:,} samples in {wall:.1f} s wall ({cpu:.1f} s CPU); tip deflection at 300 N: median {q[1]:.2f} mm, "
      f"95 % interval [{q[0]:.2f}, {q[2]:.2f}] mm; error estimate max {b.error_estimate_mm.max():.2g} mm, "
      f"{b.converged.mean():.1%} within {ritz.DEFAULT_TOL_MM} mm")
