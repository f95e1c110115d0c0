"""The distributed Ewald grid (vesflow/layerpot/ewald_grid.py) on one process: the ES kernel's
spreading and interpolation against direct sums at each tolerance, the Fourier part against the
replicated (NUFFT) path for single and double layers, periodic and free space, and the boxes."""
import dataclasses
import math

import numpy as np
import pytest
import scipy.fft

from vesflow._kernels import spread as sp
from vesflow.errors import SettingsError
from vesflow.layerpot import ewald, ewald_grid as eg


def direct_type1(y, c, m):
    """F[z, y, x] = sum_s c_s exp(-i (m_x y_x + m_y y_y + m_z y_z)), the modes m on every axis."""
    e = [np.exp(-1j * np.outer(m, y[:, a])) for a in range(3)]
    return np.einsum("s,is,js,ks->kji", c, e[0], e[1], e[2])


@pytest.mark.parametrize("eps", [1e-6, 1e-8, 1e-10, 1e-12])
def test_es_spreading_and_interpolation_reach_the_tolerance(rng, eps):
    """Type 1 (spread, FFT, divide by psi^) and type 2 (divide, inverse FFT, interpolate) against
    the direct sums over 300 points and 15^3 modes: error below eps relative to |c|_1, |U|_1
    (finufft's measure); with the kernel one narrower than es_kernel's, above eps / 10."""
    S, K = 300, 16
    y = rng.uniform(0, 2 * np.pi, (S, 3))
    c = rng.standard_normal(S)
    m = np.arange(-K // 2 + 1, K // 2)
    F = direct_type1(y, c, m)
    U = rng.standard_normal(F.shape) + 1j * rng.standard_normal(F.shape)
    e = [np.exp(1j * np.outer(m, y[:, a])) for a in range(3)]
    u_ref = np.einsum("kji,is,js,ks->s", U, e[0], e[1], e[2])
    ups = eg.upsample_for(eps)
    w0, beta0 = eg.es_kernel(eps, ups)
    errs = []
    for w, beta in [(w0, beta0), (w0 - 1, beta0 * (w0 - 1) / w0)]:
        n = [eg.fine_size(K, ups)] * 3
        u = np.ascontiguousarray(y * n[0] / (2 * np.pi))
        box = np.zeros((1, n[2], n[1], n[0]))
        sp.spread(u, c[None], box, n, [0, 0, 0], w, beta)
        idx = np.mod(m, n[0])
        d = eg.kernel_ft(w, beta, 2 * np.pi * m / n[0])
        dd = d[:, None, None] * d[None, :, None] * d[None, None, :]
        F1 = scipy.fft.fftn(box[0])[np.ix_(idx, idx, idx)] / dd
        full = np.zeros((n[2], n[1], n[0]), dtype=complex)
        full[np.ix_(idx, idx, idx)] = U / dd
        g = scipy.fft.ifftn(full, norm="forward")
        out = np.empty((2, S))
        sp.interpolate(u, np.ascontiguousarray(np.stack([g.real, g.imag])), out, n, [0, 0, 0], w, beta, 2)
        errs.append((np.abs(F1 - F).max() / np.abs(c).sum(), np.abs(out[0] + 1j * out[1] - u_ref).max() / np.abs(U).sum()))
    assert max(errs[0]) < eps, errs
    assert max(errs[1]) > eps / 10, errs


def test_cover_is_the_shortest_periodic_arc():
    w, n = 4, 40
    # points near both ends of the axis: the arc wraps through 0
    u = np.array([1.2, 38.7, 39.9])
    start, ln = eg.cover(u, n, w)
    cells = np.mod(np.ceil(u - 0.5 * w).astype(int)[:, None] + np.arange(w), n)
    assert np.all(np.mod(cells - start, n) < ln)
    assert (start, ln) == (37, 7)                # cells 37 .. 39, 0 .. 3
    assert eg.cover(np.linspace(0, n, 30, endpoint=False), n, w) == (0, n)
    assert eg.cover(np.zeros(0), n, w) == (0, 0)


def test_a_stencil_outside_the_box_is_refused():
    box = np.zeros((1, 8, 8, 8))
    with pytest.raises(ValueError, match="leaves the grid box"):
        sp.spread(np.array([[3.0, 3.0, 7.5]]), np.ones((1, 1)), box, [32, 32, 32], [0, 0, 0], 4, 9.0)
    with pytest.raises(ValueError, match="leaves the grid box"):
        sp.interpolate(np.array([[7.5, 3.0, 3.0]]), box, np.zeros((1, 1)), [32, 32, 32], [0, 0, 0], 4, 9.0)


def scene(rng, period):
    """Eight clusters of 60 sources and 40 targets (radius 0.4) in a box of side 4 (some
    across a face when periodic), densities of both layers."""
    L = 4.0
    c = rng.uniform(0, L, (8, 3))
    src = (c[:, None] + 0.4 * rng.uniform(-1, 1, (8, 60, 3))).reshape(-1, 3)
    trg = (c[:, None] + 0.4 * rng.uniform(-1, 1, (8, 40, 3))).reshape(-1, 3)
    sid, tid = np.repeat(np.arange(8), 60), np.repeat(np.arange(8), 40)
    f = rng.standard_normal(src.shape)
    nw = rng.standard_normal(src.shape)
    g = rng.standard_normal(src.shape)
    if period is None:
        src, trg = src + 10.0, trg + 10.0            # away from the origin
    return src, sid, trg, tid, f, nw, g


def rel(u, ref):
    return float(np.abs(u - ref).max() / np.abs(ref).max())


@pytest.mark.parametrize("period", [4.0, None])
@pytest.mark.parametrize("tol", [1e-6, 1e-8, 1e-10])
def test_distributed_fourier_part_matches_the_nufft_path(rng, period, tol):
    """Single, double and both layers: the distributed path at tol against the replicated
    path with the NUFFT at 1e-13 (the same truncated mode sum): within tol / 5 of the largest
    value (measured 0.04-0.13 tol; the ES kernel at tol itself, EPS_FACTOR 1: 0.4-0.9 tol); and at tol 1e-12 against the replicated path at 1e-12: 1e-10."""
    src, sid, trg, tid, f, nw, g = scene(rng, period)
    p = ewald.choose_params(tol, np.concatenate([src, trg]), period, len(src), len(trg), 1, 9)
    exact = ewald.EwaldSum(src, sid, trg, tid, period=period, params=dataclasses.replace(p, nufft_eps=1e-13),
                           threads=1)
    dist = ewald.EwaldSum(src, sid, trg, tid, period=period, params=p, threads=1, grid="distributed")
    for dens in [dict(f_w=f), dict(nw=nw, g=g), dict(f_w=f, nw=nw, g=g)]:
        ref = exact.fourier(**dens)
        assert np.abs(ref).max() > 0
        e = rel(dist.fourier(**dens), ref)
        assert e < 0.2 * tol, (dens.keys(), e)


@pytest.mark.parametrize("period", [4.0, None])
def test_distributed_fourier_part_equals_the_replicated_one_to_1e_10(rng, period):
    src, sid, trg, tid, f, nw, g = scene(rng, period)
    p = ewald.choose_params(1e-12, np.concatenate([src, trg]), period, len(src), len(trg), 1, 9)
    rep = ewald.EwaldSum(src, sid, trg, tid, period=period, params=p, threads=1)
    dist = ewald.EwaldSum(src, sid, trg, tid, period=period, params=p, threads=1, grid="distributed")
    for dens in [dict(f_w=f), dict(nw=nw, g=g)]:
        assert rel(dist.fourier(**dens), rep.fourier(**dens)) < 1e-10
    # the whole sum (real space unchanged)
    assert rel(dist.evaluate(f, nw, g), rep.evaluate(f, nw, g)) < 1e-10


def test_grid_mode_is_checked(rng):
    src, sid, trg, tid, f, nw, g = scene(rng, 4.0)
    with pytest.raises(SettingsError, match="-ves_ewald_grid = 'slab'"):
        ewald.EwaldSum(src, sid, trg, tid, period=4.0, tol=1e-6, grid="slab")


def test_counted_grid_bytes_are_the_traced_peak_of_an_evaluation(rng):
    """One rank, periodic clusters across the faces: the box is the whole fine grid and the
    slab (counted once); the counted arrays (slab_bytes) against tracemalloc's peak of one
    evaluation: within 25 %."""
    import tracemalloc
    src, sid, trg, tid, f, nw, g = scene(rng, 4.0)
    es = ewald.EwaldSum(src, sid, trg, tid, period=4.0, tol=1e-8, threads=1, grid="distributed")
    d = es._dist
    assert d.blen == d.n and d.start == [0, 0, 0]
    assert all(v >= math.ceil(1.5 * k) for v, k in zip(d.n, es.params.modes))
    for dens, m in [(dict(f_w=f), 3), (dict(nw=nw, g=g), 6)]:
        b = d.grid_bytes(m)
        assert b["slab"] == 0 and b["box"] == 8 * math.prod(d.n)
        tracemalloc.start()
        es.fourier(**dens)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert 0.75 * b["total"] < peak < 1.25 * b["total"], (m, peak, b)
