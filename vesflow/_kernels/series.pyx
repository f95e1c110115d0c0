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
