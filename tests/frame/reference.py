"""Independent references for the frame model: the elastica (scipy solve_bvp) and linear matrix
analysis of pins built into a rigid clamp (Euler-Bernoulli / Timoshenko closed-form flexibilities)."""

import numpy as np
from scipy.integrate import solve_bvp


def elastica_tip(P, L, EI):
    """Tip (deflection across, shortening along) of an inextensible cantilever under a dead end load P
    perpendicular to its undeformed axis: EI theta'' = -P cos(theta), theta(0) = 0, theta'(L) = 0."""
    def f(s, y):
        return np.vstack([y[1], -P / EI * np.cos(y[0]), np.sin(y[0]), np.cos(y[0])])

    def bc(a, b):
        return np.array([a[0], b[1], a[2], a[3]])

    s = np.linspace(0, L, 201)
    guess = np.zeros((4, s.size))
    guess[3] = s
    sol = solve_bvp(f, bc, s, guess, tol=1e-10, max_nodes=100000)
    assert sol.success
    return float(sol.y[2, -1]), float(L - sol.y[3, -1]), float(sol.y[0, -1])


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def linear_clamp(model, W):
    """Clamp displacement at the load point and rotation under the wrench W (6), linear theory: each pin
    a Timoshenko cantilever from a rigid root at z = 0 to the clamp bottom, built into a rigid clamp."""
    L = model.clamp_bottom_mm
    EI, EA = model.bending_stiffness_Nmm2, model.youngs_modulus_MPa * model.area_mm2
    GJ = model.shear_modulus_MPa * 2 * model.second_moment_mm4
    from needletissue.frame.model import shear_factor

    kGA = shear_factor(model.poisson) * model.shear_modulus_MPa * model.area_mm2
    C = np.zeros((6, 6))  # end (u, theta) per end (F, M) of a cantilever along z
    C[0, 0] = C[1, 1] = L**3 / (3 * EI) + L / kGA
    C[0, 4] = C[4, 0] = L**2 / (2 * EI)
    C[1, 3] = C[3, 1] = -L**2 / (2 * EI)
    C[3, 3] = C[4, 4] = L / EI
    C[2, 2] = L / EA
    C[5, 5] = L / GJ
    Ki = np.linalg.inv(C)
    K = np.zeros((6, 6))
    P0 = np.array(model.load_point_mm)
    for x, y in model.needle_xy:
        T = np.eye(6)
        T[:3, 3:] = -skew(np.array([x, y, L]) - P0)
        K += T.T @ Ki @ T
    return np.linalg.solve(K, W)
