"""Closed-form incompressible homogeneous load cases, written independently of FElupe.

All laws are isotropic and incompressible here (lambda1 lambda2 lambda3 = 1). With the log strains
e_i = ln(lambda_i), the principal Cauchy stresses are sigma_i = dW/de_i - p. The three load cases
have a traction-free direction 3, so p is eliminated and the nominal (1st Piola) stress in
direction 1 is

    P = (dW/de_1 - dW/de_3) / lambda1,

uniaxial:  (lambda, lambda^-1/2, lambda^-1/2)
biaxial:   (lambda, lambda, lambda^-2)          (equibiaxial; P is the stress in either in-plane axis)
planar:    (lambda, 1, lambda^-1)               (pure shear; the 2-direction is held at stretch 1)

Invariant laws: dW/de_i = 2 lambda_i^2 W1 + 2 lambda_i^2 (I1 - lambda_i^2) W2 with W1 = dW/dI1,
W2 = dW/dI2, which for these load cases gives P = 2 (l1^2 - l3^2) (W1 + l2^2 W2) / l1.
Ogden (2 mu / alpha^2 convention, Eq. 7 of the paper): dW/de_i = sum 2 mu / alpha lambda_i^alpha.
Stresses in MPa when the parameters are in MPa.
"""

from __future__ import annotations

import numpy as np

from needletissue.errors import InputError

MODES = ("uniaxial", "biaxial", "planar")

# Parameter names per law, in the order used by fitting. Ogden takes lists mu, alpha (N terms).
PARAMETERS = {
    "neo_hooke": ("mu",),
    "mooney_rivlin": ("C10", "C01"),
    "mooney_rivlin_5": ("C10", "C01", "C20", "C11", "C02"),
    "yeoh": ("C10", "C20", "C30"),
    "ogden": ("mu", "alpha"),
}


def check_mode(mode: str) -> str:
    if mode not in MODES:
        raise InputError("mode", f"unknown load case {mode!r}; known: {', '.join(MODES)}")
    return mode


def principal_stretches(mode: str, stretch) -> np.ndarray:
    """Principal stretches (3, n) of the incompressible load case at the given stretch(es)."""
    check_mode(mode)
    lam = np.atleast_1d(np.asarray(stretch, dtype=float))
    if np.any(~np.isfinite(lam)) or np.any(lam <= 0):
        raise InputError("stretch", "every stretch must be finite and > 0")
    if mode == "uniaxial":
        return np.stack([lam, lam**-0.5, lam**-0.5])
    if mode == "biaxial":
        return np.stack([lam, lam, lam**-2])
    return np.stack([lam, np.ones_like(lam), 1 / lam])


def _invariant_derivatives(model, p, a, b):
    """(W1, W2, W11, W12, W22) of an invariant law at a = I1 - 3, b = I2 - 3."""
    zero = np.zeros_like(a)
    match model:
        case "neo_hooke":
            return p["mu"] / 2 + zero, zero, zero, zero, zero
        case "mooney_rivlin":
            return p["C10"] + zero, p["C01"] + zero, zero, zero, zero
        case "mooney_rivlin_5":
            C10, C01, C20, C11, C02 = (p[k] for k in PARAMETERS[model])
            return (C10 + 2 * C20 * a + C11 * b, C01 + C11 * a + 2 * C02 * b,
                    2 * C20 + zero, C11 + zero, 2 * C02 + zero)
        case "yeoh":
            C10, C20, C30 = (p[k] for k in PARAMETERS[model])
            return C10 + 2 * C20 * a + 3 * C30 * a**2, zero, 2 * C20 + 6 * C30 * a, zero, zero
    raise InputError("model", f"unknown model {model!r}; known: {', '.join(PARAMETERS)}")


def _ogden_terms(p):
    mu = np.atleast_1d(np.asarray(p["mu"], dtype=float))
    alpha = np.atleast_1d(np.asarray(p["alpha"], dtype=float))
    if mu.shape != alpha.shape:
        raise InputError("ogden.parameters", f"mu and alpha need the same length, got {mu.size} and {alpha.size}")
    if np.any(alpha == 0):
        raise InputError("ogden.alpha", "every alpha must be non-zero")
    return mu, alpha


def _invariants(lam):
    l2 = lam**2
    I1 = l2.sum(0)
    I2 = l2[0] * l2[1] + l2[1] * l2[2] + l2[2] * l2[0]
    return l2, I1, I2


def energy(model: str, p: dict, lam: np.ndarray) -> np.ndarray:
    """Strain energy density W (MPa) at incompressible principal stretches lam (3, n)."""
    if model == "ogden":
        mu, alpha = _ogden_terms(p)
        return sum(2 * m / a**2 * ((lam**a).sum(0) - 3) for m, a in zip(mu, alpha))
    _, I1, I2 = _invariants(lam)
    a, b = I1 - 3, I2 - 3
    match model:
        case "neo_hooke":
            return p["mu"] / 2 * a
        case "mooney_rivlin":
            return p["C10"] * a + p["C01"] * b
        case "mooney_rivlin_5":
            return p["C10"] * a + p["C01"] * b + p["C20"] * a**2 + p["C11"] * a * b + p["C02"] * b**2
        case "yeoh":
            return p["C10"] * a + p["C20"] * a**2 + p["C30"] * a**3
    raise InputError("model", f"unknown model {model!r}; known: {', '.join(PARAMETERS)}")


def log_gradient(model: str, p: dict, lam: np.ndarray) -> np.ndarray:
    """dW/de_i (3, n): principal Cauchy stresses up to the pressure."""
    if model == "ogden":
        mu, alpha = _ogden_terms(p)
        return sum(2 * m / a * lam**a for m, a in zip(mu, alpha))
    l2, I1, I2 = _invariants(lam)
    W1, W2, *_ = _invariant_derivatives(model, p, I1 - 3, I2 - 3)
    return 2 * l2 * W1 + 2 * l2 * (I1 - l2) * W2


def log_hessian(model: str, p: dict, lam: np.ndarray) -> np.ndarray:
    """d2W/de_i de_j (3, 3, n), W taken as a function of three independent log strains."""
    n = lam.shape[1]
    if model == "ogden":
        mu, alpha = _ogden_terms(p)
        diag = sum(2 * m * lam**a for m, a in zip(mu, alpha))
        H = np.zeros((3, 3, n))
        H[[0, 1, 2], [0, 1, 2]] = diag
        return H
    l2, I1, I2 = _invariants(lam)
    W1, W2, W11, W12, W22 = _invariant_derivatives(model, p, I1 - 3, I2 - 3)
    dI1 = 2 * l2
    dI2 = 2 * l2 * (I1 - l2)
    d2I1 = np.zeros((3, 3, n))
    d2I1[[0, 1, 2], [0, 1, 2]] = 4 * l2
    d2I2 = 4 * l2[:, None] * l2[None, :]
    d2I2[[0, 1, 2], [0, 1, 2]] = 4 * l2 * (I1 - l2)
    outer = lambda x, y: x[:, None] * y[None, :]  # noqa: E731
    return (W1 * d2I1 + W2 * d2I2 + W11 * outer(dI1, dI1)
            + W12 * (outer(dI1, dI2) + outer(dI2, dI1)) + W22 * outer(dI2, dI2))


def nominal_stress(model: str, parameters: dict, mode: str, stretch) -> np.ndarray:
    """Nominal (1st Piola) stress in MPa in the loaded direction, incompressible, closed form."""
    lam = principal_stretches(mode, stretch)
    g = log_gradient(model, parameters, lam)
    return (g[0] - g[2]) / lam[0]


def initial_shear_modulus(model: str, p: dict) -> float:
    """mu0 = small-strain shear modulus (MPa)."""
    match model:
        case "neo_hooke":
            return float(p["mu"])
        case "mooney_rivlin" | "mooney_rivlin_5":
            return 2 * (p["C10"] + p["C01"])
        case "yeoh":
            return 2 * p["C10"]
        case "ogden":
            return float(np.sum(_ogden_terms(p)[0]))
    raise InputError("model", f"unknown model {model!r}; known: {', '.join(PARAMETERS)}")
