"""The compiled near field against its reference computations (docs/explanation/method.md, section 5.2):
the projection (series.project) against the numpy Gauss-Newton it replaced, and the near pairs'
precomputed maps (vesflow.layerpot.nearmap) against the smooth rule at the check points
evaluated every iteration (the block sums), on near pairs of close biconcave cells."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow._kernels import search, stokes
from vesflow.layerpot import near as nearmod
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.layerpot.nearmap import map_bytes_per_pair
from vesflow.surface import Surface


def reference_projection(coeffs, p, x, vesicle, th, ph, tol=1e-10, max_iter=30):
    """The numpy Gauss-Newton of vesflow.layerpot.near.Projection before it was compiled (the
    same line search, one vectorized step over the active points at a time)."""
    padded = np.ascontiguousarray(sph.transform(p).pad(np.asarray(coeffs, dtype=float)))
    vesicle = np.ascontiguousarray(vesicle, dtype=np.int64)
    th, ph = np.array(th, dtype=float), np.array(ph, dtype=float)

    def wrap(t, f):
        neg = t < 0
        t, f = np.where(neg, -t, t), np.where(neg, f + np.pi, f)
        over = t > np.pi
        t, f = np.where(over, 2 * np.pi - t, t), np.where(over, f + np.pi, f)
        return np.clip(t, 1e-12, np.pi - 1e-12), np.mod(f, 2 * np.pi)

    Y, Yt, Yp = nearmod.eval_points(padded, vesicle, th, ph)
    res = np.einsum("pk,pk->p", Y - x, Y - x)
    conv = np.zeros(len(x), dtype=bool)
    for _ in range(max_iter):
        act = ~conv
        if not act.any():
            break
        r = x[act] - Y[act]
        a11, a12, a22 = (np.einsum("pk,pk->p", u, v) for u, v in ((Yt[act], Yt[act]), (Yt[act], Yp[act]),
                                                                  (Yp[act], Yp[act])))
        b1, b2 = np.einsum("pk,pk->p", Yt[act], r), np.einsum("pk,pk->p", Yp[act], r)
        det = a11 * a22 - a12 ** 2
        dth, dph = (a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det
        idx = np.nonzero(act)[0]
        step, best = np.ones(len(idx)), res[act].copy()
        newY, newYt, newYp = Y[act].copy(), Yt[act].copy(), Yp[act].copy()
        nth, nph = th[act].copy(), ph[act].copy()
        local = np.abs(dth) + np.abs(dph) < 1e-5
        pending = np.ones(len(idx), dtype=bool)
        for _ls in range(12):
            if not pending.any():
                break
            k = np.nonzero(pending)[0]
            tt, pp = wrap(th[idx[k]] + step[k] * dth[k], ph[idx[k]] + step[k] * dph[k])
            y, yt, yp = nearmod.eval_points(padded, vesicle[idx[k]], tt, pp)
            rr = np.einsum("pk,pk->p", y - x[idx[k]], y - x[idx[k]])
            ok = (rr <= best[k] * (1.0 + 1e-14)) | local[k]
            kk = k[ok]
            newY[kk], newYt[kk], newYp[kk] = y[ok], yt[ok], yp[ok]
            nth[kk], nph[kk], best[kk] = tt[ok], pp[ok], rr[ok]
            pending[kk] = False
            step[k[~ok]] *= 0.5
        size = np.abs(step * dth) + np.abs(step * dph)
        th[idx], ph[idx], Y[idx], Yt[idx], Yp[idx] = nth, nph, newY, newYt, newYp
        res[idx] = best
        conv[idx] = (size < tol) | pending
    return th, ph, Y, conv


def cells(p, gap):
    """Two biconcave cells stacked along their thin axis (z) at about `gap` apart."""
    c = np.stack([shapes.make_shape("biconcave", p, radius=0.766, center=(0.0, 0.0, z), reduced_volume=0.65,
                                    rotation=(0.0, 5.0 * k, 0.0)) for k, z in enumerate((0.0, 0.0))])
    S = Surface(c, p)
    X = S.points()
    lift = X[0, :, 2].max() - X[1, :, 2].min() + gap
    c[1, 2, 0] += lift * np.sqrt(4 * np.pi)          # the l = 0 coefficient of z moves the cell
    return Surface(c, p)


def test_compiled_projection_matches_the_numpy_gauss_newton():
    p = 12
    S = cells(p, 0.05)
    X = S.points().reshape(-1, 3)
    rng = np.random.default_rng(3)
    # the points of cell 0 within 0.3 of cell 1 and points around them projected on cell 1, from
    # the nearest q-grid point (as the near set-up does)
    Tq = sph.transform(p, 2 * p)
    Xq = S.points(2 * p)[1].reshape(-1, 3)
    X = X[:len(X) // 2]
    X = X[np.sqrt(((X[:, None] - Xq[None]) ** 2).sum(-1)).min(axis=1) < 0.3]
    x = np.concatenate([X, X + rng.normal(0, 0.05, X.shape)])
    assert len(x) > 100
    j = np.argmin(((x[:, None] - Xq[None]) ** 2).sum(-1), axis=1)
    it, jp = np.divmod(j, Tq.nlon)
    ves = np.zeros(len(x), dtype=np.int64)
    th0, ph0 = Tq.theta[it], Tq.phi[jp]
    pr = nearmod.Projection(S.coeffs[1:], p, x, ves, th0, ph0)
    th, ph, Y, conv = reference_projection(S.coeffs[1:], p, x, ves, th0, ph0)
    assert np.array_equal(pr.converged, conv) and conv.mean() > 0.5
    scale = np.abs(X).max()
    assert np.abs(pr.point - Y).max() < 1e-12 * scale
    # the closest point is unique here: the parameters agree too (phi modulo 2 pi)
    dphi = np.angle(np.exp(1j * (pr.phi - ph)))
    assert np.abs(pr.theta - th).max() < 1e-10 and np.abs(dphi).max() < 1e-10
    # and where converged a closest point: x - Y normal to the surface
    assert np.abs(np.cross(x - pr.point, pr.normal)[conv]).max() < 1e-9


def check_point_terms(lp, near, fw, gq):
    """|c_k| |smooth rule at check point k| per pair (P, 9): the terms whose sum is the near
    correction (c = (-1, w_1..w_8), w up to ~4000 at L = 8): its rounding scale."""
    blk = np.zeros(near.blocks.shape)
    off = lp.src_off
    stokes.stokeslet_sum_blocks(lp.src_planar, stokes.planar(fw, off), off, near.blocks, near.rows, blk)
    if gq is not None:
        stokes.stresslet_sum_blocks(lp.src_planar, lp.src_nw_planar, stokes.planar(gq, off), off, near.blocks,
                                    near.rows, blk)
    coef = np.concatenate([-np.ones((len(blk), 1)), near.weights[:, 1:]], axis=1)
    return np.abs(coef) * np.abs(blk).max(axis=2)


def long_double_correction(lp, near, fw, i):
    """sum_k c_k S[f](x_k) of pair i (single layer) in long double."""
    v = near.rows[i]
    m = lp.Tq.npts
    y = lp.src[v * m:(v + 1) * m].astype(np.longdouble)
    F = fw[v * m:(v + 1) * m].astype(np.longdouble)
    coef = np.concatenate([[-1.0], near.weights[i, 1:]]).astype(np.longdouble)
    out = np.zeros(3, dtype=np.longdouble)
    for k in range(near.blocks.shape[1]):
        r = near.blocks[i, k].astype(np.longdouble) - y
        ri = 1 / np.sqrt((r * r).sum(axis=1))
        out += coef[k] * (F * ri[:, None] + r * ((r * F).sum(axis=1) * ri ** 3)[:, None]).sum(axis=0)
    return out / (8 * np.pi)


@pytest.mark.parametrize("contrast", [1.0, 4.0])
def test_near_maps_match_the_check_point_sums(contrast):
    p = 8
    S = cells(p, 0.04)
    lp = LayerPotentials(S, lam=contrast, settings=Settings(backend="direct"))
    near, maps = lp.near, lp.near_maps
    assert near is not None and maps is not None and len(maps.index) == len(near.pairs) > 50
    rng = np.random.default_rng(0)
    C = sph.n_coeffs(p)
    f = rng.standard_normal((2, 3, C)) * np.exp(-0.2 * np.arange(C))
    g = rng.standard_normal((2, 3, C)) * np.exp(-0.2 * np.arange(C)) if contrast != 1.0 else None
    fw, gq = lp._densities(f, g)
    u_self = lp.self_part(f, g)
    zero = np.zeros((len(lp.trg), 3))
    # per pair: the maps' value against the smooth rule at the 9 check points summed every iteration
    by_map = maps.apply(f, None if g is None else g * (1.0 - lp.lam)[:, None, None])
    by_sums = lp._near_minus_smooth(near, np.zeros((len(near.pairs), 3)), fw, gq)
    terms = check_point_terms(lp, near, fw, gq).sum(axis=1)
    assert np.abs(by_sums).max() > 1e-3
    assert np.all(np.abs(by_map - by_sums).max(axis=1) < 1e-12 * terms)
    if g is None:        # the worst pairs against long double: the map is the more accurate
        for i in np.argsort(-np.abs(by_map - by_sums).max(axis=1))[:3]:
            ref = long_double_correction(lp, near, fw, i)
            err_map, err_sums = np.abs(by_map[i] - ref).max(), np.abs(by_sums[i] - ref).max()
            assert err_map < 1e-12 * np.abs(ref).max() and err_map <= err_sums
    # the whole near stage: the same velocities
    a = lp._near_correct(zero.copy(), near, fw, gq, u_self, g, f, g)
    b = lp._near_correct(zero.copy(), near, fw, gq, u_self, g)             # no density coefficients: blocks
    assert np.abs(a - b).max() < 1e-12 * np.abs(lp.apply(f, g)).max()
    layers = 1 + (contrast != 1.0)
    assert maps.nbytes == len(maps.index) * map_bytes_per_pair(C, layers)


def test_near_map_budget_splits_the_pairs_and_keeps_the_values():
    p = 8
    S = cells(p, 0.04)
    full = LayerPotentials(S, settings=Settings(backend="direct", near_map_mb=0))
    assert full.near_maps is None
    P = len(full.near.pairs)
    half = (P // 2) * map_bytes_per_pair(sph.n_coeffs(p), 1) / 1e6
    part = LayerPotentials(S, settings=Settings(backend="direct", near_map_mb=half))
    assert len(part.near_maps.index) == P // 2 and len(part._near_rest.pairs) == P - P // 2
    rng = np.random.default_rng(2)
    f = rng.standard_normal((2, 3, sph.n_coeffs(p))) * np.exp(-0.2 * np.arange(sph.n_coeffs(p)))
    a, b = full.apply(f), part.apply(f)
    assert np.abs(a - b).max() < 1e-12 * np.abs(a).max()
    with pytest.raises(ValueError, match="near_map_mb"):
        Settings(near_map_mb=-1)


def test_basis_at_and_nearest_sources_match_their_numpy_forms():
    p = 10
    rng = np.random.default_rng(5)
    th, ph = rng.uniform(0.01, np.pi - 0.01, 40), rng.uniform(0, 2 * np.pi, 40)
    C = sph.n_coeffs(p)
    assert np.abs(sph.basis_at(p, th, ph) - sph.evaluate(np.eye(C), p, th, ph).T).max() < 1e-14
    src = rng.standard_normal((3 * 50, 3))
    off = np.array([0, 50, 100, 150], dtype=np.int64)
    rows = rng.integers(0, 3, 30).astype(np.int64)
    x = rng.standard_normal((30, 3))
    idx, d2 = np.empty(30, dtype=np.int64), np.empty(30)
    search.nearest_sources(src, off, rows, x, idx, d2)
    d = src.reshape(3, 50, 3)[rows] - x[:, None]
    ref = np.einsum("pmk,pmk->pm", d, d)
    assert np.array_equal(idx, ref.argmin(axis=1)) and np.allclose(d2, ref.min(axis=1), rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match="rows"):
        search.nearest_sources(src, off, np.full(30, 3, dtype=np.int64), x, idx, d2)
