"""Vesicles over MPI ranks: the partition and its collective operations (docs/parallel.md).

Layout "replicated state, distributed work": every rank holds the position coefficients of
all vesicles (N x 3 x C numbers, 10 MB for 1408 vesicles at p = 16) and, after each solve, the
velocity and tension of all of them (an Allgatherv of N x 4C); each rank sets up and applies
the self operators, forces, preconditioner blocks, near corrections, correction and
reparameterization of ITS vesicles only, and evaluates the far field at its own targets.
Once per solve set-up the q-grid sources (points, weights, normals) of all vesicles are
gathered (the geometry needed by near interactions and collision checks: replicated, not
only the near-zone surfaces); once per GMRES iteration the far-field densities and the self
potentials the near corrections start from.

The vesicles are ordered along the Morton (Z-order) curve of their centroids at the start of
the run (or of a restart) and cut into contiguous blocks of equal point count (all vesicles
have the same p: equal vesicle counts, the first N mod size ranks one more).  The partition is
static over a run: vesicles that move apart keep their rank (no repartitioning).

With one process nothing here is used (`make_partition` returns None): no gathers.
"""
from __future__ import annotations

import numpy as np

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
    block in order; idx: this rank's vesicles (global indices, in Morton order)."""

    def __init__(self, comm, order, starts):
        self.comm = comm                          # an mpi4py communicator
        self.rank, self.size = comm.Get_rank(), comm.Get_size()
        self.order = np.asarray(order, dtype=np.int64)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.counts = np.diff(self.starts)
        self.idx = self.order[self.starts[self.rank]:self.starts[self.rank + 1]]
        self.n_total = len(self.order)

    @property
    def n_local(self):
        return len(self.idx)

    def gather(self, local):
        """Allgatherv of per-vesicle arrays (n_local, ...) into (N, ...) in scene order."""
        from mpi4py import MPI
        local = np.ascontiguousarray(local, dtype=np.float64)
        item = int(np.prod(local.shape[1:], dtype=np.int64))
        out = np.empty((self.n_total,) + local.shape[1:])
        recv = np.empty(self.n_total * item)
        self.comm.Allgatherv(local.reshape(-1), [recv, self.counts * item, self.starts[:-1] * item, MPI.DOUBLE])
        out[self.order] = recv.reshape((self.n_total,) + local.shape[1:])
        return out

    def max(self, x):
        from mpi4py import MPI
        return float(self.comm.allreduce(float(x), op=MPI.MAX))

    def sum(self, x):
        return self.comm.allreduce(x)

    def any(self, flag):
        from mpi4py import MPI
        return bool(self.comm.allreduce(bool(flag), op=MPI.LOR))

    def allreduce_inplace(self, a):
        """Sum of the array a over the ranks, in place."""
        from mpi4py import MPI
        self.comm.Allreduce(MPI.IN_PLACE, a, op=MPI.SUM)
        return a

    def describe(self):
        return (f"{self.size} ranks, vesicles per rank {self.counts.min()}..{self.counts.max()} "
                "(Morton order of the centroids)")


def world_comm():
    """PETSc's COMM_WORLD as an mpi4py communicator."""
    from petsc4py import PETSc
    return PETSc.COMM_WORLD.tompi4py()


def world_size():
    from petsc4py import PETSc
    return PETSc.COMM_WORLD.getSize()


def make_partition(centroids, points_per_vesicle=None, comm=None):
    """The Partition of vesicles with these centroids (N, 3) over comm (default COMM_WORLD);
    None with one process."""
    comm = world_comm() if comm is None else comm
    if comm.Get_size() == 1:
        return None
    c = np.asarray(centroids, dtype=float).reshape(-1, 3)
    if len(c) < comm.Get_size():
        from .errors import SceneError
        raise SceneError(f"{comm.Get_size()} MPI processes for {len(c)} vesicles: each rank needs at least one "
                         f"vesicle; run at most {len(c)} processes")
    order = morton_order(c)
    w = np.ones(len(c)) if points_per_vesicle is None else np.asarray(points_per_vesicle, dtype=float)[order]
    return Partition(comm, order, balanced_blocks(w, comm.Get_size()))
