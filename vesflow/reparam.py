"""Reparameterization by tangential moves (paper 3.5; DESIGN 7).

Minimizes the spectral energy of paper 3.5

    E(Y) = sum_nm a_n^2 |Y_nm|^2,        a_n = n^2 ("n2") by default,

of the position coefficients Y while moving the points only tangentially, so that the
shape is unchanged to the discretization error.  One pseudo-time step:

    g = grad_Y E = 2 a_n^2 Y_nm          (coefficient space), synthesized on the q-grid,
    v = (I - n n^T) g / ||(I - n n^T) g||_inf,   projected back to degree p,
    dtau = min(dtau_max, (Y, v)_E / (v, v)_E),   (a, b)_E = sum a_n^2 a_nm . b_nm,
    Y <- Y - dtau v + (dtau^2 / 2) P[II(v, v) n],

stopping (per vesicle) when dtau < tol.  (Y, v)_E / (v, v)_E is the exact minimizer of the
quadratic E along -v, and (Y, v)_E >= 0 (v is a pointwise projection of the gradient), so E
decreases.  dtau is the largest point displacement of the step.  The last term (not in the
paper) is the second-order geodesic correction, II the second fundamental form: a straight
tangential step leaves the surface by (dtau^2 / 2) II(v, v); with it the area and volume
drift of the reparameterization drops from ~2e-6 to ~1e-8 per 20 steps of 1e-3.
The tangential projection is formed on the upsampled q = 2p grid (the product with n is
not band-limited; projecting from the p-grid aliases and moves the shape 2-6x more).
"""
from __future__ import annotations

import numpy as np

from . import sph
from .layerpot.near import Projection


def attenuation_weights(p, attenuation="n2"):
    """a_n, n = 0..p: "n2" (n^2, the paper's choice), "n" (n), or an explicit array."""
    n = np.arange(p + 1, dtype=float)
    if isinstance(attenuation, str):
        if attenuation == "n2":
            return n ** 2
        if attenuation == "n":
            return n
        raise ValueError(f"attenuation = {attenuation!r}: must be 'n2', 'n' or an array of length p+1")
    a = np.asarray(attenuation, dtype=float)
    if a.shape != (p + 1,):
        raise ValueError(f"attenuation array must have length p+1 = {p + 1}, got shape {a.shape}")
    return a


def spectral_energy(coeffs, p, attenuation="n2"):
    """E(Y) = sum_nm a_n^2 |Y_nm|^2 per vesicle: (N, 3, C) -> (N,)."""
    ns, _, _ = sph.index_tables(p)
    a = attenuation_weights(p, attenuation)
    c = np.asarray(coeffs, dtype=float)
    w = a[ns[:c.shape[-1]]] ** 2
    return np.einsum("...kc,c->...", c * c, w)


def project_onto(Y, X0, p):
    """Coefficients of the closest points on the surfaces X0 of the p-grid points of Y.

    A tangential move of the parameterization is tangential only to first order, and the
    degree-p projection of the move has a normal part at its truncation error: measured at
    p = 8 the shape moved by 3.4e-3 (Hausdorff) for a truncation error of 2.8e-4, and near
    contact it pushed accepted pairs into each other.  Moving each grid point to its closest
    point on the original surface (Newton projection, `lp.near.Projection`, started at the
    point's own grid parameters) leaves the shape at X0 up to the degree-p re-expansion.
    """
    N = Y.shape[0]
    T = sph.transform(p)
    pts = np.moveaxis(T.synth(Y), -2, -1).reshape(-1, 3)                 # (N M, 3), grid order
    th = np.repeat(T.theta, T.nlon)
    ph = np.tile(T.phi, T.nlat)
    ves = np.repeat(np.arange(N), T.npts)
    pr = Projection(X0, p, pts, ves, np.tile(th, N), np.tile(ph, N))
    on = np.where(pr.converged[:, None], pr.point, pts).reshape(N, T.npts, 3)
    return T.analysis(np.moveaxis(on, -1, -2))


def reparameterize(coeffs, p, dtau_max=1e-3, tol=1e-5, max_its=20, attenuation="n2", q=None, project=True):
    """Tangential gradient descent on E (paper 3.5); see the module docstring.

    coeffs (N, 3, C) (or (3, C)); q is the grid of the tangential projection (2p default);
    project: move the result's grid points back onto the original surface (`project_onto`).
    Returns (new_coeffs, iterations, energy_before (N,), energy_after (N,)); iterations is
    the number of steps taken by the slowest vesicle (energies are floats for a (3, C) input).
    """
    Y = np.array(coeffs, dtype=float)
    single = Y.ndim == 2
    if single:
        Y = Y[None]
    X0 = Y.copy()
    q = 2 * p if q is None else q
    T = sph.transform(p, q)
    ns, _, _ = sph.index_tables(p)
    w = attenuation_weights(p, attenuation)[ns[:Y.shape[-1]]] ** 2      # a_n^2 per coefficient
    e_before = np.einsum("vkc,c->v", Y * Y, w)
    act = np.arange(Y.shape[0])
    its = 0
    while its < max_its and len(act):
        Ya = Y[act]
        d = T.synth_all(Ya)                                             # values, derivatives (n, 3, M)
        dot = lambda a, b: np.einsum("vkm,vkm->vm", a, b)
        nrm = np.cross(d["t"], d["p"], axis=1)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        g = T.synth(2.0 * w * Ya)                                       # gradient on the grid
        g -= dot(g, nrm)[:, None, :] * nrm                              # (I - n n^T) g
        gmax = np.linalg.norm(g, axis=1).max(axis=1)                    # ||.||_inf over points
        v = T.analysis(g / np.where(gmax > 0, gmax, 1.0)[:, None, None])
        num = np.einsum("vkc,vkc,c->v", Ya, v, w)
        den = np.einsum("vkc,vkc,c->v", v, v, w)
        with np.errstate(divide="ignore", invalid="ignore"):
            dtau = np.where(den > 0, np.minimum(dtau_max, num / den), 0.0)
        go = dtau >= tol
        if not go.any():
            break
        d = {k: a[go] for k, a in d.items()}
        nrm, v, dtau, act = nrm[go], v[go], dtau[go], act[go]
        # geodesic (second-order) term: the point follows the surface, X - dtau v + dtau^2/2 II(v, v) n
        vg = T.synth(v)
        E, F, G = dot(d["t"], d["t"]), dot(d["t"], d["p"]), dot(d["p"], d["p"])
        bt, bp = dot(vg, d["t"]), dot(vg, d["p"])
        det = E * G - F * F
        vt, vp = (G * bt - F * bp) / det, (E * bp - F * bt) / det
        II = dot(d["tt"], nrm) * vt * vt + 2.0 * dot(d["tp"], nrm) * vt * vp + dot(d["pp"], nrm) * vp * vp
        curv = T.analysis(II[:, None, :] * nrm)
        Y[act] += -dtau[:, None, None] * v + 0.5 * dtau[:, None, None] ** 2 * curv
        its += 1
    if its and project:
        Y = project_onto(Y, X0, p)
    e_after = np.einsum("vkc,c->v", Y * Y, w)
    if single:
        return Y[0], its, float(e_before[0]), float(e_after[0])
    return Y, its, e_before, e_after
