# cython: language_level=3
"""Spreading to and interpolation from a box of a periodic uniform grid with the
"exponential of semicircle" kernel (Barnett, Magland and af Klinteberg 2019)::

    psi(z) = exp(beta (sqrt(1 - z^2) - 1)),  |z| < 1,   z = (j - u) / (w / 2)

for a point at grid coordinate u (cells j = ceil(u - w/2) .. + w - 1 on each axis, taken
modulo the grid size n).  The grid array is a box of the periodic grid: per axis the cells
start, start + 1, ..., start + L - 1 (modulo n); every cell a point touches must lie in it.
Arrays: box (m, Lz, Ly, Lx), points u (S, 3) in grid units (x, y, z) in [0, n); the
distributed Fourier part of the Ewald sum (vesflow.layerpot.ewald_grid) is the caller.
"""
import numpy as np
from cython.parallel cimport parallel, prange
from libc.math cimport ceil, exp, sqrt
from libc.stdlib cimport free, malloc

DEF MAXW = 32


cdef inline int _weights(double u, long n, long start, long L, int w, double beta, double* k,
                         long* idx) noexcept nogil:
    """Kernel values k[0..w) and box indices idx[0..w) of one axis; 1 if a cell is outside the box."""
    cdef long i0 = <long>ceil(u - 0.5 * w), j
    cdef double z, half = 0.5 * w
    cdef int t, bad = 0
    for t in range(w):
        z = (i0 + t - u) / half
        k[t] = exp(beta * (sqrt(1.0 - z * z) - 1.0)) if z * z < 1.0 else 0.0
        j = (i0 + t - start) % n
        if j < 0:
            j = j + n
        if j >= L:
            bad = 1
            j = 0
        idx[t] = j
    return bad


def _check(box, u, n, start, w):
    if w < 2 or w > MAXW:
        raise ValueError(f"kernel width {w} outside 2 .. {MAXW}")
    if u.shape[1] != 3 or len(n) != 3 or len(start) != 3:
        raise ValueError("points (S, 3), n and start of 3 axes (x, y, z)")


def spread(const double[:, ::1] u, const double[:, ::1] c, double[:, :, :, ::1] box, n, start, int w,
           double beta):
    """box[a, z, y, x] += sum_s c[a, s] psi_z psi_y psi_x (module docstring); c (m, S)."""
    _check(box, u, n, start, w)
    cdef long S = u.shape[0], m = c.shape[0]
    if c.shape[1] != S or box.shape[0] != m:
        raise ValueError("c must be (m, S) with m = box.shape[0]")
    cdef long nx = n[0], ny = n[1], nz = n[2], sx = start[0], sy = start[1], sz = start[2]
    cdef long Lz = box.shape[1], Ly = box.shape[2], Lx = box.shape[3]
    cdef double kx[MAXW]
    cdef double ky[MAXW]
    cdef double kz[MAXW]
    cdef long ix[MAXW]
    cdef long iy[MAXW]
    cdef long iz[MAXW]
    cdef long s, a, b, t, ci, base
    cdef int bad = 0
    cdef double v, vz, vzy
    cdef double* row
    cdef bint run
    cdef double* pb = &box[0, 0, 0, 0] if box.size else NULL
    if S == 0 or m == 0:
        return
    with nogil:
        for s in range(S):
            bad |= _weights(u[s, 0], nx, sx, Lx, w, beta, kx, ix)
            bad |= _weights(u[s, 1], ny, sy, Ly, w, beta, ky, iy)
            bad |= _weights(u[s, 2], nz, sz, Lz, w, beta, kz, iz)
            if bad:
                break
            run = ix[w - 1] == ix[0] + w - 1          # the x cells contiguous in the box (no wrap)
            for ci in range(m):
                v = c[ci, s]
                for a in range(w):
                    vz = v * kz[a]
                    for b in range(w):
                        vzy = vz * ky[b]
                        base = ((ci * Lz + iz[a]) * Ly + iy[b]) * Lx
                        if run:
                            row = pb + base + ix[0]
                            for t in range(w):
                                row[t] += vzy * kx[t]
                        else:
                            for t in range(w):
                                pb[base + ix[t]] += vzy * kx[t]
    if bad:
        raise ValueError("spread: a point's stencil leaves the grid box")


def interpolate(const double[:, ::1] u, const double[:, :, :, ::1] box, double[:, ::1] out, n, start, int w,
                double beta, int threads=1):
    """out[a, t] = sum_cells box[a, cell] psi (module docstring); out (m, T).  OpenMP over the points."""
    _check(box, u, n, start, w)
    cdef long T = u.shape[0], m = box.shape[0]
    if out.shape[1] != T or out.shape[0] != m:
        raise ValueError("out must be (m, T) with m = box.shape[0]")
    cdef long nx = n[0], ny = n[1], nz = n[2], sx = start[0], sy = start[1], sz = start[2]
    cdef long Lz = box.shape[1], Ly = box.shape[2], Lx = box.shape[3]
    cdef long s, a, b, t, ci, base
    cdef long bad = 0
    cdef double acc, accy, accz
    cdef double* kx
    cdef long* ix
    cdef const double* pb = &box[0, 0, 0, 0] if box.size else NULL
    if T == 0 or m == 0:
        return
    with nogil, parallel(num_threads=max(1, threads)):
        kx = <double*>malloc(3 * MAXW * sizeof(double))        # per thread: x, y, z weights
        ix = <long*>malloc(3 * MAXW * sizeof(long))
        for s in prange(T, schedule="static"):
            if (_weights(u[s, 0], nx, sx, Lx, w, beta, kx, ix)
                    + _weights(u[s, 1], ny, sy, Ly, w, beta, kx + MAXW, ix + MAXW)
                    + _weights(u[s, 2], nz, sz, Lz, w, beta, kx + 2 * MAXW, ix + 2 * MAXW)) > 0:
                bad += 1
                continue
            for ci in range(m):
                accz = 0.0
                for a in range(w):
                    accy = 0.0
                    for b in range(w):
                        base = ((ci * Lz + ix[2 * MAXW + a]) * Ly + ix[MAXW + b]) * Lx
                        acc = 0.0
                        if ix[w - 1] == ix[0] + w - 1:           # contiguous x cells
                            base = base + ix[0]
                            for t in range(w):
                                acc = acc + pb[base + t] * kx[t]
                        else:
                            for t in range(w):
                                acc = acc + pb[base + ix[t]] * kx[t]
                        accy = accy + acc * kx[MAXW + b]
                    accz = accz + accy * kx[2 * MAXW + a]
                out[ci, s] = accz
        free(kx)
        free(ix)
    if bad:
        raise ValueError("interpolate: a point's stencil leaves the grid box")
