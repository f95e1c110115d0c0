"""Spherical harmonics: round trips, derivatives, rotations (docs/explanation/validation.md, Surfaces)."""
import numpy as np
import pytest

from vesflow import sph


@pytest.mark.parametrize("p", [1, 4, 8, 16, 32])
def test_round_trip_on_the_p_grid(p, rng):
    T = sph.transform(p)
    c = rng.standard_normal((7, sph.n_coeffs(p)))
    err = np.abs(T.analysis(T.synth(c)) - c).max()
    print(f"p={p}: |P Q c - c| = {err:.2e}")
    assert err < 1e-13


@pytest.mark.parametrize("p,q", [(8, 9), (8, 16), (16, 33)])
def test_full_space_round_trip_on_a_finer_grid(p, q, rng):
    T = sph.transform(p, q)
    c = rng.standard_normal((3, sph.n_full(p)))
    assert np.abs(T.analysis(T.synth(c), full=True) - c).max() < 1e-12


def test_m_equal_p_sine_mode_vanishes_on_the_p_grid():
    p = 6
    e = np.zeros(sph.n_full(p))
    e[-1] = 1.0
    assert np.abs(sph.transform(p).synth(e)).max() < 1e-14
    assert np.abs(sph.transform(p, p + 1).synth(e)).max() > 0.1


def test_orthonormality_and_known_harmonic():
    p = 5
    T = sph.transform(p, 8)
    Y = T.synth(np.eye(sph.n_full(p)))
    G = (Y * T.weights) @ Y.T
    assert np.abs(G - np.eye(sph.n_full(p))).max() < 1e-13
    # Y_1^0 = sqrt(3 / 4 pi) cos(theta); Y_2^{2,c} = sqrt(15 / 16 pi) sin^2 cos(2 phi)
    tt, pp = np.meshgrid(T.theta, T.phi, indexing="ij")
    assert np.allclose(Y[sph.flat_index(p, 1, 0)], np.sqrt(3 / (4 * np.pi)) * np.cos(tt).ravel(), atol=1e-14)
    y22 = np.sqrt(15 / (16 * np.pi)) * (np.sin(tt) ** 2 * np.cos(2 * pp)).ravel()
    assert np.allclose(Y[sph.flat_index(p, 2, 2, 0)], y22, atol=1e-14)


@pytest.mark.parametrize("d", ["t", "p", "tt", "tp", "pp"])
def test_derivatives_against_finite_differences(d, rng):
    p = 10
    T = sph.transform(p, 14)
    c = rng.standard_normal(sph.n_full(p)) / (1 + np.arange(sph.n_full(p)))
    tt, pp = np.meshgrid(T.theta, T.phi, indexing="ij")
    tt, pp = tt.ravel(), pp.ravel()
    h = 1e-4
    f = lambda dt, dp: sph.evaluate(c, p, tt + dt, pp + dp)
    fd = {"t": (f(h, 0) - f(-h, 0)) / (2 * h), "p": (f(0, h) - f(0, -h)) / (2 * h),
          "tt": (f(h, 0) - 2 * f(0, 0) + f(-h, 0)) / h ** 2, "pp": (f(0, h) - 2 * f(0, 0) + f(0, -h)) / h ** 2,
          "tp": (f(h, h) - f(h, -h) - f(-h, h) + f(-h, -h)) / (4 * h * h)}[d]
    exact = T.synth(c, d)
    assert np.abs(exact - fd).max() < 1e-5 * np.abs(exact).max()
    assert np.allclose(T.synth_all(c)[d], exact, atol=1e-13)


def test_transpose_is_the_adjoint(rng):
    p, q = 8, 13
    T = sph.transform(p, q)
    c = rng.standard_normal(sph.n_full(p))
    v = rng.standard_normal(T.npts)
    assert np.isclose(T.synth(c) @ v, c @ T.synth_transpose(v, full=True), rtol=1e-13)


@pytest.mark.parametrize("p", [4, 8, 16, 32])
def test_rotation_consistency(p, rng):
    """Rotating coefficients then evaluating = evaluating at rotated points (to 1e-12 relative)."""
    T = sph.transform(p, p + 1)
    c = rng.standard_normal((2, sph.n_full(p)))
    theta0, phi0 = 0.83, 2.1
    g = sph.rotate_to_pole(c, p, theta0, phi0)
    tt, pp = np.meshgrid(T.theta, T.phi, indexing="ij")
    tr, pr = sph.rotation_y_points(theta0, tt.ravel(), pp.ravel())
    ref = sph.evaluate(c, p, tr, pr + phi0)
    err = np.abs(T.synth(g) - ref).max() / np.abs(ref).max()
    print(f"p={p}: rotation error {err:.2e}")
    assert err < 1e-12
    # the north pole of the rotated field is the value at (theta0, phi0)
    pole = sph.evaluate(g, p, [0.0], [0.0])[:, 0]
    assert np.allclose(pole, sph.evaluate(c, p, [theta0], [phi0])[:, 0], atol=1e-12 * np.abs(ref).max())


def test_rotation_preserves_norm(rng):
    p = 12
    c = rng.standard_normal(sph.n_full(p))
    assert np.isclose(np.linalg.norm(sph.rotate_to_pole(c, p, 1.1, 0.4)), np.linalg.norm(c), rtol=1e-13)


def test_resample_and_filter(rng):
    c = rng.standard_normal(sph.n_coeffs(6))
    up = sph.resample(c, 6, 12)
    assert np.allclose(sph.resample(up, 12, 6), c)
    T6, T12 = sph.transform(6, 20), sph.transform(12, 20)
    assert np.allclose(T6.synth(c), T12.synth(up), atol=1e-13)
    ns = sph.index_tables(6)[0][: len(c)]
    f = sph.filter_coeffs(c, 6, np.exp(-np.arange(7.0)))
    assert np.allclose(f, c * np.exp(-ns))


@pytest.mark.parametrize("p, q", [(6, 6), (8, 11)])
def test_analysis_rows_is_the_analysis_along_the_first_axis(p, q, rng):
    """Transform.analysis_rows (the operators' projection, docs/explanation/performance.md "Time per step") equals analysis of the transposed values, reduced and full."""
    T = sph.transform(p, q)
    v = rng.standard_normal((T.npts, 7))
    for full in (False, True):
        ref = T.analysis(v.T, full=full).T
        assert np.abs(T.analysis_rows(v, full=full) - ref).max() < 1e-14 * np.abs(ref).max()
    assert np.abs(T.analysis_rows(v, scale=-2.5) + 2.5 * T.analysis(v.T).T).max() < 1e-14 * np.abs(v).max()


def test_rotate_z_with_an_angle_per_row_and_its_inverse(rng):
    """rotate_z broadcasts alpha (J, 1) against coefficients (J, 3, C): row by row as with a
    scalar angle, which shifts phi (checked at points), and alpha then -alpha is the identity."""
    p = 7
    c = rng.standard_normal((5, 3, sph.n_coeffs(p)))
    alpha = rng.uniform(-4, 4, 5)
    got = sph.rotate_z(c, p, alpha[:, None])
    assert got.shape == (5, 3, sph.n_full(p))
    theta, phi = rng.uniform(0.1, 3.0, 9), rng.uniform(0, 6.3, 9)
    for j in range(5):
        ref = sph.evaluate(c[j], p, theta, phi + alpha[j])
        assert np.abs(sph.evaluate(got[j], p, theta, phi) - ref).max() < 1e-13 * np.abs(ref).max()
    back = sph.rotate_z(got, p, -alpha[:, None])
    assert np.abs(back[..., :-1] - c).max() < 1e-14 * np.abs(c).max() and np.abs(back[..., -1]).max() < 1e-14
