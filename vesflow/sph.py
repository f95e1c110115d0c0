"""Real spherical harmonics on Gauss-Legendre grids (docs/explanation/method.md, section 2; paper 3.1).

Basis (orthonormal on the unit sphere, no Condon-Shortley phase):
    Y_n^0 = lam_n^0(cos t),  Y_n^{m,c} = sqrt2 lam_n^m(cos t) cos(m p),  Y_n^{m,s} = sqrt2 lam_n^m(cos t) sin(m p)
with lam_n^m = sqrt((2n+1)/(4 pi) (n-m)!/(n+m)!) P_n^m, so that int lam^2 dx = 1/(2 pi).

Flat coefficient layout of degree p ("full", (p+1)^2 entries), m-blocks:
    [m=0: n=0..p] [m=1 cos: n=1..p] [m=1 sin: n=1..p] ... [m=p cos: n=p] [m=p sin: n=p]
The last entry, the (n=p, m=p, sin) mode, vanishes at every point of the p-grid (2p longitudes),
so fields of the method live in the "reduced" space of the first C = (p+1)^2 - 1 entries
(docs/explanation/conventions.md).  Rotations act on the full space; synthesis on a q-grid with q > p
resolves it.

Grids: q+1 Gauss-Legendre latitudes (cos theta descending), 2q longitudes phi_j = pi j / q,
flattened latitude-major.  All transforms are batched over leading axes.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

SQRT2 = np.sqrt(2.0)


def n_full(p):
    """Number of coefficients of the full degree-p space."""
    return (p + 1) ** 2


def n_coeffs(p):
    """Number of coefficients of the reduced degree-p space (m = p sine mode dropped)."""
    return (p + 1) ** 2 - 1


@lru_cache(maxsize=None)
def index_tables(p):
    """Per flat index: degree n, order m, kind (0 = cos, 1 = sin).  Read-only arrays."""
    ns, ms, ks = [], [], []
    for m in range(p + 1):
        for kind in ((0,) if m == 0 else (0, 1)):
            for n in range(m, p + 1):
                ns.append(n)
                ms.append(m)
                ks.append(kind)
    out = tuple(np.array(a, dtype=np.int64) for a in (ns, ms, ks))
    for a in out:
        a.flags.writeable = False
    return out


def flat_index(p, n, m, kind=0):
    """Flat position of mode (n, m, kind) in the degree-p layout."""
    ns, ms, ks = index_tables(p)
    hit = np.nonzero((ns == n) & (ms == m) & (ks == kind))[0]
    if len(hit) != 1:
        raise ValueError(f"no mode n={n}, m={m}, kind={kind} at degree {p}")
    return int(hit[0])


def legendre(p, x):
    """Normalized associated Legendre functions and theta derivatives.

    Returns (lam, dlam, d2lam), each of shape (p+1 [m], len(x), p+1 [n]), zero for n < m;
    derivatives are with respect to theta = arccos(x) (|x| < 1 required).
    """
    x = np.asarray(x, dtype=float)
    s = np.sqrt(1.0 - x * x)
    lam = np.zeros((p + 1, len(x), p + 1))
    mm = 1.0 / np.sqrt(4.0 * np.pi) * np.ones_like(x)
    for m in range(p + 1):
        if m > 0:
            mm = mm * np.sqrt((2.0 * m + 1.0) / (2.0 * m)) * s
        lam[m, :, m] = mm
        if m + 1 <= p:
            lam[m, :, m + 1] = np.sqrt(2.0 * m + 3.0) * x * mm
        for n in range(m + 2, p + 1):
            a = np.sqrt((4.0 * n * n - 1.0) / (n * n - m * m))
            b = np.sqrt(((n - 1.0) ** 2 - m * m) / (4.0 * (n - 1.0) ** 2 - 1.0))
            lam[m, :, n] = a * (x * lam[m, :, n - 1] - b * lam[m, :, n - 2])
    dlam = np.zeros_like(lam)
    with np.errstate(divide="ignore", invalid="ignore"):   # derivatives are undefined at the poles
        dlam, d2lam = _legendre_derivatives(p, x, s, lam, dlam)
    return lam, dlam, d2lam


def _legendre_derivatives(p, x, s, lam, dlam):
    for m in range(p + 1):
        for n in range(m, p + 1):
            prev = lam[m, :, n - 1] if n - 1 >= m else 0.0
            c = np.sqrt((2.0 * n + 1.0) / (2.0 * n - 1.0) * (n * n - m * m)) if n > m else 0.0
            dlam[m, :, n] = (n * x * lam[m, :, n] - c * prev) / s
    nn = np.arange(p + 1)[None, None, :]
    mq = np.arange(p + 1)[:, None, None]
    cot = (x / s)[None, :, None]
    d2lam = -cot * dlam - (nn * (nn + 1) - mq * mq / (s * s)[None, :, None]) * lam
    return dlam, d2lam


@lru_cache(maxsize=None)
def gauss_grid(q):
    """Latitudes and longitudes of the q-grid: (theta (q+1,), phi (2q,), GL weights (q+1,))."""
    x, w = np.polynomial.legendre.leggauss(q + 1)
    order = np.argsort(-x)
    x, w = x[order], w[order]
    theta = np.arccos(x)
    phi = np.pi * np.arange(2 * q) / q
    for a in (theta, phi, w):
        a.flags.writeable = False
    return theta, phi, w


class Transform:
    """Synthesis Q (coefficients -> q-grid values, with derivatives) and analysis P (q-grid ->
    degree-p coefficients) for degree p on the q-grid, batched over leading axes.

    Cost O(p^2 q + p q^2) per field: a Legendre step (one small matrix per m, batched matmul)
    and a Fourier step (dense trig matrices, BLAS).
    """

    def __init__(self, p, q=None):
        q = p if q is None else q
        if q < p:
            raise ValueError(f"quadrature order q = {q} must be >= p = {p}")
        self.p, self.q = p, q
        self.theta, self.phi, self.glw = gauss_grid(q)
        self.nlat, self.nlon = q + 1, 2 * q
        self.npts = self.nlat * self.nlon
        self.nfull = n_full(p)
        self.ncoef = n_coeffs(p)
        x = np.cos(self.theta)
        self.lam, self.dlam, self.d2lam = legendre(p, x)
        self._lam_T = np.ascontiguousarray(np.swapaxes(self.lam, 1, 2))
        self.sin_theta = np.sqrt(1.0 - x * x)
        # quadrature weight per grid point on the unit sphere (w_i pi / q)
        self.weights = np.repeat(self.glw * np.pi / q, self.nlon)
        # gather: padded (kind, m, n) <- flat
        ns, ms, ks = index_tables(p)
        self._pad_index = (ks, ms, ns)
        self._pad_flat = (ks * (p + 1) + ms) * (p + 1) + ns
        m = np.arange(p + 1)
        ang = np.outer(m, self.phi)                        # (p+1, nlon)
        c = np.where(m == 0, 1.0, SQRT2)[:, None]
        self.cos_m = c * np.cos(ang)
        self.sin_m = c * np.sin(ang)
        self.sin_m[0] = 0.0
        mm = m[:, None].astype(float)
        # analysis in phi: exact discrete inverse on 2q points, 1 / (c_m^2 N_m) with
        # N_m = sum_j cos^2(m phi_j) = q (0 < m < q), 2q (m = 0 and the Nyquist mode m = q)
        nm = np.full(p + 1, float(q))
        nm[0] = 2.0 * q
        if p == q:
            nm[q] = 2.0 * q
        aw = 2.0 * np.pi / (c[:, 0] ** 2 * nm)
        self._trig_analysis = np.ascontiguousarray(np.concatenate([self.cos_m, self.sin_m], axis=0) * np.tile(aw, 2)[:, None])
        # the stacked [cos; sin] matrices of the Fourier step: values and d/dphi (synth_first)
        self._trig_values = np.ascontiguousarray(np.concatenate([self.cos_m, self.sin_m], axis=0))
        # synthesis: rows in (m, s) order (s = cos, sin), for values, d/dphi and d2/dphi2
        inter = lambda c, s_: np.ascontiguousarray(np.stack([c, s_], axis=1).reshape(2 * (p + 1), -1))
        self._trig_ms = inter(self.cos_m, self.sin_m)
        self._trig_ms_p = inter(-mm * self.sin_m, mm * self.cos_m)
        self._trig_ms_pp = inter(-mm * mm * self.cos_m, -mm * mm * self.sin_m)
        self._dlam_T = np.ascontiguousarray(np.swapaxes(self.dlam, 1, 2))
        self._d2lam_T = np.ascontiguousarray(np.swapaxes(self.d2lam, 1, 2))

    # ---------------------------------------------------------------- padding
    def pad(self, coeffs):
        """Flat (..., C or (p+1)^2) -> padded (..., 2, p+1 [m], p+1 [n])."""
        coeffs = np.asarray(coeffs, dtype=float)
        k = coeffs.shape[-1]
        if k not in (self.ncoef, self.nfull):
            raise ValueError(f"expected {self.ncoef} or {self.nfull} coefficients for p = {self.p}, got {k}")
        M = self.p + 1
        out = np.zeros(coeffs.shape[:-1] + (2 * M * M,))
        out[..., self._pad_flat[:k]] = coeffs
        return out.reshape(coeffs.shape[:-1] + (2, M, M))

    def unpad(self, padded, full=False):
        """Padded (..., 2, p+1, p+1) -> flat (..., C) or (..., (p+1)^2)."""
        k = self.nfull if full else self.ncoef
        ks, ms, ns = (a[:k] for a in self._pad_index)
        return padded[..., ks, ms, ns]

    # ---------------------------------------------------------------- synthesis
    def _pad_msbn(self, coeffs):
        """Flat (..., k) -> padded (M [m], 2 [cos/sin], B, N [n]) with B the product of the
        leading axes: the layout in which both synthesis GEMMs read their operands in place."""
        coeffs = np.asarray(coeffs, dtype=float)
        k = coeffs.shape[-1]
        if k not in (self.ncoef, self.nfull):
            raise ValueError(f"expected {self.ncoef} or {self.nfull} coefficients for p = {self.p}, got {k}")
        B = math.prod(coeffs.shape[:-1])
        M = self.p + 1
        ks, ms, ns = (a[:k] for a in self._pad_index)
        out = np.zeros((M, 2, B, M))
        out[ms, ks, :, ns] = coeffs.reshape(B, k).T
        return out.reshape(M, 2 * B, M)

    def _synth_layout(self, padded, table_T, trig, lead):
        """Legendre step (one GEMM per m: (2B, N) @ (N, I)) then the Fourier step as one GEMM of
        the (B I, 2M) matrix read in place (column index (m, s)) with trig ((m, s), J) rows."""
        Z = np.matmul(padded, table_T)                                   # (M, 2B, I) = [m, s, b, i]
        M, B2, I = Z.shape
        out = Z.reshape(2 * M, (B2 // 2) * I).T @ trig                   # (B I, J)
        return out.reshape(lead + (I * trig.shape[1],))

    def synth(self, coeffs, d=None):
        """Q: values on the q-grid, (..., npts).  d selects a derivative: None, 't', 'p', 'tt', 'tp', 'pp'."""
        coeffs = np.asarray(coeffs, dtype=float)
        table = {None: self._lam_T, "p": self._lam_T, "pp": self._lam_T,
                 "t": self._dlam_T, "tp": self._dlam_T, "tt": self._d2lam_T}[d]
        trig = {None: self._trig_ms, "t": self._trig_ms, "tt": self._trig_ms,
                "p": self._trig_ms_p, "tp": self._trig_ms_p, "pp": self._trig_ms_pp}[d]
        return self._synth_layout(self._pad_msbn(coeffs), table, trig, coeffs.shape[:-1])

    def synth_first(self, coeffs):
        """Values and first derivatives (values, d/dtheta, d/dphi), each (..., npts): two
        Legendre steps and three Fourier GEMMs."""
        coeffs = np.asarray(coeffs, dtype=float)
        lead = coeffs.shape[:-1]
        padded = self._pad_msbn(coeffs)
        Z0 = np.matmul(padded, self._lam_T)
        Z1 = np.matmul(padded, self._dlam_T)
        M, B2, I = Z0.shape
        A0 = Z0.reshape(2 * M, (B2 // 2) * I).T
        A1 = Z1.reshape(2 * M, (B2 // 2) * I).T
        shape = lead + (self.npts,)
        return ((A0 @ self._trig_ms).reshape(shape), (A1 @ self._trig_ms).reshape(shape),
                (A0 @ self._trig_ms_p).reshape(shape))

    def synth_all(self, coeffs, values=True):
        """Values and first and second derivatives at once: dict with keys '', 't', 'p', 'tt', 'tp', 'pp'
        ('' left out when not values)."""
        coeffs = np.asarray(coeffs, dtype=float)
        lead = coeffs.shape[:-1]
        padded = self._pad_msbn(coeffs)
        A = {}
        for name, table in (("0", self._lam_T), ("1", self._dlam_T), ("2", self._d2lam_T)):
            Z = np.matmul(padded, table)
            M, B2, I = Z.shape
            A[name] = Z.reshape(2 * M, (B2 // 2) * I).T
        out = {}
        shape = lead + (self.npts,)
        for key, a, trig in (("", "0", self._trig_ms), ("p", "0", self._trig_ms_p), ("pp", "0", self._trig_ms_pp),
                             ("t", "1", self._trig_ms), ("tp", "1", self._trig_ms_p), ("tt", "2", self._trig_ms)):
            if key == "" and not values:
                continue
            out[key] = (A[a] @ trig).reshape(shape)
        return out

    # ---------------------------------------------------------------- analysis
    def analysis(self, values, full=False):
        """P: q-grid values (..., npts) -> degree-p coefficients (..., C) (or full (p+1)^2).

        Exact inverse of synth on the degree-p space (reduced space when q = p), and the
        L2 projection onto it for fields of degree <= q.
        """
        values = np.asarray(values, dtype=float)
        return self._analysis_like(values, self._trig_analysis, self.glw, full)

    def _analysis_like(self, values, trig, latw, full):
        """Fourier projection with trig = [acos; asin] (2M, nlon), latitude weights, then the
        transposed Legendre step.  Layout (s = cos/sin, m, b = batch, i = latitude) throughout,
        so that both GEMMs read their operands in place and the result is gathered once; the
        Legendre step per order m over the degrees n >= m only (1/3 less time at p = 16)."""
        lead = values.shape[:-1]
        B = math.prod(lead)
        M = self.p + 1
        g = values.reshape(B * self.nlat, self.nlon)
        F = trig @ g.T                                                       # (2M, B*I): [s, m, b, i]
        F = F.reshape(2, M, B, self.nlat)
        if latw is not None:
            F *= latw
        Ft = F.transpose(0, 1, 3, 2)
        padded = np.empty((2, M, M, B))                                      # (2, M, N, B); n < m unused
        for m in range(M):                                                   # lam_n^m = 0 for n < m
            np.matmul(self._lam_T[m, m:], Ft[:, m], out=padded[:, m, m:])
        k = self.nfull if full else self.ncoef
        out = padded.reshape(2 * M * M, B)[self._pad_flat[:k]]              # (k, B)
        return np.ascontiguousarray(out.T).reshape(lead + (k,))

    def analysis_rows(self, values, full=False, scale=1.0):
        """P along the first axis: values (npts, B) on the grid -> coefficients (C or (p+1)^2, B),
        times ``scale`` (folded into the latitude weights).  The same two steps as analysis,
        in the layout that reads the rows in place: per latitude a (2M, nlon) @ (nlon, B) GEMM,
        then per (s, m) the Legendre step (N, I) @ (I, B) on strided slices: 100 MFLOP for
        B = 6C at p = q = 16, against 550 for the dense (C, npts) analysis matrix."""
        values = np.asarray(values, dtype=float)
        B = values.shape[1]
        M = self.p + 1
        F = np.matmul(self._trig_analysis, values.reshape(self.nlat, self.nlon, B))   # (I, 2M, B)
        F = F.reshape(self.nlat, 2, M, B).transpose(1, 2, 0, 3)                     # (2, M, I, B)
        lam_w = self._lam_T * (self.glw * scale)                                     # weights on the small table
        padded = np.empty((2, M, M, B))                                              # (2, M, N, B); n < m unused
        for m in range(M):
            np.matmul(lam_w[m, m:], F[:, m], out=padded[:, m, m:])
        k = self.nfull if full else self.ncoef
        return padded.reshape(2 * M * M, B)[self._pad_flat[:k]]

    def synth_transpose(self, values, full=False):
        """Q^T: the transpose of synth as a linear map, (..., npts) -> (..., C) or (..., (p+1)^2)."""
        values = np.asarray(values, dtype=float)
        return self._analysis_like(values, self._trig_values, None, full)

    def integrate(self, values):
        """Integral over the unit sphere of a q-grid field (..., npts)."""
        return np.asarray(values) @ self.weights


@lru_cache(maxsize=64)
def transform(p, q=None):
    """Cached Transform(p, q)."""
    return Transform(p, p if q is None else q)


@lru_cache(maxsize=16)
def basis_on_grid(p, q):
    """Values and derivatives of the C degree-p basis functions on the q-grid: dict of (C, npts)
    (keys '', 't', 'p', 'tt', 'tp', 'pp', as Transform.synth_all), read-only."""
    out = transform(p, q).synth_all(np.eye(n_coeffs(p)))
    for a in out.values():
        a.flags.writeable = False
    return out


def resample(coeffs, p_from, p_to):
    """Coefficients of degree p_from re-expressed at degree p_to (zero-padding or truncation = filter)."""
    coeffs = np.asarray(coeffs, dtype=float)
    if p_from == p_to:
        return coeffs.copy()
    Tf, Tt = transform(p_from), transform(p_to)
    padded = Tf.pad(coeffs)
    pm = min(p_from, p_to)
    out = np.zeros(coeffs.shape[:-1] + (2, p_to + 1, p_to + 1))
    out[..., :pm + 1, :pm + 1] = padded[..., :pm + 1, :pm + 1]
    full = coeffs.shape[-1] == n_full(p_from) and p_to >= p_from
    return Tt.unpad(out, full=full)


def filter_coeffs(coeffs, p, attenuation):
    """Multiply every coefficient of degree n by attenuation(n) (array of length p+1)."""
    ns, _, _ = index_tables(p)
    k = np.asarray(coeffs).shape[-1]
    return np.asarray(coeffs) * np.asarray(attenuation)[ns[:k]]


# ------------------------------------------------------------------------ evaluation anywhere
def evaluate(coeffs, p, theta, phi):
    """Values of degree-p fields at arbitrary points (theta, phi): (..., C) -> (..., npoints)."""
    theta = np.asarray(theta, dtype=float).ravel()
    phi = np.asarray(phi, dtype=float).ravel()
    T = transform(p)
    padded = T.pad(coeffs)
    lam, _, _ = legendre(p, np.cos(theta))                   # (M, P, N)
    m = np.arange(p + 1)
    c = np.where(m == 0, 1.0, SQRT2)[:, None]
    cosm = c * np.cos(np.outer(m, phi))                      # (M, P)
    sinm = c * np.sin(np.outer(m, phi))
    F = np.einsum("...kmn,mPn->...kmP", padded, lam, optimize=True)
    return np.einsum("...mP,mP->...P", F[..., 0, :, :], cosm) + np.einsum("...mP,mP->...P", F[..., 1, :, :], sinm)


def basis_values(p, theta, phi):
    """The C basis functions at the points (theta, phi): (P, C), evaluate(eye(C), ...).T entry
    for entry, without its (C, 2, p + 1, P) intermediate (78 kB per point at p = 16)."""
    T = transform(p)
    ks, ms, ns = (a[:T.ncoef] for a in T._pad_index)
    theta = np.asarray(theta, dtype=float).ravel()
    phi = np.asarray(phi, dtype=float).ravel()
    lam, _, _ = legendre(p, np.cos(theta))                   # (M, P, N)
    m = np.arange(p + 1)
    c = np.where(m == 0, 1.0, SQRT2)[:, None]
    trig = np.stack([c * np.cos(np.outer(m, phi)), c * np.sin(np.outer(m, phi))])    # (2, M, P)
    return (lam[ms, :, ns] * trig[ks, ms, :]).T


# ------------------------------------------------------------------------ rotations
def rotation_y_points(beta, theta, phi):
    """Angles of R_y(beta) applied to the unit vectors (theta, phi)."""
    x = np.sin(theta) * np.cos(phi)
    y = np.sin(theta) * np.sin(phi)
    z = np.cos(theta)
    cb, sb = np.cos(beta), np.sin(beta)
    xr, zr = cb * x + sb * z, -sb * x + cb * z
    return np.arccos(np.clip(zr, -1.0, 1.0)), np.arctan2(y, xr)


@lru_cache(maxsize=4096)   # 2 (p+1) tilts per operator assembly; must not thrash
def wigner_blocks(p, beta):
    """Rotation of degree-p coefficients by a tilt R_y(beta), per degree n.

    The field g(y) = f(R_y(beta) y) has coefficients D(beta) f, D block diagonal in n.
    Returns a tuple over n of (index array into the full flat layout, block (2n+1, 2n+1)).
    Computed by exact projection on the (p+1)-grid, which resolves the full degree-p space.
    """
    T = transform(p, p + 1)
    tt, pp = np.meshgrid(T.theta, T.phi, indexing="ij")
    tr, pr = rotation_y_points(beta, tt.ravel(), pp.ravel())
    basis = evaluate(np.eye(n_full(p)), p, tr, pr)           # (K, npts): basis_k(R y)
    D = T.analysis(basis, full=True).T                       # D[j, k] = <Y_j, Y_k o R>
    ns, _, _ = index_tables(p)
    blocks = []
    for n in range(p + 1):
        idx = np.nonzero(ns == n)[0]
        blocks.append((idx, np.ascontiguousarray(D[np.ix_(idx, idx)])))
    return tuple(blocks)


def rotate_z(coeffs, p, alpha, tables=None):
    """Coefficients of g(theta, phi) = f(theta, phi + alpha), full layout (..., (p+1)^2).

    alpha may be an array broadcast against the leading axes of coeffs.  Per coefficient k
    of order m: out_k = c_k cos(m alpha) + c_k' s_k sin(m alpha), with k' the sine (cosine)
    partner of a cosine (sine) coefficient and s_k = +1 (-1); one gather of the partners and
    whole-row products (no per-order slices: slow for many short rows).  ``tables`` =
    z_rotation_tables(p, alpha), when the same angles rotate many arrays (the trigonometric
    functions then cost more than the rotation); alpha is ignored then.
    """
    coeffs = np.asarray(coeffs, dtype=float)
    if coeffs.shape[-1] != n_full(p):
        coeffs = np.concatenate([coeffs, np.zeros(coeffs.shape[:-1] + (1,))], axis=-1)
    cos_t, sin_t = z_rotation_tables(p, alpha) if tables is None else tables
    out = coeffs * cos_t
    out += np.take(coeffs, _z_rotation_index(p)[0], axis=-1) * sin_t
    return out


def z_rotation_tables(p, alpha):
    """(cos(m alpha), s sin(m alpha)) per coefficient of the full layout, shape alpha.shape +
    ((p+1)^2,): rotate_z's factors (sign s as there)."""
    partner, m, sign = _z_rotation_index(p)
    ang = m * np.asarray(alpha, dtype=float)[..., None]
    return np.cos(ang), sign * np.sin(ang)


@lru_cache(maxsize=None)
def _z_rotation_index(p):
    """rotate_z's tables over the full layout: the partner of each coefficient (the sine
    coefficient of the same (n, m) for a cosine one and vice versa; itself for m = 0), its
    order m (float) and the sign of the sine term (+1 cosine, -1 sine, 0 for m = 0)."""
    ns, ms, ks = index_tables(p)
    partner = np.arange(len(ns))
    cos_idx = np.nonzero((ks == 0) & (ms > 0))[0]
    sin_idx = cos_idx + (p + 1 - ms[cos_idx])
    partner[cos_idx], partner[sin_idx] = sin_idx, cos_idx
    sign = np.where(ms == 0, 0.0, np.where(ks == 0, 1.0, -1.0))
    return partner, ms.astype(float), sign


@lru_cache(maxsize=None)
def degree_order(p):
    """(perm, offsets): the full layout's indices sorted by degree n (within a degree in the
    order of wigner_blocks' idx), and where each degree starts in that order ((p+2,))."""
    ns = index_tables(p)[0]
    perm = np.concatenate([np.nonzero(ns == n)[0] for n in range(p + 1)])
    offsets = np.concatenate([[0], np.cumsum([np.count_nonzero(ns == n) for n in range(p + 1)])])
    perm.flags.writeable = False
    return perm, offsets


def apply_degree_blocks(coeffs, p, blocks, transpose=False):
    """coeffs (..., (p+1)^2) times the block-diagonal matrix of wigner_blocks-like ``blocks``
    ((idx, B_n) per degree) from the right: out[..., idx_n] = coeffs[..., idx_n] @ B_n^T (or
    @ B_n with transpose).  One gather into degree order, one GEMM per degree over all rows
    (the leading axes flattened: not one small GEMM per leading index), one scatter."""
    perm, offs = degree_order(p)
    x = np.take(coeffs, perm, axis=-1)
    shape = x.shape
    x = x.reshape(-1, shape[-1])
    y = np.empty_like(x)
    for n, (_, block) in enumerate(blocks):
        a, b = offs[n], offs[n + 1]
        np.matmul(x[:, a:b], block if transpose else block.T, out=y[:, a:b])
    return np.take(y, np.argsort(perm), axis=-1).reshape(shape)


def rotate_y(coeffs, p, beta):
    """Coefficients of g(y) = f(R_y(beta) y) (full layout in and out)."""
    coeffs = np.asarray(coeffs, dtype=float)
    if coeffs.shape[-1] != n_full(p):
        coeffs = np.concatenate([coeffs, np.zeros(coeffs.shape[:-1] + (1,))], axis=-1)
    return apply_degree_blocks(coeffs, p, wigner_blocks(p, float(beta)))


def rotate_to_pole(coeffs, p, theta0, phi0):
    """Coefficients of g(y) = f(R_z(phi0) R_y(theta0) y): the point (theta0, phi0) moved to the north pole."""
    return rotate_y(rotate_z(coeffs, p, phi0), p, theta0)
