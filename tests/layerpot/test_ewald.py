"""Spectral Ewald sums (vesflow/layerpot/ewald.py): periodic against a classical Ewald sum with
a direct k-sum (independent code path), the Hasimoto constant of a cubic lattice, independence
of the splitting xi, and free space against the direct sum."""
import itertools
import math

import numpy as np
import pytest
from scipy.special import erfc

from vesflow._kernels import ewald as ek
from vesflow._kernels import paths
from vesflow._kernels import stokes
from vesflow import shapes, sph
from vesflow.layerpot import ewald
from vesflow.layerpot.singular import SYM
from vesflow.surface import Surface

SQPI = math.sqrt(math.pi)


# ------------------------------------------------------------------ closed forms (numpy)
def g_full(r, f):
    """G(r) f / (8 pi), rows."""
    rr = np.sum(r * r, -1)
    ri = 1 / np.sqrt(rr)
    return (f * ri[..., None] + r * (np.sum(r * f, -1) * ri ** 3)[..., None]) / (8 * np.pi)


def t_full(r, nw, g):
    rr = np.sum(r * r, -1)
    return -6 * (np.sum(r * nw, -1) * np.sum(r * g, -1) / rr ** 2.5)[..., None] * r / (8 * np.pi)


def g_real(r, f, xi):
    """G^R(r) f / (8 pi) (Hasimoto), rows; r != 0."""
    rr = np.sum(r * r, -1)
    d = np.sqrt(rr)
    e = np.exp(-xi ** 2 * rr)
    ec = erfc(xi * d) / d
    ci = ec - 2 * xi * e / SQPI
    cr = (ec + 2 * xi * e / SQPI) / rr * np.sum(r * f, -1)
    return (ci[..., None] * f + cr[..., None] * r) / (8 * np.pi)


def t_real(r, nw, g, xi):
    rr = np.sum(r * r, -1)
    d = np.sqrt(rr)
    e = np.exp(-xi ** 2 * rr) / SQPI
    A = 4 * xi ** 3 * e
    B = -2 * (3 * erfc(xi * d) / d ** 5 + (6 * xi / d ** 4 + 4 * xi ** 3 / d ** 2) * e)
    rn, rg, gn = np.sum(r * nw, -1), np.sum(r * g, -1), np.sum(g * nw, -1)
    out = A[..., None] * (g * rn[..., None] + nw * rg[..., None]) + (A * gn + B * rn * rg)[..., None] * r
    return out / (8 * np.pi)


def smooth_part_decimal(r, f, nw, g, xi):
    """G^F(r) f / (8 pi) + T^F(r):(g nw) / (8 pi) in 50-digit decimal arithmetic (closed forms)."""
    from decimal import Decimal as D, localcontext
    with localcontext() as ctx:
        ctx.prec = 60
        pi = D("3.14159265358979323846264338327950288419716939937510582097494")
        sq = pi.sqrt()

        def erf(z):
            s, t, n = D(0), z, 0
            while True:
                term = t / (2 * n + 1)
                s += term
                if abs(term) < D(10) ** -55:
                    return 2 * s / sq
                n += 1
                t *= -z * z / n
        r, f, nw, g = ([D(float(x)) for x in v] for v in (r, f, nw, g))
        xi = D(xi)
        d = sum(x * x for x in r).sqrt()
        z = xi * d
        e = (-z * z).exp()
        ci = erf(z) / d + 2 * xi * e / sq
        ca = (erf(z) / d - 2 * xi * e / sq) / d ** 2
        rf = sum(a * b for a, b in zip(r, f))
        e = e / sq
        A = 4 * xi ** 3 * e
        b = -6 * erf(z) / d ** 5 + (12 * xi / d ** 4 + 8 * xi ** 3 / d ** 2) * e
        rn = sum(a * c for a, c in zip(r, nw))
        rg = sum(a * c for a, c in zip(r, g))
        gn = sum(a * c for a, c in zip(g, nw))
        return [float((ci * f[i] + ca * rf * r[i] - A * (g[i] * rn + nw[i] * rg) + (-A * gn + b * rn * rg) * r[i])
                      / (8 * pi)) for i in range(3)]


def classical_ewald(src, f, nw, g, sid, trg, tid, L, xi, nimg=2, nk=None):
    """Periodic sum by the classical Ewald method: real-space sum over (2 nimg + 1)^3 image
    cells and a DIRECT sum over the wave vectors |n_a| <= nk (no NUFFT, no cell lists);
    the target's own vesicle at its given position left out."""
    if nk is None:
        nk = int(math.ceil(2 * xi * 6.2 * L / (2 * math.pi)))
    shifts = L * np.array(list(itertools.product(range(-nimg, nimg + 1), repeat=3)), dtype=float)
    zero = np.flatnonzero(np.all(shifts == 0, axis=1))[0]
    u = np.zeros((trg.shape[0], 3))
    for t in range(trg.shape[0]):
        r = trg[t][None, None, :] - src[None, :, :] + shifts[:, None, :]
        keep = np.ones(r.shape[:2], dtype=bool)
        own = sid == tid[t]
        keep[zero, own] = False
        if f is not None:
            u[t] += g_real(r, f[None], xi)[keep].sum(0)
            u[t] -= (g_full(r[zero, own], f[own]) - g_real(r[zero, own], f[own], xi)).sum(0)
        if g is not None:
            u[t] += t_real(r, nw[None], g[None], xi)[keep].sum(0)
            u[t] -= (t_full(r[zero, own], nw[own], g[own]) - t_real(r[zero, own], nw[own], g[own], xi)).sum(0)
    n = np.arange(-nk, nk + 1)
    kv = 2 * np.pi / L * np.array(list(itertools.product(n, n, n)), dtype=float)
    kv = kv[np.any(kv != 0, axis=1)]
    k2 = np.sum(kv ** 2, 1)
    psi = (1 + k2 / (4 * xi ** 2)) * np.exp(-k2 / (4 * xi ** 2)) / k2 ** 2
    ph = np.exp(-1j * kv @ src.T)                            # (K, S)
    U = np.zeros((kv.shape[0], 3), dtype=complex)
    if f is not None:
        F = ph @ f
        U += k2[:, None] * F - kv * np.sum(kv * F, 1)[:, None]
    if g is not None:
        S = np.einsum("ks,sj,sl->kjl", ph, g, nw)
        S = 0.5 * (S + np.transpose(S, (0, 2, 1)))
        Sk = np.einsum("kjl,kl->kj", S, kv)
        tr = np.einsum("kjj->k", S)
        kSk = np.sum(kv * Sk, 1)
        U += 1j * (k2[:, None] * (2 * Sk + kv * tr[:, None]) - 2 * kv * kSk[:, None])
    U *= psi[:, None] / L ** 3
    u += np.real(np.exp(1j * trg @ kv.T) @ U)
    return u


def clusters(rng, nclus, per, L, radius, ntrg_per, free_trg=0):
    """Sources in clusters ("vesicles") of radius ``radius`` around random centres in [0, L)^3,
    given unwrapped (a cluster near a face sticks out of the box); targets likewise plus
    ``free_trg`` targets with an id no source has."""
    c = rng.uniform(0, L, (nclus, 3))
    src = (c[:, None, :] + radius * rng.uniform(-1, 1, (nclus, per, 3))).reshape(-1, 3)
    trg = (c[:, None, :] + radius * rng.uniform(-1, 1, (nclus, ntrg_per, 3))).reshape(-1, 3)
    sid = np.repeat(np.arange(nclus), per)
    tid = np.repeat(np.arange(nclus), ntrg_per)
    if free_trg:
        trg = np.concatenate([trg, rng.uniform(0, L, (free_trg, 3))])
        tid = np.concatenate([tid, np.full(free_trg, -7)])
    perm = rng.permutation(src.shape[0])                    # ids need not be sorted
    return src[perm], sid[perm], trg, tid


def rel_err(u, ref):
    return float(np.max(np.abs(u - ref)) / np.max(np.abs(ref)))


# ------------------------------------------------------------------ the kernels
def test_smooth_part_is_full_minus_real_and_accurate_at_small_r(rng):
    xi = 2.3
    r = rng.standard_normal((50, 3))
    r *= (rng.uniform(0.2, 1.5, 50) / np.linalg.norm(r, axis=1))[:, None]
    f, nw, g = rng.standard_normal((3, 50, 3))
    ref = g_full(r, f) - g_real(r, f, xi) + t_full(r, nw, g) - t_real(r, nw, g, xi)
    assert np.max(np.abs(ek.smooth_part(r, f, nw, g, xi) - ref)) < 1e-12
    # small r, both sides of the series switch (z = SERIES_Z): against 50-digit arithmetic
    for z in (1e-6, 0.01, 0.9 * ek.SERIES_Z, 1.1 * ek.SERIES_Z, 0.5):
        d = rng.standard_normal(3)
        rz = d / np.linalg.norm(d) * z / xi
        fz, nwz, gz = rng.standard_normal((3, 3))
        ref = np.array(smooth_part_decimal(rz, fz, nwz, gz, xi))
        got = ek.smooth_part(rz[None], fz[None], nwz[None], gz[None], xi)[0]
        assert np.max(np.abs(got - ref)) < 1e-14 * np.max(np.abs(ref)), z
    # G^F(0) = 4 xi / sqrt(pi) I / (8 pi), T^F(0) = 0
    at0 = ek.smooth_part(np.zeros((20, 3)), f[:20], nw[:20], g[:20], xi)
    assert np.allclose(at0, 4 * xi / SQPI * f[:20] / (8 * np.pi), rtol=1e-14, atol=0)


@pytest.mark.parametrize("xi, rc", [(2.3, 1.9), (5.0, 1.1), (1.0, 6.0), (4.0, 1.6)])
def test_real_space_coefficients_without_libm(xi, rc):
    """erfc and exp of the vectorized real-space kernel (ewaldsum.h) against scipy, on [0, rc]
    and beyond (z up to 6.4), relative to each function's largest value (and erfc relative)."""
    r = np.linspace(1e-9, rc, 20001)
    z, sq = xi * r, SQPI
    e, ec = np.exp(-z * z), erfc(z)
    ref = np.stack([ec - 2 * z * e / sq, ec + 2 * z * e / sq, 4 * xi ** 3 * e / sq,
                    -2 * (3 * ec + (6 * z + 4 * z ** 3) * e / sq)], 1)
    got = ek.real_coefficients(xi, r)
    err = np.abs(got - ref).max(axis=0) / np.abs(ref).max(axis=0)
    assert np.all(err < 1e-13), err
    # erfc itself, relatively, down to 1e-18: (a1 + a2) / 2
    assert np.max(np.abs(0.5 * (got[:, 0] + got[:, 1]) / ec - 1)) < 1e-13


@pytest.mark.parametrize("own", ["subtract", "smooth"])
@pytest.mark.parametrize("period", [None, 1.7, 6.0])
def test_avx512_and_portable_real_space_loops_agree(rng, period, own):
    """The real-space sum by the AVX-512 loop and by the portable vectorized loop (ewaldsum.h):
    single + double layer, own vesicles (summed, or left out), a coincident pair, free space
    and periodic boxes with (1.7: fewer than 5 cells per axis) and without per-pair minimum
    images."""
    L = 6.0 if period is None else period
    src, sid, trg, tid = clusters(rng, 8, 40, L, 0.3 * min(L, 2.0), 10, free_trg=5)
    trg[0] = src[3]                                    # coincident with a source of another vesicle
    tid[0] = -7                                        # (a free target: own="smooth" needs small vesicles)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    rc = 0.28 * L                                      # own="smooth": extent 0.6 L + rc below L
    params = ewald.make_params(1e-8, ewald._exponents(math.log(1e8))[0] / rc, rc, np.concatenate([src, trg]),
                               period=period)
    es = ewald.EwaldSum(src, sid, trg, tid, period=period, params=params, double_layer=True, own=own)
    try:
        have = ek.set_vector_path(True)
        a = es.real_space(f, nw, g)
        ek.set_vector_path(False)
        b = es.real_space(f, nw, g)
    finally:
        ek.set_vector_path(True)
    if not have:
        pytest.skip("no AVX-512 on this CPU")
    assert rel_err(a, b) < 1e-13


def plain_real_space(src, sid, trg, tid, f, nw, g, xi, rc, period):
    """The real-space sum over the other vesicles' sources inside rc (minimum image when
    periodic), pair by pair with scipy's erfc (module docstring of ewald.pyx), r = 0: -G^F(0) f."""
    out = np.zeros(trg.shape)
    for t in range(trg.shape[0]):
        keep = sid != tid[t]
        r = trg[t] - src[keep]
        if period is not None:
            r -= period * np.round(r / period)
        rr = np.einsum("ij,ij->i", r, r)
        at0 = rr == 0.0
        ins = (rr < rc * rc) & ~at0
        r, rr, fk, nk, gk = r[ins], rr[ins], f[keep][ins], nw[keep][ins], g[keep][ins]
        rn = np.sqrt(rr)
        z = xi * rn
        e = np.exp(-z * z)
        a1 = erfc(z) - 2 * z * e / math.sqrt(math.pi)
        a2 = erfc(z) + 2 * z * e / math.sqrt(math.pi)
        rf = np.einsum("ij,ij->i", r, fk)
        u = (a1 / rn)[:, None] * fk + (a2 * rf / rn ** 3)[:, None] * r
        A = 4 * xi ** 3 * e / math.sqrt(math.pi)
        B = -2 * (3 * erfc(z) + (6 * z + 4 * z ** 3) * e / math.sqrt(math.pi)) / rn ** 5
        r_n, r_g, g_n = (np.einsum("ij,ij->i", *p) for p in ((r, nk), (r, gk), (gk, nk)))
        u += A[:, None] * (r_n[:, None] * gk + r_g[:, None] * nk + g_n[:, None] * r) + (B * r_n * r_g)[:, None] * r
        out[t] = u.sum(0) - 4 * xi / math.sqrt(math.pi) * f[keep][at0].sum(0)
    return out / (8 * math.pi)


@pytest.mark.parametrize("period, rc_frac, radius_frac", [(None, 0.28, 0.3), (6.0, 0.28, 0.3), (6.0, 0.45, 0.05),
                                                          (1.7, 0.28, 0.3)])
def test_real_space_in_place_matches_a_plain_pair_sum(rng, period, rc_frac, radius_frac):
    """The real space with the own vesicle left out (sources in place, cell ranges culled
    against each target, the periodic shift applied to the target) equals a plain sum over the
    pairs inside rc to rounding, on both vector paths: free space, a period of 7 cells per axis
    (image shifts per cell row), one of 4 (minimum image per pair) and a small box; a target on
    another vesicle's source (r = 0)."""
    L = 6.0 if period is None else period
    src, sid, trg, tid = clusters(rng, 8, 40, L, radius_frac * min(L, 2.0), 10, free_trg=5)
    trg[0] = src[3]
    tid[0] = -7
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    rc = rc_frac * L
    params = ewald.make_params(1e-8, ewald._exponents(math.log(1e8))[0] / rc, rc, np.concatenate([src, trg]),
                               period=period)
    es = ewald.EwaldSum(src, sid, trg, tid, period=period, params=params, double_layer=True, own="smooth")
    ref = plain_real_space(src, sid, trg, tid, f, nw, g, params.xi, rc, period)
    try:
        # every vector path this CPU runs (vesflow._kernels.paths: avx512, avx2, generic)
        for path in paths.PATHS[:paths.PATHS.index(ek.set_vector_path(True)) + 1]:
            ek.set_vector_path(path)
            assert rel_err(es.real_space(f, nw, g), ref) < 1e-13
            assert rel_err(es.real_space(f), plain_real_space(src, sid, trg, tid, f, 0 * nw, 0 * g, params.xi, rc,
                                                              period)) < 1e-13
    finally:
        ek.set_vector_path(True)
    if period is not None and rc_frac > 0.4:
        assert np.any(es._real.ncell < 5)                  # the minimum-image case is the one tested


# ------------------------------------------------------------------ own="smooth"
def own_smooth_share(src, sid, trg, tid, f, nw, g, xi):
    """sum over the target's own sources of G^F f + T^F:(g nw) / (8 pi) (ek.smooth_part), (T, 3)."""
    out = np.zeros(trg.shape)
    for t in range(trg.shape[0]):
        own = np.flatnonzero(sid == tid[t])
        if own.size:
            z = np.zeros((own.size, 3))
            r = np.ascontiguousarray(trg[t] - src[own])
            out[t] = ek.smooth_part(r, np.ascontiguousarray(z if f is None else f[own]),
                                    np.ascontiguousarray(z if g is None else nw[own]),
                                    np.ascontiguousarray(z if g is None else g[own]), xi).sum(0)
    return out


@pytest.mark.parametrize("tol", [1e-6, 1e-10])
@pytest.mark.parametrize("period", [None, 4.0])
def test_own_smooth_sum_minus_the_own_smooth_share_is_the_sum_over_other_vesicles(rng, tol, period):
    """EwaldSum(own="smooth") leaves the targets' own vesicles out of the real space and
    subtracts nothing: minus the own sources' smooth share it is the sum over the other
    vesicles (own="subtract", and the classical / direct sum) to tol; a cutoff below the
    clusters' size (0.8 of it), so that many own pairs lie beyond rc; free targets (no own
    vesicle) and a target on an own source (r = 0: G^F(0) finite)."""
    L = 4.0 if period is None else period
    src, sid, trg, tid = clusters(rng, 12, 60, L, 0.5, 12, free_trg=6)
    trg[1] = src[np.flatnonzero(sid == tid[1])[0]]
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    rc = 0.8
    pts = np.concatenate([src, trg])
    params = ewald.make_params(tol, ewald._exponents(math.log(1 / tol))[0] / rc, rc, pts, period=period)
    smooth = ewald.EwaldSum(src, sid, trg, tid, params=params, period=period, double_layer=True, own="smooth")
    sub = ewald.EwaldSum(src, sid, trg, tid, params=params, period=period, double_layer=True)
    for dens in ((f, None, None), (None, nw, g)):
        ref = np.zeros(trg.shape)
        if period is None and dens[0] is not None:
            stokes.stokeslet_sum_excl(src, f, sid, trg, tid, ref)
        elif period is None:
            stokes.stresslet_sum_excl(src, nw, g, sid, trg, tid, ref)
        else:
            ref = classical_ewald(src, *dens, sid, trg, tid, L, xi=4.0 / L)
        share = own_smooth_share(src, sid, trg, tid, *dens, params.xi)
        got = smooth.evaluate(*dens) - share
        old = sub.evaluate(*dens)
        rows = slice(None) if period is None else np.arange(trg.shape[0]) != 1   # classical: NaN at r = 0
        assert np.abs(share).max() > 0.1 * np.abs(ref[rows]).max()
        assert rel_err(got[rows], ref[rows]) < tol
        assert rel_err(got, old) < tol


def test_own_smooth_refuses_a_vesicle_whose_images_reach_within_rc(rng):
    """own="smooth" leaves out every image of the own vesicle: a cluster of extent 1.2 in a
    period of 1.7 with rc 0.6 would lose its images' real-space pairs: an error, not a result."""
    src, sid, trg, tid = clusters(rng, 3, 30, 1.7, 0.6, 5)
    params = ewald.make_params(1e-6, ewald._exponents(math.log(1e6))[0] / 0.6, 0.6, np.concatenate([src, trg]),
                               period=1.7)
    with pytest.raises(ValueError, match="own = 'smooth'"):
        ewald.EwaldSum(src, sid, trg, tid, params=params, period=1.7, own="smooth")
    with pytest.raises(ValueError, match="own"):
        ewald.EwaldSum(src, sid, trg, tid, params=params, period=1.7, own="exclude")


def test_smooth_kernel_tables_match_the_smooth_part(rng):
    """ek.smooth_kernel_tables (vectorized, erf without libm, series below z = 1/2) against
    ek.smooth_part (libm, series below SERIES_Z) for z = xi r from 0 (a coincident source)
    across the series switch to 4, both kernels, relative to the largest entry: 1e-13."""
    xi = 2.7
    x = rng.standard_normal((7, 3))
    dirs = rng.standard_normal((7, 300, 3))
    dirs /= np.linalg.norm(dirs, axis=2)[..., None]
    z = np.concatenate([[0.0, 1e-9, 0.4999, 0.5, 0.5001], np.linspace(0.0, 4.0, 295)])
    for t in range(7):
        y = np.ascontiguousarray(x[t] - dirs[t] * (z / xi)[:, None])
        w = rng.uniform(0.5, 2.0, len(z))
        nw = rng.standard_normal((len(z), 3))
        S = np.empty((1, 6, len(z)))
        D = np.empty((1, 6, len(z)))
        ek.smooth_kernel_tables(np.ascontiguousarray(x[t:t + 1]), y, w, nw, xi, S, D)
        r = np.ascontiguousarray(x[t] - y)
        for ab, (a, b) in enumerate(zip(*SYM)):
            e_b = np.zeros((len(z), 3))
            e_b[:, b] = 1.0
            zero = np.zeros((len(z), 3))
            ref_s = ek.smooth_part(r, np.ascontiguousarray(e_b * w[:, None]), zero, zero, xi)[:, a]
            ref_d = ek.smooth_part(r, zero, np.ascontiguousarray(nw), e_b, xi)[:, a]
            assert np.abs(S[0, ab] - ref_s).max() < 1e-13 * np.abs(ref_s).max()
            assert np.abs(D[0, ab] - ref_d).max() < 1e-13 * np.abs(ref_d).max()


def test_own_smooth_operators_are_the_smooth_share_in_coefficient_space(rng):
    """E_v f (vesflow.layerpot.own_smooth) is minus the p-grid analysis of the own smooth share
    of the far-field densities (q-grid values times weights; the double layer with n w), one
    biconcave vesicle, p = 6, q = 12, against ek.smooth_part pair by pair."""
    from vesflow.layerpot.own_smooth import OwnSmoothOperators
    p, q, xi, mu = 6, 12, 2.1, 1.7
    S = Surface(shapes.make_shape("biconcave", p, center=(0.3, -0.2, 0.1), rotation=(0.4, 1.1, 0.2))[None], p)
    geo = S.geometry(q)
    x = S.points().reshape(1, -1, 3)
    y, w = geo.X.reshape(1, -1, 3), geo.dA.reshape(1, -1)
    nw = (geo.normal * geo.dA[..., None]).reshape(1, -1, 3)
    E = OwnSmoothOperators(x, y, w, nw, xi, p, q, True, True, viscosity=mu)
    C = sph.n_coeffs(p)
    f, g = rng.standard_normal((2, 1, 3, C))
    Tq, Tp = sph.transform(p, q), sph.transform(p)
    fq = Tq.synth(f)[0].T * (w[0] / mu)[:, None]
    gq = Tq.synth(g)[0].T
    share = own_smooth_share(y[0], np.zeros(len(fq)), x[0], np.zeros(len(x[0])), fq, nw[0], gq, xi)
    ref = -Tp.analysis(share.T[None])
    got = E.apply(f, g)
    assert np.abs(got - ref).max() < 1e-12 * np.abs(ref).max()
    only_f = -Tp.analysis(own_smooth_share(y[0], np.zeros(len(fq)), x[0], np.zeros(len(x[0])), fq, None, None,
                                           xi).T[None])
    assert np.abs(E.apply(f) - only_f).max() < 1e-12 * np.abs(only_f).max()


@pytest.mark.parametrize("tol, period", [(1e-6, 7.5), (1e-10, 7.5), (1e-6, None),
                                         pytest.param(1e-10, None, marks=pytest.mark.slow)])
def test_layer_potentials_with_the_own_vesicle_in_the_set_up_match_the_old_mode(rng, monkeypatch, tol, period):
    """LayerPotentials.apply with the ewald far field, Settings.ewald_own "smooth"
    against "subtract" and, in free space, against the direct backend, both layers (lambda != 1),
    27 spheres in a periodic box, 8 in free space; the cutoff 1.2 (below the spheres' diameter:
    most own pairs beyond it)."""
    from vesflow.layerpot.evaluator import LayerPotentials, Settings
    rc = 1.2

    def fixed_cutoff(tol, points, period=None, *args, ncomp=3, **kw):
        return ewald.make_params(tol, ewald._exponents(math.log(1 / tol))[0] / rc, rc, points, period)
    monkeypatch.setattr(ewald, "choose_params", fixed_cutoff)
    p, side = 6, (3 if period else 2)
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = 2.5 * (ijk + 0.5) + rng.uniform(-0.1, 0.1, ijk.shape)
    S = Surface(np.stack([shapes.make_shape("sphere", p, center=tuple(c)) for c in centres]), p)
    n = len(centres)
    f, g = rng.standard_normal((2, n, 3, sph.n_coeffs(p)))
    lam = np.linspace(0.2, 4.0, n)
    out = {}
    for own in ("smooth", "subtract"):
        lp = LayerPotentials(S, lam=lam, settings=Settings(backend="ewald", fmm_eps=tol, period=period, ewald_own=own))
        assert lp.far.smooth_own == (own == "smooth") and (lp.own_ops is not None) == (own == "smooth")
        assert lp.far.ewald.params.rc == rc
        out[own] = lp.apply(f, g)
        if own == "smooth":
            lp.own_ops, ops = None, lp.own_ops
            assert rel_err(lp.apply(f, g), out[own]) > 1e-2
            lp.own_ops = ops
    # the own smooth share is large: without E_v the result is wrong
    assert rel_err(out["smooth"], out["subtract"]) < tol
    if period is None:
        lp = LayerPotentials(S, lam=lam, settings=Settings(backend="direct"))
        assert rel_err(out["smooth"], lp.apply(f, g)) < tol


def test_ewald_own_auto_takes_smooth_when_the_set_up_pays_over_the_applications(rng):
    """Settings.ewald_own "auto" (the default): the own smooth operators when the cost model's
    saving per application times applies_per_setup exceeds their set-up, else the subtraction in
    the iteration; the figures of the choice are kept (lp.own_auto) and the two choices give the
    same velocities to the Ewald tol."""
    from vesflow.layerpot.evaluator import APPLIES_PER_SETUP, LayerPotentials, Settings
    p, side = 6, 3
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    centres = 2.5 * (ijk + 0.5) + rng.uniform(-0.1, 0.1, ijk.shape)
    S = Surface(np.stack([shapes.make_shape("sphere", p, center=tuple(c)) for c in centres]), p)
    f = rng.standard_normal((len(centres), 3, sph.n_coeffs(p)))
    out = {}
    for applies, want in ((1e6, "smooth"), (1e-3, "subtract")):
        lp = LayerPotentials(S, settings=Settings(backend="ewald", fmm_eps=1e-6, period=7.5, ewald_own="auto",
                                                  applies_per_setup=applies))
        a = lp.own_auto
        assert a["saving"] > 0 and a["setup"] > 0 and a["applies"] == applies
        assert lp.far_own == want and (lp.own_ops is not None) == (want == "smooth")
        out[want] = lp.apply(f)
    assert rel_err(out["smooth"], out["subtract"]) < 1e-6
    # E_v in float32 from tol 1e-6 up (LayerPotentials._own_dtype), float64 below
    lp = LayerPotentials(S, settings=Settings(backend="ewald", fmm_eps=1e-6, period=7.5, ewald_own="smooth"))
    assert lp.own_ops.single.dtype == np.float32
    lp64 = LayerPotentials(S, settings=Settings(backend="ewald", fmm_eps=1e-8, period=7.5, ewald_own="smooth"))
    assert lp64.own_ops.single.dtype == np.float64
    assert rel_err(lp.apply(f), lp64.apply(f)) < 1e-6
    lp = LayerPotentials(S, settings=Settings(backend="ewald", fmm_eps=1e-6, period=7.5))
    a = lp.own_auto
    assert a["applies"] == APPLIES_PER_SETUP
    assert lp.far_own == ("smooth" if a["saving"] * APPLIES_PER_SETUP > a["setup"] else "subtract")
    with pytest.raises(ValueError, match="ewald_own"):
        Settings(ewald_own="smoth")


# ------------------------------------------------------------------ periodic
def test_classical_reference_is_independent_of_xi(rng):
    L = 1.7
    src, sid, trg, tid = clusters(rng, 4, 6, L, 0.2, 3, free_trg=3)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    a = classical_ewald(src, f, nw, g, sid, trg, tid, L, xi=4.0 / L)
    b = classical_ewald(src, f, nw, g, sid, trg, tid, L, xi=6.0 / L)
    assert rel_err(a, b) < 1e-12


@pytest.fixture(scope="module")
def periodic_case():
    """Clusters in a periodic cube and the classical Ewald sums of both layers."""
    rng = np.random.default_rng(7)
    L = 1.7
    src, sid, trg, tid = clusters(rng, 10, 30, L, 0.25, 8, free_trg=6)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    ref_s = classical_ewald(src, f, None, None, sid, trg, tid, L, xi=4.0 / L)
    ref_d = classical_ewald(src, None, nw, g, sid, trg, tid, L, xi=4.0 / L)
    return L, src, sid, trg, tid, f, nw, g, ref_s, ref_d


@pytest.mark.parametrize("tol", [1e-4, 1e-7, 1e-10])
@pytest.mark.parametrize("layer", ["single", "double"])
def test_periodic_ewald_matches_the_classical_sum(periodic_case, tol, layer):
    L, src, sid, trg, tid, f, nw, g, ref_s, ref_d = periodic_case
    es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, period=L, double_layer=layer == "double")
    if layer == "single":
        err = rel_err(es.evaluate(f_w=f), ref_s)
    else:
        err = rel_err(es.evaluate(nw=nw, g=g), ref_d)
    assert err < tol, (err, es.params)


def test_periodic_ewald_is_independent_of_xi(rng):
    L = 2.0
    src, sid, trg, tid = clusters(rng, 12, 40, L, 0.3, 10)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    pts = np.concatenate([src, trg])
    u = []
    for xi in (6.0, 9.0, 14.0):
        p = ewald.make_params(1e-11, xi, ewald._exponents(math.log(1e11))[0] / xi, pts, period=L)
        u.append(ewald.EwaldSum(src, sid, trg, tid, params=p).evaluate(f, nw, g))
    assert rel_err(u[0], u[1]) < 1e-10
    assert rel_err(u[0], u[2]) < 1e-10


@pytest.mark.parametrize("L, nufft", [(1.0, "ducc0"), (3.0, "ducc0"), (3.0, "finufft")])
def test_hasimoto_constant_of_a_cubic_lattice_of_point_forces(L, nufft):
    """One point force F per cell: the velocity at a lattice point minus the point's own
    Stokeslet is -2.837297 F / (6 pi L) (Hasimoto 1959: drag of a simple-cubic array,
    U = F / (6 pi a) (1 - 1.7601 c^(1/3) + ...) = F/(6 pi a) - 2.837297 F / (6 pi L))."""
    F = np.array([[0.3, -1.0, 2.0]])
    x = np.array([[0.4, 0.1, 0.7]]) * L
    es = ewald.EwaldSum(x, [0], x, [0], tol=1e-10, period=L, nufft=nufft)
    u = es.evaluate(f_w=F)
    assert np.allclose(u, -2.837297 * F / (6 * np.pi * L), rtol=2e-7, atol=0)


# ------------------------------------------------------------------ free space
@pytest.mark.parametrize("tol, nufft", [(1e-4, "ducc0"), (1e-7, "ducc0"), (1e-10, "ducc0"), (1e-7, "finufft"),
                                        (1e-10, "finufft")])
def test_free_space_ewald_matches_the_direct_sum_random_points(rng, tol, nufft):
    src, sid, trg, tid = clusters(rng, 20, 50, 3.0, 0.3, 15, free_trg=10)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, double_layer=True, nufft=nufft)
    for f_, nw_, g_ in ((f, None, None), (None, nw, g)):
        ref = np.zeros((trg.shape[0], 3))
        if f_ is not None:
            stokes.stokeslet_sum_excl(src, f_, sid, trg, tid, ref)
        else:
            stokes.stresslet_sum_excl(src, nw_, g_, sid, trg, tid, ref)
        err = rel_err(es.evaluate(f_, nw_, g_), ref)
        assert err < tol, (err, es.params)


@pytest.mark.parametrize("tol", [1e-4, 1e-10])
def test_free_space_ewald_matches_the_direct_sum_vesicle_surfaces(rng, tol):
    """Touching-distance vesicles of three shapes: q-grid sources with area weights, p-grid
    targets (one of them coincides with sources of its own vesicle on the equator), single
    and double layer together."""
    p, q = 8, 16
    placed = [("sphere", (0, 0, 0)), ("biconcave", (2.3, 0.1, 0)), ("oblate", (0.2, 2.2, 0.3)),
              ("prolate", (2.1, 2.4, 0.5)), ("biconcave", (1.0, 1.1, 1.9))]
    S = Surface(np.stack([shapes.make_shape(s, p, center=c, rotation=tuple(rng.uniform(0, 3, 3)))
                          for s, c in placed]), p)
    geo = S.geometry(q)
    n = len(placed)
    src = np.ascontiguousarray(geo.X.reshape(-1, 3))
    w = geo.dA.reshape(-1)
    nw = np.ascontiguousarray((geo.normal * geo.dA[..., None]).reshape(-1, 3))
    sid = np.repeat(np.arange(n), src.shape[0] // n)
    trg = np.ascontiguousarray(S.points().reshape(-1, 3))
    tid = np.repeat(np.arange(n), trg.shape[0] // n)
    f_w = rng.standard_normal(src.shape) * w[:, None]
    g = rng.standard_normal(src.shape)
    ref = np.zeros(trg.shape)
    stokes.stokeslet_sum_excl(src, f_w, sid, trg, tid, ref)
    stokes.stresslet_sum_excl(src, nw, g, sid, trg, tid, ref)
    es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, double_layer=True)
    err = rel_err(es.evaluate(f_w, nw, g), ref)
    assert err < tol, (err, es.params)


# ------------------------------------------------------------------ FarField backend
def test_farfield_ewald_backend_matches_direct_in_the_layer_potentials(rng):
    """-ves_far ewald through LayerPotentials (far sum + near and self corrections) agrees with
    the direct backend to the far-field tolerance, both layers (viscosity contrast)."""
    from vesflow.layerpot.evaluator import LayerPotentials, Settings
    p = 6
    centres = [(0, 0, 0), (2.2, 0.3, 0), (0.1, 2.3, 0.2), (2.0, 2.1, 1.2)]
    S = Surface(np.stack([shapes.make_shape("oblate", p, center=c, rotation=tuple(rng.uniform(0, 3, 3)))
                          for c in centres]), p)
    f, g = rng.standard_normal((2, len(centres), 3, sph.n_coeffs(p)))
    out = {}
    for backend in ("direct", "ewald"):
        lp = LayerPotentials(S, lam=0.4, settings=Settings(backend=backend, fmm_eps=1e-9))
        assert lp.far.backend == backend
        out[backend] = lp.apply(f, g)
    assert rel_err(out["ewald"], out["direct"]) < 1e-9


@pytest.mark.parametrize("rc", [0.5, 1.5, 4.0])
def test_cost_model_pair_count_in_free_space_counts_the_pairs_near_the_faces(rng, rc):
    """The cost model's expected pairs closer than rc for uniform points in a free-space box
    (the box's autocorrelation over the ball) against a count: within 3 %; the periodic
    estimate 4/3 pi rc^3 / V overcounts by 1.1x, 1.5x and 3.7x here (measured: 0.3 %, 0.3 %, 0.6 % off)."""
    box = np.array([3.0, 5.0, 8.0])
    x = rng.uniform(0, 1, (3000, 3)) * box
    d2 = np.sum((x[:, None, :] - x[None, :, :]) ** 2, -1)
    counted = (np.count_nonzero(d2 < rc * rc) - x.shape[0]) / (x.shape[0] * (x.shape[0] - 1))
    p = ewald.make_params(1e-6, 1.0, rc, np.concatenate([[0, 0, 0], box]).reshape(2, 3))
    assert p.box == pytest.approx(tuple(box))
    assert ewald._pair_fraction(p) == pytest.approx(counted, rel=0.03)


def test_auto_takes_the_predicted_fastest_backend():
    from vesflow.layerpot import far
    assert far.choose_backend(1000, 1000, "auto", 1e-8, t_ewald=1e-9) == "ewald"
    assert far.choose_backend(1000, 1000, "auto", 1e-8, t_ewald=1e3) == "direct"
    assert far.choose_backend(1000, 1000, "auto", 1e-8, t_ewald=1e3, periodic=True) == "ewald"
    with pytest.raises(Exception, match="periodic"):
        far.choose_backend(1000, 1000, "direct", periodic=True)
    # a small free-space problem: the model predicts the direct sum faster, and FarField follows
    src = np.random.default_rng(0).uniform(0, 1, (200, 3))
    ff = far.FarField(src, np.arange(200) // 20, src, np.arange(200) // 20, backend="auto")
    assert ff.backend == "direct"


# ------------------------------------------------------------------ periodic layer potentials
def test_periodic_layer_potentials_are_translation_invariant_across_the_box_faces(rng):
    """Close vesicles in a periodic box: translating the whole suspension so that a close pair
    straddles a face, and moving one vesicle by a period, changes nothing (the near pairs are
    found across the faces by minimum image, the Ewald sum is periodic)."""
    from vesflow.layerpot.evaluator import LayerPotentials, Settings
    p, L = 6, 5.0
    centres = np.array([(1.0, 1.0, 1.0), (3.15, 1.1, 1.0), (1.2, 3.3, 2.5)])    # gap of the first two ~0.1
    coeffs = np.stack([shapes.make_shape("sphere", p, center=c) for c in centres])
    f, g = rng.standard_normal((2, len(centres), 3, sph.n_coeffs(p)))
    settings = Settings(backend="ewald", fmm_eps=1e-10, period=L)

    def run(shift, moved):
        c = coeffs.copy()
        c[:, :, 0] += np.sqrt(4 * np.pi) * (shift + moved)
        lp = LayerPotentials(Surface(c, p), lam=0.5, settings=settings)
        return lp.apply(f, g), lp.n_near_pairs

    u0, n0 = run(np.zeros(3), np.zeros((3, 3)))
    moved = np.zeros((3, 3))
    moved[1, 0] = L
    moved[2] = (-L, L, -L)
    u1, n1 = run(np.array([1.9, -1.0, 0.3]), moved)        # the close pair straddles x = 5
    assert n0 > 0 and n1 == n0
    assert rel_err(u1, u0) < 1e-8


@pytest.mark.parametrize("phi, rtol", [(0.01, 1e-3), (0.05, 1e-2)])
def test_spherical_vesicle_in_a_periodic_cube_sediments_at_hasimotos_velocity(phi, rtol):
    """A spherical vesicle (one per cube of side L, volume fraction phi) under gravity: the
    surface-averaged velocity against the simple-cubic expansion U/U0 = 1 - 1.7601 phi^(1/3)
    + phi - 1.5593 phi^2 + 3.9799 phi^(8/3) - 3.0734 phi^(10/3) (Hasimoto 1959; Sangani and
    Acrivos 1982).  Measured: 0.630748 vs 0.630660 (phi 0.01), 0.400614 vs 0.398884 (0.05)."""
    petsc4py = pytest.importorskip("petsc4py")
    petsc4py.init([])
    from vesflow.layerpot.evaluator import Settings
    from vesflow.operator import VesicleParams
    from vesflow.stepper import Physics, Stepper
    p, a, drho = 8, 1.0, 1.0
    L = (4 * np.pi / 3 / phi) ** (1 / 3) * a
    c = shapes.make_shape("sphere", p, radius=a, center=(0.3, 0.2, 0.1))[None]
    st = Stepper(c, p, VesicleParams([0.1], [1.0], [drho]), Physics(gravity=np.array([0.0, 0.0, -1.0])),
                 lp_settings=Settings(backend="ewald", fmm_eps=1e-10, period=L))
    u = sph.transform(p).synth(st.velocity().u)[0]
    w = Surface(c, p).geometry().dA.reshape(-1)
    ratio = -(u[2] * w).sum() / w.sum() / (2 * drho * a * a / 9)
    f3 = phi ** (1 / 3)
    expected = 1 - 1.7601 * f3 + phi - 1.5593 * phi ** 2 + 3.9799 * phi ** (8 / 3) - 3.0734 * phi ** (10 / 3)
    assert ratio == pytest.approx(expected, rel=rtol)


def test_single_and_double_layer_in_two_passes_when_the_grids_do_not_fit(rng, monkeypatch):
    src, sid, trg, tid = clusters(rng, 6, 20, 2.0, 0.3, 5)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    es = ewald.EwaldSum(src, sid, trg, tid, tol=1e-8, double_layer=True)
    one = es.evaluate(f, nw, g)
    calls = []
    fourier = es.fourier
    monkeypatch.setattr(es, "fourier", lambda *a, **k: calls.append(1) or fourier(*a, **k))
    monkeypatch.setattr(ewald, "MAX_GRID_BYTES", 1)
    two = es.evaluate(f, nw, g)
    assert len(calls) == 2 and rel_err(two, one) < 1e-13


@pytest.mark.slow
@pytest.mark.parametrize("tol, xi", [(1e-4, 2.0), (1e-8, 1.0), (1e-10, 0.5)])
def test_free_space_accuracy_with_a_large_splitting_in_a_large_box(tol, xi):
    """Sparse clusters in a box of side 12 with xi B up to 24 (a stress test of the window
    and of the stresslet's error prefactors): both layers within tol of the direct sum."""
    rng = np.random.default_rng(4)
    src, sid, trg, tid = clusters(rng, 40, 30, 12.0, 0.5, 10, free_trg=10)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    pts = np.concatenate([src, trg])
    p = ewald.make_params(tol, xi, ewald._exponents(math.log(1 / tol))[0] / xi, pts)
    es = ewald.EwaldSum(src, sid, trg, tid, params=p)
    for dens, kern in (((f, None, None), lambda o: stokes.stokeslet_sum_excl(src, f, sid, trg, tid, o)),
                       ((None, nw, g), lambda o: stokes.stresslet_sum_excl(src, nw, g, sid, trg, tid, o))):
        ref = np.zeros(trg.shape)
        kern(ref)
        assert rel_err(es.evaluate(*dens), ref) < tol


def sphere_lattice(rng, n, p, q, spacing=2.5):
    """Unit spheres on a jittered lattice as benchmarks/far_field.py: p-grid targets, q-grid
    sources with Gauss-Legendre area weights, area-weighted random densities."""
    side = int(np.ceil(n ** (1 / 3)))
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    centres = spacing * ijk + rng.uniform(-0.2, 0.2, (n, 3))

    def grid(m):
        x, w = np.polynomial.legendre.leggauss(m + 1)
        x, w = x[::-1], w[::-1]
        th, ph = np.meshgrid(np.arccos(x), np.pi * np.arange(2 * m) / m, indexing="ij")
        pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
        return pts, np.repeat(w * np.pi / m, 2 * m)
    tp, sp, sw = grid(p)[0], *grid(q)
    trg = (centres[:, None] + tp[None]).reshape(-1, 3)
    src = (centres[:, None] + sp[None]).reshape(-1, 3)
    sid, tid = np.repeat(np.arange(n), sp.shape[0]), np.repeat(np.arange(n), tp.shape[0])
    f = rng.standard_normal(src.shape) * np.tile(sw, n)[:, None]
    nw = (src - np.repeat(centres, sp.shape[0], axis=0)) * np.tile(sw, n)[:, None]
    return src, sid, trg, tid, f, nw, rng.standard_normal(src.shape)


@pytest.mark.parametrize("layer", ["single", "double"])
def test_periodic_ewald_error_at_the_nufft_accuracy_it_requests(rng, layer):
    """The NUFFT runs at eps = NUFFT_EPS_FACTOR * tol (1.0): 8 spheres of benchmarks/far_field.py
    (p = 16, q = 32) in a periodic box of 5 against the Ewald sum at 1e-13, single layer alone
    (the Stokeslet's error prefactor) and double layer: error below tol / 2 at 1e-4 and 1e-6.
    Measured 0.24 / 0.16 tol (single), 0.23 / 0.15 (double); with eps = 5 tol 1.02 / 0.43 and
    0.69 / 0.77 tol, with 3 tol 0.55 / 0.28 and 0.34 / 0.43 (experiments/nufft_eps_margin.py)."""
    src, sid, trg, tid, f, nw, g = sphere_lattice(np.random.default_rng(0), 8, 16, 32)
    dbl = layer == "double"
    dens = (None, nw, g) if dbl else (f, None, None)
    ref = ewald.EwaldSum(src, sid, trg, tid, tol=1e-13, period=5.0, double_layer=dbl).evaluate(*dens)
    for tol in (1e-4, 1e-6):
        es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, period=5.0, double_layer=dbl)
        assert es.params.nufft_eps == pytest.approx(ewald.NUFFT_EPS_FACTOR * tol)
        assert rel_err(es.evaluate(*dens), ref) < 0.5 * tol, (tol, es.params)


@pytest.mark.parametrize("own", ["subtract", "smooth"])
@pytest.mark.parametrize("q", [24, 40])
def test_ewald_far_field_with_grids_whose_shared_points_coincide_only_up_to_rounding(rng, q, own):
    """At p = 16 the q = 24 and 40 grids share equator points with the p-grid targets only up
    to rounding (longitudes 2 pi k / 32 against 2 pi m / 2q): with own="subtract" the own
    vesicle's real-space pair and its subtracted full kernel cancel two 1/r ~ 1e16 terms unless
    the target is snapped onto the source (it was 2.5e-2 off the direct sum at q = 24, 5e-9 at
    q = 32); own="smooth" has no own pair (the smooth share G^F is finite there), no snap."""
    from vesflow.layerpot.evaluator import LayerPotentials, Settings
    p = 16
    S = Surface(np.stack([shapes.make_shape("sphere", p, center=c) for c in [(0, 0, 0), (2.5, 0.2, 0.1)]]), p)
    f = rng.standard_normal((2, 3, sph.n_coeffs(p)))
    out = {}
    for backend in ("direct", "ewald"):
        lp = LayerPotentials(S, lam=1.0, settings=Settings(backend=backend, fmm_eps=1e-6, q_far=q, ewald_own=own))
        assert lp.far.backend == backend
        out[backend] = lp.apply(f)
    assert lp.far.smooth_own == (own == "smooth")
    assert (lp.far.n_snapped > 0) == (own == "subtract")
    assert rel_err(out["ewald"], out["direct"]) < 1e-6
