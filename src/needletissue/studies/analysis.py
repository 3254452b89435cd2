"""Distributions and sensitivity indices of study outputs.

Sensitivity:
- Standardized regression coefficients (SRC) for every sampled study (Monte Carlo, Latin hypercube,
  grid): the least-squares fit y ~ b0 + sum b_j x_j, then SRC_j = b_j std(x_j) / std(y). For a model
  close to linear (R^2 near 1, reported) SRC_j^2 is the share of the variance due to x_j. Cheap, and
  correct only as far as R^2 says.
- Sobol first-order and total indices for the ``sobol`` method (Saltelli design), computed by
  scipy.stats.sobol_indices (Saltelli 2010 first order, Jansen total) with bootstrap 95 % intervals.
  Valid for any nonlinearity. 95 % intervals: percentile bootstrap over the base samples.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

PERCENTILES = (2.5, 5, 25, 50, 75, 95, 97.5)


def statistics(results: pd.DataFrame, outputs: list[str]) -> dict:
    """Mean, std, min, max and percentiles of each output over the successful cases."""
    ok = results[results["status"] == "ok"]
    out = {}
    for o in outputs:
        y = ok[o].to_numpy(dtype=float)
        y = y[np.isfinite(y)]
        if y.size == 0:
            out[o] = {"n": 0}
            continue
        q = np.percentile(y, PERCENTILES)
        out[o] = {"n": int(y.size), "mean": float(y.mean()), "std": float(y.std(ddof=1)) if y.size > 1 else 0.0,
                  "min": float(y.min()), "max": float(y.max()),
                  **{f"p{p:g}": float(v) for p, v in zip(PERCENTILES, q)}}
    return out


def src(results: pd.DataFrame, params: list[str], outputs: list[str]) -> dict:
    """Standardized regression coefficients and R^2 per output (successful cases only)."""
    ok = results[results["status"] == "ok"]
    X = ok[params].to_numpy(dtype=float)
    sx = X.std(axis=0, ddof=1) if len(X) > 1 else np.zeros(len(params))
    varied = sx > 0
    out = {}
    for o in outputs:
        y = ok[o].to_numpy(dtype=float)
        keep = np.isfinite(y)
        if keep.sum() <= varied.sum() + 1:
            out[o] = {"method": "SRC", "indices": {}, "r2": None}
            continue
        Xv, yv = X[keep][:, varied], y[keep]
        A = np.column_stack([np.ones(len(yv)), Xv])
        coef, *_ = np.linalg.lstsq(A, yv, rcond=None)
        sy = yv.std(ddof=1)
        resid = yv - A @ coef
        r2 = 1.0 - float(resid @ resid) / float(((yv - yv.mean()) ** 2).sum()) if sy > 0 else None
        idx = dict.fromkeys(params, 0.0)
        for name, b, s in zip(np.asarray(params)[varied], coef[1:], sx[varied]):
            idx[str(name)] = float(b * s / sy) if sy > 0 else 0.0
        out[o] = {"method": "SRC", "indices": idx, "r2": r2}
    return out


def sobol(results: pd.DataFrame, params: list[str], outputs: list[str], seed: int) -> dict:
    """Sobol first-order and total indices from a Saltelli design (column 'block': A, B, AB<j>)."""
    from scipy.stats import sobol_indices

    d = len(params)
    blocks = {b: g.sort_values("case_id") for b, g in results.groupby("block")}
    n = len(blocks["A"])
    out = {}
    for o in outputs:
        fA = blocks["A"][o].to_numpy(float)
        fB = blocks["B"][o].to_numpy(float)
        fAB = np.stack([blocks[f"AB{j}"][o].to_numpy(float) for j in range(d)])
        # A failed case removes its sample index from every matrix (still a valid Saltelli design).
        keep = np.isfinite(fA) & np.isfinite(fB) & np.isfinite(fAB).all(axis=0)
        if keep.sum() < 4 or np.var(np.concatenate([fA[keep], fB[keep]])) == 0:
            out[o] = {"method": "Sobol (Saltelli)", "first_order": {}, "total": {}, "n_base": int(keep.sum())}
            continue
        fa, fb, fab = fA[keep][None], fB[keep][None], fAB[:, keep][:, None]
        res = sobol_indices(func={"f_A": fa, "f_B": fb, "f_AB": fab}, n=fa.shape[1])
        # Percentile bootstrap over sample rows (scipy's own .bootstrap is BCa and ~100x slower).
        rng = np.random.default_rng(seed)
        boot_s1, boot_st = [], []
        for _ in range(200):
            i = rng.integers(0, fa.shape[1], fa.shape[1])
            r = sobol_indices(func={"f_A": fa[:, i], "f_B": fb[:, i], "f_AB": fab[:, :, i]}, n=len(i))
            boot_s1.append(r.first_order.ravel())
            boot_st.append(r.total_order.ravel())
        lo1, hi1 = np.percentile(boot_s1, [2.5, 97.5], axis=0)
        lot, hit = np.percentile(boot_st, [2.5, 97.5], axis=0)
        out[o] = {
            "method": "Sobol (Saltelli 2010 first order, Jansen total; scipy.stats.sobol_indices), "
                      "95 % percentile bootstrap",
            "n_base": int(keep.sum()), "n_base_requested": n,
            "first_order": {p: float(v) for p, v in zip(params, res.first_order.ravel())},
            "total": {p: float(v) for p, v in zip(params, res.total_order.ravel())},
            "first_order_ci95": {p: [float(a), float(b)] for p, a, b in zip(params, lo1, hi1)},
            "total_ci95": {p: [float(a), float(b)] for p, a, b in zip(params, lot, hit)},
        }
    return out
