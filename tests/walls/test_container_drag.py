"""A rigid sphere at the centre of a concentric spherical container (docs/explanation/walls.md, "Tests").

Drag 6 pi mu a U K(lambda), lambda = a / b, with the wall-correction factor

    K = (1 - lambda^5) / (1 - 9/4 lambda + 5/2 lambda^3 - 9/4 lambda^5 + lambda^6)

(Happel & Brenner, Low Reynolds Number Hydrodynamics, 1965, section 4-22, after Cunningham 1910
and Williams 1915; `test_wall_correction_factor_from_the_stream_function` derives it again).  A
spherical vesicle (locked: it moves as a rigid sphere, vesflow.stepper.sphere_constraints)
settling under gravity at the centre of the container: the whole coupled system (vesicle,
wall density, one GMRES) against F / (6 pi mu a K)."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot.wall import Wall
from vesflow.operator import VesicleParams
from vesflow.stepper import Physics, Stepper


def K(lam):
    return (1 - lam ** 5) / (1 - 9 / 4 * lam + 5 / 2 * lam ** 3 - 9 / 4 * lam ** 5 + lam ** 6)


def test_wall_correction_factor_from_the_stream_function():
    """The Stokes stream function psi = f(r) sin^2 theta, f = A r^4 + B r^2 + C r + D / r, of a
    sphere of radius a moving with U inside a sphere of radius b at rest (u = U on r = a, 0 on
    r = b); only the Stokeslet term C r carries a force: F = 8 pi mu C, so K = C / (3 a U / 4)."""
    for lam in (0.2, 0.4, 0.6, 0.8):
        a, b, U = lam, 1.0, 1.0
        f = lambda r: [r ** 4, r ** 2, r, 1 / r]
        df = lambda r: [4 * r ** 3, 2 * r, 1, -1 / r ** 2]
        A, B, C, D = np.linalg.solve([f(a), df(a), f(b), df(b)], [U * a * a / 2, U * a, 0, 0])
        assert abs(C / (0.75 * a * U) / K(lam) - 1) < 1e-12


# (lambda, vesicle p, wall p): the vesicle's degree is what the narrow gap at 0.6 needs (its near
# zone h_n = sqrt(A / 2p) reaches the wall: p = 8 gives 9.3e-4, p = 12 2.2e-5, p = 16 3e-11); a
# viscosity contrast (the vesicle's double layer at the wall points) changes nothing for a locked sphere
CASES = [(0.2, 8, 12, 1.0), (0.4, 8, 12, 1.0), (0.6, 12, 12, 1.0), (0.4, 8, 12, 5.0), (0.6, 12, 12, 0.2)]


@pytest.mark.parametrize("lam,p,pw,contrast", CASES)
def test_settling_sphere_in_a_spherical_container(lam, p, pw, contrast):
    a, mu, drho, g = 1.0, 1.5, 0.8, np.array([0.0, 0.0, -2.0])
    wall = Wall(shapes.make_shape("sphere", pw, radius=a / lam), pw)
    c = shapes.make_shape("sphere", p, radius=a)[None]
    st = Stepper(c, p, VesicleParams([0.1], [contrast], [drho], viscosity=mu), Physics(gravity=g, viscosity=mu),
                 wall=wall)
    sol = st.velocity()
    U = sph.transform(p).synth(sol.u)[0]                       # (3, M): a rigid translation
    F = drho * 4 / 3 * np.pi * a ** 3 * g
    exact = F / (6 * np.pi * mu * a * K(lam))
    err = np.abs(U - exact[:, None]).max() / np.linalg.norm(exact)
    free = np.linalg.norm(exact) * K(lam)
    print(f"lambda = {lam}, contrast {contrast}: |U| = {abs(U[2].mean()):.6f}, exact {np.linalg.norm(exact):.6f} (free space {free:.6f}), "
          f"relative error {err:.1e}, GMRES its {sol.its}")
    assert err < 5e-3
    assert sol.wall is not None and abs(wall.flux(sol.wall)) < 1e-8 * np.abs(sol.wall).max()
