"""Dynamics: checks under "Dynamics" in VALIDATION.md that need no adaptivity."""
import numpy as np
import pytest

petsc4py = pytest.importorskip("petsc4py")
petsc4py.init([])

from vesflow import shapes, sph  # noqa: E402
from vesflow.errors import ConvergenceError  # noqa: E402
from vesflow.operator import VesicleParams  # noqa: E402
from vesflow.stepper import Physics, Stepper  # noqa: E402
from vesflow.surface import Surface  # noqa: E402


@pytest.mark.parametrize("lam", [1.0, 5.0])
def test_sedimenting_spherical_vesicle_moves_at_stokes_velocity(lam):
    """U = 2 drho g a^2 / (9 mu) for any viscosity contrast (to 1e-4; we get round-off)."""
    p, a, drho, mu = 8, 1.3, 0.7, 2.0
    g = np.array([0.0, 0.0, -1.5])
    c = shapes.make_shape("sphere", p, radius=a, center=(1, 2, 3))[None]
    st = Stepper(c, p, VesicleParams([0.1], [lam], [drho], viscosity=mu), Physics(gravity=g, viscosity=mu))
    sol = st.velocity()
    U = sph.transform(p).synth(sol.u)[0]
    exact = 2 * drho * a * a / (9 * mu) * g
    err = np.abs(U - exact[:, None]).max() / np.linalg.norm(exact)
    print(f"lambda={lam}: sedimentation velocity error {err:.1e}, GMRES its {sol.its}")
    assert err < 1e-10


def test_resting_sphere_stays_at_rest_with_constant_tension():
    p = 8
    c = shapes.make_shape("sphere", p)[None]
    st = Stepper(c, p, VesicleParams([0.1], [1.0], [0.0]))
    for _ in range(3):
        sol = st.step(0.1)
    assert np.abs(sph.transform(p).synth(sol.u)).max() < 1e-12
    sigma = sph.transform(p).synth(sol.sigma)[0]
    assert np.ptp(sigma) < 1e-10


def test_relaxing_ellipsoid_loses_bending_energy_monotonically():
    p, dt = 8, 0.05
    c = shapes.make_shape("ellipsoid", p, axes=(1.0, 1.0, 1.6))[None]
    st = Stepper(c, p, VesicleParams([1.0], [1.0], [0.0]))
    S0 = st.surface
    E = [S0.bending_energy(1.0)[0]]
    for _ in range(12):
        st.step(dt)
        E.append(st.surface.bending_energy(1.0)[0])
    E = np.array(E)
    S = st.surface
    print("bending energy", E[0], "->", E[-1], "area drift", S.area()[0] / S0.area()[0] - 1,
          "volume drift", S.volume()[0] / S0.volume()[0] - 1)
    assert np.all(np.diff(E) < 0)
    assert E[-1] < 0.998 * E[0]
    assert abs(S.area()[0] / S0.area()[0] - 1) < 5e-3 and abs(S.volume()[0] / S0.volume()[0] - 1) < 5e-3


def test_first_order_convergence_in_dt():
    p, T = 8, 0.4
    c = shapes.make_shape("ellipsoid", p, axes=(1.0, 1.0, 1.5))[None]

    def final(dt):
        st = Stepper(c, p, VesicleParams([1.0], [1.0], [0.0]))
        for _ in range(int(round(T / dt))):
            st.step(dt)
        return st.coeffs

    ref = final(0.0125)
    errs = [np.abs(final(dt) - ref).max() for dt in (0.1, 0.05)]
    # error against a fine reference: e(dt) ~ C (dt - dt_ref)
    rate = np.log((errs[0]) / (errs[1])) / np.log(2)
    corrected = np.log(errs[0] / errs[1]) / np.log((0.1 - 0.0125) / (0.05 - 0.0125))
    print(f"time errors {errs}, observed order {rate:.2f} (reference-corrected {corrected:.2f})")
    assert 0.8 < corrected < 1.3


def test_two_vesicles_in_shear_pass_and_gmres_converges():
    p = 8
    c = np.stack([shapes.make_shape("oblate", p, reduced_volume=0.85, center=(-1.6, 0, 0.3)),
                  shapes.make_shape("oblate", p, reduced_volume=0.85, center=(1.6, 0, -0.3))])
    st = Stepper(c, p, VesicleParams([0.01] * 2, [1.0] * 2, [0.0] * 2),
                 Physics(flow="shear", flow_args={"rate": 1.0}))
    x0 = Surface(c, p).centroid()
    for _ in range(3):
        sol = st.step(0.05)
        assert sol.its < 30
    dx = st.surface.centroid() - x0
    # the upper vesicle (z > 0) moves in +x with about the shear velocity, the lower one in -x
    assert dx[0, 0] > 0.6 * 0.15 * 0.3 and dx[1, 0] < -0.6 * 0.15 * 0.3


def test_failed_solve_raises_convergence_error():
    from petsc4py import PETSc
    p = 8
    c = shapes.make_shape("ellipsoid", p, axes=(1.0, 1.0, 1.5))[None]
    st = Stepper(c, p, VesicleParams([1.0], [1.0], [0.0]), Physics(flow="shear", flow_args={"rate": 1.0}),
                 ksp_prefix="fail_")
    opts = PETSc.Options()
    opts["fail_ksp_max_it"] = 1
    opts["fail_pc_type"] = "none"
    opts["fail_ksp_rtol"] = 1e-14
    try:
        with pytest.raises(ConvergenceError, match="iterations"):
            st.step(0.1)
    finally:
        for k in ("fail_ksp_max_it", "fail_pc_type", "fail_ksp_rtol"):
            opts.delValue(k)
