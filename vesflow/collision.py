"""Collision detection after a candidate step (paper 3.3).

Every p-grid point X within h_n of another surface is projected on it (the near-singular
projection); n(X0) . (X - X0) <= 0 means the surfaces touch or cross.
"""
from __future__ import annotations

import numpy as np

from . import sph
from ._kernels import search
from .layerpot.near import Projection, near_distance


def signed_gaps(surface, q):
    """Signed distances of every near (point, other vesicle) pair: (pairs (P, 2), distances (P,))."""
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q)
    src = np.ascontiguousarray(surface.points(q).reshape(-1, 3))
    src_id = np.repeat(np.arange(N, dtype=np.int64), Tq.npts)
    trg = np.ascontiguousarray(surface.points().reshape(-1, 3))
    trg_id = np.repeat(np.arange(N, dtype=np.int64), sph.transform(p).npts)
    h = float(near_distance(surface.area(), q).max())
    pairs, _ = search.near_pairs(trg, trg_id, src, src_id, h)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if not len(pairs):
        return pairs, np.zeros(0)
    srcv = src.reshape(N, -1, 3)
    d2 = np.einsum("pmk,pmk->pm", srcv[pairs[:, 1]] - trg[pairs[:, 0]][:, None],
                   srcv[pairs[:, 1]] - trg[pairs[:, 0]][:, None])
    it, jp = np.divmod(d2.argmin(axis=1), Tq.nlon)
    proj = Projection(surface.coeffs, p, trg[pairs[:, 0]], pairs[:, 1], Tq.theta[it], Tq.phi[jp])
    return pairs, proj.signed_distance


def contacts(surface, q):
    """Number of p-grid points on or behind another vesicle's surface."""
    _, d = signed_gaps(surface, q)
    return int(np.count_nonzero(d <= 0))


def min_gap(surface, q):
    _, d = signed_gaps(surface, q)
    return float(d.min()) if len(d) else np.inf
