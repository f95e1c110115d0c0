"""Collision detection after a candidate step (paper 3.3).

Every p-grid point X within h_n of another surface is projected on it (the near-singular
projection); n(X0) . (X - X0) <= 0 means the surfaces touch or cross.
"""
from __future__ import annotations

import numpy as np

from . import sph
from .layerpot.near import Projection, near_distance, near_pairs_images


def signed_gaps(surface, q, period=None, part=None):
    """Signed distances of every near (point, other vesicle) pair: (pairs (P, 2), distances (P,)).
    ``period``: triply periodic box (minimum image, vesflow.layerpot.near.near_pairs_images).
    ``part`` (vesflow.parallel.Partition): only the p-grid points of this rank's vesicles,
    against every surface (their q-grid points and areas gathered: no geometry of the other
    vesicles is computed); pairs[:, 0] then counts the points of this rank's vesicles."""
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q)
    src_id = np.repeat(np.arange(N, dtype=np.int64), Tq.npts)
    if part is None:
        mine = np.arange(N, dtype=np.int64)
        src = np.ascontiguousarray(surface.points(q).reshape(-1, 3))
        trg = np.ascontiguousarray(surface.points().reshape(-1, 3))
        area = surface.area()
    else:
        from .surface import Surface
        mine = np.asarray(part.idx, dtype=np.int64)
        local = Surface(surface.coeffs[mine], p)
        n = len(mine)
        allg = part.gather(np.concatenate([local.points(q).reshape(n, -1), local.area()[:, None]], axis=1))
        src = np.ascontiguousarray(allg[:, :-1].reshape(-1, 3))
        area = allg[:, -1]
        trg = np.ascontiguousarray(local.points().reshape(-1, 3))
    trg_id = np.repeat(mine, sph.transform(p).npts)
    h = float(near_distance(area, q).max())
    src_off = np.arange(N + 1, dtype=np.int64) * Tq.npts
    pairs, tpos = near_pairs_images(trg, trg_id, src, src_id, src_off, h, period)
    if not len(pairs):
        return pairs, np.zeros(0)
    srcv = src.reshape(N, -1, 3)
    d2 = np.einsum("pmk,pmk->pm", srcv[pairs[:, 1]] - tpos[:, None], srcv[pairs[:, 1]] - tpos[:, None])
    it, jp = np.divmod(d2.argmin(axis=1), Tq.nlon)
    proj = Projection(surface.coeffs, p, tpos, pairs[:, 1], Tq.theta[it], Tq.phi[jp])
    return pairs, proj.signed_distance


def contacts(surface, q, period=None, part=None):
    """Number of p-grid points on or behind another vesicle's surface (with a partition: of this
    rank's vesicles; the caller sums over the ranks)."""
    _, d = signed_gaps(surface, q, period, part)
    return int(np.count_nonzero(d <= 0))


def min_gap(surface, q, period=None):
    _, d = signed_gaps(surface, q, period)
    return float(d.min()) if len(d) else np.inf
