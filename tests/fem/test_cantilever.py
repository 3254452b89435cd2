"""Cantilever of needle material (E = 110 GPa, nu = 0.3, square section) against beam theory.

Small load: Timoshenko (Euler-Bernoulli + shear, Cowper's shear coefficient). Large load: the
inextensible elastica, solved independently with SciPy's solve_bvp and checked against Bisshopp &
Drucker (1945). Also: linear tetrahedra lock in bending (why the needle needs tetra10), and the
observed convergence order of the tip deflection under uniform refinement.
"""

import numpy as np
import pytest
from scipy.integrate import solve_bvp

from needletissue import materials
from needletissue.fem import FEModel, Fixed, SurfaceForce, TaggedMesh, solve

E = materials.get("needle").parameters["E"]
NU = materials.get("needle").parameters["nu"]


def elastica_tip(alpha: float) -> tuple[float, float]:
    """Cantilever, dead tip load normal to the undeformed axis, alpha = P L^2 / (E I):
    theta'' = -alpha cos(theta) on s in [0, 1], theta(0) = 0, theta'(1) = 0.
    Returns (transverse, axial shortening) tip displacement / L."""
    s = np.linspace(0, 1, 101)

    def f(s, y):
        return np.vstack([y[1], -alpha * np.cos(y[0]), np.sin(y[0]), np.cos(y[0])])

    y0 = np.zeros((4, s.size))
    y0[3] = s
    sol = solve_bvp(f, lambda a, b: np.array([a[0], b[1], a[2], a[3]]), s, y0, tol=1e-10)
    assert sol.success
    return float(sol.y[2, -1]), float(1 - sol.y[3, -1])


def test_elastica_reference_matches_bisshopp_drucker():
    # Bisshopp & Drucker, Q. Appl. Math. 3 (1945): vertical tip deflection / L at PL^2/EI = 1 and 2
    assert elastica_tip(1.0)[0] == pytest.approx(0.3017, abs=1e-4)
    assert elastica_tip(2.0)[0] == pytest.approx(0.4935, abs=1e-4)


def cantilever(L, h, nx, ny, P, order=2, **kw):
    m = TaggedMesh.box((L, h, h), (nx + 1, ny + 1, ny + 1), origin=(0, -h / 2, -h / 2), region="needle")
    model = FEModel(m, {"needle": "needle"}, order=order)
    r = solve(model, [Fixed("xmin"), SurfaceForce("xmax", (0.0, 0.0, P))], [1.0], progress=False,
              results=False, **kw)[-1]
    return r.displacement[model.mesh.surface_nodes("xmax")].mean(0), model


def timoshenko(L, h, P):
    I, A, G = h**4 / 12, h * h, E / (2 * (1 + NU))
    kappa = 10 * (1 + NU) / (12 + 11 * NU)  # Cowper, rectangular section
    return P * L**3 / (3 * E * I) + P * L / (kappa * G * A)


L, H = 100.0, 2.0  # slenderness 50, like a 5 mm pin over 250 mm
I = H**4 / 12


def test_small_load_matches_timoshenko_within_1_percent():
    P = 1e-4 * E * I / L**2  # tip deflection 3e-5 L: geometrically linear
    u, _ = cantilever(L, H, 50, 1, P)
    assert u[2] / timoshenko(L, H, P) == pytest.approx(1.0, abs=0.01)


def test_linear_tetrahedra_lock_in_bending():
    """Same mesh, same dofs budget: tetra10 within 1 %, tetra4 more than 20x worse."""
    P = 1e-4 * E * I / L**2
    ref = timoshenko(L, H, P)
    u2, m2 = cantilever(L, H, 50, 1, P, order=2)
    u1, m1 = cantilever(L, H, 100, 2, P, order=1)
    assert m1.ndof >= m2.ndof
    e1, e2 = abs(u1[2] / ref - 1), abs(u2[2] / ref - 1)
    assert e2 < 0.01 and e1 > 20 * e2


def test_large_load_matches_elastica_within_1_percent():
    alpha = 2.0  # tip rotation ~ 0.9 rad; max bending strain alpha h / (2 L) = 2 %
    u, _ = cantilever(L, H, 50, 1, alpha * E * I / L**2, initial_step=0.25)
    dz, dx = elastica_tip(alpha)
    assert u[2] / L == pytest.approx(dz, rel=0.01)
    assert -u[0] / L == pytest.approx(dx, rel=0.01)


def test_observed_convergence_order_quadratic():
    """Uniform refinement (h, h/2, h/4) of a short cantilever: Richardson's observed order of the tip
    deflection. Tetra10 displacement functionals converge at up to O(h^4) for smooth solutions; the
    clamped edges are singular (Poisson contraction restrained), which caps it near 2."""
    Ls, hs = 20.0, 2.0
    P = 1e-4 * E * hs**4 / 12 / Ls**2
    u = [cantilever(Ls, hs, 5 * k, k, P)[0][2] for k in (1, 2, 4)]
    p = np.log2((u[1] - u[0]) / (u[2] - u[1]))
    assert u[0] < u[1] < u[2]  # stiff -> converging from below, monotonically
    assert 1.5 < p < 4.5


@pytest.mark.slow
def test_large_load_fine_mesh_within_half_percent():
    """~20 s: two elements across the section."""
    alpha = 2.0
    u, _ = cantilever(L, H, 50, 2, alpha * E * I / L**2, initial_step=0.25)
    assert u[2] / L == pytest.approx(elastica_tip(alpha)[0], rel=0.005)


def test_round_pin_needs_curved_tetra10():
    """A 5 mm round pin, 2 elements across: gmsh order-2 tetra10 (midside nodes on the cylinder)
    is within 1.5 % of Timoshenko; straight midpoints (a polygonal section, smaller I) are > 20 % soft."""
    import gmsh

    D, Lp, P = 5.0, 60.0, 10.0

    def pin(curved):
        gmsh.initialize(["-nt", "1"])
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            v = gmsh.model.occ.addCylinder(0, 0, 0, Lp, 0, 0, D / 2)
            gmsh.model.occ.synchronize()
            gmsh.model.addPhysicalGroup(3, [v], name="needle")
            for d, t in gmsh.model.getEntities(2):
                x = gmsh.model.occ.getCenterOfMass(d, t)[0]
                if abs(x) < 1e-6 or abs(x - Lp) < 1e-6:
                    gmsh.model.addPhysicalGroup(2, [t], name="clamped" if abs(x) < 1e-6 else "tip")
            gmsh.option.setNumber("Mesh.MeshSizeMax", 2.5)
            gmsh.option.setNumber("Mesh.MeshSizeMin", 2.5)
            gmsh.model.mesh.generate(3)
            if curved:
                gmsh.model.mesh.setOrder(2)
            return TaggedMesh.from_gmsh()
        finally:
            gmsh.finalize()

    I, A, G = np.pi * D**4 / 64, np.pi * D**2 / 4, E / (2 * (1 + NU))
    ref = P * Lp**3 / (3 * E * I) + P * Lp / (6 * (1 + NU) / (7 + 6 * NU) * G * A)
    tips = {}
    for curved in (True, False):
        model = FEModel(pin(curved), {"needle": "needle"}, order=2)
        r = solve(model, [Fixed("clamped"), SurfaceForce("tip", (0, 0, P))], [1.0], progress=False, results=False)
        tips[curved] = r[-1].displacement[model.mesh.surface_nodes("tip"), 2].mean()
    assert tips[True] / ref == pytest.approx(1.0, abs=0.015)
    assert tips[False] / ref > 1.2
