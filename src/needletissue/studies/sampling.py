"""Case tables from a study config: grid, Monte Carlo, Latin hypercube, Saltelli (Sobol) designs.

Every method draws uniforms in [0, 1)^d with a fixed seed and maps them through each parameter's
inverse CDF (scipy.stats), so one seed gives one case table on any machine.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pandas as pd
from scipy import stats
from scipy.stats import qmc

from needletissue.studies.config import ParameterSpec, StudyConfig


def frozen_distribution(p: ParameterSpec):
    """The scipy.stats frozen distribution of a parameter."""
    match p.distribution:
        case "uniform":
            return stats.uniform(loc=p.low, scale=p.high - p.low)
        case "normal":
            return stats.norm(loc=p.mean, scale=p.std)
        case "truncnorm":
            a, b = (p.low - p.mean) / p.std, (p.high - p.mean) / p.std
            return stats.truncnorm(a, b, loc=p.mean, scale=p.std)
        case "lognormal":
            return stats.lognorm(s=p.sigma, scale=p.median)
    raise AssertionError(p.distribution)


def _map(cfg: StudyConfig, u: np.ndarray) -> dict[str, np.ndarray]:
    # Keep u strictly inside (0, 1): the ppf of unbounded laws is infinite at the ends.
    u = np.clip(u, 1e-12, 1 - 1e-12)
    return {name: frozen_distribution(p).ppf(u[:, j]) for j, (name, p) in enumerate(cfg.parameters.items())}


def design(cfg: StudyConfig) -> pd.DataFrame:
    """All cases of the study: a DataFrame with ``case_id`` and one column per varied parameter.

    For ``sobol`` a column ``block`` says which Saltelli matrix a row belongs to (A, B or AB<j>).
    """
    s = cfg.study
    names = list(cfg.parameters)
    d = len(names)
    if s.method == "grid":
        rows = list(itertools.product(*(cfg.parameters[n].values for n in names)))
        cols = {n: np.array([r[j] for r in rows], dtype=float) for j, n in enumerate(names)}
        df = pd.DataFrame(cols)
    elif s.method == "monte_carlo":
        u = np.random.default_rng(s.seed).random((s.samples, d))
        df = pd.DataFrame(_map(cfg, u))
    elif s.method == "latin_hypercube":
        u = qmc.LatinHypercube(d=d, seed=s.seed).random(s.samples)
        df = pd.DataFrame(_map(cfg, u))
    elif s.method == "sobol":
        df = _saltelli(cfg, names)
    else:
        raise AssertionError(s.method)
    df.insert(0, "case_id", np.arange(len(df), dtype=np.int64))
    return df


def _saltelli(cfg: StudyConfig, names: list[str]) -> pd.DataFrame:
    """A, B from one scrambled Sobol' sequence in 2d dimensions, then AB_j = A with column j from B,
    the layout scipy.stats.sobol_indices expects for f_A, f_B, f_AB."""
    n, d = cfg.study.samples, len(names)
    m = math.ceil(math.log2(n))
    u = qmc.Sobol(d=2 * d, scramble=True, seed=cfg.study.seed).random_base2(m)[:n]
    A, B = u[:, :d], u[:, d:]
    blocks = [("A", A), ("B", B)]
    for j in range(d):
        AB = A.copy()
        AB[:, j] = B[:, j]
        blocks.append((f"AB{j}", AB))
    frames = []
    for label, U in blocks:
        f = pd.DataFrame(_map(cfg, U))
        f.insert(0, "block", label)
        frames.append(f)
    return pd.concat(frames, ignore_index=True)
