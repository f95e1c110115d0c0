"""Vesicles over MPI ranks: the partition and its collective operations (docs/explanation/parallel.md).

Layout "replicated state, distributed work": every rank holds the position coefficients of
all vesicles (N x 3 x C numbers, 10 MB for 1408 vesicles at p = 16) and, after each solve, the
velocity and tension of all of them (an Allgatherv of N x 4C); each rank sets up and applies
the self operators, forces, preconditioner blocks, near corrections, correction and
reparameterization of ITS vesicles only, and evaluates the far field at its own targets.

Surfaces (q-grid points, weights, normals) are not gathered: each rank computes its own
vesicles' and receives those of the other ranks' vesicles whose bounding box lies within a
distance (the near zone, the collision zone, the Ewald real-space cutoff) of one of its own
(`Halo`: the boxes are gathered, 6 numbers per vesicle, and the rows exchanged by one
Alltoallv with non-zero counts between neighbours only); per GMRES iteration the same halo
receives the densities and self potentials the near corrections start from.  The direct far
field passes each rank's source block around the ring of ranks (`Partition.ring`).

The vesicles are ordered along the Morton (Z-order) curve of their centroids at the start of
the run (or of a restart) and cut into contiguous blocks of equal point count (all vesicles
have the same p: equal vesicle counts, the first N mod size ranks one more).  The partition is
static over a run: vesicles that move apart keep their rank (no repartitioning).

A serial run is the one-rank case (`Partition.single`: one rank owns every vesicle, in scene
order; its halo is empty and its collectives return their argument), so that the layer
potentials take one code path whatever the number of processes.
"""
from __future__ import annotations

import numpy as np

from .errors import SceneError

MORTON_BITS = 10      # per coordinate: a 1024^3 grid over the centroids' bounding box


def morton_order(points):
    """Indices sorting points (N, 3) along the Z-order curve of their bounding cube (stable;
    bits interleaved x, y, z from the lowest)."""
    x = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(x) <= 1:
        return np.arange(len(x))
    lo, span = x.min(axis=0), float(np.ptp(x, axis=0).max())
    cells = (1 << MORTON_BITS) - 1
    ijk = np.floor((x - lo) / (span if span > 0 else 1.0) * cells).astype(np.int64)
    code = np.zeros(len(x), dtype=np.int64)
    for b in range(MORTON_BITS):
        for d in range(3):
            code |= ((ijk[:, d] >> b) & 1) << (3 * b + d)
    return np.argsort(code, kind="stable")


def balanced_blocks(weights, size):
    """Starts (size + 1,) of contiguous blocks of `weights` (in order) with near-equal sums:
    block r ends at the first prefix sum >= (r + 1) W / size."""
    w = np.asarray(weights, dtype=float)
    cum = np.concatenate([[0.0], np.cumsum(w)])
    total = cum[-1]
    starts = [0]
    for r in range(1, size):
        starts.append(int(np.searchsorted(cum, r * total / size - 1e-9 * total, side="left")))
    starts.append(len(w))
    return np.maximum.accumulate(np.asarray(starts, dtype=np.int64))


class Partition:
    """Which vesicles each rank owns, and the collectives over them.

    order: all vesicle indices, rank 0's first (Morton order); starts: offsets of each rank's
    block in order; idx: this rank's vesicles (global indices, in Morton order).  comm None:
    one process (`single`), the collectives return their argument."""

    def __init__(self, comm, order, starts):
        self.comm = comm                          # an mpi4py communicator, or None: one process
        self.rank, self.size = (0, 1) if comm is None else (comm.Get_rank(), comm.Get_size())
        self.order = np.asarray(order, dtype=np.int64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.counts = np.diff(self.starts)
        self.idx = self.order[self.starts[self.rank]:self.starts[self.rank + 1]]
        self.n_total = len(self.order)

    @classmethod
    def single(cls, n):
        """The partition of a serial run: one process owns all n vesicles, in scene order."""
        return cls(None, np.arange(n, dtype=np.int64), np.array([0, n], dtype=np.int64))

    @property
    def n_local(self):
        return len(self.idx)

    def gather(self, local):
        """Allgatherv of per-vesicle arrays (n_local, ...) into (N, ...) in scene order."""
        local = np.ascontiguousarray(local, dtype=np.float64)
        out = np.empty((self.n_total,) + local.shape[1:])
        if self.comm is None:
            out[self.order] = local
            return out
        from mpi4py import MPI
        item = int(np.prod(local.shape[1:], dtype=np.int64))
        recv = np.empty(self.n_total * item)
        self.comm.Allgatherv(local.reshape(-1), [recv, self.counts * item, self.starts[:-1] * item, MPI.DOUBLE])
        out[self.order] = recv.reshape((self.n_total,) + local.shape[1:])
        return out

    def block_vesicles(self, r):
        """Rank r's vesicles in increasing id order (the order of its block in `ring`)."""
        return np.sort(self.order[self.starts[r]:self.starts[r + 1]])

    def owner(self):
        """(N,): the rank that owns each vesicle."""
        own = np.empty(self.n_total, dtype=np.int64)
        for r in range(self.size):
            own[self.order[self.starts[r]:self.starts[r + 1]]] = r
        return own

    def ring(self, block, lengths, fn):
        """fn(data, r) for the block of every rank r (this rank's first, then rank - 1, rank - 2,
        ...): each block (a float64 array, `lengths[r]` numbers on rank r) is passed to rank + 1
        and received from rank - 1, size - 1 times; the transfer of the next block is posted
        before fn works on the current one (overlap).  Memory: two buffers of the largest block."""
        lengths = np.asarray(lengths, dtype=np.int64)
        block = np.ascontiguousarray(block, dtype=np.float64).reshape(-1)
        if block.size != lengths[self.rank]:
            raise ValueError(f"ring: this rank's block has {block.size} numbers, lengths says {lengths[self.rank]}")
        if self.size == 1:
            fn(block, self.rank)
            return
        from mpi4py import MPI
        bufs = [np.empty(int(lengths.max())), np.empty(int(lengths.max()))]
        owner = self.rank
        cur = bufs[0][:block.size]
        cur[:] = block
        right, left = (self.rank + 1) % self.size, (self.rank - 1) % self.size
        for step in range(self.size):
            reqs = []
            if step < self.size - 1:
                nxt_owner = (owner - 1) % self.size
                nxt = bufs[(step + 1) % 2][:int(lengths[nxt_owner])]
                reqs = [self.comm.Irecv([nxt, MPI.DOUBLE], source=left, tag=77),
                        self.comm.Isend([cur, MPI.DOUBLE], dest=right, tag=77)]
            fn(cur, owner)
            if reqs:
                MPI.Request.Waitall(reqs)
                cur, owner = nxt, nxt_owner

    def max(self, x):
        if self.comm is None:
            return float(x)
        from mpi4py import MPI
        return float(self.comm.allreduce(float(x), op=MPI.MAX))

    def sum(self, x):
        return x if self.comm is None else self.comm.allreduce(x)

    def any(self, flag):
        if self.comm is None:
            return bool(flag)
        from mpi4py import MPI
        return bool(self.comm.allreduce(bool(flag), op=MPI.LOR))

    def allreduce_inplace(self, a):
        """Sum of the array a over the ranks, in place."""
        if self.comm is None:
            return a
        from mpi4py import MPI
        self.comm.Allreduce(MPI.IN_PLACE, a, op=MPI.SUM)
        return a

    def alltoall(self, items):
        """Item r of `items` to rank r; returns the items each rank sent here (mpi4py alltoall)."""
        return list(items) if self.comm is None else self.comm.alltoall(items)

    def alltoallv(self, send, send_counts, recv, recv_counts):
        """Alltoallv of float64 rows: send_counts[r] numbers of `send` (in rank order) to rank r,
        recv_counts[r] numbers into `recv` from rank r."""
        sd = np.concatenate([[0], np.cumsum(send_counts)[:-1]])
        rd = np.concatenate([[0], np.cumsum(recv_counts)[:-1]])
        if self.comm is None:
            recv[:] = send
            return
        from mpi4py import MPI
        self.comm.Alltoallv([send, send_counts, sd, MPI.DOUBLE], [recv, recv_counts, rd, MPI.DOUBLE])

    def describe(self):
        return (f"{self.size} ranks, vesicles per rank {self.counts.min()}..{self.counts.max()} "
                "(Morton order of the centroids)")


def vesicle_boxes(*point_sets):
    """(n, 2, 3): the lower and upper corners of each vesicle's points, over every set given
    (arrays (n, m, 3), e.g. its p-grid and q-grid points)."""
    lo = np.min([np.asarray(x).min(axis=1) for x in point_sets], axis=0)
    hi = np.max([np.asarray(x).max(axis=1) for x in point_sets], axis=0)
    return np.stack([lo, hi], axis=1)


def box_gaps(a, b, period=None):
    """(len(a), len(b)): the distance between boxes a (n, 2, 3) and b (m, 2, 3) (0 if they
    overlap), minimum image per axis in a periodic box of side(s) `period`: a lower bound of
    the distance between any point of one box and any point (or image) of the other."""
    ca, ha = 0.5 * (a[:, 0] + a[:, 1]), 0.5 * (a[:, 1] - a[:, 0])
    cb, hb = 0.5 * (b[:, 0] + b[:, 1]), 0.5 * (b[:, 1] - b[:, 0])
    d = cb[None] - ca[:, None]
    if period is not None:
        L = np.broadcast_to(np.asarray(period, dtype=float), (3,))
        d -= L * np.round(d / L)
    gap = np.maximum(np.abs(d) - (ha[:, None] + hb[None]), 0.0)
    return np.sqrt(np.einsum("ijk,ijk->ij", gap, gap))


class Halo:
    """The other ranks' vesicles within `distance` of this rank's, and their exchange.

    boxes (N, 2, 3): every vesicle's bounding box (`vesicle_boxes`, gathered).  `need`: the
    vesicles of other ranks whose box lies within `distance` of the box of one of this rank's
    vesicles (minimum image with `period`); `known`: this rank's vesicles and `need`, in
    increasing id order, the rows `exchange` returns.  Each rank tells the owners what it
    needs (alltoall of the id lists), so the send lists are the owners' copies of them.
    distance = inf: every vesicle (a gather)."""

    CHUNK = 1 << 18          # box pairs per vectorized block of the search

    def __init__(self, part, boxes, distance, period=None):
        self.part = part
        boxes = np.asarray(boxes, dtype=float).reshape(-1, 2, 3)
        owner = part.owner()
        others = np.flatnonzero(owner != part.rank)
        if np.isinf(distance):
            need = others
        else:
            hit = np.zeros(len(others), dtype=bool)
            mine = boxes[part.idx]
            step = max(1, self.CHUNK // max(len(mine), 1))
            for k in range(0, len(others), step):
                sl = slice(k, k + step)
                hit[sl] = (box_gaps(mine, boxes[others[sl]], period) <= distance).any(axis=0)
            need = others[hit]
        self.distance = float(distance)
        self.need = need                                    # increasing ids
        need_from = [need[owner[need] == r] for r in range(part.size)]
        send_to = part.alltoall(need_from)                  # my vesicles each rank needs
        self.known = np.union1d(part.idx, need).astype(np.int64)
        pos_local = {int(v): k for k, v in enumerate(part.idx)}
        self._send_rows = np.array([pos_local[int(v)] for lst in send_to for v in lst], dtype=np.int64)
        self._send_counts = np.array([len(x) for x in send_to], dtype=np.int64)
        self._recv_counts = np.array([len(x) for x in need_from], dtype=np.int64)
        recv_ids = np.concatenate(need_from).astype(np.int64) if need_from else np.zeros(0, dtype=np.int64)
        self._recv_pos = np.searchsorted(self.known, recv_ids)
        self._own_pos = np.searchsorted(self.known, part.idx)
        self.n_sent = int(self._send_counts.sum())
        # one process owning its vesicles in id order: its rows are already those of `known`
        self._as_is = part.size == 1 and np.array_equal(self._own_pos, np.arange(len(self._own_pos)))

    @property
    def n_received(self):
        return len(self.need)

    def own_rows(self):
        """Rows of `known` that are this rank's vesicles (increasing ids)."""
        return np.searchsorted(self.known, np.sort(self.part.idx))

    def exchange(self, local):
        """Per-vesicle rows (n_local, ...) of this rank's vesicles (part.idx order) -> rows
        (len(known), ...) of `known`: one Alltoallv, non-zero counts between neighbours only
        (one process: `local` itself, no copy)."""
        local = np.ascontiguousarray(local, dtype=np.float64)
        if self._as_is:
            return local
        shape = local.shape[1:]
        item = int(np.prod(shape, dtype=np.int64))
        flat = local.reshape(len(local), item)
        send = np.ascontiguousarray(flat[self._send_rows])
        recv = np.empty((len(self._recv_pos), item))
        self.part.alltoallv(send, self._send_counts * item, recv, self._recv_counts * item)
        out = np.empty((len(self.known), item))
        out[self._own_pos] = flat
        out[self._recv_pos] = recv
        return out.reshape((len(self.known),) + shape)

    def exchange_rows(self, *arrays):
        """`exchange` of several per-vesicle arrays (n_local, ...) in one message: a list of
        their rows of `known`, each array in its own shape."""
        arrays = [np.ascontiguousarray(a, dtype=np.float64) for a in arrays]
        if self._as_is:
            return arrays
        n = len(self.part.idx)
        cols = np.cumsum([int(np.prod(a.shape[1:], dtype=np.int64)) for a in arrays])[:-1]
        rows = np.split(self.exchange(np.concatenate([a.reshape(n, -1) for a in arrays], axis=1)), cols, axis=1)
        return [r.reshape((len(self.known),) + a.shape[1:]) for r, a in zip(rows, arrays)]


def world_comm():
    """PETSc's COMM_WORLD as an mpi4py communicator."""
    from petsc4py import PETSc
    return PETSc.COMM_WORLD.tompi4py()


def world_size():
    from petsc4py import PETSc
    return PETSc.COMM_WORLD.getSize()


def make_partition(centroids, points_per_vesicle=None, comm=None):
    """The Partition of vesicles with these centroids (N, 3) over comm (default COMM_WORLD);
    with one process `Partition.single` (scene order)."""
    comm = world_comm() if comm is None else comm
    c = np.asarray(centroids, dtype=float).reshape(-1, 3)
    if comm.Get_size() == 1:
        return Partition.single(len(c))
    if len(c) < comm.Get_size():
        raise SceneError(f"{comm.Get_size()} MPI processes for {len(c)} vesicles: each rank needs at least one "
                         f"vesicle; run at most {len(c)} processes")
    order = morton_order(c)
    w = np.ones(len(c)) if points_per_vesicle is None else np.asarray(points_per_vesicle, dtype=float)[order]
    return Partition(comm, order, balanced_blocks(w, comm.Get_size()))
