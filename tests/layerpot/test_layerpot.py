"""Layer potentials: every check under "Layer potentials" in docs/explanation/validation.md."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.layerpot.singular import SelfOperators
from vesflow.surface import Surface

SHAPES = {"sphere": {}, "ellipsoid": {"axes": (1, 1, 3)}, "biconcave": {}}


def surface(shape, p, **kw):
    return Surface(shapes.make_shape(shape, p, rotation=(10, 20, 30), **SHAPES[shape], **kw)[None], p)


def const_density(N, p, k=0, value=1.0):
    g = np.zeros((N, 3, sph.n_coeffs(p)))
    g[:, k, 0] = np.sqrt(4 * np.pi) * value
    return g


def test_single_layer_of_uniform_traction_on_a_sphere():
    p, a = 12, 1.3
    S = Surface(shapes.make_shape("sphere", p, radius=a)[None], p)
    lp = LayerPotentials(S, settings=Settings(q_self=32, q_far=32))
    f0 = np.array([0.3, -0.2, 0.5])
    f = np.zeros((1, 3, sph.n_coeffs(p)))
    f[0, :, 0] = np.sqrt(4 * np.pi) * f0
    on = sph.transform(p).synth(lp.self_part(f))[0].T
    assert np.abs(on - 2 * a * f0 / 3).max() < 1e-13
    for depth in (0.2, 0.97):                                            # far and near interior points
        inside = lp.evaluate_at(S.points()[0, ::7] * depth, f)
        assert np.abs(inside - 2 * a * f0 / 3).max() < 1e-8


@pytest.mark.parametrize("n", [1, 2, 4, 7])
def test_single_layer_toroidal_eigenvalues(n):
    p = 10
    S = Surface(shapes.make_shape("sphere", p)[None], p)
    ops = SelfOperators(S.coeffs, p, 20)
    g = S.geometry(p)
    e = np.zeros(sph.n_coeffs(p))
    e[sph.flat_index(p, n, min(n, 2))] = 1
    tor = np.cross(g.X, g.grad(sph.transform(p).synth(e)[None]))
    c = sph.transform(p).analysis(np.moveaxis(tor, -1, -2))
    u = SelfOperators.apply(ops.single, c)
    assert np.abs(u - c / (2 * n + 1)).max() < 1e-12 * np.abs(c).max()


@pytest.mark.parametrize("shape,tol", [("sphere", 1e-12), ("ellipsoid", 1e-7), ("biconcave", 1e-3)])
def test_double_layer_of_one_on_surface(shape, tol):
    p = 16
    S = surface(shape, p)
    ops = SelfOperators(S.coeffs, p, 32, want_single=False, want_double=True)
    for k in range(3):
        vals = sph.transform(p).synth(SelfOperators.apply(ops.double, const_density(1, p, k)))[0]
        expect = np.zeros((3, 1)); expect[k] = 0.5
        err = np.abs(vals - expect).max()
        print(f"{shape}: |pv D[e_{k}] - e_{k}/2| = {err:.1e}")
        assert err < tol


def test_self_error_converges_spectrally_in_q():
    p, errs, qs = 12, [], [16, 24, 32, 48]
    S = surface("biconcave", p)
    for q in qs:
        ops = SelfOperators(S.coeffs, p, q, want_single=False, want_double=True)
        errs.append(np.abs(sph.transform(p).synth(SelfOperators.apply(ops.double, const_density(1, p)))[0, 0] - 0.5).max())
    rate = -np.polyfit(qs, np.log(errs), 1)[0]
    print("self D[1] errors", ["%.1e" % e for e in errs], f"rate exp(-{rate:.3f} q)")
    assert rate > 0.08 and errs[-1] < 1e-4


@pytest.mark.parametrize("shape,tol_out,tol_in", [("sphere", 1e-9, 1e-9), ("ellipsoid", 1e-5, None),
                                                  ("biconcave", 5e-4, None)])
@pytest.mark.parametrize("dist", [1e-1, 1e-3, 1e-5])
def test_double_layer_identity_near_targets(shape, tol_out, tol_in, dist):
    """D[1] = 0 outside and 1 inside at 1e-1, 1e-3, 1e-5 R from the surface (p = 16, q = 32)."""
    p = 16
    S = surface(shape, p)
    lp = LayerPotentials(S, lam=0.0, settings=Settings(q_self=32, q_far=32))
    g = S.geometry(p)
    idx = np.random.default_rng(3).choice(g.X.shape[1], 30, replace=False)
    R0 = S.effective_radius()[0]
    out = lp.evaluate_at(g.X[0, idx] + dist * R0 * g.normal[0, idx], 0 * const_density(1, p), const_density(1, p))
    err_out = np.abs(out).max()
    print(f"{shape} d={dist:g}: outside error {err_out:.1e}")
    assert err_out < tol_out
    if tol_in is not None:
        inn = lp.evaluate_at(g.X[0, idx] - dist * R0 * g.normal[0, idx], 0 * const_density(1, p), const_density(1, p))
        assert np.abs(inn - [1, 0, 0]).max() < tol_in


def test_greens_identity_with_a_point_force():
    """u = G(x - x0) F from a point force outside; with t its traction (outward normal) and the
    lambda = 0 kernels, S[t] + D[u] = u inside and 0 outside (docs/explanation/validation.md;
    with D[1] = +1 inside, the representation formula carries a plus sign)."""
    p, q = 16, 32
    S = surface("ellipsoid", p)
    x0, F = np.array([0.2, 3.5, -0.4]), np.array([0.3, 1.0, -0.7])
    stokeslet = lambda x: ((F / np.linalg.norm(x - x0, axis=-1)[..., None])
                           + (x - x0) * ((x - x0) @ F)[..., None] / np.linalg.norm(x - x0, axis=-1)[..., None] ** 3) / (8 * np.pi)
    g = S.geometry(q)
    r = g.X[0] - x0
    rn = np.linalg.norm(r, axis=1)[:, None]
    t = -(3 / (4 * np.pi)) * ((r @ F) * np.einsum("ik,ik->i", r, g.normal[0]))[:, None] * r / rn ** 5
    T = sph.transform(p, q)
    tc, uc = T.analysis(t.T)[None], T.analysis(stokeslet(g.X[0]).T)[None]
    lp = LayerPotentials(S, lam=0.0, settings=Settings(q_self=q, q_far=q))
    gp = S.geometry(p)
    idx = np.arange(0, gp.X.shape[1], 13)
    R0 = S.effective_radius()[0]
    scale = np.abs(stokeslet(gp.X[0])).max()
    for d in (1e-1, 1e-3, 1e-5):
        v_out = lp.evaluate_at(gp.X[0, idx] + d * R0 * gp.normal[0, idx], tc, uc)
        print(f"Green d={d:g}: outside {np.abs(v_out).max() / scale:.1e} relative")
        assert np.abs(v_out).max() < 1e-5 * scale
    # interior targets: only where the interpolation line (h_n .. 2 h_n inward) stays inside;
    # the thin ellipsoid (semi-axes ~0.55, 0.55, 1.65) allows that only far from its surface
    lp_in = LayerPotentials(S, lam=0.0, settings=Settings(q_self=q, q_far=q, near_factor=0.5))
    inner = np.array([[0.0, 0.0, 0.0]])
    assert np.abs(lp_in.evaluate_at(inner, tc, uc) - stokeslet(inner)).max() < 1e-7 * scale


def test_error_estimate_per_regime_for_two_close_vesicles():
    """D[1] over two close vesicles: 1/2 on the own surface (self), 0 at near and far targets."""
    p = 8
    c = np.stack([shapes.make_shape("oblate", p, reduced_volume=0.85, center=(0, 0, 0)),
                  shapes.make_shape("oblate", p, reduced_volume=0.85, center=(2.45, 0.0, 0.3))])
    S = Surface(c, p)
    lp = LayerPotentials(S, lam=[0.0, 0.0], settings=Settings(q_self=16, q_far=16))
    assert lp.n_near_pairs > 0
    est = lp.error_estimate()
    print("error estimate", est)
    assert est["self"] < 1e-3 and est["near"] < 1e-2 and est["far"] < 1e-3



def test_near_blend_weight_is_c2_and_switches_from_one_to_zero():
    from vesflow.layerpot.near import blend_weight
    s = np.array([-1.0, 0.0, 0.5, 1.0, 2.0])
    assert np.allclose(blend_weight(s), [1.0, 1.0, 0.5, 0.0, 0.0])
    e = 1e-4                                   # first and second derivatives vanish at both ends
    for s0 in (0.0, 1.0):
        w = blend_weight(np.array([s0 - e, s0, s0 + e]))
        assert abs(w[2] - w[0]) / (2 * e) < 1e-6 and abs(w[2] - 2 * w[1] + w[0]) / e ** 2 < 1e-2      # 10 e: no jump in w''
