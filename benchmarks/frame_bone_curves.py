"""What the FE says about the pin in the bone: a beam-on-Winkler fit of each configuration's pin axis below
the cortex (benchmarks/frame_sweep/fe_sweep_curves.json), the evidence behind the frame model's plate bone
law (docs/frame.md, "Bone: the plate law").

    PYTHONPATH=src python benchmarks/frame_bone_curves.py [--force 100]

For each configuration (needle 1, at the given force) the lateral axis displacement u(z) for z below the
cortex (-depth .. -cortex - 1 mm) is fitted by the free-tip solution of EI u'''' + k u = 0 (tip: u'' =
u''' = 0; two amplitudes and k by least squares, k scanned in log space). Printed: k (N/mm^2), k / E_s,
the fit's relative rms, and where the axis crosses zero (the pivot) against the cortex bottom.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
from scipy.optimize import minimize_scalar

HERE = Path(__file__).parent
E_PIN, E_CANCELLOUS = 110000.0, 150.0


def winkler_fit(z, u, depth, EI):
    """(k N/mm^2, relative rms) of the free-tip beam on a Winkler foundation through (z, u)."""
    x = z + depth  # from the tip

    def basis(beta):
        bx = beta * x
        B = np.stack([np.exp(bx) * np.cos(bx), np.exp(bx) * np.sin(bx), np.exp(-bx) * np.cos(bx),
                      np.exp(-bx) * np.sin(bx)], 1)
        b = beta  # u'' and u''' of the four functions at x = 0: the free tip's two conditions
        C = np.array([[0.0, 2 * b * b, 0.0, -2 * b * b], [-2 * b**3, 2 * b**3, 2 * b**3, 2 * b**3]])
        return B @ np.linalg.svd(C)[2][2:].T

    def ssr(lb):
        Bm = basis(math.exp(lb))
        c, *_ = np.linalg.lstsq(Bm, u, rcond=None)
        return float(np.sum((Bm @ c - u) ** 2))

    r = minimize_scalar(ssr, bounds=(math.log(0.01), math.log(1.0)), method="bounded")
    return 4 * EI * math.exp(r.x) ** 4, math.sqrt(r.fun / len(u)) / np.abs(u).max()


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--force", type=float, default=100.0)
    a = p.parse_args(argv)
    curves = json.loads((HERE / "frame_sweep" / "fe_sweep_curves.json").read_text())
    recs = {(r["config_id"], r["force_N"]): r for r in
            json.loads((HERE / "frame_sweep" / "fe_sweep.json").read_text())["results"]}
    print("config  d mm  depth  cortex  k N/mm^2  k/E_s  rel rms  pivot z mm")
    for e in curves:
        if e["force_N"] != a.force:
            continue
        rec = recs[(e["config_id"], e["force_N"])]
        d, h, tc = rec["diameter_mm"], rec["depth_mm"], rec["cortical_thickness_mm"]
        z = np.array(e["curves"]["needle_1"]["z_mm"])
        U = np.array(e["curves"]["needle_1"]["displacement_mm"])
        below = z < -tc - 1.0
        direction = np.linalg.svd(U[below][:, :2])[2][0]  # the plane the pin bends in
        u_all = U[:, :2] @ direction
        k, rel = winkler_fit(z[below], u_all[below], h, E_PIN * math.pi * d**4 / 64)
        s = np.flatnonzero(np.diff(np.sign(u_all[z < 0])))  # the pivot: where the axis crosses zero
        zp = float(np.interp(0.0, u_all[s[-1]: s[-1] + 2], z[s[-1]: s[-1] + 2])) if s.size else float("nan")
        if u_all[s[-1]] > u_all[s[-1] + 1] if s.size else False:
            zp = float(np.interp(0.0, u_all[s[-1]: s[-1] + 2][::-1], z[s[-1]: s[-1] + 2][::-1]))
        print(f"{e['config_id']:6s} {d:5.2f} {h:6.1f} {tc:6.2f} {k:9.0f} {k / E_CANCELLOUS:6.2f} {rel:8.4f} "
              f"{zp:7.2f} (cortex bottom {-tc:.2f})")


if __name__ == "__main__":
    main()
