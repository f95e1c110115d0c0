# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Direct Stokes layer-potential sums, source points -> target points (docs/explanation/method.md, section 4).

All kernels use mu = 1 (the caller scales by 1/mu) and ``r = x - y`` (target minus source):

* Stokeslet (single layer, 2.8)::

      S(x, y) f = (1/(8 pi)) (f / r + r (r . f) / r^3)

* Stresslet, the lambda = 0 double-layer kernel (2.9)::

      D(x, y) g = -(3/(4 pi)) (r . n_y) (r . g) r / r^5

  The caller multiplies the density by ``(1 - lambda_j)`` of its source vesicle.

Sources carry their quadrature weight (``f_k w_k``, ``n_k w_k``; docs/explanation/conventions.md), so
every sum is a plain sum over source points.  Every function ACCUMULATES into ``out``
(``out += ...``): pass zeros for a plain evaluation.  Pairs at distance exactly 0 are
skipped (the exact-zero test, never a tolerance: the quadrature rules that call these
kernels rely on it).  The GIL is released and the loop over targets (or pairs) is an
OpenMP ``prange``; the number of threads follows ``OMP_NUM_THREADS``.

Arrays: points and vectors are C-contiguous ``(n, 3)`` float64; group ids, offsets and
pair lists are int64 (``long`` on Linux).  Group ("vesicle") ids are arbitrary integers;
only equality matters.
"""
import numpy as np

from vesflow._kernels import paths

from cython.parallel cimport prange
from libc.math cimport sqrt, M_PI
cimport openmp

cdef extern from "pairsum.h" nogil:
    # the unexcluded range sums, vectorized (pairsum.h)
    void vf_stokeslet_range(const double* src, const double* f, Py_ssize_t s0, Py_ssize_t s1,
                            const double* x, double* o)
    void vf_stresslet_range(const double* src, const double* nw, const double* g, Py_ssize_t s0,
                            Py_ssize_t s1, const double* x, double* o)
    int vf_pairsum_set(int mode)
    void vf_stokeslet_targets(const double* src, const double* f, Py_ssize_t s0, Py_ssize_t s1,
                              const double* x, Py_ssize_t K, double* o)
    void vf_stresslet_targets(const double* src, const double* nw, const double* g, Py_ssize_t s0,
                              Py_ssize_t s1, const double* x, Py_ssize_t K, double* o)
    int vf_pairsum_use()
    int vf_path_best()
    void vf_stokeslet_planar_targets(const double* src, const double* f, Py_ssize_t m, const double* x,
                                     Py_ssize_t K, double* o)
    void vf_stresslet_planar_targets(const double* src, const double* nw, const double* g, Py_ssize_t m,
                                     const double* x, Py_ssize_t K, double* o)
    void vf_both_planar_targets(const double* src, const double* f, const double* nw, const double* g,
                                Py_ssize_t m, const double* x, Py_ssize_t K, double* o)

cdef double INV8PI = 1.0 / (8.0 * M_PI)      # Stokeslet prefactor 1 / (8 pi mu), mu = 1
cdef double M3_4PI = -3.0 / (4.0 * M_PI)     # stresslet prefactor -3 / (4 pi)


# ---------------------------------------------------------------------------------------
# one target against a contiguous range of sources [s0, s1), optional group exclusion
# ---------------------------------------------------------------------------------------
cdef inline void _stokeslet_range(const double* src, const double* f,
                                  Py_ssize_t s0, Py_ssize_t s1,
                                  const long* src_id, long excl,
                                  const double* x, double* o) noexcept nogil:
    """o[0:3] += sum_{s0 <= s < s1, src_id[s] != excl} S(x, src_s) f_s  (src_id NULL: no exclusion,
    the vectorized loop of pairsum.h)."""
    if src_id == NULL:
        vf_stokeslet_range(src, f, s0, s1, x, o)
        return
    cdef Py_ssize_t s
    cdef double r0, r1, r2, rr, ri, rf
    cdef double a0 = 0.0, a1 = 0.0, a2 = 0.0
    cdef double x0 = x[0], x1 = x[1], x2 = x[2]
    for s in range(s0, s1):
        if src_id != NULL and src_id[s] == excl:
            continue
        r0 = x0 - src[3 * s]
        r1 = x1 - src[3 * s + 1]
        r2 = x2 - src[3 * s + 2]
        rr = r0 * r0 + r1 * r1 + r2 * r2
        if rr == 0.0:
            continue
        ri = 1.0 / sqrt(rr)
        rf = (r0 * f[3 * s] + r1 * f[3 * s + 1] + r2 * f[3 * s + 2]) * (ri * ri * ri)
        a0 = a0 + f[3 * s] * ri + r0 * rf
        a1 = a1 + f[3 * s + 1] * ri + r1 * rf
        a2 = a2 + f[3 * s + 2] * ri + r2 * rf
    o[0] += a0 * INV8PI
    o[1] += a1 * INV8PI
    o[2] += a2 * INV8PI


cdef inline void _stresslet_range(const double* src, const double* nw, const double* g,
                                  Py_ssize_t s0, Py_ssize_t s1,
                                  const long* src_id, long excl,
                                  const double* x, double* o) noexcept nogil:
    """o[0:3] += sum_{s0 <= s < s1, src_id[s] != excl} D(x, src_s) g_s  (src_id NULL: no exclusion,
    the vectorized loop of pairsum.h)."""
    if src_id == NULL:
        vf_stresslet_range(src, nw, g, s0, s1, x, o)
        return
    cdef Py_ssize_t s
    cdef double r0, r1, r2, rr, ri, ri2, c
    cdef double a0 = 0.0, a1 = 0.0, a2 = 0.0
    cdef double x0 = x[0], x1 = x[1], x2 = x[2]
    for s in range(s0, s1):
        if src_id != NULL and src_id[s] == excl:
            continue
        r0 = x0 - src[3 * s]
        r1 = x1 - src[3 * s + 1]
        r2 = x2 - src[3 * s + 2]
        rr = r0 * r0 + r1 * r1 + r2 * r2
        if rr == 0.0:
            continue
        ri = 1.0 / sqrt(rr)
        ri2 = ri * ri
        # (r.n)(r.g) / r^5
        c = ((r0 * nw[3 * s] + r1 * nw[3 * s + 1] + r2 * nw[3 * s + 2])
             * (r0 * g[3 * s] + r1 * g[3 * s + 1] + r2 * g[3 * s + 2])) * (ri2 * ri2 * ri)
        a0 = a0 + c * r0
        a1 = a1 + c * r1
        a2 = a2 + c * r2
    o[0] += a0 * M3_4PI
    o[1] += a1 * M3_4PI
    o[2] += a2 * M3_4PI


cdef inline const double* _p2(const double[:, ::1] a) noexcept:
    """Data pointer of an (n, 3) array (NULL when empty: never dereferenced then)."""
    return &a[0, 0] if a.shape[0] > 0 else NULL


cdef inline const long* _p1(const long[::1] a) noexcept:
    return &a[0] if a.shape[0] > 0 else NULL


cdef inline double* _pw(double[:, ::1] a) noexcept:
    return &a[0, 0] if a.shape[0] > 0 else NULL


# ---------------------------------------------------------------------------------------
# argument checks (Python level, before the GIL is released)
# ---------------------------------------------------------------------------------------
cdef _check3(name, a):
    if a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {tuple(a.shape[:2])}")


cdef _check_same(name_a, Py_ssize_t na, name_b, Py_ssize_t nb):
    if na != nb:
        raise ValueError(f"{name_a} and {name_b} must have the same length ({na} != {nb})")


# ---------------------------------------------------------------------------------------
# all sources -> all targets
def set_vector_path(path):
    """Run the pair sums of pairsum.h by the vector path `path`: "avx512", "avx2", "generic"
    (vesflow._kernels.paths), True (the best this CPU runs) or False ("generic"); a
    SettingsError if the CPU cannot run it.  Returns the path's name."""
    vf_pairsum_set(paths.index(path, vf_path_best()))
    return vector_path()


def vector_path():
    """The name of the vector path the pair sums run ("avx512", "avx2" or "generic")."""
    return paths.PATHS[vf_pairsum_use()]


vf_pairsum_set(paths.from_environment(vf_path_best()))


# ---------------------------------------------------------------------------------------
def stokeslet_sum(const double[:, ::1] src, const double[:, ::1] f,
                  const double[:, ::1] trg, double[:, ::1] out):
    """out[t] += sum_s S(trg_t, src_s) f_s  (Stokeslet, docs/explanation/method.md, section 4, eq. 2.8), mu = 1.

    ``S f = (1/(8 pi)) (f/r + r (r.f)/r^3)``, ``r = trg_t - src_s``; pairs with r == 0 are skipped.
    src, f: (S, 3) (f already times the quadrature weight); trg, out: (T, 3).
    """
    _check3("src", src); _check3("f", f); _check3("trg", trg); _check3("out", out)
    _check_same("src", src.shape[0], "f", f.shape[0])
    _check_same("trg", trg.shape[0], "out", out.shape[0])
    cdef Py_ssize_t t, nt = trg.shape[0], ns = src.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pf = _p2(f)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    # the AVX2 path: 2 targets at a time share the de-interleaved sources (the same values)
    cdef Py_ssize_t kc = 2 if vf_pairsum_use() == 1 else 1, nc = (nt + kc - 1) // kc
    with nogil:
        for t in prange(nc, schedule="static"):
            if kc == 1:
                _stokeslet_range(ps, pf, 0, ns, NULL, 0, pt + 3 * t, po + 3 * t)
            else:
                vf_stokeslet_targets(ps, pf, 0, ns, pt + 3 * kc * t, min(kc, nt - kc * t), po + 3 * kc * t)


def stresslet_sum(const double[:, ::1] src, const double[:, ::1] nw, const double[:, ::1] g,
                  const double[:, ::1] trg, double[:, ::1] out):
    """out[t] += sum_s D(trg_t, src_s) g_s  (lambda = 0 double layer, docs/explanation/method.md, section 4, eq. 2.9).

    ``D g = -(3/(4 pi)) (r.nw)(r.g) r / r^5``, ``r = trg_t - src_s``; r == 0 skipped.
    nw: normal times quadrature weight (S, 3); g: density (S, 3).
    """
    _check3("src", src); _check3("nw", nw); _check3("g", g); _check3("trg", trg); _check3("out", out)
    _check_same("src", src.shape[0], "nw", nw.shape[0])
    _check_same("src", src.shape[0], "g", g.shape[0])
    _check_same("trg", trg.shape[0], "out", out.shape[0])
    cdef Py_ssize_t t, nt = trg.shape[0], ns = src.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pn = _p2(nw)
    cdef const double* pg = _p2(g)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    cdef Py_ssize_t kc = 2 if vf_pairsum_use() == 1 else 1, nc = (nt + kc - 1) // kc
    with nogil:
        for t in prange(nc, schedule="static"):
            if kc == 1:
                _stresslet_range(ps, pn, pg, 0, ns, NULL, 0, pt + 3 * t, po + 3 * t)
            else:
                vf_stresslet_targets(ps, pn, pg, 0, ns, pt + 3 * kc * t, min(kc, nt - kc * t), po + 3 * kc * t)


# ---------------------------------------------------------------------------------------
# everything except the target's own group ("far field minus self")
# ---------------------------------------------------------------------------------------
cdef bint _sorted(const long* ids, Py_ssize_t n) noexcept nogil:
    cdef Py_ssize_t i
    for i in range(1, n):
        if ids[i] < ids[i - 1]:
            return False
    return True


cdef inline Py_ssize_t _lower(const long* ids, Py_ssize_t n, long key) noexcept nogil:
    """First index i with ids[i] >= key (ids sorted)."""
    cdef Py_ssize_t lo = 0, hi = n, mid
    while lo < hi:
        mid = (lo + hi) // 2
        if ids[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


def stokeslet_sum_excl(const double[:, ::1] src, const double[:, ::1] f, const long[::1] src_id,
                       const double[:, ::1] trg, const long[::1] trg_id, double[:, ::1] out):
    """As :func:`stokeslet_sum`, skipping the sources with ``src_id[s] == trg_id[t]``.

    With group id = vesicle index this is the sum over all OTHER vesicles (section 4, the
    j != i terms evaluated by the smooth rule).
    """
    _check3("src", src); _check3("f", f); _check3("trg", trg); _check3("out", out)
    _check_same("src", src.shape[0], "f", f.shape[0])
    _check_same("src", src.shape[0], "src_id", src_id.shape[0])
    _check_same("trg", trg.shape[0], "out", out.shape[0])
    _check_same("trg", trg.shape[0], "trg_id", trg_id.shape[0])
    cdef Py_ssize_t t, nt = trg.shape[0], ns = src.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pf = _p2(f)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    cdef const long* pid = _p1(src_id)
    cdef Py_ssize_t lo, hi
    with nogil:
        if _sorted(pid, ns):        # the own group is one range [lo, hi): sum around it, no test per pair
            for t in prange(nt, schedule="static"):
                lo = _lower(pid, ns, trg_id[t])
                hi = _lower(pid, ns, trg_id[t] + 1)
                vf_stokeslet_range(ps, pf, 0, lo, pt + 3 * t, po + 3 * t)
                vf_stokeslet_range(ps, pf, hi, ns, pt + 3 * t, po + 3 * t)
        else:
            for t in prange(nt, schedule="static"):
                _stokeslet_range(ps, pf, 0, ns, pid, trg_id[t], pt + 3 * t, po + 3 * t)


def stresslet_sum_excl(const double[:, ::1] src, const double[:, ::1] nw, const double[:, ::1] g,
                       const long[::1] src_id,
                       const double[:, ::1] trg, const long[::1] trg_id, double[:, ::1] out):
    """As :func:`stresslet_sum`, skipping the sources with ``src_id[s] == trg_id[t]``."""
    _check3("src", src); _check3("nw", nw); _check3("g", g); _check3("trg", trg); _check3("out", out)
    _check_same("src", src.shape[0], "nw", nw.shape[0])
    _check_same("src", src.shape[0], "g", g.shape[0])
    _check_same("src", src.shape[0], "src_id", src_id.shape[0])
    _check_same("trg", trg.shape[0], "out", out.shape[0])
    _check_same("trg", trg.shape[0], "trg_id", trg_id.shape[0])
    cdef Py_ssize_t t, nt = trg.shape[0], ns = src.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pn = _p2(nw)
    cdef const double* pg = _p2(g)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    cdef const long* pid = _p1(src_id)
    cdef Py_ssize_t lo, hi
    with nogil:
        if _sorted(pid, ns):
            for t in prange(nt, schedule="static"):
                lo = _lower(pid, ns, trg_id[t])
                hi = _lower(pid, ns, trg_id[t] + 1)
                vf_stresslet_range(ps, pn, pg, 0, lo, pt + 3 * t, po + 3 * t)
                vf_stresslet_range(ps, pn, pg, hi, ns, pt + 3 * t, po + 3 * t)
        else:
            for t in prange(nt, schedule="static"):
                _stresslet_range(ps, pn, pg, 0, ns, pid, trg_id[t], pt + 3 * t, po + 3 * t)


# ---------------------------------------------------------------------------------------
# (target, source vesicle) pairs: one vesicle's sources only
# ---------------------------------------------------------------------------------------
cdef _check_pairs(const long[:, ::1] pairs, const long[::1] src_off, Py_ssize_t ns,
                  Py_ssize_t nt, double[:, ::1] out):
    cdef Py_ssize_t p, nv = src_off.shape[0] - 1
    if pairs.shape[1] != 2:
        raise ValueError(f"pairs must have shape (P, 2), got ({pairs.shape[0]}, {pairs.shape[1]})")
    _check3("out", out)
    _check_same("pairs", pairs.shape[0], "out", out.shape[0])
    if nv < 0:
        raise ValueError("src_off must have at least one entry (offsets of V vesicles: V + 1 entries)")
    if src_off[0] < 0 or src_off[nv] > ns:
        raise ValueError(f"src_off must lie in [0, {ns}] (number of sources)")
    for p in range(nv):
        if src_off[p + 1] < src_off[p]:
            raise ValueError(f"src_off must be non-decreasing (src_off[{p + 1}] < src_off[{p}])")
    for p in range(pairs.shape[0]):
        if pairs[p, 0] < 0 or pairs[p, 0] >= nt:
            raise IndexError(f"pairs[{p}, 0] = {pairs[p, 0]}: target index out of range [0, {nt})")
        if pairs[p, 1] < 0 or pairs[p, 1] >= nv:
            raise IndexError(f"pairs[{p}, 1] = {pairs[p, 1]}: vesicle index out of range [0, {nv})")


def stokeslet_sum_pairs(const double[:, ::1] src, const double[:, ::1] f, const long[::1] src_off,
                        const double[:, ::1] trg, const long[:, ::1] pairs, double[:, ::1] out):
    """out[p] += sum_{s in src_off[v]:src_off[v+1]} S(trg_t, src_s) f_s  for pairs[p] = (t, v).

    Stokeslet of :func:`stokeslet_sum` restricted to the sources of one vesicle v (its
    sources are the contiguous range ``src_off[v]:src_off[v+1]``).  Used to subtract the
    smooth-rule contribution of near and self pairs (docs/explanation/method.md, section 5.3).  out: (P, 3).
    """
    _check3("src", src); _check3("f", f); _check3("trg", trg)
    _check_same("src", src.shape[0], "f", f.shape[0])
    _check_pairs(pairs, src_off, src.shape[0], trg.shape[0], out)
    cdef Py_ssize_t p, t, v, npairs = pairs.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pf = _p2(f)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    with nogil:
        for p in prange(npairs, schedule="dynamic", chunksize=16):
            t = pairs[p, 0]
            v = pairs[p, 1]
            _stokeslet_range(ps, pf, src_off[v], src_off[v + 1], NULL, 0, pt + 3 * t, po + 3 * p)


def stresslet_sum_pairs(const double[:, ::1] src, const double[:, ::1] nw, const double[:, ::1] g,
                        const long[::1] src_off,
                        const double[:, ::1] trg, const long[:, ::1] pairs, double[:, ::1] out):
    """out[p] += sum_{s in src_off[v]:src_off[v+1]} D(trg_t, src_s) g_s  for pairs[p] = (t, v).

    Stresslet of :func:`stresslet_sum` restricted to one vesicle's sources.  out: (P, 3).
    """
    _check3("src", src); _check3("nw", nw); _check3("g", g); _check3("trg", trg)
    _check_same("src", src.shape[0], "nw", nw.shape[0])
    _check_same("src", src.shape[0], "g", g.shape[0])
    _check_pairs(pairs, src_off, src.shape[0], trg.shape[0], out)
    cdef Py_ssize_t p, t, v, npairs = pairs.shape[0]
    cdef const double* ps = _p2(src)
    cdef const double* pn = _p2(nw)
    cdef const double* pg = _p2(g)
    cdef const double* pt = _p2(trg)
    cdef double* po = _pw(out)
    with nogil:
        for p in prange(npairs, schedule="dynamic", chunksize=16):
            t = pairs[p, 0]
            v = pairs[p, 1]
            _stresslet_range(ps, pn, pg, src_off[v], src_off[v + 1], NULL, 0, pt + 3 * t, po + 3 * p)


def max_threads():
    """Number of OpenMP threads the kernels use (``omp_get_max_threads()``, set by OMP_NUM_THREADS)."""
    return openmp.omp_get_max_threads()


# ---------------------------------------------------------------------------------------
# kernel tables of the singular (self) quadrature (vesflow.layerpot.singular)
# ---------------------------------------------------------------------------------------
def self_kernel_tables(const double[:, ::1] target, const double[:, :, ::1] x,
                       const double[:, :, ::1] xt, const double[:, :, ::1] xp,
                       const double[::1] lam_w, double[:, :, ::1] single, double[:, :, ::1] double_):
    """The 6 components a <= b (order 00, 01, 02, 11, 12, 22) of the symmetric kernels times the
    Graham-Sloan weights, for J targets and the rotated surfaces x (J, 3, M) with their theta /
    phi derivatives xt, xp (J, 3, M):

        single[j, ab, m] = (1/(8 pi)) (delta_ab / r + r_a r_b / r^3) W lam_w[m]
        double[j, ab, m] = -(3/(4 pi)) r_a r_b (r . (x_t x x_p)) / r^5 lam_w[m]

    with r = target[j] - x[j, :, m] and W = |x_t x x_p|.  Either output may have shape
    (0, 0, 0) to skip it.  Writes (does not accumulate).  OpenMP over targets."""
    cdef Py_ssize_t J = x.shape[0], M = x.shape[2], j, m
    cdef bint want_s = single.shape[0] > 0, want_d = double_.shape[0] > 0
    if x.shape[1] != 3 or xt.shape[0] != J or xp.shape[0] != J or target.shape[0] != J or lam_w.shape[0] != M:
        raise ValueError("self_kernel_tables: inconsistent shapes")
    if (want_s and (single.shape[0] != J or single.shape[1] != 6 or single.shape[2] != M)) or \
       (want_d and (double_.shape[0] != J or double_.shape[1] != 6 or double_.shape[2] != M)):
        raise ValueError("self_kernel_tables: outputs must be (J, 6, M)")
    cdef double r0, r1, r2, n0, n1, n2, rr, rinv, w, s1, s3, d5
    with nogil:
        for j in prange(J, schedule="static"):
            for m in range(M):
                r0 = target[j, 0] - x[j, 0, m]
                r1 = target[j, 1] - x[j, 1, m]
                r2 = target[j, 2] - x[j, 2, m]
                n0 = xt[j, 1, m] * xp[j, 2, m] - xt[j, 2, m] * xp[j, 1, m]
                n1 = xt[j, 2, m] * xp[j, 0, m] - xt[j, 0, m] * xp[j, 2, m]
                n2 = xt[j, 0, m] * xp[j, 1, m] - xt[j, 1, m] * xp[j, 0, m]
                rr = r0 * r0 + r1 * r1 + r2 * r2
                rinv = 1.0 / sqrt(rr)
                if want_s:
                    w = sqrt(n0 * n0 + n1 * n1 + n2 * n2) * lam_w[m]
                    s1 = INV8PI * rinv * w
                    s3 = s1 * rinv * rinv
                    single[j, 0, m] = s1 + s3 * r0 * r0
                    single[j, 1, m] = s3 * r0 * r1
                    single[j, 2, m] = s3 * r0 * r2
                    single[j, 3, m] = s1 + s3 * r1 * r1
                    single[j, 4, m] = s3 * r1 * r2
                    single[j, 5, m] = s1 + s3 * r2 * r2
                if want_d:
                    d5 = M3_4PI * (r0 * n0 + r1 * n1 + r2 * n2) * rinv * rinv * rinv * rinv * rinv * lam_w[m]
                    double_[j, 0, m] = d5 * r0 * r0
                    double_[j, 1, m] = d5 * r0 * r1
                    double_[j, 2, m] = d5 * r0 * r2
                    double_[j, 3, m] = d5 * r1 * r1
                    double_[j, 4, m] = d5 * r1 * r2
                    double_[j, 5, m] = d5 * r2 * r2


# ---------------------------------------------------------------------------------------
# Blocks of K targets against the sources of one vesicle (the near correction: a near pair's
# target and its 8 line points), each target by the vectorized range sum of pairsum.h (the
# sources in vector lanes, AVX-512 where the CPU has it): 1.48 ns per pair for two vesicles at
# p = 16 against 2.32 ns for a loop vectorized across the K targets at the baseline -march
# (the same values as stokeslet_sum_pairs, bit for bit).
# ---------------------------------------------------------------------------------------
DEF KMAX = 16


cdef _check_blocks(const double[:, :, ::1] trg, const long[::1] ves, const long[::1] src_off, Py_ssize_t ns,
                   const double[:, :, ::1] out):
    cdef Py_ssize_t p, nv = src_off.shape[0] - 1
    if trg.shape[2] != 3 or out.shape[2] != 3:
        raise ValueError("trg and out must have shape (P, K, 3)")
    if trg.shape[1] > KMAX:
        raise ValueError(f"at most {KMAX} targets per block, got {trg.shape[1]}")
    if out.shape[0] != trg.shape[0] or out.shape[1] != trg.shape[1] or ves.shape[0] != trg.shape[0]:
        raise ValueError("trg (P, K, 3), ves (P,) and out (P, K, 3) must agree")
    if nv < 0 or src_off[0] < 0 or src_off[nv] > ns:
        raise ValueError(f"src_off must lie in [0, {ns}] (number of sources)")
    for p in range(ves.shape[0]):
        if not (0 <= ves[p] < nv):
            raise ValueError(f"ves[{p}] = {ves[p]} is not a vesicle index in [0, {nv})")


def planar(const double[:, ::1] a, const long[::1] src_off):
    """The (n, 3) array `a` in the layout of the block sums: vesicle v's rows
    ``src_off[v] .. src_off[v+1]`` (m of them) as three runs of m values (x, y, z components)
    from position ``3 src_off[v]``.  Returns a new (3 n,) array."""
    _check3("a", a)
    cdef Py_ssize_t nv = src_off.shape[0] - 1, v, s, d, m, o
    if nv < 0 or (nv > 0 and (src_off[0] != 0 or src_off[nv] != a.shape[0])):
        raise ValueError(f"src_off must run from 0 to the number of rows ({a.shape[0]})")
    out = np.empty(3 * a.shape[0])
    cdef double[::1] po = out
    for v in range(nv):
        o, m = src_off[v], src_off[v + 1] - src_off[v]
        if m < 0:
            raise ValueError(f"src_off must not decrease (vesicle {v})")
        for d in range(3):
            for s in range(m):
                po[3 * o + d * m + s] = a[o + s, d]
    return out


cdef _check_planar(name, const double[::1] a, Py_ssize_t ns):
    if a.shape[0] != 3 * ns:
        raise ValueError(f"{name} must be planar (stokes.planar) with 3 x {ns} values, got {a.shape[0]}")


def stokeslet_sum_blocks(const double[::1] src, const double[::1] f, const long[::1] src_off,
                         const double[:, :, ::1] trg, const long[::1] ves, double[:, :, ::1] out):
    """out[p, k] += sum_{s in src_off[v]:src_off[v+1]} S(trg[p, k], src_s) f_s, v = ves[p]:
    as :func:`stokeslet_sum_pairs` for the K (<= 16) targets of block p at once (vectorized
    across them; the same values).  src, f: the sources and densities in the planar layout of
    :func:`planar` (the vector loops then read them without de-interleaving: 12 permutes
    fewer per 8 sources and 4 targets); trg, out: (P, K, 3)."""
    cdef Py_ssize_t ns = src_off[src_off.shape[0] - 1] if src_off.shape[0] else 0
    _check_planar("src", src, ns); _check_planar("f", f, ns)
    _check_blocks(trg, ves, src_off, ns, out)
    cdef Py_ssize_t p, n = trg.shape[0]
    cdef int K = trg.shape[1]
    if n == 0 or K == 0:
        return
    cdef const double* ps = &src[0]
    cdef const double* pf = &f[0]
    # the blocks in the order of their source vesicle: consecutive blocks reuse its sources
    # from the cache (N = 512: 26 MB of sources and as much density)
    cdef long[::1] order = np.argsort(ves, kind="stable")
    cdef Py_ssize_t k, o, m
    with nogil:
        for k in prange(n, schedule="dynamic", chunksize=16):
            p = order[k]
            o = src_off[ves[p]]
            m = src_off[ves[p] + 1] - o
            vf_stokeslet_planar_targets(ps + 3 * o, pf + 3 * o, m, &trg[p, 0, 0], K, &out[p, 0, 0])


def stresslet_sum_blocks(const double[::1] src, const double[::1] nw, const double[::1] g,
                         const long[::1] src_off, const double[:, :, ::1] trg, const long[::1] ves,
                         double[:, :, ::1] out):
    """out[p, k] += sum_{s in src_off[v]:src_off[v+1]} D(trg[p, k], src_s) g_s, v = ves[p]
    (as :func:`stresslet_sum_pairs`, K targets per block at once).  src, nw, g: planar
    (:func:`planar`); trg, out: (P, K, 3)."""
    cdef Py_ssize_t ns = src_off[src_off.shape[0] - 1] if src_off.shape[0] else 0
    _check_planar("src", src, ns); _check_planar("nw", nw, ns); _check_planar("g", g, ns)
    _check_blocks(trg, ves, src_off, ns, out)
    cdef Py_ssize_t p, n = trg.shape[0]
    cdef int K = trg.shape[1]
    if n == 0 or K == 0:
        return
    cdef const double* ps = &src[0]
    cdef const double* pn = &nw[0]
    cdef const double* pg = &g[0]
    cdef long[::1] order = np.argsort(ves, kind="stable")
    cdef Py_ssize_t k, o, m
    with nogil:
        for k in prange(n, schedule="dynamic", chunksize=16):
            p = order[k]
            o = src_off[ves[p]]
            m = src_off[ves[p] + 1] - o
            vf_stresslet_planar_targets(ps + 3 * o, pn + 3 * o, pg + 3 * o, m, &trg[p, 0, 0], K, &out[p, 0, 0])


def stokeslet_stresslet_sum_blocks(const double[::1] src, const double[::1] f, const double[::1] nw,
                                   const double[::1] g, const long[::1] src_off, const double[:, :, ::1] trg,
                                   const long[::1] ves, double[:, :, ::1] out):
    """:func:`stokeslet_sum_blocks` (density f) then :func:`stresslet_sum_blocks` (nw, g) in one
    pass over the sources, sharing r and 1/r: bit for bit the two calls, ~0.7x their time.  All
    source arrays planar (:func:`planar`); trg, out: (P, K, 3)."""
    cdef Py_ssize_t ns = src_off[src_off.shape[0] - 1] if src_off.shape[0] else 0
    _check_planar("src", src, ns); _check_planar("f", f, ns); _check_planar("nw", nw, ns); _check_planar("g", g, ns)
    _check_blocks(trg, ves, src_off, ns, out)
    cdef Py_ssize_t p, n = trg.shape[0]
    cdef int K = trg.shape[1]
    if n == 0 or K == 0:
        return
    cdef const double* ps = &src[0]
    cdef const double* pf = &f[0]
    cdef const double* pn = &nw[0]
    cdef const double* pg = &g[0]
    cdef long[::1] order = np.argsort(ves, kind="stable")
    cdef Py_ssize_t k, o, m
    with nogil:
        for k in prange(n, schedule="dynamic", chunksize=16):
            p = order[k]
            o = src_off[ves[p]]
            m = src_off[ves[p] + 1] - o
            vf_both_planar_targets(ps + 3 * o, pf + 3 * o, pn + 3 * o, pg + 3 * o, m, &trg[p, 0, 0], K,
                                   &out[p, 0, 0])


# ---------------------------------------------------------------------------------------
# The near correction as a fixed linear map of the density (nearmap.h): per near pair the
# combined kernel rows R (6, m) over its vesicle's m sources, set up once per geometry; the
# rows projected on the coefficients (vesflow.layerpot.nearmap) are applied every iteration.
# ---------------------------------------------------------------------------------------
cdef extern from "nearmap.h" nogil:
    void vf_nearmap_stokeslet(const double* src, const double* w, Py_ssize_t m, const double* x,
                              const double* c, int K, double* R)
    void vf_nearmap_stresslet(const double* src, const double* nw, Py_ssize_t m, const double* x,
                              const double* c, int K, double* R)
    void vf_nearmap_apply(const double* A, const double* d, Py_ssize_t n, double* o)


def near_map_rows(const double[::1] src, const double[::1] weight, const long[::1] src_off,
                  const double[:, :, ::1] trg, const double[:, ::1] coef, const long[::1] ves,
                  double[:, :, ::1] out, bint double_layer=False):
    """out[p] (6, m) = sum_k coef[p, k] K(trg[p, k], y_s) for the m sources y_s of vesicle ves[p]
    (all vesicles must have m sources): the symmetric components xx, xy, xz, yy, yz, zz of the
    Stokeslet times weight_s (the quadrature weight over mu; weight (n,)) or, double_layer, of
    the stresslet with normal-times-weight ``weight`` (planar, 3 n).  src planar
    (:func:`planar`); trg (P, K, 3), coef (P, K); out (P, 6, m), overwritten."""
    cdef Py_ssize_t ns = src_off[src_off.shape[0] - 1] if src_off.shape[0] else 0
    _check_planar("src", src, ns)
    if weight.shape[0] != (3 * ns if double_layer else ns):
        raise ValueError(f"weight must have {3 * ns if double_layer else ns} values, got {weight.shape[0]}")
    if coef.shape[0] != trg.shape[0] or coef.shape[1] != trg.shape[1]:
        raise ValueError("coef must have the shape (P, K) of trg's first two axes")
    if trg.shape[2] != 3 or out.shape[0] != trg.shape[0] or out.shape[1] != 6 or ves.shape[0] != trg.shape[0]:
        raise ValueError("trg (P, K, 3), ves (P,) and out (P, 6, m) must agree")
    cdef Py_ssize_t p, v, n = trg.shape[0], m = out.shape[2], nv = src_off.shape[0] - 1
    for p in range(n):
        v = ves[p]
        if not (0 <= v < nv) or src_off[v + 1] - src_off[v] != m:
            raise ValueError(f"ves[{p}] = {v}: must be a vesicle index in [0, {nv}) with {m} sources")
    if n == 0:
        return
    cdef int K = trg.shape[1]
    cdef const double* ps = &src[0]
    cdef const double* pw = &weight[0]
    cdef Py_ssize_t o
    with nogil:
        for p in prange(n, schedule="dynamic", chunksize=8):
            o = src_off[ves[p]]
            if double_layer:
                vf_nearmap_stresslet(ps + 3 * o, pw + 3 * o, m, &trg[p, 0, 0], &coef[p, 0], K, &out[p, 0, 0])
            else:
                vf_nearmap_stokeslet(ps + 3 * o, pw + o, m, &trg[p, 0, 0], &coef[p, 0], K, &out[p, 0, 0])


def near_map_apply(const double[:, :, ::1] A, const long[::1] ves, const double[:, :, ::1] d, double[:, ::1] out):
    """out[p] += A[p] d[ves[p]]: A (P, 6, C) the symmetric 3 x 3 blocks (xx, xy, xz, yy, yz, zz)
    per coefficient, d (N, 3, C) the densities' coefficients, out (P, 3)."""
    if A.shape[1] != 6 or d.shape[1] != 3 or A.shape[2] != d.shape[2]:
        raise ValueError(f"A (P, 6, C) and d (N, 3, C) must agree, got (6, C) = ({A.shape[1]}, {A.shape[2]}) "
                         f"and (3, C) = ({d.shape[1]}, {d.shape[2]})")
    if ves.shape[0] != A.shape[0] or out.shape[0] != A.shape[0] or out.shape[1] != 3:
        raise ValueError("A (P, 6, C), ves (P,) and out (P, 3) must agree")
    cdef Py_ssize_t p, n = A.shape[0], C = A.shape[2], nv = d.shape[0]
    for p in range(n):
        if not (0 <= ves[p] < nv):
            raise ValueError(f"ves[{p}] = {ves[p]} is not a density index in [0, {nv})")
    if n == 0 or C == 0:
        return
    with nogil:
        for p in prange(n, schedule="static"):
            vf_nearmap_apply(&A[p, 0, 0], &d[ves[p], 0, 0], C, &out[p, 0])
