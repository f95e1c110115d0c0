"""Reparameterization by tangential moves (paper 3.5; docs/explanation/method.md, section 7).

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
Finally the grid points are put back on the original surface (`project_onto`): once per
call in a run (1.8e-3 shape change on a badly parameterized prolate at p = 8, truncation
error 2.8e-4; in a shear run the change equals the run's discretization error), or iterated
(project_its > 1: 2.1e-4), which the run uses only near contact: at every step it keeps the
descent from converging (docs/explanation/robustness.md section 2).
"""
from __future__ import annotations

import numpy as np

from . import sph
from .layerpot.near import Projection


ATTENUATIONS = ("n2", "n", "n16", "step")


def attenuation_weights(p, attenuation="n2"):
    """a_n, n = 0..p, the schemes of the paper's Fig. 4: "n2" (n^2, its choice), "n" (n), "n16"
    (n^16, scaled by p^-14 so that a_p = p^2 as for "n2"), "step" (H(n - 2p/3): only the top
    third of the degrees, the scheme of the earlier papers), or an explicit array."""
    n = np.arange(p + 1, dtype=float)
    if isinstance(attenuation, str):
        if attenuation == "n2":
            return n ** 2
        if attenuation == "n":
            return n
        if attenuation == "n16":
            return n ** 2 * (n / p) ** 14
        if attenuation == "step":
            return np.where(n >= 2.0 * p / 3.0, 1.0, 0.0)
        raise ValueError(f"attenuation = {attenuation!r}: must be one of {', '.join(ATTENUATIONS)} "
                         "or an array of length p+1")
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


def truncation_estimate(coeffs, p):
    """Spectral estimate of the truncation error of degree-p surfaces: the norm of their
    degree-p coefficients, (N, 3, C) -> (N,).  For the distorted prolate of
    tests/stepping/test_robustness.py it is 1.7x / 2.1x / 2.4x the measured distance of the interpolant to
    the exact shape at p = 8 / 12 / 16."""
    ns, _, _ = sph.index_tables(p)
    c = np.asarray(coeffs, dtype=float)
    top = ns[:c.shape[-1]] == p
    return np.sqrt(np.einsum("vkc,vkc->v", c[..., top], c[..., top]))


def project_onto(Y, X0, p, omega=1.0, rtol=0.1, stall=0.8, max_its=1):
    """Degree-p surfaces Y whose p-grid points lie on the surfaces X0 (alternating projections).

    A tangential move of the parameterization is tangential only to first order, and its
    degree-p re-expansion has a normal part: unprojected, the distorted prolate of the tests
    moved by 3.4e-3 / 4.6e-4 / 6.9e-5 (Hausdorff) at p = 8 / 12 / 16 for truncation errors of
    2.8e-4 / 7e-6 / 1.8e-7, and near contact that pushed accepted pairs into each other.  One
    iteration (max_its of them): move every grid point to its closest point on X0 (Newton projection,
    `lp.near.Projection`, started at the previous closest point), re-expand at degree p, and
    over-relax by omega (the re-expansion keeps ~60% of a correction, so omega = 1 converges
    at a rate ~0.6, omega = 1.5 twice as fast).  Stops per vesicle when the largest grid-point
    distance to X0 is below rtol x `truncation_estimate(X0)` or no longer falls by `stall`.
    Measured on the distorted prolate, one / iterated (max_its = 10, omega = 1.5): shape change
    1.8e-3 / 2.1e-4 at p = 8, 2.1e-4 / 4.4e-6 at p = 12 (truncation error 2.8e-4, 7e-6).
    """
    Y = np.array(Y, dtype=float)
    N = Y.shape[0]
    T = sph.transform(p)
    th = np.tile(np.repeat(T.theta, T.nlon), (N, 1))
    ph = np.tile(np.tile(T.phi, T.nlat), (N, 1))
    tol = rtol * truncation_estimate(X0, p)
    prev = np.full(N, np.inf)
    act = np.arange(N)
    last = Y.copy()
    for _ in range(max_its):
        pts = np.moveaxis(T.synth(Y[act]), -2, -1).reshape(-1, 3)
        ves = np.repeat(act, T.npts)
        pr = Projection(X0, p, pts, ves, th[act].ravel(), ph[act].ravel())
        th[act], ph[act] = pr.theta.reshape(len(act), -1), pr.phi.reshape(len(act), -1)
        # a point whose Newton did not converge keeps its place (and does not count)
        dist = np.abs(np.where(pr.converged, pr.signed_distance, 0.0)).reshape(len(act), -1).max(axis=1)
        worse = dist > prev[act]
        Y[act[worse]] = last[worse]                                     # keep the best iterate
        go = (dist > tol[act]) & (dist < stall * prev[act])
        if not go.any():
            break
        on = np.where(pr.converged[:, None], pr.point, pts).reshape(len(act), T.npts, 3)
        target = T.analysis(np.moveaxis(on, -1, -2))
        last = Y[act[go]].copy()
        Y[act[go]] += omega * (target[go] - Y[act[go]])
        prev[act] = dist
        act = act[go]
    return Y


def reparameterize(coeffs, p, dtau_max=1e-3, tol=1e-5, max_its=20, attenuation="n2", q=None, project=True,
                   project_its=1):
    """Tangential gradient descent on E (paper 3.5); see the module docstring.

    coeffs (N, 3, C) (or (3, C)); q is the grid of the tangential projection (2p default);
    project: move the result's grid points back onto the original surface (`project_onto`,
    project_its times; iterated, over-relaxed by 1.5).
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
        d = T.synth_all(Ya, values=False)                               # derivatives (n, 3, M)
        dot = lambda a, b: np.einsum("vkm,vkm->vm", a, b)
        nrm = np.cross(d["t"], d["p"], axis=1)
        nrm /= np.sqrt(dot(nrm, nrm))[:, None, :]
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
        if not go.all():
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
        Y = project_onto(Y, X0, p, max_its=project_its, omega=1.0 if project_its == 1 else 1.5)
    e_after = np.einsum("vkc,c->v", Y * Y, w)
    if single:
        return Y[0], its, float(e_before[0]), float(e_after[0])
    return Y, its, e_before, e_after
