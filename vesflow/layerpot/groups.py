"""Sources grouped by vesicle: sorted by vesicle id, with each target's vesicle among them, the
layout of the far-field backends' own-vesicle sums (vesflow.layerpot.far, .ewald)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VesicleGroups:
    """perm: the stable sort of the sources by id (None when they are sorted already); src,
    sid: the sources and their ids in that order; ids: the distinct ids, increasing; off
    (len(ids) + 1,): offsets of each id's sources in that order; trg_vi: each target's index
    into ids, -1 when no source has its id."""
    perm: np.ndarray | None
    src: np.ndarray
    sid: np.ndarray
    ids: np.ndarray
    off: np.ndarray
    trg_vi: np.ndarray

    def sorted(self, a):
        """A per-source array's rows in the sorted order."""
        return a if self.perm is None else np.ascontiguousarray(a[self.perm])


def group_by_vesicle(src, src_id, trg_id):
    """The VesicleGroups of sources src (S, 3) with ids src_id (S,) for targets with ids trg_id (T,)."""
    sid, perm = src_id, None
    if sid.size and np.any(sid[1:] < sid[:-1]):
        perm = np.argsort(sid, kind="stable")
        sid = sid[perm]
    ids, starts = np.unique(sid, return_index=True)
    trg_vi = np.full(trg_id.shape[0], -1, dtype=np.int64)
    if ids.size:
        vi = np.minimum(np.searchsorted(ids, trg_id), ids.size - 1)
        trg_vi = np.where(ids[vi] == trg_id, vi, -1).astype(np.int64)
    return VesicleGroups(perm, src if perm is None else np.ascontiguousarray(src[perm]), np.ascontiguousarray(sid),
                         ids, np.append(starts, sid.size).astype(np.int64), trg_vi)
