# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Real-space part of the spectral Ewald sums (Hasimoto splitting; docs/far_field.md, "Ewald").

With ``r = x - y`` (target minus source), ``z = xi r``, ``e = exp(-z^2)`` and the kernels of
method reference section 4 written as ``S = G / (8 pi)``, ``D g = T:(g nw) / (8 pi)``
(``G = I/r + r r^T/r^3``, ``T_ijl = -6 r_i r_j r_l / r^5``), the Hasimoto split
``G = G^R + G^F``, ``T = T^R + T^F`` has the real-space parts (Hasimoto 1959; Lindbo and
Tornberg 2010, eq. 2.5; af Klinteberg and Tornberg 2014 for the stresslet)::

    G^R = (erfc(z)/r - 2 xi e/sqrt(pi)) I + (erfc(z)/r + 2 xi e/sqrt(pi)) r r^T / r^2
    T^R = A (delta_ij r_l + delta_jl r_i + delta_il r_j) + B r_i r_j r_l
          A = 4 xi^3 e / sqrt(pi)
          B = -2 (3 erfc(z)/r^5 + (6 xi / r^4 + 4 xi^3 / r^2) e / sqrt(pi))

and the smooth parts ``G^F = G - G^R``, ``T^F = T - T^R`` (the own-vesicle terms below are
``-G^F`` inside rc; :func:`smooth_part` evaluates them directly, for the tests)::

    G^F = (erf(z)/r + 2 xi e/sqrt(pi)) I + a r r^T,       a = (erf(z)/r - 2 xi e/sqrt(pi)) / r^2
    T^F = -A (delta r + ...) + b r r r,                   b = -6 erf(z)/r^5 - (B + 6 erfc(z)/r^5)

``a`` and ``b`` cancel catastrophically for small ``z``; below ``z = SERIES_Z`` they are
evaluated from their Taylor series (``a = (2 xi^3/sqrt(pi)) sum_{n>=1} (-1)^(n+1) 2n/(2n+1)
z^(2n-2)/n!``, ``b = -(16 xi^5/sqrt(pi)) sum_{m>=2} (-1)^m m(m-1)/((2m+1) m!) z^(2m-4)``).
``G^F(0) = 4 xi / sqrt(pi) I``, ``T^F(0) = 0``.

:class:`RealSpace` sums, for every target ``t``, over all sources ``s`` and periodic images
``n`` (periodic) or the sources (free space) inside the cutoff, the target's own vesicle
included, and subtracts the own vesicle's full kernel at the given (unwrapped) positions::

    sum_{(s, n), 0 < |r| < rc} G^R(r) f_s  -  sum_{s own, r != 0} G(x_t - y_s) f_s  -  sum_{r = 0} G^F(0) f_s

(and the same for ``T``; with ``skip_own``, EwaldSum(own="smooth"), the target's own vesicle
is left out of the sum instead and nothing is subtracted: a cell's targets are grouped by own
vesicle, one candidate buffer per group without that vesicle's sources).  Inside rc the own
terms are ``G^R - G = -G^F``, beyond it ``-G``
(``G^R`` is below tol there), so that the Fourier part over ALL sources plus this gives the
Ewald sum without the own vesicle.  A coincident pair (``r = 0``) is skipped like the direct
sum skips it, i.e. ``-G^F(0) f`` is added to cancel the Fourier part's share.  Periodic:
minimum image (the image shift of each neighbour cell; per pair only along an axis of fewer
than 5 cells), ``rc < L/2`` per axis (the caller guarantees it, so a pair inside rc is one
image).  Cell lists (cells of side >= rc / 2, sources and targets sorted by cell once per
geometry) and an OpenMP ``prange`` over the cells holding targets: the sources of a cell's
125 neighbour cells are copied once into a buffer (structure of arrays, image shifts added)
that every target of the cell sums in one vectorized loop (``ewaldsum.h``: erfc and exp
without libm, out-of-cutoff pairs masked); the own-vesicle sums are the vectorized direct
sums of ``pairsum.h``.  Every output row ACCUMULATES (``out += ...``).
"""
import numpy as np

from cython.parallel cimport prange
from libc.math cimport sqrt, exp, erf, M_PI
from libc.stdlib cimport malloc, free

cdef extern from "ewaldsum.h" nogil:
    enum: VF_BLOCK
    void vf_ewald_real(const double* b, Py_ssize_t n, Py_ssize_t ld, const double* x, double xi, double rc2,
                       const double* mL, const double* iL, int mi, int sl, int dl, double* o)
    void vf_real_coefficients(double r, double xi, double* c)
    void vf_smooth_row(const double* x, const double* y0, const double* y1, const double* y2, const double* w,
                       const double* n0, const double* n1, const double* n2, Py_ssize_t S, double xi,
                       double* sg, double* db)
    int vf_real_path_avx512
    int vf_pairsum_path(int avx512)
    int vf_avx512_available()
    void vf_stokeslet_range(const double* src, const double* f, Py_ssize_t s0, Py_ssize_t s1,
                            const double* x, double* o)
    void vf_stresslet_range(const double* src, const double* nw, const double* g, Py_ssize_t s0,
                            Py_ssize_t s1, const double* x, double* o)
    void vf_stokeslet_targets(const double* src, const double* f, Py_ssize_t s0, Py_ssize_t s1,
                              const double* x, Py_ssize_t K, double* o)
    void vf_stresslet_targets(const double* src, const double* nw, const double* g, Py_ssize_t s0,
                              Py_ssize_t s1, const double* x, Py_ssize_t K, double* o)


cdef double INV8PI = 1.0 / (8.0 * M_PI)
cdef double SQPI = 1.7724538509055160273          # sqrt(pi)
SERIES_Z = 0.2
cdef double _SERIES_Z = 0.2
# cells of side >= rc / SUB, (2 SUB + 1)^3 neighbour cells: 2 visits (2.5 rc)^3 instead of
# (3 rc)^3 for a sphere of (4/3) pi rc^3
cdef long SUB = 2



def set_vector_path(bint avx512):
    """Use the AVX-512 real-space loop and own-vesicle range sums (True; only if the CPU has
    AVX-512F/DQ) or the portable vectorized ones (False); returns whether AVX-512 is now used.
    Default: AVX-512 where available (tests compare the two)."""
    global vf_real_path_avx512
    vf_real_path_avx512 = 1 if (avx512 and vf_avx512_available()) else 0
    vf_pairsum_path(vf_real_path_avx512)
    return bool(vf_real_path_avx512)


set_vector_path(True)


def real_coefficients(double xi, const double[::1] r):
    """The real-space coefficients at radii r > 0 as the kernel computes them (ewaldsum.h),
    (n, 4): ``erfc(z) -+ 2 z e / sqrt(pi)`` (G^R: ``/ r`` of I and ``/ r^3`` of r r^T),
    ``A = 4 xi^3 e / sqrt(pi)`` and ``B r^5 = -2 (3 erfc(z) + (6 z + 4 z^3) e / sqrt(pi))`` (T^R),
    ``z = xi r``, ``e = exp(-z^2)`` (tests)."""
    out = np.empty((r.shape[0], 4))
    cdef double[:, ::1] o = out
    cdef Py_ssize_t i
    for i in range(r.shape[0]):
        vf_real_coefficients(r[i], xi, &o[i, 0])
    return out


cdef inline void _gf_coef(double rr, double xi, double* ci, double* ca) noexcept nogil:
    """G^F(r) = ci I + ca r r^T (any r, also 0; series below z = SERIES_Z)."""
    cdef double r = sqrt(rr), z = xi * r, z2 = z * z, e = exp(-z2)
    cdef double t, s
    cdef int n
    if z < _SERIES_Z:
        # erf(z)/r = (2 xi/sqrt(pi)) sum (-1)^n z^2n / (n! (2n+1));  a by its series
        s = 0.0
        t = 1.0
        for n in range(0, 12):
            s += t / (2 * n + 1)
            t *= -z2 / (n + 1)
        ci[0] = 2.0 * xi / SQPI * s + 2.0 * xi * e / SQPI
        s = 0.0
        t = 1.0                    # (-1)^(n+1) z^(2n-2) / n!, n = 1
        for n in range(1, 13):
            s += t * (2.0 * n) / (2 * n + 1)
            t *= -z2 / (n + 1)
        ca[0] = 2.0 * xi * xi * xi / SQPI * s
    else:
        ci[0] = erf(z) / r + 2.0 * xi * e / SQPI
        ca[0] = (erf(z) / r - 2.0 * xi * e / SQPI) / rr


cdef inline void _tf_coef(double rr, double xi, double* A, double* b) noexcept nogil:
    """T^F(r) = -A (delta r + ...) + b r r r (any r, also 0; series below z = SERIES_Z)."""
    cdef double r = sqrt(rr), z = xi * r, z2 = z * z, e = exp(-z2) / SQPI
    cdef double xi3 = xi * xi * xi, s, t, ri2
    cdef int m
    A[0] = 4.0 * xi3 * e
    if z < _SERIES_Z:
        s = 0.0
        t = 0.5                    # (-1)^m z^(2m-4) / m!, m = 2
        for m in range(2, 14):
            s += t * m * (m - 1) / (2.0 * m + 1)
            t *= -z2 / (m + 1)
        b[0] = -16.0 * xi3 * xi * xi / SQPI * s
    else:
        ri2 = 1.0 / rr
        b[0] = -6.0 * erf(z) * ri2 * ri2 / r + (12.0 * xi * ri2 * ri2 + 8.0 * xi3 * ri2) * e


cdef inline void _gf_apply(double r0, double r1, double r2, double ci, double ca,
                           const double* f, double* a) noexcept nogil:
    """a[0:3] -= (ci I + ca r r^T) f."""
    cdef double t = ca * (r0 * f[0] + r1 * f[1] + r2 * f[2])
    a[0] -= ci * f[0] + t * r0
    a[1] -= ci * f[1] + t * r1
    a[2] -= ci * f[2] + t * r2


cdef inline void _tf_apply(double r0, double r1, double r2, double A, double b,
                           const double* nw, const double* g, double* a) noexcept nogil:
    """a[0:3] -= (-A (delta r + ...) + b r r r):(g nw)."""
    cdef double rn = r0 * nw[0] + r1 * nw[1] + r2 * nw[2]
    cdef double rg = r0 * g[0] + r1 * g[1] + r2 * g[2]
    cdef double gn = g[0] * nw[0] + g[1] * nw[1] + g[2] * nw[2]
    cdef double c = -A * gn + b * rn * rg
    a[0] -= -A * (g[0] * rn + nw[0] * rg) + c * r0
    a[1] -= -A * (g[1] * rn + nw[1] * rg) + c * r1
    a[2] -= -A * (g[2] * rn + nw[2] * rg) + c * r2


cdef inline void _gf_minus(double r0, double r1, double r2, double rr, double xi,
                           const double* f, double* a) noexcept nogil:
    """a[0:3] -= G^F(r) f (any r, also 0)."""
    cdef double ci, ca
    _gf_coef(rr, xi, &ci, &ca)
    _gf_apply(r0, r1, r2, ci, ca, f, a)


cdef inline void _tf_minus(double r0, double r1, double r2, double rr, double xi,
                           const double* nw, const double* g, double* a) noexcept nogil:
    """a[0:3] -= T^F(r):(g nw) (any r; 0 at r = 0)."""
    cdef double A, b
    _tf_coef(rr, xi, &A, &b)
    _tf_apply(r0, r1, r2, A, b, nw, g, a)



def smooth_part(const double[:, ::1] r, const double[:, ::1] f, const double[:, ::1] nw,
                const double[:, ::1] g, double xi):
    """``G^F(r_k) f_k / (8 pi) + T^F(r_k):(g_k nw_k) / (8 pi)`` for each row k, (n, 3) (tests)."""
    cdef Py_ssize_t k, n = r.shape[0]
    out = np.zeros((n, 3))
    cdef double[:, ::1] o = out
    cdef double a[3]
    for k in range(n):
        a[0] = 0.0; a[1] = 0.0; a[2] = 0.0
        rr = r[k, 0] ** 2 + r[k, 1] ** 2 + r[k, 2] ** 2
        _gf_minus(r[k, 0], r[k, 1], r[k, 2], rr, xi, &f[k, 0], a)
        _tf_minus(r[k, 0], r[k, 1], r[k, 2], rr, xi, &nw[k, 0], &g[k, 0], a)
        o[k, 0] = -a[0] * INV8PI; o[k, 1] = -a[1] * INV8PI; o[k, 2] = -a[2] * INV8PI
    return out


def smooth_kernel_tables(const double[:, ::1] x, const double[:, ::1] y, const double[::1] w,
                         const double[:, ::1] nw, double xi, double[:, :, ::1] single, double[:, :, ::1] double_):
    """The smooth (Fourier) parts of the kernels between targets x (T, 3) and sources y (S, 3),
    the 6 components a <= b (order 00, 01, 02, 11, 12, 22, as stokes.self_kernel_tables)::

        single[t, ab, s] = G^F_ab(x_t - y_s) w_s / (8 pi)
        double[t, ab, s] = sum_l T^F_abl(x_t - y_s) nw[s, l] / (8 pi)
                         = (-A (delta_ab (r.nw) + nw_a r_b + r_a nw_b) + b (r.nw) r_a r_b) / (8 pi)

    (module docstring; finite at r = 0; vectorized, ewaldsum.h's vf_smooth_row: erf without
    libm, the series below z = 1/2).  Either output may have shape (0, 0, 0) to skip it.
    Writes (does not accumulate).  One thread (the callers map over vesicles)."""
    cdef Py_ssize_t T = x.shape[0], S = y.shape[0], t
    cdef bint want_s = single.shape[0] > 0, want_d = double_.shape[0] > 0
    if x.shape[1] != 3 or y.shape[1] != 3 or w.shape[0] != S or (want_d and (nw.shape[0] != S or nw.shape[1] != 3)):
        raise ValueError("smooth_kernel_tables: inconsistent shapes")
    if (want_s and (single.shape[0] != T or single.shape[1] != 6 or single.shape[2] != S)) or \
       (want_d and (double_.shape[0] != T or double_.shape[1] != 6 or double_.shape[2] != S)):
        raise ValueError("smooth_kernel_tables: outputs must be (T, 6, S)")
    if T == 0 or S == 0 or not (want_s or want_d):
        return
    cdef double[:, ::1] ys = np.ascontiguousarray(np.asarray(y).T)
    cdef double[:, ::1] ns = np.ascontiguousarray(np.asarray(nw).T) if want_d else ys
    cdef double* ps
    cdef double* pd
    with nogil:
        for t in range(T):
            ps = &single[t, 0, 0] if want_s else NULL
            pd = &double_[t, 0, 0] if want_d else NULL
            vf_smooth_row(&x[t, 0], &ys[0, 0], &ys[1, 0], &ys[2, 0], &w[0], &ns[0, 0], &ns[1, 0], &ns[2, 0], S, xi,
                          ps, pd)


cdef inline double complex _unpack(const double complex* P, Py_ssize_t grid, Py_ssize_t c, Py_ssize_t at,
                                   Py_ssize_t mirror) noexcept nogil:
    """Transform of real component c from the packed pairs (grid: modes per pair; at, mirror:
    the flat indices of k and -k): P_p = A + i B (p = c // 2), A at k is (P_p(k) + conj P_p(-k)) / 2,
    B is (P_p(k) - conj P_p(-k)) / (2 i)."""
    cdef const double complex* q = P + (c // 2) * grid
    cdef double complex a = q[at], b = q[mirror].conjugate()
    if c % 2 == 0:
        return 0.5 * (a + b)
    return -0.5j * (a - b)


def kspace_apply(const double complex[:, :, :, ::1] P, const double[:, :, ::1] psi,
                 const double[::1] k0, const double[::1] k1, const double[::1] k2,
                 bint single, bint double, double scale, double complex[:, :, :, ::1] W):
    """Fourier-space multiplication of the Ewald sum (vesflow/layerpot/ewald.py), one pass:

        U_a = scale Psi [ (k^2 F_a - k_a (k.F)) + i (k^2 (2 (S k)_a + k_a tr S) - 2 k_a (k.S k)) ]

    on real sources packed two to a transform and real results packed likewise (a real
    function's transform is Hermitian, so A + i B separates at k and -k):

    P: (ceil(m / 2), n0, n1, n2), the type-1 transforms of the m real source components in
    pairs (c_0 + i c_1, c_2 + i c_3, ...): the single-layer F_0..2 first (if ``single``), then
    the six components (00, 11, 22, 01, 02, 12) of S (if ``double``);
    W: (2, n0, n1, n2) gets U_0 + i U_1 and U_2, so that the type-2 transform of W holds
    u_0 + i u_1 and u_2.  The modes with an index -n/2 (no mirror -k on the grid) are set to
    0: they are beyond k_max (docs/far_field.md).
    psi: (n0/2 + 1, n1/2 + 1, n2/2 + 1), Psi at |k| (Psi is even in each component of k);
    k0, k1, k2: the wave numbers of the modes (-n/2 .. n/2 - 1, times 2 pi / period).
    OpenMP over the first axis.
    """
    cdef Py_ssize_t n0 = k0.shape[0], n1 = k1.shape[0], n2 = k2.shape[0]
    cdef Py_ssize_t i, j, l, o = 3 if single else 0
    cdef Py_ssize_t h0 = n0 // 2, h1 = n1 // 2, h2 = n2 // 2
    cdef Py_ssize_t m = o + (6 if double else 0)
    if n0 % 2 or n1 % 2 or n2 % 2 or psi.shape[0] != h0 + 1 or psi.shape[1] != h1 + 1 or psi.shape[2] != h2 + 1:
        raise ValueError("even mode counts and psi of shape (n/2 + 1) per axis required")
    if W.shape[0] != 2 or W.shape[1] != n0 or W.shape[2] != n1 or W.shape[3] != n2:
        raise ValueError("W must have shape (2,) + the mode grid")
    if P.shape[0] != (m + 1) // 2 or P.shape[1] != n0 or P.shape[2] != n1 or P.shape[3] != n2:
        raise ValueError(f"P must have shape ({(m + 1) // 2},) + the mode grid")
    cdef double a, b, c, kk, ps
    cdef double complex f0, f1, f2, kf, s00, s11, s22, s01, s02, s12, q0, q1, q2, tr, ksk, u0, u1, u2
    cdef Py_ssize_t grid = n0 * n1 * n2, at, mr
    cdef const double complex* pp = &P[0, 0, 0, 0]
    cdef double complex* pw = &W[0, 0, 0, 0]
    with nogil:
        for i in prange(n0, schedule="static"):
            for j in range(n1):
                for l in range(n2):
                    at = (i * n1 + j) * n2 + l
                    if i == 0 or j == 0 or l == 0:
                        pw[at] = 0
                        pw[grid + at] = 0
                        continue
                    mr = ((n0 - i) * n1 + (n1 - j)) * n2 + (n2 - l)
                    a = k0[i]
                    b = k1[j]
                    c = k2[l]
                    kk = a * a + b * b + c * c
                    ps = psi[i - h0 if i >= h0 else h0 - i, j - h1 if j >= h1 else h1 - j,
                             l - h2 if l >= h2 else h2 - l] * scale
                    u0 = 0
                    u1 = 0
                    u2 = 0
                    if single:
                        f0 = _unpack(pp, grid, 0, at, mr)
                        f1 = _unpack(pp, grid, 1, at, mr)
                        f2 = _unpack(pp, grid, 2, at, mr)
                        kf = a * f0 + b * f1 + c * f2
                        u0 = kk * f0 - a * kf
                        u1 = kk * f1 - b * kf
                        u2 = kk * f2 - c * kf
                    if double:
                        s00 = _unpack(pp, grid, o, at, mr)
                        s11 = _unpack(pp, grid, o + 1, at, mr)
                        s22 = _unpack(pp, grid, o + 2, at, mr)
                        s01 = _unpack(pp, grid, o + 3, at, mr)
                        s02 = _unpack(pp, grid, o + 4, at, mr)
                        s12 = _unpack(pp, grid, o + 5, at, mr)
                        q0 = s00 * a + s01 * b + s02 * c
                        q1 = s01 * a + s11 * b + s12 * c
                        q2 = s02 * a + s12 * b + s22 * c
                        tr = s00 + s11 + s22
                        ksk = a * q0 + b * q1 + c * q2
                        u0 = u0 + 1j * (kk * (2.0 * q0 + a * tr) - 2.0 * a * ksk)
                        u1 = u1 + 1j * (kk * (2.0 * q1 + b * tr) - 2.0 * b * ksk)
                        u2 = u2 + 1j * (kk * (2.0 * q2 + c * tr) - 2.0 * c * ksk)
                    pw[at] = (u0 + 1j * u1) * ps
                    pw[grid + at] = u2 * ps


# ---------------------------------------------------------------------------------------
# The real-space sum with its cell structure built ONCE per geometry (a GMRES solve applies it
# with new densities every iteration): sources and targets sorted by cell, sources stored
# contiguously in cell order (wrapped positions), the periodic image shift of each neighbour
# cell computed per cell instead of a minimum image per pair.
# ---------------------------------------------------------------------------------------
ctypedef struct _Cells:
    long n[3]
    double L[3]
    bint periodic
    bint mi_any
    double mL[3]              # L on an axis of fewer than 2 SUB + 1 cells (minimum image per pair), else 0
    double iL[3]
    double rc2
    double xi
    const double* ys          # wrapped source positions, cell order
    const long* cstart        # sources of cell c: cstart[c] .. cstart[c + 1]
    const long* tstart        # targets (cell order) of cell c: tstart[c] .. tstart[c + 1]
    const double* xw          # wrapped targets, cell order
    const long* torder        # original index of each cell-ordered target
    const double* fc          # densities in cell order (NULL: layer absent)
    const double* nwc
    const double* gc
    const long* svi           # own="smooth": vesicle index of each cell-ordered source (NULL: own pairs summed)
    const long* tvi           # and of each cell-ordered target (-1: none; a cell's targets grouped by it)


cdef void _cell_targets(const _Cells* b, long c, double* out) noexcept nogil:
    """out[3 torder[t] + a] += real-space sum of every target t of cell c."""
    cdef long c0 = c // (b.n[1] * b.n[2]), c1 = (c // b.n[2]) % b.n[1], c2 = c % b.n[2]
    cdef long lo[3]
    cdef long hi[3]
    cdef long cc[3]
    cdef long nb[125]
    cdef double sh[375]
    cdef long nnb = 0, d0, d1, d2, e0, e1, e2, t, j, m, k, nc = 0, s
    cdef double o[3]
    cdef bint do_sl = b.fc != NULL, do_dl = b.gc != NULL
    cc[0] = c0
    cc[1] = c1
    cc[2] = c2
    for j in range(3):
        if b.periodic and b.mL[j] != 0.0:
            lo[j] = 0
            hi[j] = b.n[j] - 1
        elif b.periodic:
            lo[j] = cc[j] - SUB
            hi[j] = cc[j] + SUB
        else:
            lo[j] = cc[j] - SUB if cc[j] >= SUB else 0
            hi[j] = cc[j] + SUB if cc[j] + SUB < b.n[j] else b.n[j] - 1
    for d0 in range(lo[0], hi[0] + 1):
        e0 = (d0 + b.n[0]) % b.n[0]
        for d1 in range(lo[1], hi[1] + 1):
            e1 = (d1 + b.n[1]) % b.n[1]
            for d2 in range(lo[2], hi[2] + 1):
                e2 = (d2 + b.n[2]) % b.n[2]
                nb[nnb] = (e0 * b.n[1] + e1) * b.n[2] + e2
                nc += b.cstart[nb[nnb] + 1] - b.cstart[nb[nnb]]
                # the image of the neighbour cell next to cell c: source + shift
                sh[3 * nnb] = b.L[0] * ((d0 - e0) // b.n[0]) if b.periodic else 0.0
                sh[3 * nnb + 1] = b.L[1] * ((d1 - e1) // b.n[1]) if b.periodic else 0.0
                sh[3 * nnb + 2] = b.L[2] * ((d2 - e2) // b.n[2]) if b.periodic else 0.0
                nnb += 1
    cdef long ncol = 3 + (3 if do_sl else 0) + (6 if do_dl else 0)
    cdef long ld = (nc + VF_BLOCK - 1) // VF_BLOCK * VF_BLOCK, i, n_in, t0, t1, skip
    cdef double* buf = NULL
    cdef double* col
    if nc > 0:
        buf = <double*> malloc(ld * ncol * sizeof(double))
    t0 = b.tstart[c]
    while t0 < b.tstart[c + 1]:
        # the targets t0 .. t1 - 1 share their own vesicle (own="smooth": its sources are left
        # out of their candidates; otherwise one group, nothing skipped)
        t1 = b.tstart[c + 1]
        skip = -1
        if b.svi != NULL:
            skip = b.tvi[t0]
            t1 = t0 + 1
            while t1 < b.tstart[c + 1] and b.tvi[t1] == skip:
                t1 += 1
        n_in = 0
        if nc > 0:
            # the candidates in structure-of-arrays columns of length ld: y + shift, f, nw, g
            k = 0
            for m in range(nnb):
                for j in range(b.cstart[nb[m]], b.cstart[nb[m] + 1]):
                    if skip >= 0 and b.svi[j] == skip:
                        continue
                    buf[k] = b.ys[3 * j] + sh[3 * m]
                    buf[ld + k] = b.ys[3 * j + 1] + sh[3 * m + 1]
                    buf[2 * ld + k] = b.ys[3 * j + 2] + sh[3 * m + 2]
                    col = buf + 3 * ld
                    if do_sl:
                        col[k] = b.fc[3 * j]
                        col[ld + k] = b.fc[3 * j + 1]
                        col[2 * ld + k] = b.fc[3 * j + 2]
                        col = col + 3 * ld
                    if do_dl:
                        col[k] = b.nwc[3 * j]
                        col[ld + k] = b.nwc[3 * j + 1]
                        col[2 * ld + k] = b.nwc[3 * j + 2]
                        col[3 * ld + k] = b.gc[3 * j]
                        col[4 * ld + k] = b.gc[3 * j + 1]
                        col[5 * ld + k] = b.gc[3 * j + 2]
                    k += 1
            n_in = k
            for j in range(ncol):                    # the padding rows: read (masked), never summed
                for i in range(n_in, ld):
                    buf[j * ld + i] = 0.0
        for t in range(t0, t1):
            o[0] = 0.0
            o[1] = 0.0
            o[2] = 0.0
            if n_in > 0:
                vf_ewald_real(buf, n_in, ld, b.xw + 3 * t, b.xi, b.rc2, b.mL, b.iL, b.mi_any, do_sl, do_dl, o)
            s = b.torder[t]
            out[3 * s] += o[0]
            out[3 * s + 1] += o[1]
            out[3 * s + 2] += o[2]
        t0 = t1
    free(buf)


class RealSpace:
    """The real-space sum (module docstring) for a fixed geometry: the cell lists and sorted
    points are built once here, :meth:`apply` takes the densities.

    src (S, 3) SORTED by vesicle id, vesicle v's sources ``src_off[v] .. src_off[v+1]``,
    src_id (S,); trg (T, 3), trg_id (T,), trg_vi (T,): index v of the target's own vesicle or
    -1; lo, length (3,): the box (periodic: the period cell; free: a box holding every point);
    skip_own: leave every target's own vesicle out, no own subtraction (module docstring).
    """

    def __init__(self, src, src_id, src_off, trg, trg_id, trg_vi, double xi, double rc, lo, length,
                 bint periodic, bint skip_own=False):
        src_np = np.ascontiguousarray(src, dtype=np.float64).reshape(-1, 3)
        trg_np = np.ascontiguousarray(trg, dtype=np.float64).reshape(-1, 3)
        ns, nt = src_np.shape[0], trg_np.shape[0]
        if not (rc > 0.0 and xi > 0.0):
            raise ValueError(f"rc and xi must be positive, got {rc}, {xi}")
        lo_np = np.asarray(lo, dtype=np.float64).reshape(3)
        len_np = np.asarray(length, dtype=np.float64).reshape(3)
        ncell = np.maximum(1, np.floor(len_np / (rc / SUB))).astype(np.int64)
        while np.prod(ncell) > 4 * ns + 64:
            j = int(np.argmax(ncell))
            ncell[j] = max(1, ncell[j] // 2)
        side = np.where(len_np > 0, len_np / ncell, 1.0)
        if periodic:
            if np.any(rc >= 0.5 * len_np):
                raise ValueError(f"periodic real-space cutoff rc = {rc} must be below half the period {len_np}")
            sw = lo_np + np.mod(src_np - lo_np, len_np)
            tw = lo_np + np.mod(trg_np - lo_np, len_np)
        else:
            sw, tw = src_np, trg_np
        ncells = int(np.prod(ncell))

        def key(pw):
            c = np.clip(np.floor((pw - lo_np) / side).astype(np.int64), 0, ncell - 1)
            return (c[:, 0] * ncell[1] + c[:, 1]) * ncell[2] + c[:, 2]

        skey, tkey = key(sw), key(tw)
        sorder = np.argsort(skey, kind="stable")
        vi = np.asarray(trg_vi, dtype=np.int64).reshape(-1)
        nv = len(src_off) - 1
        # skip_own: a cell's targets grouped by their own vesicle (one candidate buffer per group)
        torder = np.lexsort((vi, tkey)) if skip_own else np.argsort(tkey, kind="stable")
        self.skip_own = bool(skip_own)
        self.svi = self.tvi = None
        if skip_own:
            src_vi = np.repeat(np.arange(nv, dtype=np.int64), np.diff(np.asarray(src_off, dtype=np.int64)))
            self.svi = np.ascontiguousarray(src_vi[sorder], dtype=np.int64)
            self.tvi = np.ascontiguousarray(vi[torder], dtype=np.int64)
        self.ncell, self.length, self.periodic, self.xi, self.rc = ncell, len_np, bool(periodic), xi, rc
        self.ns, self.nt = ns, nt
        self.sorder = sorder
        self.cstart = np.zeros(ncells + 1, dtype=np.int64)
        self.cstart[1:] = np.cumsum(np.bincount(skey, minlength=ncells))
        self.tstart = np.zeros(ncells + 1, dtype=np.int64)
        self.tstart[1:] = np.cumsum(np.bincount(tkey, minlength=ncells))
        self.tcells = np.flatnonzero(np.diff(self.tstart)).astype(np.int64)   # cells holding targets
        self.ys = np.ascontiguousarray(sw[sorder])
        self.xw = np.ascontiguousarray(tw[torder])
        # the targets with an own vesicle grouped by it (own-vesicle sums): original indices
        # oidx, given positions xo, vesicle v's at ostart[v] .. ostart[v + 1]
        self.oidx = np.ascontiguousarray(np.flatnonzero(vi >= 0)[np.argsort(vi[vi >= 0], kind="stable")], dtype=np.int64)
        self.xo = np.ascontiguousarray(trg_np[self.oidx]).reshape(-1, 3)
        self.ostart = np.zeros(nv + 1, dtype=np.int64)
        self.ostart[1:] = np.cumsum(np.bincount(vi[vi >= 0], minlength=nv))
        self.torder = np.ascontiguousarray(torder, dtype=np.int64)
        self.src = src_np
        self.src_off = np.ascontiguousarray(src_off, dtype=np.int64)

    def apply(self, f, nw, g, out):
        """out (T, 3) += the real-space sum, 1/(8 pi) included; f (S, 3) or (0, 3): single-layer
        density times weight; nw, g (S, 3) or (0, 3): double layer; id-sorted as src."""
        _apply_cells(self, np.ascontiguousarray(f, dtype=np.float64), np.ascontiguousarray(nw, dtype=np.float64),
                     np.ascontiguousarray(g, dtype=np.float64), out)


def _apply_cells(rs, const double[:, ::1] f, const double[:, ::1] nw, const double[:, ::1] g, double[:, ::1] out):
    cdef Py_ssize_t ns = rs.ns, nt = rs.nt
    cdef bint do_sl = f.shape[0] > 0, do_dl = g.shape[0] > 0
    if do_sl and f.shape[0] != ns:
        raise ValueError(f"f has {f.shape[0]} rows, src has {ns}")
    if do_dl and (g.shape[0] != ns or nw.shape[0] != ns):
        raise ValueError(f"nw, g have {nw.shape[0]}, {g.shape[0]} rows, src has {ns}")
    if out.shape[0] != nt:
        raise ValueError(f"out has {out.shape[0]} rows, trg has {nt}")
    if nt == 0 or ns == 0 or not (do_sl or do_dl):
        return
    sorder = rs.sorder
    cdef double[:, ::1] fc = np.ascontiguousarray(np.asarray(f)[sorder]) if do_sl else None
    cdef double[:, ::1] nwc = np.ascontiguousarray(np.asarray(nw)[sorder]) if do_dl else None
    cdef double[:, ::1] gc = np.ascontiguousarray(np.asarray(g)[sorder]) if do_dl else None
    cdef double[:, ::1] ys = rs.ys, xw = rs.xw, xo = rs.xo, src = rs.src
    cdef long[::1] cstart = rs.cstart, tstart = rs.tstart
    cdef long[::1] torder = rs.torder, src_off = rs.src_off, tcells = rs.tcells, ostart = rs.ostart
    cdef _Cells b
    cdef int j
    b.mi_any = False
    for j in range(3):
        b.n[j] = rs.ncell[j]
        b.L[j] = rs.length[j]
        b.mL[j] = rs.length[j] if (rs.periodic and rs.ncell[j] < 2 * SUB + 1) else 0.0
        b.iL[j] = 1.0 / rs.length[j] if b.mL[j] != 0.0 else 0.0
        b.mi_any = b.mi_any or b.mL[j] != 0.0
    b.periodic = rs.periodic
    b.rc2 = rs.rc * rs.rc
    b.xi = rs.xi
    b.ys = &ys[0, 0]
    b.cstart = &cstart[0]
    b.tstart = &tstart[0]
    b.xw = &xw[0, 0]
    b.torder = &torder[0]
    b.fc = &fc[0, 0] if do_sl else NULL
    b.nwc = &nwc[0, 0] if do_dl else NULL
    b.gc = &gc[0, 0] if do_dl else NULL
    cdef long[::1] svi, tvi
    b.svi = NULL
    b.tvi = NULL
    if rs.skip_own:
        svi = rs.svi
        tvi = rs.tvi
        b.svi = &svi[0]
        b.tvi = &tvi[0]
    cdef double* po = &out[0, 0]
    cdef const long* pc = &tcells[0]
    cdef Py_ssize_t k, nc = tcells.shape[0]
    with nogil:
        for k in prange(nc, schedule="dynamic", chunksize=8):
            _cell_targets(&b, pc[k], po)
    if rs.skip_own:
        return
    # minus each vesicle's full kernel at its own targets (r = 0 skipped), the targets of a
    # vesicle 4 at a time against its sources (pairsum.h)
    own = np.zeros((xo.shape[0], 3))
    cdef double[:, ::1] ow = own
    cdef Py_ssize_t v, nv = ostart.shape[0] - 1
    cdef const double* pf = &f[0, 0] if do_sl else NULL
    cdef const double* pn = &nw[0, 0] if do_dl else NULL
    cdef const double* pg = &g[0, 0] if do_dl else NULL
    if xo.shape[0] > 0:
        with nogil:
            for v in prange(nv, schedule="dynamic"):
                if ostart[v + 1] > ostart[v]:
                    if do_sl:
                        vf_stokeslet_targets(&src[0, 0], pf, src_off[v], src_off[v + 1], &xo[ostart[v], 0],
                                             ostart[v + 1] - ostart[v], &ow[ostart[v], 0])
                    if do_dl:
                        vf_stresslet_targets(&src[0, 0], pn, pg, src_off[v], src_off[v + 1], &xo[ostart[v], 0],
                                             ostart[v + 1] - ostart[v], &ow[ostart[v], 0])
        _scatter_sub(out, rs.oidx, own)


def _scatter_sub(double[:, ::1] out, const long[::1] idx, const double[:, ::1] val):
    """out[idx[k]] -= val[k] (distinct idx)."""
    cdef Py_ssize_t k
    for k in range(idx.shape[0]):
        out[idx[k], 0] -= val[k, 0]
        out[idx[k], 1] -= val[k, 1]
        out[idx[k], 2] -= val[k, 2]
