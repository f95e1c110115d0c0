# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Spherical-harmonic series and their first derivatives at arbitrary points (docs/explanation/method.md, section 2).

``eval_points(padded, vesicle, theta, phi, val, dtheta, dphi)``: for each point i the series
of group ``vesicle[i]`` (padded coefficients ``padded[v, k, kind, m, n]``, vesflow.sph.Transform.pad
layout: kind 0 = cos, 1 = sin) at (theta_i, phi_i); writes values and theta / phi derivatives
``(P, k)``.  The normalized associated Legendre functions follow the recurrences of
vesflow.sph.legendre exactly (lam_n^m = sqrt((2n+1)/(4 pi) (n-m)!/(n+m)!) P_n^m, no
Condon-Shortley phase, sqrt 2 for m > 0), O(p^2 k) per point, no temporaries: the projection
of points on surfaces (near-singular set-up, collision check, reparameterization) evaluates
a few points per vesicle many times.  theta must lie in (0, pi) (the derivative divides by
sin theta).  The loop over points is an OpenMP prange.
"""
from cython.parallel cimport prange
from libc.math cimport sqrt, cos, sin, M_PI
from libc.stdlib cimport malloc, free


def eval_points(const double[:, :, :, :, ::1] padded, const long[::1] vesicle,
                const double[::1] theta, const double[::1] phi,
                double[:, ::1] val, double[:, ::1] dtheta, double[:, ::1] dphi):
    cdef Py_ssize_t P = theta.shape[0], K = padded.shape[1], M = padded.shape[3]
    cdef Py_ssize_t i
    if vesicle.shape[0] != P or phi.shape[0] != P or val.shape[0] != P or val.shape[1] != K:
        raise ValueError("eval_points: inconsistent shapes")
    if dtheta.shape[0] != P or dphi.shape[0] != P or dtheta.shape[1] != K or dphi.shape[1] != K:
        raise ValueError("eval_points: inconsistent derivative shapes")
    with nogil:
        for i in prange(P, schedule="static"):
            _one(padded, vesicle[i], theta[i], phi[i], K, M, i, val, dtheta, dphi)


cdef void _one(const double[:, :, :, :, ::1] padded, long v, double th, double ph,
               Py_ssize_t K, Py_ssize_t M, Py_ssize_t i,
               double[:, ::1] val, double[:, ::1] dtheta, double[:, ::1] dphi) noexcept nogil:
    cdef double x = cos(th), s = sin(th)
    cdef double *lam = <double*> malloc(2 * M * sizeof(double))
    cdef double *dl = lam + M
    cdef double mm = 1.0 / sqrt(4.0 * M_PI), a, b, c, cm, sm, cmn, smn, prev
    cdef double f0c, f0s, f1c, f1s
    cdef Py_ssize_t m, n, k
    for k in range(K):
        val[i, k] = 0.0
        dtheta[i, k] = 0.0
        dphi[i, k] = 0.0
    for m in range(M):
        if m > 0:
            mm = mm * sqrt((2.0 * m + 1.0) / (2.0 * m)) * s
        # lam[n] for n = m .. M-1 (degree p = M - 1)
        lam[m] = mm
        if m + 1 < M:
            lam[m + 1] = sqrt(2.0 * m + 3.0) * x * mm
        for n in range(m + 2, M):
            a = sqrt((4.0 * n * n - 1.0) / (n * n - m * m))
            b = sqrt(((n - 1.0) * (n - 1.0) - m * m) / (4.0 * (n - 1.0) * (n - 1.0) - 1.0))
            lam[n] = a * (x * lam[n - 1] - b * lam[n - 2])
        for n in range(m, M):
            prev = lam[n - 1] if n - 1 >= m else 0.0
            c = sqrt((2.0 * n + 1.0) / (2.0 * n - 1.0) * (n * n - m * m)) if n > m else 0.0
            dl[n] = (n * x * lam[n] - c * prev) / s
        cmn = 1.0 if m == 0 else sqrt(2.0)
        cm = cmn * cos(m * ph)
        sm = cmn * sin(m * ph)
        for k in range(K):
            f0c = 0.0
            f0s = 0.0
            f1c = 0.0
            f1s = 0.0
            for n in range(m, M):
                f0c = f0c + padded[v, k, 0, m, n] * lam[n]
                f0s = f0s + padded[v, k, 1, m, n] * lam[n]
                f1c = f1c + padded[v, k, 0, m, n] * dl[n]
                f1s = f1s + padded[v, k, 1, m, n] * dl[n]
            val[i, k] += f0c * cm + f0s * sm
            dtheta[i, k] += f1c * cm + f1s * sm
            dphi[i, k] += m * (f0s * cm - f0c * sm)
    free(lam)


# ---------------------------------------------------------------------------------------
# the OpenMP thread count of this process (vesflow.threads sets it per step)
# ---------------------------------------------------------------------------------------
cimport openmp


def set_num_threads(int n):
    """omp_set_num_threads(n) for the calling thread's later parallel regions (every kernel of
    vesflow._kernels shares the one libgomp of the process)."""
    if n < 1:
        raise ValueError(f"set_num_threads: n = {n} must be >= 1")
    openmp.omp_set_num_threads(n)


def get_max_threads():
    return openmp.omp_get_max_threads()


# ---------------------------------------------------------------------------------------
# Closest points on surfaces (vesflow.layerpot.near.Projection): Gauss-Newton on |X - x|^2 per
# point with a backtracking line search, the series evaluated by the recurrences of _one with
# their coefficients tabulated once per call (the same expressions: the same values)
# ---------------------------------------------------------------------------------------
from libc.math cimport fabs, floor, fmod


cdef struct _Tables:
    double* a        # (M, M) a[m, n]
    double* b        # (M, M) b[m, n]
    double* c        # (M, M) c[m, n]


cdef void _tables(_Tables* T, Py_ssize_t M) noexcept nogil:
    """The coefficients of the Legendre recurrences of _one (a, b: values; c: derivatives)."""
    cdef Py_ssize_t m, n
    for m in range(M):
        for n in range(M):
            T.a[m * M + n] = 0.0
            T.b[m * M + n] = 0.0
            T.c[m * M + n] = 0.0
        for n in range(m + 2, M):
            T.a[m * M + n] = sqrt((4.0 * n * n - 1.0) / (n * n - m * m))
            T.b[m * M + n] = sqrt(((n - 1.0) * (n - 1.0) - m * m) / (4.0 * (n - 1.0) * (n - 1.0) - 1.0))
        for n in range(m + 1, M):
            T.c[m * M + n] = sqrt((2.0 * n + 1.0) / (2.0 * n - 1.0) * (n * n - m * m))


cdef void _eval3(const double[:, :, :, :, ::1] padded, long v, double th, double ph, Py_ssize_t M,
                 const _Tables* T, double* lam, double* Y, double* Yt, double* Yp) noexcept nogil:
    """_one for the 3 components of vesicle v at (th, ph), with the tabulated coefficients."""
    cdef double x = cos(th), s = sin(th)
    cdef double *dl = lam + M
    cdef double mm = 1.0 / sqrt(4.0 * M_PI), cm, sm, cmn, prev
    cdef double f0c, f0s, f1c, f1s
    cdef Py_ssize_t m, n, k
    for k in range(3):
        Y[k] = 0.0
        Yt[k] = 0.0
        Yp[k] = 0.0
    for m in range(M):
        if m > 0:
            mm = mm * sqrt((2.0 * m + 1.0) / (2.0 * m)) * s
        lam[m] = mm
        if m + 1 < M:
            lam[m + 1] = sqrt(2.0 * m + 3.0) * x * mm
        for n in range(m + 2, M):
            lam[n] = T.a[m * M + n] * (x * lam[n - 1] - T.b[m * M + n] * lam[n - 2])
        for n in range(m, M):
            prev = lam[n - 1] if n - 1 >= m else 0.0
            dl[n] = (n * x * lam[n] - T.c[m * M + n] * prev) / s
        cmn = 1.0 if m == 0 else sqrt(2.0)
        cm = cmn * cos(m * ph)
        sm = cmn * sin(m * ph)
        for k in range(3):
            f0c = 0.0
            f0s = 0.0
            f1c = 0.0
            f1s = 0.0
            for n in range(m, M):
                f0c = f0c + padded[v, k, 0, m, n] * lam[n]
                f0s = f0s + padded[v, k, 1, m, n] * lam[n]
                f1c = f1c + padded[v, k, 0, m, n] * dl[n]
                f1s = f1s + padded[v, k, 1, m, n] * dl[n]
            Y[k] += f0c * cm + f0s * sm
            Yt[k] += f1c * cm + f1s * sm
            Yp[k] += m * (f0s * cm - f0c * sm)


cdef inline double _dot3(const double* a, const double* b) noexcept nogil:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


cdef inline double _dist2(const double* y, const double* x) noexcept nogil:
    cdef double d0 = y[0] - x[0], d1 = y[1] - x[1], d2 = y[2] - x[2]
    return d0 * d0 + d1 * d1 + d2 * d2


cdef inline void _wrap(double* th, double* ph) noexcept nogil:
    """vesflow.layerpot.near._wrap: theta in (0, pi) by crossing a pole, phi in [0, 2 pi)."""
    cdef double t = th[0], f = ph[0], two_pi = 2.0 * M_PI, r
    if t < 0:
        t = -t
        f = f + M_PI
    if t > M_PI:
        t = two_pi - t
        f = f + M_PI
    if t < 1e-12:
        t = 1e-12
    if t > M_PI - 1e-12:
        t = M_PI - 1e-12
    r = fmod(f, two_pi)                 # numpy's mod: the sign of the divisor
    if r != 0.0 and r < 0.0:
        r = r + two_pi
    th[0] = t
    ph[0] = r


cdef void _project_one(const double[:, :, :, :, ::1] padded, long v, const double* x, double* th, double* ph,
                       double* Y, double* Yt, double* Yp, unsigned char* conv, double tol, int max_iter,
                       Py_ssize_t M, const _Tables* T, double* lam) noexcept nogil:
    cdef double r[3]
    cdef double y[3]
    cdef double yt[3]
    cdef double yp[3]
    cdef double res, a11, a12, a22, b1, b2, det, dth, dph, step, best, tt, pp, rr, size
    cdef bint local, pending
    cdef int it, ls, k
    _eval3(padded, v, th[0], ph[0], M, T, lam, Y, Yt, Yp)
    res = _dist2(Y, x)
    conv[0] = 0
    for it in range(max_iter):
        for k in range(3):
            r[k] = x[k] - Y[k]
        a11 = _dot3(Yt, Yt)
        a12 = _dot3(Yt, Yp)
        a22 = _dot3(Yp, Yp)
        b1 = _dot3(Yt, r)
        b2 = _dot3(Yp, r)
        det = a11 * a22 - a12 * a12
        dth = (a22 * b1 - a12 * b2) / det
        dph = (a11 * b2 - a12 * b1) / det
        step = 1.0
        best = res
        # a full step below 1e-5 is in Newton's quadratic range: taken without the residual test
        local = fabs(dth) + fabs(dph) < 1e-5
        pending = True
        for ls in range(12):
            tt = th[0] + step * dth
            pp = ph[0] + step * dph
            _wrap(&tt, &pp)
            _eval3(padded, v, tt, pp, M, T, lam, y, yt, yp)
            rr = _dist2(y, x)
            if rr <= best * (1.0 + 1e-14) or local:
                for k in range(3):
                    Y[k] = y[k]
                    Yt[k] = yt[k]
                    Yp[k] = yp[k]
                th[0] = tt
                ph[0] = pp
                best = rr
                pending = False
                break
            step = step * 0.5
        size = fabs(step * dth) + fabs(step * dph)
        res = best
        if size < tol or pending:
            conv[0] = 1
            break


def project(const double[:, :, :, :, ::1] padded, const long[::1] vesicle, const double[:, ::1] x,
            double[::1] theta, double[::1] phi, double[:, ::1] Y, double[:, ::1] Yt, double[:, ::1] Yp,
            unsigned char[::1] converged, double tol=1e-10, int max_iter=30):
    """Closest points of the targets x (P, 3) on the series of vesicles ``vesicle`` (padded (V, 3,
    2, M, M)): Gauss-Newton on |X(theta, phi) - x|^2 from (theta, phi) (P,) (updated in place) with
    a backtracking line search of 12 halvings, a full step below 1e-5 taken without the residual
    test, stopping at a step below tol (vesflow.layerpot.near.Projection).  Writes the point Y and
    its derivatives Yt, Yp (P, 3) and converged (P,)."""
    cdef Py_ssize_t P = x.shape[0], M = padded.shape[3], i
    if padded.shape[1] != 3 or x.shape[1] != 3:
        raise ValueError("project: padded (V, 3, 2, M, M) and x (P, 3) expected")
    if (vesicle.shape[0] != P or theta.shape[0] != P or phi.shape[0] != P or Y.shape[0] != P or Yt.shape[0] != P
            or Yp.shape[0] != P or converged.shape[0] != P or Y.shape[1] != 3 or Yt.shape[1] != 3 or Yp.shape[1] != 3):
        raise ValueError("project: inconsistent shapes")
    for i in range(P):
        if not (0 <= vesicle[i] < padded.shape[0]):
            raise ValueError(f"project: vesicle[{i}] = {vesicle[i]} is not in [0, {padded.shape[0]})")
    if P == 0:
        return
    cdef _Tables T
    T.a = <double*> malloc(3 * M * M * sizeof(double))
    T.b = T.a + M * M
    T.c = T.b + M * M
    _tables(&T, M)
    cdef double* lam
    try:
        with nogil:
            for i in prange(P, schedule="dynamic", chunksize=64):
                lam = <double*> malloc(2 * M * sizeof(double))
                _project_one(padded, vesicle[i], &x[i, 0], &theta[i], &phi[i], &Y[i, 0], &Yt[i, 0], &Yp[i, 0],
                             &converged[i], tol, max_iter, M, &T, lam)
                free(lam)
    finally:
        free(T.a)


def basis_points(const double[::1] theta, const double[::1] phi, const long[::1] ns, const long[::1] ms,
                 const long[::1] ks, double[:, ::1] out):
    """out[i, c] = lam_n^m(cos theta_i) c_m (cos m phi_i if kind 0 else sin m phi_i) for the flat
    index c of degree ns[c], order ms[c] and kind ks[c] (vesflow.sph.index_tables; c_m = 1 for
    m = 0, sqrt 2 else): the basis functions at the points, by the recurrences of
    vesflow.sph.legendre_values (sin theta as sqrt(1 - cos^2), as there)."""
    cdef Py_ssize_t P = theta.shape[0], C = ns.shape[0], M = 0, i, c
    if phi.shape[0] != P or out.shape[0] != P or out.shape[1] != C or ms.shape[0] != C or ks.shape[0] != C:
        raise ValueError("basis_points: theta, phi (P,), ns, ms, ks (C,) and out (P, C) must agree")
    for c in range(C):
        if ns[c] < ms[c] or ms[c] < 0 or not (0 <= ks[c] <= 1):
            raise ValueError(f"basis_points: index {c}: degree {ns[c]}, order {ms[c]}, kind {ks[c]} is not a basis function")
        M = max(M, ns[c] + 1)
    if P == 0 or C == 0:
        return
    cdef _Tables T
    T.a = <double*> malloc(3 * M * M * sizeof(double))
    T.b = T.a + M * M
    T.c = T.b + M * M
    _tables(&T, M)
    cdef double* lam
    try:
        with nogil:
            for i in prange(P, schedule="static"):
                lam = <double*> malloc((M * M + 2 * M) * sizeof(double))
                _basis_one(theta[i], phi[i], M, &T, lam, ns, ms, ks, &out[i, 0])
                free(lam)
    finally:
        free(T.a)


cdef void _basis_one(double th, double ph, Py_ssize_t M, const _Tables* T, double* lam, const long[::1] ns,
                     const long[::1] ms, const long[::1] ks, double* out) noexcept nogil:
    cdef double x = cos(th), s = sqrt(1.0 - x * x), mm = 1.0 / sqrt(4.0 * M_PI)
    cdef double* cs = lam + M * M
    cdef double* sn = cs + M
    cdef Py_ssize_t m, n, c
    for m in range(M):
        if m > 0:
            mm = mm * sqrt((2.0 * m + 1.0) / (2.0 * m)) * s
        lam[m * M + m] = mm
        if m + 1 < M:
            lam[m * M + m + 1] = sqrt(2.0 * m + 3.0) * x * mm
        for n in range(m + 2, M):
            lam[m * M + n] = T.a[m * M + n] * (x * lam[m * M + n - 1] - T.b[m * M + n] * lam[m * M + n - 2])
        cs[m] = (1.0 if m == 0 else sqrt(2.0)) * cos(m * ph)
        sn[m] = (1.0 if m == 0 else sqrt(2.0)) * sin(m * ph)
    for c in range(ns.shape[0]):
        out[c] = lam[ms[c] * M + ns[c]] * (cs[ms[c]] if ks[c] == 0 else sn[ms[c]])
