"""Self interaction: singular quadrature assembled into per-vesicle operators (docs/explanation/method.md, section 5.1; paper 3.2.1).

For a target t = (theta0, phi0) of the p-grid the surface and the density are rotated so
that t sits at the north pole, g = f o R_z(phi0) R_y(theta0), evaluated on the q-grid and
integrated with the Graham-Sloan weights

    Lambda_i = w_i (pi/q) 2 sin(theta_i/2) sum_{n=0..q} P_n(cos theta_i)

applied to the integrand K(X_t, X(y)) f(y) W(y)/sin(theta).  As a linear map of the density
coefficients the row of target t is R_t^T Q_q^T (Lambda o W o K), assembled through the
transposed transforms (never forming Q R_t); projecting the rows on the p-grid with P gives
the Galerkin operator S_hat = P S (3C x 3C per vesicle), applied with one batched GEMM.

Precision (-ves_self_precision): the operators are assembled in float64 one vesicle at a time
and stored in `dtype` (float64, or float32 at half the memory); float32 operators are applied in
float32 (the density rounded to float32, the result returned in float64), docs/explanation/parallel.md.

Double layer: the lambda = 0 kernel -(3/4pi)(r.n_y) r r^T / r^5 gives the principal value;
the limits from outside/inside are pv -/+ density/2.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.special import eval_legendre

from .. import sph, threads
from .._kernels import stokes

# self operators smaller than this (bytes) are applied in one thread: waking a second one costs
# more than it saves (MIN_P_THREADS in vesflow.threads for the set-up; measured below)
MIN_BYTES_THREADED = 32e6

INV8PI = 1.0 / (8.0 * np.pi)
DL_COEF = -3.0 / (4.0 * np.pi)
# the 6 components a <= b of a symmetric 3x3 kernel (the order of stokes.self_kernel_tables)
# and the index of component (a, b) among them
SYM = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))
FULL = np.array([[0, 1, 2], [1, 3, 4], [2, 4, 5]])
NONE = np.empty((0, 0, 0))


@lru_cache(maxsize=16)
def graham_sloan_weights(q):
    """Lambda_i on the q-grid (npts,): integrates g / chord exactly for g of degree <= q."""
    theta, _, w = sph.gauss_grid(q)
    x = np.cos(theta)
    legsum = sum(eval_legendre(n, x) for n in range(q + 1))
    lam = w * (np.pi / q) * 2.0 * np.sin(theta / 2.0) * legsum
    return np.repeat(lam, 2 * q)


def project_rows(rows, p, scale=1.0):
    """scale P R for the rows R (M, 6, k >= C) of the p-grid targets (the 6 components a <= b
    of a symmetric kernel, SYM; columns: density coefficients), by the fast analysis along
    the target axis (sph.Transform.analysis_rows), laid out as the (3C, 3C) operator with
    blocks [a, b] = component FULL[a, b] (the density in the reduced space: k' < C)."""
    C = sph.n_coeffs(p)
    M, _, k = rows.shape
    proj = sph.transform(p).analysis_rows(rows.reshape(M, 6 * k), scale=scale).reshape(C, 6, k)
    out = np.empty((3, C, 3, C))
    for ab, (a, b) in enumerate(zip(*SYM)):
        out[a, :, b] = proj[:, ab, :C]
        if a != b:
            out[b, :, a] = proj[:, ab, :C]
    return out.reshape(3 * C, 3 * C)


class SelfOperators:
    """Per-vesicle Galerkin self operators of degree p with singular quadrature order q.

    S[v] (3C, 3C): coefficients of the density f (component-major: [b, k]) ->
    coefficients of S_v[f] on vesicle v's own surface.  D[v] likewise for the principal
    value of the lambda = 0 double layer (only built when want_double).
    """

    def __init__(self, coeffs, p, q=None, want_single=True, want_double=False, viscosity=1.0, dtype=np.float64):
        coeffs = np.asarray(coeffs, dtype=float)
        self.p = p
        self.q = 2 * p if q is None else q
        if self.q <= p:
            raise ValueError(f"singular quadrature order q = {self.q} must exceed p = {p}")
        C = sph.n_coeffs(p)
        nves = coeffs.shape[0]
        dtype = np.dtype(dtype)
        if dtype not in (np.float64, np.float32):
            raise ValueError(f"SelfOperators dtype = {dtype}: must be float64 or float32")
        self.single = np.empty((nves, 3 * C, 3 * C), dtype) if want_single else None
        self.double = np.empty((nves, 3 * C, 3 * C), dtype) if want_double else None
        def store(v):               # one vesicle's float64 operators at a time (peak memory)
            S, D = self._assemble(coeffs[v], want_single, want_double)
            if want_single:
                np.divide(S, viscosity, out=self.single[v])   # in place: no (3C)^2 temporary
            if want_double:
                self.double[v] = D
        threads.map_vesicles(store, range(nves), p)

    @property
    def nbytes(self):
        """Bytes held by the operators."""
        return sum(a.nbytes for a in (self.single, self.double) if a is not None)

    def _assemble(self, X, want_single, want_double):
        """Both kernels are symmetric in (a, b): only the 6 components a <= b (SYM) are
        integrated, rotated back and projected.  The z-rotation of the surface depends on the
        target's longitude alone: done once for all latitudes; per latitude remain the tilt
        R_y(theta0), the synthesis, the kernel tables, Q^T and the rotations back.  The rows
        of all targets are projected on the p-grid by the fast analysis along the target axis
        (project_rows)."""
        p, q = self.p, self.q
        Tp, Tq = sph.transform(p), sph.transform(p, q)
        C, K = sph.n_coeffs(p), sph.n_full(p)
        lam_w = graham_sloan_weights(q) / np.repeat(Tq.sin_theta, Tq.nlon)  # Lambda / sin(theta)
        Xt_grid = Tp.synth(X).T.reshape(Tp.nlat, Tp.nlon, 3)
        kinds = [w for w, on in (("S", want_single), ("D", want_double)) if on]
        rows = {w: np.empty((Tp.nlat, Tp.nlon, 6, K)) for w in kinds}   # R_t^T Q^T (Lambda W K) per target
        phis = Tp.phi
        ker = {w: np.empty((len(phis), 6, Tq.npts)) for w in kinds}      # kernel x weights (stokes.self_kernel_tables)
        Xz = sph.rotate_z(np.broadcast_to(X, (len(phis), 3, C)), p, phis[:, None])   # f o R_z(phi0), (J, 3, K)
        z_back = sph.z_rotation_tables(p, -phis[:, None])                    # D_z(phi0)^T = D_z(-phi0)
        for i0, theta0 in enumerate(Tp.theta):
            # rotated surface, one per target on this latitude: (J, 3, Mq) with derivatives
            blocks = sph.wigner_blocks(p, float(theta0))
            x, xt, xp = Tq.synth_first(sph.apply_degree_blocks(Xz, p, blocks))
            stokes.self_kernel_tables(np.ascontiguousarray(Xt_grid[i0]), x, xt, xp, lam_w,
                                      ker["S"] if want_single else NONE, ker["D"] if want_double else NONE)
            for which in kinds:
                R = Tq.synth_transpose(ker[which], full=True)                       # (J, 6, K)
                back = sph.apply_degree_blocks(R, p, blocks, transpose=True)        # D_y(theta0)^T
                rows[which][i0] = sph.rotate_z(back, p, None, tables=z_back)
        out = []
        for which in ("S", "D"):
            if which not in rows:
                out.append(None)
                continue
            out.append(project_rows(rows.pop(which).reshape(Tp.npts, 6, K), p))
        return out[0], out[1]

    # ------------------------------------------------------------------ apply
    @staticmethod
    def apply(ops, density_coeffs):
        """Batched GEMV: ops (N, 3C, 3C), density (N, 3, C) -> (N, 3, C) float64 (float32
        operators: the product in float32).  Memory-bound (it reads every operator once: 3 GB at
        N = 512, p = 16), so the vesicles are split into one contiguous range per thread
        (vesflow.threads.map_vesicles: up to OMP_NUM_THREADS, only idle cores), each range one
        np.matmul, which releases the GIL (BLAS on one thread meanwhile); operators below
        MIN_BYTES_THREADED in one call."""
        N, _, C = density_coeffs.shape
        x = density_coeffs.reshape(N, 3 * C, 1)
        if ops.dtype == np.float32:
            x = x.astype(np.float32)
        out = np.empty((N, 3 * C, 1), dtype=ops.dtype)
        n = threads.vesicle_threads(N) if ops.nbytes >= MIN_BYTES_THREADED else 1
        if n <= 1:
            np.matmul(ops, x, out=out)
        else:
            cut = np.linspace(0, N, n + 1).round().astype(int)
            ranges = [slice(a, b) for a, b in zip(cut[:-1], cut[1:])]
            threads.map_vesicles(lambda r: np.matmul(ops[r], x[r], out=out[r]), ranges)
        return out.reshape(N, 3, C).astype(np.float64, copy=False)
