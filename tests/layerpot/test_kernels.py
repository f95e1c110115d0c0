"""Compiled kernels (vesflow/_kernels) and far-field backends (vesflow/layerpot/far.py).

Kernels of the docs/explanation/method.md, section 4 (mu = 1, r = x - y):
  Stokeslet  S f = (1/(8 pi)) (f/r + r (r.f)/r^3)
  stresslet  D g = -(3/(4 pi)) (r.nw)(r.g) r / r^5
"""
import os
import subprocess
import sys

import numpy as np
import pytest

from vesflow._kernels import paths, search, stokes
from vesflow.errors import SettingsError
from vesflow.layerpot import far

RTOL = 1e-13


# ----------------------------------------------------------------------------- references
def ref_stokeslet(src, f, trg, mask=None):
    r = trg[:, None, :] - src[None, :, :]
    rr = np.einsum("tsk,tsk->ts", r, r)
    keep = rr > 0 if mask is None else (rr > 0) & mask
    with np.errstate(divide="ignore", invalid="ignore"):
        ri = np.where(keep, 1.0 / np.sqrt(rr), 0.0)
    rf = np.einsum("tsk,sk->ts", r, f)
    return (f[None] * ri[..., None] + r * (rf * ri**3)[..., None]).sum(1) / (8 * np.pi)


def ref_stresslet(src, nw, g, trg, mask=None):
    r = trg[:, None, :] - src[None, :, :]
    rr = np.einsum("tsk,tsk->ts", r, r)
    keep = rr > 0 if mask is None else (rr > 0) & mask
    with np.errstate(divide="ignore", invalid="ignore"):
        ri = np.where(keep, 1.0 / np.sqrt(rr), 0.0)
    c = np.einsum("tsk,sk->ts", r, nw) * np.einsum("tsk,sk->ts", r, g) * ri**5
    return -3.0 / (4 * np.pi) * (r * c[..., None]).sum(1)


def relerr(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


def sphere_grid(q, radius=1.0, centre=(0.0, 0.0, 0.0)):
    """q-grid of docs/explanation/conventions.md on a sphere: points, outward normals, area weights."""
    x, w = np.polynomial.legendre.leggauss(q + 1)
    order = np.argsort(-x)
    x, w = x[order], w[order]
    th, ph = np.meshgrid(np.arccos(x), np.pi * np.arange(2 * q) / q, indexing="ij")
    n = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    wts = np.repeat(w * np.pi / q, 2 * q) * radius**2     # W / sin(theta) = radius^2
    return np.asarray(centre) + radius * n, n, wts


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


@pytest.fixture
def cloud(rng):
    src = rng.uniform(-1, 1, (400, 3))
    trg = rng.uniform(-1.5, 1.5, (250, 3))
    trg[7] = src[11]                       # an exact coincidence: skipped (r == 0)
    return src, trg


# ----------------------------------------------------------------------------- vector paths
# every path this CPU runs (an AVX-512 machine tests all three: a CI machine with AVX2 only
# runs avx2 and generic, so an error of a path must fail where it can run)
PATHS_HERE = paths.PATHS[:paths.PATHS.index(stokes.set_vector_path(True)) + 1]


@pytest.fixture(params=PATHS_HERE)
def path(request):
    """Run the test on one vector path of pairsum.h (stokes module), the best one afterwards."""
    try:
        assert stokes.set_vector_path(request.param) == request.param == stokes.vector_path()
        yield request.param
    finally:
        stokes.set_vector_path(True)


def test_range_sums_match_numpy_on_every_path(rng, cloud, path):
    """pairsum.h's range sums (AVX-512: 8 lanes, rsqrt14 + 2 Newton steps; AVX2: 4 lanes,
    float rsqrt + Newton + a third-order step; generic: the compiled loops) against numpy:
    Stokeslet and stresslet, a coincident pair (skipped), 397 sources (not a multiple of 4 or 8)."""
    src, trg = cloud
    src = src[:397]
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    a, b = np.zeros_like(trg), np.zeros_like(trg)
    stokes.stokeslet_sum(src, f, trg, a)
    stokes.stresslet_sum(src, nw, g, trg, b)
    assert np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    assert relerr(a, ref_stokeslet(src, f, trg)) < RTOL
    assert relerr(b, ref_stresslet(src, nw, g, trg)) < RTOL
    for m in (1, 2, 3, 5, 6, 7):                      # the partial blocks alone
        a = np.zeros((3, 3))
        stokes.stokeslet_sum(src[:m], f[:m], trg[:3], a)
        assert relerr(a, ref_stokeslet(src[:m], f[:m], trg[:3])) < RTOL


def test_extreme_distances_on_every_path(path):
    """Distances outside the single-precision range of the AVX2 estimate (|r|^2 < 1e-36 or
    > 1e36: 1/r lane by lane) beside ordinary ones, and a relative accuracy below 1e-14 for
    distances over 12 decades."""
    src = np.zeros((6, 3))
    src[:, 0] = [1e-20, -3e-19, 2e19, 0.5, 1e-10, 1e10]
    trg = np.zeros((1, 3))
    for k in range(6):
        f = np.zeros((6, 3))
        f[k, 1] = 1.0
        out = np.zeros((1, 3))
        stokes.stokeslet_sum(src, f, trg, out)
        want = 1.0 / (8 * np.pi * abs(src[k, 0]))
        assert abs(out[0, 1] - want) <= 1e-15 * want, (k, out[0, 1], want)
    r = np.logspace(-6, 6, 397)
    src = np.stack([r, 0.3 * r, -0.2 * r], 1)
    f = np.ones_like(src)
    out = np.zeros((1, 3))
    stokes.stokeslet_sum(src, f, trg, out)
    assert relerr(out, ref_stokeslet(src, f, trg)) < 1e-14


def test_vector_path_choice():
    """The path by name, True (the best) and False (generic); an unknown name is a one-line
    SettingsError naming the valid ones; VESFLOW_SIMD sets the path of both kernel modules at
    import and is checked likewise."""
    try:
        assert stokes.set_vector_path(False) == "generic" == stokes.vector_path()
        assert stokes.set_vector_path(True) == PATHS_HERE[-1]
        with pytest.raises(SettingsError, match="must be one of generic, avx2, avx512"):
            stokes.set_vector_path("sse")
        assert stokes.vector_path() == PATHS_HERE[-1]           # unchanged by the error
    finally:
        stokes.set_vector_path(True)
    code = "from vesflow._kernels import stokes, ewald; print(stokes.vector_path(), ewald.vector_path())"
    for name in PATHS_HERE:
        res = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, VESFLOW_SIMD=name),
                             capture_output=True, text=True, check=True)
        assert res.stdout.split() == [name, name]
    res = subprocess.run([sys.executable, "-c", code], env=dict(os.environ, VESFLOW_SIMD="avx3"),
                         capture_output=True, text=True)
    assert res.returncode != 0 and "VESFLOW_SIMD=avx3: must be one of generic, avx2, avx512" in res.stderr


# ----------------------------------------------------------------------------- plain sums
def test_stokeslet_sum_matches_numpy(rng, cloud):
    src, trg = cloud
    f = rng.standard_normal(src.shape)
    out = np.zeros_like(trg)
    stokes.stokeslet_sum(src, f, trg, out)
    assert np.all(np.isfinite(out))
    assert relerr(out, ref_stokeslet(src, f, trg)) < RTOL
    # accumulates into out
    stokes.stokeslet_sum(src, f, trg, out)
    assert relerr(out, 2 * ref_stokeslet(src, f, trg)) < RTOL


def test_stresslet_sum_matches_numpy(rng, cloud):
    src, trg = cloud
    nw, g = rng.standard_normal(src.shape), rng.standard_normal(src.shape)
    out = np.ones_like(trg)
    stokes.stresslet_sum(src, nw, g, trg, out)
    assert np.all(np.isfinite(out))
    assert relerr(out - 1.0, ref_stresslet(src, nw, g, trg)) < RTOL


def test_shape_errors(rng):
    a = np.zeros((5, 3))
    with pytest.raises(ValueError):
        stokes.stokeslet_sum(a, np.zeros((4, 3)), a, a.copy())
    with pytest.raises(ValueError):
        stokes.stokeslet_sum(np.zeros((5, 2)), np.zeros((5, 2)), a, a.copy())
    out = np.zeros((0, 3))
    stokes.stokeslet_sum(np.zeros((0, 3)), np.zeros((0, 3)), out, out)   # empty is fine


# ----------------------------------------------------------------------------- exclusion and pairs
@pytest.mark.parametrize("ids", ["random", "sorted"])
def test_excl_variants(rng, cloud, ids, path):
    """Unsorted ids take the per-pair test; sorted ids (vesicle order, the run's case) the sums
    around the own group's range (pairsum.h), including ids no source has (-1, 7)."""
    src, trg = cloud
    src_id = rng.integers(0, 6, src.shape[0])
    if ids == "sorted":
        src_id = np.sort(src_id)
    trg_id = rng.integers(-1, 8, trg.shape[0])         # -1, 6, 7: free targets, nothing excluded
    f, nw, g = (rng.standard_normal(src.shape) for _ in range(3))
    mask = trg_id[:, None] != src_id[None, :]
    out = np.zeros_like(trg)
    stokes.stokeslet_sum_excl(src, f, src_id, trg, trg_id, out)
    assert relerr(out, ref_stokeslet(src, f, trg, mask)) < RTOL
    out = np.zeros_like(trg)
    stokes.stresslet_sum_excl(src, nw, g, src_id, trg, trg_id, out)
    assert relerr(out, ref_stresslet(src, nw, g, trg, mask)) < RTOL


def test_pairs_variants(rng, cloud, path):
    src, trg = cloud
    sizes = np.array([50, 0, 120, 80, 150])            # an empty vesicle too
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    f, nw, g = (rng.standard_normal(src.shape) for _ in range(3))
    pairs = np.stack([rng.integers(0, trg.shape[0], 300), rng.integers(0, sizes.size, 300)], 1)
    pairs[0] = [7, 0]                                  # trg[7] == src[11], in vesicle 0
    out_s = np.zeros((pairs.shape[0], 3))
    out_d = np.zeros((pairs.shape[0], 3))
    stokes.stokeslet_sum_pairs(src, f, off, trg, pairs, out_s)
    stokes.stresslet_sum_pairs(src, nw, g, off, trg, pairs, out_d)
    ref_s = np.zeros_like(out_s)
    ref_d = np.zeros_like(out_d)
    for k, (t, v) in enumerate(pairs):
        sl = slice(off[v], off[v + 1])
        ref_s[k] = ref_stokeslet(src[sl], f[sl], trg[t:t + 1])[0]
        ref_d[k] = ref_stresslet(src[sl], nw[sl], g[sl], trg[t:t + 1])[0]
    assert np.all(out_s[pairs[:, 1] == 1] == 0.0)
    assert relerr(out_s, ref_s) < RTOL
    assert relerr(out_d, ref_d) < RTOL
    with pytest.raises(IndexError):
        stokes.stokeslet_sum_pairs(src, f, off, trg, np.array([[0, 5]]), np.zeros((1, 3)))


def test_block_kernels_equal_the_pair_kernels_exactly(rng, cloud, path):
    """Blocks of 9 targets against one vesicle (the near correction), vectorized across the
    block: on the vector paths bit for bit the values of the pair kernels (the same lanes per
    target), on the compiled loops to rounding; a coincident point contributing 0."""
    exact = (lambda a, b: np.array_equal(a, b)) if path != "generic" else \
        (lambda a, b: np.abs(a - b).max() <= 1e-13 * np.abs(b).max())
    src, trg = cloud
    sizes = np.array([50, 0, 120, 80, 150])
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    f, nw, g = (rng.standard_normal(src.shape) for _ in range(3))
    P, K = 40, 9
    ves = rng.integers(0, sizes.size, P).astype(np.int64)
    ves[0] = 0
    blocks = np.ascontiguousarray(trg[rng.integers(0, trg.shape[0], P * K)].reshape(P, K, 3))
    blocks[0, 4] = trg[7]                              # == src[11], in vesicle 0
    pairs = np.ascontiguousarray(np.stack([np.arange(P * K), np.repeat(ves, K)], 1), dtype=np.int64)
    for pair_kernel, block_kernel, dens in ((stokes.stokeslet_sum_pairs, stokes.stokeslet_sum_blocks, (f,)),
                                            (stokes.stresslet_sum_pairs, stokes.stresslet_sum_blocks, (nw, g))):
        ref = np.zeros((P * K, 3))
        pair_kernel(src, *dens, off, blocks.reshape(-1, 3), pairs, ref)
        ref = ref.reshape(P, K, 3)
        planar = [stokes.planar(a, off) for a in (src,) + dens]
        for k in (9, 5, 4, 2, 1):                       # passes of 3 (2) targets and the shorter rest
            out = np.zeros((P, k, 3))
            block_kernel(*planar, off, np.ascontiguousarray(blocks[:, :k]), ves, out)
            assert exact(out, ref[:, :k]) and np.all(np.isfinite(out))
            assert np.all(out[ves == 1] == 0.0) and np.any(out[0] != 0.0)
    # both layers in one pass: bit for bit the Stokeslet call followed by the stresslet call
    planar = [stokes.planar(a, off) for a in (src, f, nw, g)]
    for k in (1, 2, 5, 9):
        b = np.ascontiguousarray(blocks[:, :k])
        ref = np.zeros((P, k, 3))
        stokes.stokeslet_sum_blocks(planar[0], planar[1], off, b, ves, ref)
        stokes.stresslet_sum_blocks(planar[0], planar[2], planar[3], off, b, ves, ref)
        out = np.zeros((P, k, 3))
        stokes.stokeslet_stresslet_sum_blocks(*planar, off, b, ves, out)
        assert exact(out, ref) and np.all(out[ves == 1] == 0.0) and np.any(out[0] != 0.0)
    # against numpy pair by pair (the last, both layers, at k = 9)
    want = np.stack([ref_stokeslet(src[off[v]:off[v + 1]], f[off[v]:off[v + 1]], blocks[p])
                     + ref_stresslet(src[off[v]:off[v + 1]], nw[off[v]:off[v + 1]], g[off[v]:off[v + 1]], blocks[p])
                     if off[v + 1] > off[v] else np.zeros((K, 3)) for p, v in enumerate(ves)])
    assert relerr(out, want) < RTOL
    sp, fp = stokes.planar(src, off), stokes.planar(f, off)
    with pytest.raises(ValueError, match="at most 16"):
        stokes.stokeslet_sum_blocks(sp, fp, off, np.zeros((1, 17, 3)), np.zeros(1, dtype=np.int64),
                                    np.zeros((1, 17, 3)))
    with pytest.raises(ValueError, match="not a vesicle index"):
        stokes.stokeslet_sum_blocks(sp, fp, off, blocks[:1], np.array([5]), np.zeros((1, K, 3)))
    with pytest.raises(ValueError, match="must be planar"):
        stokes.stokeslet_sum_blocks(sp[:-3], fp, off, blocks[:1], ves[:1], np.zeros((1, K, 3)))
    # the planar layout: vesicle v's x, y, z runs from 3 off[v]
    for v in range(sizes.size):
        o, m = off[v], off[v + 1] - off[v]
        assert np.array_equal(sp[3 * o:3 * (o + m)].reshape(3, m), src[o:o + m].T)


# ----------------------------------------------------------------------------- near search
def brute_near(trg, trg_id, src, src_id, h):
    d = np.sqrt(((trg[:, None, :] - src[None, :, :]) ** 2).sum(-1))
    res = {}
    for t, s in zip(*np.nonzero((d <= h) & (trg_id[:, None] != src_id[None, :]))):
        key = (int(t), int(src_id[s]))
        res[key] = min(res.get(key, np.inf), d[t, s])
    keys = sorted(res)
    return np.array(keys, dtype=np.int64).reshape(-1, 2), np.array([res[k] for k in keys])


@pytest.mark.parametrize("h", [0.05, 0.3, 2.0])
def test_near_pairs_matches_brute_force(rng, h):
    # 12 "vesicles": noisy spheres of radius 0.5 with centres in a 3-box, some touching
    centres = rng.uniform(0, 3, (12, 3))
    pts, _, _ = sphere_grid(8, 0.5)
    src = (centres[:, None, :] + pts[None] + 0.01 * rng.standard_normal((12,) + pts.shape)).reshape(-1, 3)
    src_id = np.repeat(np.arange(12) * 7 - 20, pts.shape[0])     # arbitrary ids, negative too
    trg = np.concatenate([src[::5] + 0.02 * rng.standard_normal(src[::5].shape),
                          rng.uniform(-1, 4, (200, 3)), [[1e3, 0.0, 0.0]]])
    trg_id = np.concatenate([src_id[::5], np.full(201, 999)])
    pairs, dist = search.near_pairs(trg, trg_id, src, src_id, h)
    ref_pairs, ref_dist = brute_near(trg, trg_id, src, src_id, h)
    assert pairs.dtype == np.int64 and dist.dtype == np.float64
    assert pairs.shape[0] > 0
    np.testing.assert_array_equal(pairs, ref_pairs)
    np.testing.assert_allclose(dist, ref_dist, rtol=1e-15, atol=0)


def test_near_pairs_sparse_domain(rng):
    # two clusters 1e7 apart with h = 1e-2: a dense grid over the box would have 1e27 cells
    a = rng.uniform(0, 0.1, (300, 3))
    src = np.concatenate([a, a + 1e7])
    src_id = np.repeat([0, 1, 2, 3], 150)
    trg = src + 1e-3
    trg_id = src_id.copy()
    pairs, dist = search.near_pairs(trg, trg_id, src, src_id, 1e-2)
    ref_pairs, ref_dist = brute_near(trg, trg_id, src, src_id, 1e-2)
    np.testing.assert_array_equal(pairs, ref_pairs)
    np.testing.assert_allclose(dist, ref_dist, rtol=1e-12)
    empty, d = search.near_pairs(trg[:0], trg_id[:0], src, src_id, 0.1)
    assert empty.shape == (0, 2) and d.shape == (0,)
    with pytest.raises(ValueError):
        search.near_pairs(trg, trg_id, src, src_id, 0.0)


def test_coincident_sources():
    src = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])
    off = np.array([0, 2, 4])
    trg = np.array([[1 + 1e-14, 0, 0], [1 + 1e-14, 0, 0], [2.5, 0, 0], [3, 0, 0]])
    vi = np.array([0, 1, 1, -1])
    np.testing.assert_array_equal(search.coincident_sources(src, off, trg, vi, 1e-12), [1, -1, -1, -1])


# ----------------------------------------------------------------------------- normalizations
def test_stokeslet_normalization_rigid_sphere():
    """Uniform traction f0 on a sphere of radius a: u = 2 a f0 / 3 inside (rigid translation)."""
    a, c = 1.7, np.array([0.3, -0.2, 0.5])
    pts, _, w = sphere_grid(24, a, c)
    f0 = np.array([0.4, -1.1, 2.0])
    trg = np.array([c, c + 0.35 * a * np.array([0.6, 0.0, 0.8])])
    out = np.zeros((2, 3))
    stokes.stokeslet_sum(pts, f0 * w[:, None], trg, out)
    expect = 2 * a * f0 / 3
    assert np.abs(out[0] - expect).max() < 1e-13 * np.abs(expect).max()   # degree-2 integrand: exact
    assert np.abs(out[1] - expect).max() < 1e-10 * np.abs(expect).max()   # smooth: spectral


def test_stresslet_normalization_double_layer_identity():
    """D[e_k](x) = e_k inside, 0 outside (lambda = 0 kernel, section 4 / eq. 3.10)."""
    a, c = 1.3, np.array([1.0, 2.0, -0.5])
    pts, n, w = sphere_grid(32, a, c)
    trg = np.array([c + 0.3 * a * np.array([0.0, 0.6, -0.8]), c + 4.0 * a * np.array([1.0, 0.0, 0.0])])
    for k in range(3):
        g = np.zeros_like(pts)
        g[:, k] = 1.0
        out = np.zeros((2, 3))
        stokes.stresslet_sum(pts, n * w[:, None], g, trg, out)
        np.testing.assert_allclose(out[0], np.eye(3)[k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(out[1], 0.0, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- far field
def spheres_scene(rng, nves=4, p=8, q=16):
    centres = 2.6 * np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.9]])[:nves] + rng.uniform(-0.1, 0.1, (nves, 3))
    tp, _, _ = sphere_grid(p)
    sp, sn, sw = sphere_grid(q)
    # equator targets coincide with q-grid sources up to rounding: nudge them by 1e-15
    trg = (centres[:, None] + tp[None]).reshape(-1, 3) + 1e-15 * rng.standard_normal((nves * tp.shape[0], 3))
    src = (centres[:, None] + sp[None]).reshape(-1, 3)
    trg_id = np.repeat(np.arange(nves), tp.shape[0])
    src_id = np.repeat(np.arange(nves), sp.shape[0])
    w = np.tile(sw, nves)[:, None]
    return src, src_id, trg, trg_id, rng.standard_normal(src.shape) * w, np.tile(sn, (nves, 1)) * w, \
        rng.standard_normal(src.shape)


def test_far_direct_excludes_self(rng):
    src, src_id, trg, trg_id, f_w, nw, g = spheres_scene(rng, nves=3, p=4, q=6)
    mask = trg_id[:, None] != src_id[None, :]
    u = far.far_single_layer(src, f_w, src_id, trg, trg_id, backend="direct")
    assert relerr(u, ref_stokeslet(src, f_w, trg, mask)) < RTOL
    u = far.far_double_layer(src, nw, g, src_id, trg, trg_id, backend="direct")
    assert relerr(u, ref_stresslet(src, nw, g, trg, mask)) < RTOL


@pytest.mark.skipif(not far._have_fmm(), reason="fmm3dpy not installed")
def test_far_fmm_matches_direct(rng):
    src, src_id, trg, trg_id, f_w, nw, g = spheres_scene(rng)
    perm = rng.permutation(src.shape[0])                      # sources need not be grouped
    src, src_id, f_w, nw, g = src[perm], src_id[perm], f_w[perm], nw[perm], g[perm]
    direct = far.FarField(src, src_id, trg, trg_id, backend="direct")
    fmm = far.FarField(src, src_id, trg, trg_id, backend="fmm", eps=far.DEFAULT_EPS)
    assert fmm.n_snapped > 0                                   # the equator targets
    for dens in (dict(f_w=f_w), dict(nw=nw, g=g), dict(f_w=f_w, nw=nw, g=g)):
        ref = direct.evaluate(**dens)
        assert relerr(fmm.evaluate(**dens), ref) < far.DEFAULT_EPS


def test_backend_choice():
    assert far.choose_backend(100, 100, "auto") == "direct"
    assert far.choose_backend(10, 10, "direct") == "direct"
    with pytest.raises(SettingsError):
        far.choose_backend(10, 10, "treecode")
    with pytest.raises(SettingsError):
        far.FarField(np.zeros((1, 3)), [0], np.zeros((1, 3)), [0], backend="direct", eps=0.0)


@pytest.mark.parametrize("p", [3, 8, 16])
def test_series_at_points_matches_the_numpy_evaluation(p):
    """_kernels.series.eval_points (the projection's evaluator) equals near.eval_series (the
    numpy einsum over sph.legendre) for values and both derivatives, at random points of
    several vesicles; and its values equal sph.evaluate."""
    from vesflow import shapes, sph
    from vesflow.layerpot.near import eval_points, eval_series
    rng = np.random.default_rng(p)
    c = np.stack([shapes.make_shape("oblate", p, reduced_volume=0.7, rotation=(10, 20, 30)),
                  shapes.make_shape("prolate", p, reduced_volume=0.8, center=(1, 2, 3))])
    n = 257
    v = rng.integers(0, 2, n)
    th, ph = rng.uniform(1e-3, np.pi - 1e-3, n), rng.uniform(-1, 7, n)
    got = eval_points(np.ascontiguousarray(sph.transform(p).pad(c)), v, th, ph)
    ref = eval_series(c[v], p, th, ph)
    for a, b in zip(got, ref):
        assert np.abs(a - b).max() < 1e-12 * np.abs(b).max()
    direct = np.stack([sph.evaluate(c[k], p, th, ph).T for k in range(2)])[v, np.arange(n)]
    assert np.abs(got[0] - direct).max() < 1e-12
