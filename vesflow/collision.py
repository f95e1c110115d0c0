"""Collision detection after a candidate step (paper 3.3).

Every p-grid point X within h_n of another surface is projected on it (the near-singular
projection); n(X0) . (X - X0) <= 0 means the surfaces touch or cross.
"""
from __future__ import annotations

import numpy as np

from . import sph
from .layerpot.evaluator import NEAR_CHUNK, vesicles_of
from .layerpot.near import Projection, near_distance, near_pairs_images
from .parallel import Halo, Partition, vesicle_boxes


def signed_gaps(surface, q, period=None, part=None, stats=None):
    """Signed distances of every near (point, other vesicle) pair: (pairs (P, 2), distances (P,));
    near_projection's, without the projection."""
    pairs, proj = near_projection(surface, q, period, part, stats)
    return pairs, (proj.signed_distance if proj is not None else np.zeros(0))


def near_projection(surface, q, period=None, part=None, stats=None):
    """Closest points on the other vesicles of every near (point, other vesicle) pair: (pairs
    (P, 2), vesflow.layerpot.near.Projection or None if no pair): pairs[:, 0] a p-grid point
    (vesicle-major), pairs[:, 1] the other vesicle; the projection's signed_distance and its
    normal (outward of the other vesicle).
    ``period``: triply periodic box (minimum image, vesflow.layerpot.near.near_pairs_images).
    ``part`` (vesflow.parallel.Partition; default the one-rank Partition.single): only the
    p-grid points of this rank's vesicles, against its own surfaces and those of the other
    ranks' vesicles whose bounding box lies within h_n of one of its own (vesflow.parallel.Halo:
    their q-grid points exchanged, no geometry of the other vesicles computed); pairs[:, 0]
    then counts the points of this rank's vesicles.  ``stats`` (a dict): receives "received",
    the surfaces received."""
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q)
    part = Partition.single(N) if part is None else part
    mine = np.asarray(part.idx, dtype=np.int64)
    local = vesicles_of(surface, mine)
    n = len(mine)
    xq, xp = local.points(q), local.points()
    h = float(near_distance([part.max(float(local.area().max()))], q).max())
    halo = Halo(part, part.gather(vesicle_boxes(xq, xp)), h * (1.0 + 1e-6), period)
    known = halo.known
    src = np.ascontiguousarray(halo.exchange(xq.reshape(n, -1)).reshape(-1, 3))
    trg = np.ascontiguousarray(xp.reshape(-1, 3))
    coeffs = surface.coeffs[known]
    if stats is not None:
        stats["received"] = halo.n_received
    src_id = np.repeat(known, Tq.npts)
    trg_id = np.repeat(mine, sph.transform(p).npts)
    src_off = np.arange(len(known) + 1, dtype=np.int64) * Tq.npts
    pairs, tpos = near_pairs_images(trg, trg_id, src, src_id, src_off, h, period)
    if not len(pairs):
        return pairs, None
    rows = np.searchsorted(known, pairs[:, 1])
    srcv = src.reshape(len(known), -1, 3)
    nearest = np.empty(len(pairs), dtype=np.int64)
    for k0 in range(0, len(pairs), NEAR_CHUNK):      # (NEAR_CHUNK, Mq, 3) at a time, not (P, Mq, 3)
        sl = slice(k0, k0 + NEAR_CHUNK)
        d = srcv[rows[sl]] - tpos[sl][:, None]
        nearest[sl] = np.einsum("pmk,pmk->pm", d, d).argmin(axis=1)
    it, jp = np.divmod(nearest, Tq.nlon)
    return pairs, Projection(coeffs, p, tpos, rows, Tq.theta[it], Tq.phi[jp])


def contacts(surface, q, period=None, part=None, stats=None):
    """Number of p-grid points on or behind another vesicle's surface (with a partition: of this
    rank's vesicles; the caller sums over the ranks).  stats: as signed_gaps."""
    _, d = signed_gaps(surface, q, period, part, stats)
    return int(np.count_nonzero(d <= 0))


def min_gap(surface, q, period=None):
    _, d = signed_gaps(surface, q, period)
    return float(d.min()) if len(d) else np.inf
