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


# ---------------------------------------------------------------------------------------
# The real-space sum with its cell structure built ONCE per geometry (a GMRES solve applies it
# with new densities every iteration): sources and targets sorted by cell, sources stored
# contiguously in cell order (wrapped positions), the periodic image shift of each neighbour
# cell computed per cell instead of a minimum image per pair.
# ---------------------------------------------------------------------------------------
ctypedef struct _Cells:
    long n[3]
    double L[3]
    double lo[3]              # the box's corner and the cells' sides (neighbour-cell culling)
    double side[3]
    bint periodic
    bint mi_any
    double mL[3]              # L on an axis of fewer than 2 SUB + 1 cells (minimum image per pair), else 0
    double iL[3]
    double rc2
    double rc2_cull           # rc^2 with a relative margin: a cell is skipped when farther than this
    double xi
    Py_ssize_t ld             # leading dimension of the source columns (>= S + VF_BLOCK)
    const double* ys          # wrapped source positions, cell order, 3 columns of ld
    const double* dens        # densities in cell order, columns of ld: f (3), nw, g (3 + 3)
    const long* cstart        # sources of cell c: cstart[c] .. cstart[c + 1]
    const long* crun          # runs (one vesicle's sources in one cell) of cell c: crun[c] .. crun[c + 1]
    const long* rstart        # sources of run r: rstart[r] .. rstart[r + 1]
    const long* rvi           # vesicle index of run r
    const long* tstart        # targets (cell order) of cell c: tstart[c] .. tstart[c + 1]
    const double* xw          # wrapped targets, cell order
    const long* torder        # original index of each cell-ordered target
    const long* tvi           # own="smooth": own vesicle of each cell-ordered target (-1: none); NULL: own pairs summed
    bint do_sl
    bint do_dl


cdef inline double _gap(double x, double a, double w) noexcept nogil:
    """Distance from x to the interval [a, a + w] (0 inside)."""
    if x < a:
        return a - x
    if x > a + w:
        return x - a - w
    return 0.0


cdef void _cell_targets(const _Cells* b, long c, double* out) noexcept nogil:
    """out[3 torder[t] + a] += real-space sum of every target t of cell c.  The neighbour cells
    go by rows along axis 2 (consecutive cells of one image shift hold one range of sources);
    per group of targets with one own vesicle, the rows' pieces without that vesicle's runs are
    listed once; per target, the rows and cells farther than rc from it are dropped, the pieces
    clipped to the remaining cells and summed in place, the target moved by minus their shift."""
    cdef long cc[3]
    cdef long lo[3]
    cdef long hi[3]
    cdef long ec[3 * MAXW]                    # wrapped cell index of each neighbour position, per axis (2 SUB + 1 each)
    cdef double shc[3 * MAXW]                 # image shift, per axis
    cdef double bxc[3 * MAXW]                 # cell corner (unwrapped), per axis
    cdef long nc3[3]
    cdef double gp[3 * MAXW]                  # per target: gap to each neighbour position, per axis, squared
    cdef long j, k, i0, i1, i2, t, s, r, a, ca, cb, nr, np_, skip, cap = 0, first, last, t0, t1, base, s0, s1
    cdef long nrow, row
    cdef double o[3]
    cdef double x0, x1, x2, g01, gg
    cdef vf_range* rg
    cdef long* pc                       # pieces: 4 per piece (row, first and last position, unused)
    cdef long* ps                       # pieces' source ranges: s0, s1
    cdef long prow[MAXW * MAXW + 1]
    cc[0] = c // (b.n[1] * b.n[2])
    cc[1] = (c // b.n[2]) % b.n[1]
    cc[2] = c % b.n[2]
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
        nc3[j] = hi[j] - lo[j] + 1
        for k in range(nc3[j]):
            ec[MAXW * j + k] = (lo[j] + k + b.n[j]) % b.n[j]
            shc[MAXW * j + k] = b.L[j] * ((lo[j] + k - ec[MAXW * j + k]) // b.n[j]) if b.periodic else 0.0
            bxc[MAXW * j + k] = b.lo[j] + (lo[j] + k) * b.side[j]
    nrow = nc3[0] * nc3[1]
    for i0 in range(nc3[0]):
        for i1 in range(nc3[1]):
            base = (ec[i0] * b.n[1] + ec[MAXW + i1]) * b.n[2]
            for i2 in range(nc3[2]):
                cap += b.crun[base + ec[2 * MAXW + i2] + 1] - b.crun[base + ec[2 * MAXW + i2]] + 1
    cap += 2 * nrow + 1
    rg = <vf_range*> malloc(cap * sizeof(vf_range))
    pc = <long*> malloc(cap * 3 * sizeof(long))
    ps = <long*> malloc(cap * 2 * sizeof(long))
    t0 = b.tstart[c]
    while t0 < b.tstart[c + 1]:
        # the targets t0 .. t1 - 1 share their own vesicle (skip; -1: none)
        skip = b.tvi[t0] if b.tvi != NULL else -1
        t1 = t0 + 1
        while t1 < b.tstart[c + 1] and (b.tvi[t1] if b.tvi != NULL else -1) == skip:
            t1 += 1
        # the group's pieces, row by row: per segment of consecutive cells (one shift), its
        # sources without the runs of vesicle skip
        np_ = 0
        for i0 in range(nc3[0]):
            for i1 in range(nc3[1]):
                row = i0 * nc3[1] + i1
                prow[row] = np_
                base = (ec[i0] * b.n[1] + ec[MAXW + i1]) * b.n[2]
                i2 = 0
                while i2 < nc3[2]:
                    ca = i2
                    while i2 + 1 < nc3[2] and ec[2 * MAXW + i2 + 1] == ec[2 * MAXW + i2] + 1:
                        i2 += 1
                    cb = i2
                    i2 += 1
                    a = b.cstart[base + ec[2 * MAXW + ca]]
                    if skip >= 0:
                        for r in range(b.crun[base + ec[2 * MAXW + ca]], b.crun[base + ec[2 * MAXW + cb] + 1]):
                            if b.rvi[r] == skip:
                                if b.rstart[r] > a:
                                    pc[3 * np_] = base
                                    pc[3 * np_ + 1] = ca
                                    pc[3 * np_ + 2] = cb
                                    ps[2 * np_] = a
                                    ps[2 * np_ + 1] = b.rstart[r]
                                    np_ += 1
                                a = b.rstart[r + 1]
                    s = b.cstart[base + ec[2 * MAXW + cb] + 1]
                    if s > a:
                        pc[3 * np_] = base
                        pc[3 * np_ + 1] = ca
                        pc[3 * np_ + 2] = cb
                        ps[2 * np_] = a
                        ps[2 * np_ + 1] = s
                        np_ += 1
        prow[nrow] = np_
        for t in range(t0, t1):
            x0 = b.xw[3 * t]
            x1 = b.xw[3 * t + 1]
            x2 = b.xw[3 * t + 2]
            for j in range(3):
                for k in range(nc3[j]):
                    gg = 0.0 if b.mL[j] != 0.0 else _gap(b.xw[3 * t + j], bxc[MAXW * j + k], b.side[j])
                    gp[MAXW * j + k] = gg * gg
            nr = 0
            for i0 in range(nc3[0]):
                for i1 in range(nc3[1]):
                    g01 = gp[i0] + gp[MAXW + i1]
                    if g01 > b.rc2_cull:
                        continue
                    # the row's cells within rc: first .. last (an interval: the distance is convex)
                    first = -1
                    last = -1
                    for i2 in range(nc3[2]):
                        if g01 + gp[2 * MAXW + i2] <= b.rc2_cull:
                            if first < 0:
                                first = i2
                            last = i2
                    if first < 0:
                        continue
                    row = i0 * nc3[1] + i1
                    for k in range(prow[row], prow[row + 1]):
                        ca = pc[3 * k + 1] if pc[3 * k + 1] > first else first
                        cb = pc[3 * k + 2] if pc[3 * k + 2] < last else last
                        if ca > cb:
                            continue
                        s0 = b.cstart[pc[3 * k] + ec[2 * MAXW + ca]]
                        s1 = b.cstart[pc[3 * k] + ec[2 * MAXW + cb] + 1]
                        s0 = ps[2 * k] if ps[2 * k] > s0 else s0
                        s1 = ps[2 * k + 1] if ps[2 * k + 1] < s1 else s1
                        if s0 >= s1:
                            continue
                        rg[nr].s0 = s0
                        rg[nr].s1 = s1
                        rg[nr].x[0] = x0 - shc[i0]
                        rg[nr].x[1] = x1 - shc[MAXW + i1]
                        rg[nr].x[2] = x2 - shc[2 * MAXW + pc[3 * k + 1]]
                        nr += 1
            o[0] = 0.0
            o[1] = 0.0
            o[2] = 0.0
            if nr > 0:
                vf_ewald_real(b.ys, b.dens, b.ld, rg, nr, b.xi, b.rc2, b.mL, b.iL, b.mi_any, b.do_sl, b.do_dl, o)
            s = b.torder[t]
            out[3 * s] += o[0]
            out[3 * s + 1] += o[1]
            out[3 * s + 2] += o[2]
        t0 = t1
    free(rg)
    free(pc)
    free(ps)


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
        vi = np.asarray(trg_vi, dtype=np.int64).reshape(-1)
        nv = len(src_off) - 1
        src_vi = np.repeat(np.arange(nv, dtype=np.int64), np.diff(np.asarray(src_off, dtype=np.int64)))
        # sources by cell, within a cell by vesicle (stable: each vesicle's run keeps its surface order)
        sorder = np.lexsort((src_vi, skey))
        torder = np.lexsort((vi, tkey)) if skip_own else np.argsort(tkey, kind="stable")
        self.skip_own = bool(skip_own)
        self.tvi = np.ascontiguousarray(vi[torder], dtype=np.int64) if skip_own else None
        self.ncell, self.length, self.periodic, self.xi, self.rc = ncell, len_np, bool(periodic), xi, rc
        self.lo, self.side = lo_np, side
        self.ns, self.nt = ns, nt
        self.sorder = sorder
        self.cstart = np.zeros(ncells + 1, dtype=np.int64)
        self.cstart[1:] = np.cumsum(np.bincount(skey, minlength=ncells))
        self.tstart = np.zeros(ncells + 1, dtype=np.int64)
        self.tstart[1:] = np.cumsum(np.bincount(tkey, minlength=ncells))
        self.tcells = np.flatnonzero(np.diff(self.tstart)).astype(np.int64)   # cells holding targets
        # runs: the sources of one vesicle in one cell (cell c's runs crun[c] .. crun[c + 1])
        ks, vs = skey[sorder], src_vi[sorder]
        heads = np.flatnonzero(np.r_[True, (ks[1:] != ks[:-1]) | (vs[1:] != vs[:-1])]) if ns else np.zeros(0, np.int64)
        self.rstart = np.ascontiguousarray(np.r_[heads, ns], dtype=np.int64)
        self.rvi = np.ascontiguousarray(vs[heads], dtype=np.int64)
        self.crun = np.ascontiguousarray(np.searchsorted(heads, self.cstart), dtype=np.int64)
        # source positions in place, structure of arrays, VF_BLOCK padding rows (read, masked)
        self.ld = ns + VF_BLOCK
        self.ys = np.zeros((3, self.ld))
        self.ys[:, :ns] = sw[sorder].T
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


cdef void _gather_columns(const double[:, ::1] a, const long[::1] order, double[:, ::1] out, Py_ssize_t col) noexcept:
    """out[col + c, k] = a[order[k], c] (c < 3): rows in cell order into columns (OpenMP)."""
    cdef Py_ssize_t k, j, n = order.shape[0]
    with nogil:
        for k in prange(n, schedule="static"):
            j = order[k]
            out[col, k] = a[j, 0]
            out[col + 1, k] = a[j, 1]
            out[col + 2, k] = a[j, 2]


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
    # the densities in cell order, columns of ld rows (the padding rows 0)
    cdef Py_ssize_t ld = rs.ld
    dens_np = np.empty((3 * (do_sl + 2 * do_dl), ld))
    dens_np[:, ns:] = 0.0
    cdef double[:, ::1] dens = dens_np
    cdef long[::1] sorder = rs.sorder
    cdef Py_ssize_t col = 0
    if do_sl:
        _gather_columns(f, sorder, dens, col)
        col += 3
    if do_dl:
        _gather_columns(nw, sorder, dens, col)
        _gather_columns(g, sorder, dens, col + 3)
    cdef double[:, ::1] ys = rs.ys, xw = rs.xw, xo = rs.xo, src = rs.src
    cdef long[::1] cstart = rs.cstart, tstart = rs.tstart, crun = rs.crun, rstart = rs.rstart, rvi = rs.rvi
    cdef long[::1] torder = rs.torder, src_off = rs.src_off, tcells = rs.tcells, ostart = rs.ostart
    cdef _Cells b
    cdef int j
    b.mi_any = False
    for j in range(3):
        b.n[j] = rs.ncell[j]
        b.L[j] = rs.length[j]
        b.lo[j] = rs.lo[j]
        b.side[j] = rs.side[j]
        b.mL[j] = rs.length[j] if (rs.periodic and rs.ncell[j] < 2 * SUB + 1) else 0.0
        b.iL[j] = 1.0 / rs.length[j] if b.mL[j] != 0.0 else 0.0
        b.mi_any = b.mi_any or b.mL[j] != 0.0
    b.periodic = rs.periodic
    b.rc2 = rs.rc * rs.rc
    b.rc2_cull = b.rc2 * (1.0 + 1e-9)
    b.xi = rs.xi
    b.ld = ld
    b.ys = &ys[0, 0]
    b.dens = &dens[0, 0]
    b.cstart = &cstart[0]
    b.crun = &crun[0]
    b.rstart = &rstart[0]
    b.rvi = &rvi[0] if rvi.shape[0] > 0 else NULL
    b.tstart = &tstart[0]
    b.xw = &xw[0, 0]
    b.torder = &torder[0]
    b.do_sl = do_sl
    b.do_dl = do_dl
    cdef long[::1] tvi
    b.tvi = NULL
    if rs.skip_own:
        tvi = rs.tvi
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
