"""Near-singular evaluation (docs/explanation/method.md, section 5.2; paper 3.2.2) and the projection it rests on.

A target x within h_n of another surface is projected on it, x -> Y0 = X(theta*, phi*), by
Gauss-Newton on |X(theta, phi) - x|^2 with exact spherical-harmonic derivatives and a
backtracking line search (the paper fits 3x3 quadratic patches; the series itself is
cheaper to differentiate exactly at O(p^2) per point and needs no patch switching).  The
layer potential is then evaluated with the smooth rule at L points Y0 + n0 h (1 + l/(L-1)),
l = 0..L-1, and Lagrange-interpolated, together with the on-surface limit at Y0, to x.

The projection is public: collision detection and repulsion reuse it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import sph
from .._kernels import series
from .._kernels import search
from ..errors import SettingsError

L_POINTS = 8


def blend_weight(s):
    """1 for s <= 0, 0 for s >= 1, the C^2 quintic 1 - (10 s^3 - 15 s^4 + 6 s^5) between: the
    weight of the near-singular value beyond h_n (s = (d / h_n - 1) / blend), so that the
    velocity is a C^2 function of the positions where targets leave the near zone."""
    s = np.clip(np.asarray(s, dtype=float), 0.0, 1.0)
    return 1.0 - s ** 3 * (10.0 - 15.0 * s + 6.0 * s ** 2)


def near_distance(area, q, factor=1.0):
    """Near-zone width h_n = factor * sqrt(A / q) (paper 3.2.2, A the largest vesicle area)."""
    return factor * np.sqrt(np.max(area) / q) * np.ones_like(np.asarray(area, dtype=float))


def eval_series(coeffs, p, theta, phi, derivs=True):
    """Values (and theta/phi derivatives) of per-point series coeffs (P, k, C) at (theta, phi) (P,)."""
    T = sph.transform(p)
    padded = T.pad(coeffs)                                            # (P, k, 2, M, N)
    lam, dlam, _ = sph.legendre(p, np.cos(theta))                     # (M, P, N)
    m = np.arange(p + 1)
    c = np.where(m == 0, 1.0, sph.SQRT2)
    cosm = c[:, None] * np.cos(np.outer(m, phi))                      # (M, P)
    sinm = c[:, None] * np.sin(np.outer(m, phi))
    def fourier(F, cs, sn):
        return np.einsum("pkm,mp->pk", F[:, :, 0], cs) + np.einsum("pkm,mp->pk", F[:, :, 1], sn)
    F0 = np.einsum("pkamn,mpn->pkam", padded, lam, optimize=True)
    val = fourier(F0, cosm, sinm)
    if not derivs:
        return val
    F1 = np.einsum("pkamn,mpn->pkam", padded, dlam, optimize=True)
    dt = fourier(F1, cosm, sinm)
    dp = fourier(F0, -m[:, None] * sinm, m[:, None] * cosm)
    return val, dt, dp


def eval_points(padded, vesicle, theta, phi):
    """Values and theta / phi derivatives (P, k) at (theta, phi) (P,) of the series of vesicle
    `vesicle` (P,) (padded coefficients (V, k, 2, M, N), sph.Transform.pad): the compiled
    kernel series.eval_points (same recurrences as eval_series, O(p^2) per point)."""
    P, k = len(theta), padded.shape[1]
    val, dt, dp = np.empty((P, k)), np.empty((P, k)), np.empty((P, k))
    series.eval_points(padded, np.ascontiguousarray(vesicle, dtype=np.int64), np.ascontiguousarray(theta, dtype=float),
                       np.ascontiguousarray(phi, dtype=float), val, dt, dp)
    return val, dt, dp


class Projection:
    """Closest points on surfaces: for targets x (P, 3) and source vesicles v (P,).

    Attributes after construction: theta, phi (P,), point Y0 (P, 3), outward normal (P, 3),
    signed distance (P,) = (x - Y0) . n0 (negative inside), converged (P,) bool.
    """

    def __init__(self, coeffs, p, targets, vesicle, start_theta, start_phi, tol=1e-10, max_iter=30):
        x = np.ascontiguousarray(targets, dtype=float)
        padded = np.ascontiguousarray(sph.transform(p).pad(np.asarray(coeffs, dtype=float)))   # (V, 3, 2, M, N)
        vesicle = np.ascontiguousarray(vesicle, dtype=np.int64)
        th, ph = np.array(start_theta, dtype=float), np.array(start_phi, dtype=float)
        Y, Yt, Yp = np.empty((len(x), 3)), np.empty((len(x), 3)), np.empty((len(x), 3))
        conv = np.zeros(len(x), dtype=np.uint8)
        # per point, compiled: Gauss-Newton with a backtracking line search (12 halvings); a full
        # step below 1e-5 is in Newton's quadratic range and taken without the residual test,
        # which near the minimum of |x - Y|^2 sees only rounding
        series.project(padded, vesicle, x, th, ph, Y, Yt, Yp, conv, float(tol), int(max_iter))
        conv = conv.astype(bool)
        n = np.cross(Yt, Yp)
        n /= np.linalg.norm(n, axis=1)[:, None]
        self.theta, self.phi, self.point, self.normal = th, ph, Y, n
        self.signed_distance = np.einsum("pk,pk->p", x - Y, n)
        self.converged = conv


def lagrange_weights(nodes, x):
    """Weights w (len(x), len(nodes)) with sum_l w_l f(nodes_l) = interpolant at x."""
    nodes = np.asarray(nodes, dtype=float)
    x = np.atleast_1d(np.asarray(x, dtype=float))
    w = np.ones((len(x), len(nodes)))
    for j in range(len(nodes)):
        for k in range(len(nodes)):
            if k != j:
                w[:, j] *= (x - nodes[k]) / (nodes[j] - nodes[k])
    return w


def line_points(projection, h):
    """Interpolation points (P, L, 3) at Y0 + n0 h_n (1 + l/(L-1)) and the node parameters (P, L+1)."""
    h = np.broadcast_to(np.asarray(h, dtype=float), projection.point.shape[:1])
    s = 1.0 + np.arange(L_POINTS) / (L_POINTS - 1.0)                   # 1 .. 2
    pts = projection.point[:, None, :] + projection.normal[:, None, :] * (h[:, None] * s)[..., None]
    nodes = np.concatenate([np.zeros((len(h), 1)), h[:, None] * s], axis=1)
    return pts, nodes


def interpolation_weights(projection, h):
    """Lagrange weights (P, L+1) from the nodes (0, h..2h) to the target's distance |d|.

    Scaled by 2h the nodes are the same for every target, (0, s_l / 2): one vectorized call.
    """
    _, nodes = line_points(projection, h)
    if not len(nodes):
        return np.zeros((0, L_POINTS + 1))
    d = np.abs(projection.signed_distance)
    return lagrange_weights(nodes[0] / nodes[0, -1], d / nodes[:, -1])


def near_pairs_images(trg, trg_id, src, src_id, src_off, h, period=None):
    """Near (target, vesicle) pairs, with the target's position in the vesicle's frame.

    Free space (``period`` None): :func:`vesflow._kernels.search.near_pairs`; the positions are
    the targets'.  Triply periodic (``period`` a number or 3 numbers): minimum image.  Each
    vesicle ``v`` (sources ``src_off[v] .. src_off[v+1]``, sorted by id) is moved by the
    lattice vector ``s_v`` that brings its centroid into the period cell, the targets are
    wrapped into the cell and copied to the 26 neighbouring cells where they lie within the
    largest vesicle radius + h of the cell, and a pair found for a copy ``y`` gets the
    position ``y - s_v``: the image of the target nearest to vesicle v at its given
    (unwrapped) position.  The period must exceed a vesicle's diameter + 2 h (a vesicle near
    its own image is not detected).  Returns ``(pairs (P, 2) int64, positions (P, 3))``.
    """
    trg = np.ascontiguousarray(trg, dtype=np.float64)
    if period is None:
        pairs, _ = search.near_pairs(trg, trg_id, src, src_id, h)
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        return pairs, trg[pairs[:, 0]]
    L = np.broadcast_to(np.asarray(period, dtype=np.float64), (3,))
    nv = len(src_off) - 1
    counts = np.diff(src_off)
    cent = np.add.reduceat(src, src_off[:-1], axis=0) / counts[:, None]
    shift = -L * np.floor(cent / L)                                     # (nv, 3)
    vrow = np.repeat(np.arange(nv), counts)
    src_w = np.ascontiguousarray(src + shift[vrow])
    radius = float(np.max(np.linalg.norm(src - cent[vrow], axis=1))) if len(src) else 0.0
    margin = radius + h
    if 2.0 * margin >= float(L.min()):
        raise SettingsError(f"[domain] period = {float(L.min()):g} must exceed a vesicle's diameter plus twice the "
                            f"near distance ({2.0 * margin:.3g}): a vesicle would be near its own image")
    tw = trg - L * np.floor(trg / L)
    copies, index = [], []
    for n in np.ndindex(3, 3, 3):
        y = tw + L * (np.asarray(n) - 1)
        keep = np.all((y > -margin) & (y < L + margin), axis=1)
        copies.append(y[keep])
        index.append(np.flatnonzero(keep))
    aug = np.ascontiguousarray(np.concatenate(copies))
    aug_t = np.concatenate(index).astype(np.int64)
    aug_id = np.ascontiguousarray(np.asarray(trg_id, dtype=np.int64)[aug_t])
    pairs, _ = search.near_pairs(aug, aug_id, src_w, src_id, h)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    ids = np.asarray(src_id, dtype=np.int64)[src_off[:-1]]             # vesicle index -> id
    vi = np.searchsorted(ids, pairs[:, 1]) if not np.all(ids == np.arange(nv)) else pairs[:, 1]
    pos = aug[pairs[:, 0]] - shift[vi]
    out = np.stack([aug_t[pairs[:, 0]], pairs[:, 1]], axis=1)
    # one image per (target, vesicle): the nearest copy (others only if the period is too small)
    key = out[:, 0] * (int(ids.max()) + 1 if len(ids) else 1) + out[:, 1]
    order = np.lexsort((np.linalg.norm(pos - cent[vi], axis=1), key))
    first = order[np.r_[True, key[order][1:] != key[order][:-1]]] if len(order) else order
    first = np.sort(first)
    return np.ascontiguousarray(out[first]), np.ascontiguousarray(pos[first])


@dataclass
class NearPairs:
    """The near (target, vesicle) pairs of a set-up and what their correction needs: each
    pair's smooth rule at its target is replaced by the line extrapolation through the target's
    projection on the vesicle (vesflow.layerpot.evaluator.LayerPotentials).

    pairs (P, 2): target index, vesicle id; tpos (P, 3): the target, at its image nearest the
    vesicle when periodic; rows (P,): the vesicle's row among the sources the set-up holds;
    projection: the target's closest point on the vesicle (a Projection of the P pairs); side
    (P,): +1 outside the vesicle, -1 inside; blocks (P, 1 + L_POINTS, 3): the target and its
    line points, where the smooth rule is evaluated; weights (P, 1 + L_POINTS): interpolation
    from the on-surface value and the line points to the target; basis (P, C): the spherical
    harmonics at the projection; blend (P,) or None: the near value's weight against the smooth
    rule beyond h_n (blend_weight)."""
    pairs: np.ndarray
    tpos: np.ndarray
    rows: np.ndarray
    projection: Projection
    side: np.ndarray
    blocks: np.ndarray
    weights: np.ndarray
    basis: np.ndarray
    blend: np.ndarray | None = None
