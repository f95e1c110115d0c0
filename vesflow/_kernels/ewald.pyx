# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Real-space part of the spectral Ewald sums (Hasimoto splitting; docs/explanation/far_field.md, "Spectral Ewald").

With ``r = x - y`` (target minus source), ``z = xi r``, ``e = exp(-z^2)`` and the kernels of
docs/explanation/method.md, section 4 written as ``S = G / (8 pi)``, ``D g = T:(g nw) / (8 pi)``
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
is left out of the sum instead and nothing is subtracted: a cell's sources are sorted by
vesicle, so that a vesicle's sources in a cell form one run, and the target's own runs are
skipped).  Inside rc the own
terms are ``G^R - G = -G^F``, beyond it ``-G``
(``G^R`` is below tol there), so that the Fourier part over ALL sources plus this gives the
Ewald sum without the own vesicle.  A coincident pair (``r = 0``) is skipped like the direct
sum skips it, i.e. ``-G^F(0) f`` is added to cancel the Fourier part's share.  Periodic:
minimum image (the image shift of each neighbour cell; per pair only along an axis of fewer
than 5 cells), ``rc < L/2`` per axis (the caller guarantees it, so a pair inside rc is one
image).  Cell lists (cells of side >= rc / 2, sources and targets sorted by cell once per
geometry) and an OpenMP ``prange`` over the cells holding targets.  The sources stay in place
(positions and, per apply, densities in cell-ordered structure-of-arrays columns): the 125
neighbour cells go as 25 rows along the last axis (consecutive cells of a row are one range of
sources); per target, the rows and cells whose box is farther than rc are dropped and the
remaining ranges (without the own runs) summed in one vectorized loop with the target moved by
minus the image shift (``ewaldsum.h``: erfc and exp without libm, out-of-cutoff pairs
masked); the own-vesicle subtraction (``skip_own`` false) uses the vectorized direct
sums of ``pairsum.h``.  Every output row ACCUMULATES (``out += ...``).
"""
import numpy as np

from vesflow._kernels import paths

from cython.parallel cimport prange
from libc.math cimport sqrt, exp, erf, M_PI
from libc.stdlib cimport malloc, free

cdef extern from "ewaldsum.h" nogil:
    enum: VF_BLOCK
    ctypedef struct vf_range:
        Py_ssize_t s0
        Py_ssize_t s1
        double x[3]
    void vf_ewald_real(const double* y, const double* d, Py_ssize_t ld, const vf_range* rg, Py_ssize_t nr,
                       double xi, double rc2, const double* mL, const double* iL, int mi, int sl, int dl, double* o)
    void vf_real_coefficients(double r, double xi, double* c)
    void vf_smooth_row(const double* x, const double* y0, const double* y1, const double* y2, const double* w,
                       const double* n0, const double* n1, const double* n2, Py_ssize_t S, double xi,
                       double* sg, double* db)
    int vf_pairsum_set(int mode)
    int vf_pairsum_use()
    int vf_path_best()
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
cdef enum:
    MAXW = 7                     # 2 SUB + 1 at most (the neighbour positions per axis)



def set_vector_path(path):
    """Run the real-space loop and the own-vesicle range sums by the vector path `path`:
    "avx512", "avx2", "generic" (vesflow._kernels.paths), True (the best this CPU runs) or
    False ("generic"); a SettingsError if the CPU cannot run it.  Returns the path's name."""
    vf_pairsum_set(paths.index(path, vf_path_best()))
    return vector_path()


def vector_path():
    """The name of the vector path the real-space and range sums run."""
    return paths.PATHS[vf_pairsum_use()]


vf_pairsum_set(paths.from_environment(vf_path_best()))


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
    0: they are beyond k_max (docs/explanation/far_field.md).
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


include "ewald_cells.pxi"     # the real-space sum over cell lists
