"""Surfaces, shapes and forces: every check under "Surfaces" in docs/explanation/validation.md."""
import numpy as np
import pytest
from scipy.special import ellipeinc, ellipkinc

from vesflow import forces, shapes, sph
from vesflow.surface import Surface


def sphere(p, R=1.0, center=(0, 0, 0)):
    return Surface(shapes.make_shape("sphere", p, radius=R, center=center), p)


def test_sphere_curvatures_area_volume():
    R, p = 1.7, 12
    S = sphere(p, R, center=(0.3, -1.0, 2.0))
    g = S.geometry(p)
    assert np.abs(g.H + 1 / R).max() < 1e-12
    assert np.abs(g.K - 1 / R ** 2).max() < 1e-12
    assert np.isclose(S.area()[0], 4 * np.pi * R ** 2, rtol=1e-13)
    assert np.isclose(S.volume()[0], 4 / 3 * np.pi * R ** 3, rtol=1e-13)
    assert np.allclose(S.centroid()[0], [0.3, -1.0, 2.0], atol=1e-13)
    assert np.isclose(S.reduced_volume()[0], 1.0, rtol=1e-13)
    assert np.isclose(S.bending_energy(0.3)[0], 4 * np.pi * 0.3, rtol=1e-12)
    # outward normal
    assert np.all(np.einsum("nik,nik->ni", g.normal, g.X - [0.3, -1.0, 2.0]) > 0)


@pytest.mark.parametrize("shape,kw", [("ellipsoid", {"axes": (1, 2, 0.7)}), ("biconcave", {}),
                                      ("oblate", {"reduced_volume": 0.85})])
def test_laplace_of_position_is_twice_H_n(shape, kw):
    p = 16
    g = Surface(shapes.make_shape(shape, p, rotation=(20, 40, 60), **kw), p).geometry(2 * p)
    lapX = g.laplace_vector(g.X)
    assert np.abs(lapX - 2 * g.H[..., None] * g.normal).max() < 1e-7 * np.abs(g.H).max()


@pytest.mark.parametrize("n,m", [(1, 0), (3, 2), (6, 5), (9, 1)])
def test_laplace_beltrami_spectrum_unit_sphere(n, m):
    g = sphere(8).geometry(16)
    T = sph.transform(16, 16)
    e = np.zeros(sph.n_coeffs(16))
    e[sph.flat_index(16, n, m)] = 1
    f = T.synth(e)[None]
    assert np.abs(g.laplace(f) + n * (n + 1) * f).max() < 1e-10


@pytest.mark.parametrize("shape,kw", [("ellipsoid", {"axes": (1, 1.5, 0.6)}), ("biconcave", {}),
                                      ("prolate", {"reduced_volume": 0.75}), ("oblate", {"reduced_volume": 0.9})])
def test_closed_surface_identities(shape, kw):
    p = 20
    S = Surface(shapes.make_shape(shape, p, rotation=(15, 70, 5), center=(1, 2, 3), **kw), p)
    g = S.geometry(2 * p)
    assert abs(g.integrate(g.K)[0] / (4 * np.pi) - 1) < 1e-9              # Gauss-Bonnet
    assert np.abs(g.integrate(g.normal)).max() < 1e-13
    assert np.abs(g.integrate(g.H[..., None] * g.normal)).max() < 1e-12
    vol_xn = g.integrate(np.einsum("nik,nik->ni", g.X, g.normal))[0] / 3
    assert np.isclose(vol_xn, S.volume()[0], rtol=1e-13)


def ellipsoid_area(a, b, c):
    a, b, c = sorted((a, b, c), reverse=True)
    phi = np.arccos(c / a)
    k2 = (a * a * (b * b - c * c)) / (b * b * (a * a - c * c))
    s = np.sin(phi)
    return 2 * np.pi * c * c + 2 * np.pi * a * b / s * (ellipeinc(phi, k2) * s * s + ellipkinc(phi, k2) * np.cos(phi) ** 2)


def test_ellipsoid_volume_exact_and_area_spectral():
    axes = (1.0, 1.6, 0.55)
    exact = ellipsoid_area(*axes)
    errs, ps = [], [4, 8, 12, 16, 24]
    for p in ps:
        S = Surface(shapes.ellipsoid_coeffs(axes, p)[None], p)
        assert np.isclose(S.volume(q=p)[0], 4 / 3 * np.pi * np.prod(axes), rtol=1e-13)
        errs.append(abs(S.area(q=p)[0] - exact) / exact)
    rate = -np.polyfit(ps[:4], np.log(np.maximum(errs[:4], 1e-16)), 1)[0]
    print("ellipsoid area errors", ["%.1e" % e for e in errs], f"observed rate exp(-{rate:.2f} p)")
    assert errs[-1] < 1e-10 and errs[2] < 1e-6 and rate > 0.8


def test_gauss_bonnet_spectral_for_biconcave():
    ps, errs = [6, 8, 12, 16, 24], []
    for p in ps:
        g = Surface(shapes.make_shape("biconcave", p), p).geometry(p)
        errs.append(abs(g.integrate(g.K)[0] / (4 * np.pi) - 1))
    rate = -np.polyfit(ps[:4], np.log(errs[:4]), 1)[0]
    print("biconcave Gauss-Bonnet errors", ["%.1e" % e for e in errs], f"observed rate exp(-{rate:.2f} p)")
    assert errs[-1] < 1e-6 and rate > 0.5 and all(np.diff(errs) < 0)


@pytest.mark.parametrize("shape,v", [("oblate", 0.85), ("oblate", 0.65), ("prolate", 0.9), ("biconcave", 0.65),
                                     ("biconcave", 0.7)])
def test_requested_reduced_volume(shape, v):
    p = 16
    c = shapes.make_shape(shape, p, radius=2.5, reduced_volume=v, rotation=(10, 20, 30))
    S = Surface(c, p)
    assert abs(S.reduced_volume(q=96)[0] - v) < 1e-8
    assert abs(S.effective_radius(q=96)[0] - 2.5) < 1e-8


def test_euler_rotation_and_placement():
    p = 8
    c = shapes.make_shape("ellipsoid", p, axes=(2, 1, 0.5), rotation=(90, 0, 0), center=(1, 1, 1))
    X = Surface(c, p).points() - 1.0
    extent = np.abs(X).max(axis=1)[0]
    assert extent[1] > extent[0] > extent[2]       # the long x axis turned onto y by Rz(90)
    R = shapes.euler_zyz((30, 50, 70))
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1)


def random_smooth(rng, shape, p):
    C = sph.n_coeffs(p)
    ns = sph.index_tables(p)[0][:C]
    return rng.standard_normal(shape + (C,)) * np.exp(-ns)


@pytest.mark.parametrize("p", [8, 16])
def test_bending_force_is_minus_energy_variation(p, rng):
    c = shapes.make_shape("ellipsoid", p, axes=(1, 1.3, 0.8), rotation=(10, 20, 30))[None]
    V, q, eps = random_smooth(rng, (1, 3), p), 3 * p, 1e-5
    E = lambda cc: Surface(cc, p).bending_energy(0.7, q=q)[0]
    fd = (E(c + eps * V) - E(c - eps * V)) / (2 * eps)
    g = Surface(c, p).geometry(q)
    Vg = np.moveaxis(sph.transform(p, q).synth(V), -2, -1)
    an = -g.integrate(np.einsum("nik,nik->ni", forces.bending_force(g, 0.7), Vg))[0]
    print(f"p={p}: dE_b finite difference {fd:.10f}, -(f_b, V) {an:.10f}")
    assert abs(fd - an) < 1e-7 * abs(fd)


@pytest.mark.parametrize("p", [8, 16])
def test_tension_force_is_minus_energy_variation(p, rng):
    c = shapes.make_shape("biconcave", p, rotation=(10, 20, 30))[None]
    V, sig, q, eps = random_smooth(rng, (1, 3), p), random_smooth(rng, (1,), p), 3 * p, 1e-5
    def E(cc):
        return Surface(cc, p).geometry(q).integrate(sph.transform(p, q).synth(sig))[0]
    fd = (E(c + eps * V) - E(c - eps * V)) / (2 * eps)
    g = Surface(c, p).geometry(q)
    Vg = np.moveaxis(sph.transform(p, q).synth(V), -2, -1)
    an = -g.integrate(np.einsum("nik,nik->ni", forces.tension_force(g, sph.transform(p, q).synth(sig)), Vg))[0]
    print(f"p={p}: dE_sigma finite difference {fd:.10f}, -(f_sigma, V) {an:.10f}")
    assert abs(fd - an) < {8: 2e-5, 16: 1e-8}[p] * abs(fd)


def test_linearized_bending_equals_bending_at_current_shape():
    p = 12
    g = Surface(shapes.make_shape("oblate", p, reduced_volume=0.8), p).geometry(2 * p)
    fb = forces.bending_force(g, 0.1)
    assert np.abs(forces.linearized_bending_force(g, 0.1, g.X) - fb).max() < 1e-8 * np.abs(fb).max()
    # linear in Y
    Y1, Y2 = g.X * 0.3, np.roll(g.X, 5, axis=1)
    B = lambda Y: forces.linearized_bending_force(g, 0.1, Y)
    assert np.allclose(B(Y1 + 2 * Y2), B(Y1) + 2 * B(Y2), atol=1e-10)


def test_gravity_traction_integrates_to_weight():
    p = 10
    S = Surface(shapes.make_shape("biconcave", p, center=(3, 0, 1)), p)
    g = S.geometry(2 * p)
    f = forces.gravity_force(g, 2.0, (0, 0, -1.5))
    assert np.allclose(g.integrate(f)[0], 2.0 * S.volume()[0] * np.array([0, 0, -1.5]), rtol=1e-12, atol=1e-13)


def test_bad_shape_arguments():
    with pytest.raises(ValueError, match="shape"):
        shapes.make_shape("cube", 8)
    with pytest.raises(ValueError, match="reduced_volume"):
        shapes.spheroid_axes("oblate", 1.3)
