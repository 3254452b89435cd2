"""Least-squares fits of incompressible hyperelastic laws to stretch / nominal-stress data.

Invariant laws (Neo-Hooke, Mooney-Rivlin 2 and 5, Yeoh) are linear in their parameters: an exact
linear least-squares solve on the closed forms, no start values. Ogden (N terms, 2 mu / alpha^2) is
linear in mu for fixed alpha: variable projection over alpha (scipy least_squares from a grid of
starts), then a joint polish of (mu, alpha).
"""

from __future__ import annotations

import csv
import itertools
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from needletissue.errors import InputError
from needletissue.materials import closed_form as cf
from needletissue.materials import stability

# fit name -> (law, number of Ogden terms or None)
FIT_MODELS = {
    "neo_hooke": ("neo_hooke", None),
    "mooney_rivlin": ("mooney_rivlin", None),
    "mooney_rivlin_5": ("mooney_rivlin_5", None),
    "yeoh": ("yeoh", None),
    "ogden": ("ogden", 1),
    "ogden2": ("ogden", 2),
    "ogden3": ("ogden", 3),
}
STRETCH_COLUMN = "stretch"
STRESS_COLUMNS = ("nominal_stress_MPa", "nominal_stress", "stress_MPa", "stress")
_ALPHA_STARTS = {1: (-8.0, -4.0, -2.0, 1.0, 2.0, 4.0, 8.0, 16.0, 24.0),
                 2: (-6.0, -2.0, 1.0, 2.0, 4.0, 8.0, 16.0, 24.0),
                 3: (-4.0, -2.0, 2.0, 4.0, 8.0, 16.0)}


@dataclass(frozen=True)
class StressData:
    """Measured nominal stress (MPa) at stretches of one incompressible load case."""

    stretch: np.ndarray
    nominal_stress_MPa: np.ndarray
    source: str = ""


@dataclass(frozen=True)
class FitResult:
    model: str  # the fit name, e.g. "ogden2"
    law: str  # the strain-energy law in the registry's terms, e.g. "ogden"
    mode: str
    parameters: dict
    rmse_MPa: float
    r2: float
    n_points: int
    stable_range: tuple[float, float]
    data_stretch_range: tuple[float, float]
    warnings: list = field(default_factory=list)

    def predict(self, stretch) -> np.ndarray:
        return cf.nominal_stress(self.law, self.parameters, self.mode, stretch)

    def to_json(self) -> dict:
        return {
            "model": self.model, "law": self.law, "mode": self.mode, "parameters": self.parameters,
            "rmse_MPa": self.rmse_MPa, "r2": self.r2, "n_points": self.n_points,
            "stable_range": list(self.stable_range), "data_stretch_range": list(self.data_stretch_range),
            "initial_shear_modulus_MPa": cf.initial_shear_modulus(self.law, self.parameters),
            "warnings": list(self.warnings),
        }


def fit_model(name: str) -> tuple[str, int | None]:
    try:
        return FIT_MODELS[name]
    except KeyError:
        raise InputError("model", f"unknown model {name!r}; known: {', '.join(FIT_MODELS)}") from None


def n_parameters(name: str) -> int:
    law, terms = fit_model(name)
    return 2 * terms if terms else len(cf.PARAMETERS[law])


def read_csv(path: str | Path) -> StressData:
    """Read a CSV with a header naming `stretch` and `nominal_stress_MPa` (lines starting with # skipped).

    Every problem raises InputError naming the file, the line and the field.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(str(path), f"cannot read the data file: {exc}") from None
    rows = [(i, r) for i, r in enumerate(csv.reader(text.splitlines()), start=1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputError(f"{path}", "empty file; expected a header 'stretch,nominal_stress_MPa' and data rows")
    header_line, header = rows[0]
    names = [h.strip().lower() for h in header]
    if STRETCH_COLUMN not in names:
        raise InputError(f"{path}, line {header_line}, field {STRETCH_COLUMN}",
                         f"missing column {STRETCH_COLUMN!r}; header is {header}")
    stress_col = next((c for c in STRESS_COLUMNS if c.lower() in names), None)
    if stress_col is None:
        raise InputError(f"{path}, line {header_line}, field {STRESS_COLUMNS[0]}",
                         f"missing column {STRESS_COLUMNS[0]!r} (nominal stress in MPa); header is {header}")
    cols = {STRETCH_COLUMN: names.index(STRETCH_COLUMN), stress_col: names.index(stress_col.lower())}
    values = {STRETCH_COLUMN: [], stress_col: []}
    for line, row in rows[1:]:
        for col, j in cols.items():
            where = f"{path}, line {line}, field {col}"
            if j >= len(row) or not row[j].strip():
                raise InputError(where, "missing value")
            try:
                v = float(row[j])
            except ValueError:
                raise InputError(where, f"expected a number, got {row[j].strip()!r}") from None
            if not np.isfinite(v):
                raise InputError(where, f"must be finite, got {row[j].strip()}")
            if col == STRETCH_COLUMN and v <= 0:
                raise InputError(where, f"stretch must be > 0, got {v}")
            values[col].append(v)
    return StressData(np.array(values[STRETCH_COLUMN]), np.array(values[stress_col]), str(path))


def _linear_fit(law, mode, lam, y):
    names = cf.PARAMETERS[law]
    A = np.stack([cf.nominal_stress(law, {n: float(n == k) for n in names}, mode, lam) for k in names], axis=1)
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1
    sv = np.linalg.svd(A / scale, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        # e.g. planar tension has I1 = I2: only C10 + C01 (and C20 + C11 + C02) are determined.
        raise InputError("model", f"{mode} data cannot determine all parameters of {law} "
                         f"({', '.join(names)}); fit uniaxial or biaxial data, or a law with fewer parameters")
    x = np.linalg.lstsq(A / scale, y, rcond=None)[0] / scale
    return {n: float(v) for n, v in zip(names, x)}


def _ogden_basis(mode, lam, alpha):
    return np.stack([cf.nominal_stress("ogden", {"mu": [1.0], "alpha": [a]}, mode, lam) for a in alpha], axis=1)


def _ogden_fit(terms, mode, lam, y):
    def projected(alpha):
        A = _ogden_basis(mode, lam, alpha)
        mu = np.linalg.lstsq(A, y, rcond=None)[0]
        return A @ mu - y, mu

    best = None
    exact = 1e-24 * float(np.sum(y**2))  # the data are reproduced to round-off: stop searching
    for start in itertools.combinations(_ALPHA_STARTS[terms], terms):
        if best is not None and best.cost <= exact:
            break
        try:
            res = least_squares(lambda a: projected(a)[0], np.array(start), method="lm", xtol=1e-12, ftol=1e-12,
                                max_nfev=200 * terms)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(res.fun)) and (best is None or res.cost < best.cost):
            best = res
    if best is None:
        raise InputError("model", f"no Ogden {terms}-term fit converged on these data")
    alpha = best.x
    mu = projected(alpha)[1]

    def full(x):
        return cf.nominal_stress("ogden", {"mu": x[:terms], "alpha": x[terms:]}, mode, lam) - y

    x = np.concatenate([mu, alpha])
    try:
        polish = least_squares(full, x, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        if np.all(np.isfinite(polish.fun)) and polish.cost <= 0.5 * np.sum(projected(alpha)[0] ** 2):
            x = polish.x
    except (ValueError, np.linalg.LinAlgError):
        pass  # keep the projected solution
    if mode == "planar":
        # (lambda, 1, 1/lambda): the terms (mu, alpha) and (mu, -alpha) give the same stress
        x = np.concatenate([x[:terms], np.abs(x[terms:])])
    order = np.argsort(x[terms:])
    return {"mu": [float(v) for v in x[:terms][order]], "alpha": [float(v) for v in x[terms:][order]]}


def fit(data: StressData, model: str, mode: str = "uniaxial") -> FitResult:
    """Fit `model` (one of FIT_MODELS) to the data; warns when the fit is unstable in the data's range."""
    law, terms = fit_model(model)
    cf.check_mode(mode)
    lam, y = np.asarray(data.stretch, float), np.asarray(data.nominal_stress_MPa, float)
    where = data.source or "data"
    k = n_parameters(model)
    if lam.size < k:
        raise InputError(f"{where}, rows", f"{lam.size} data points for {k} parameters of {model}; "
                         f"need at least {k}")
    if np.unique(lam).size < k:
        raise InputError(f"{where}, field stretch", f"only {np.unique(lam).size} distinct stretches for {k} "
                         f"parameters of {model}")
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # trial alphas may overflow
        params = _linear_fit(law, mode, lam, y) if terms is None else _ogden_fit(terms, mode, lam, y)
    pred = cf.nominal_stress(law, params, mode, lam)
    rmse = float(np.sqrt(np.mean((pred - y) ** 2)))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = float(1 - np.sum((pred - y) ** 2) / ss_tot) if ss_tot > 0 else float("nan")
    data_range = (float(lam.min()), float(lam.max()))
    notes = []
    mu0 = cf.initial_shear_modulus(law, params)
    if mu0 <= 0:
        notes.append(f"fitted initial shear modulus {mu0:.4g} MPa is not positive: the law is unstable at stretch 1")
        rng = (1.0, 1.0)
    else:
        rng = stability.stable_range(law, params, mode)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", stability.UnstableMaterialWarning)
            stability.warn_if_unstable(f"fitted {model}", law, params, mode, lam, rng)
        notes += [str(w.message) for w in caught]
    for n in notes:
        warnings.warn(n, stability.UnstableMaterialWarning, stacklevel=2)
    return FitResult(model, law, mode, params, rmse, r2, int(lam.size), rng, data_range, notes)
