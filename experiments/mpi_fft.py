"""The Ewald sum's FFTs on the ranks of one node: replicated (vesflow) against slab-distributed.

Issue 19 asks whether the Fourier part of the spectral Ewald sum should transform a grid
distributed over the ranks or a replicated one.  Both paths spread each rank's own sources
and interpolate at its own targets (that work is divided by the ranks either way); they differ
in the FFTs and the communication around them, which this script times on the fine (upsampled)
grid of the NUFFT, n = upsampfac x modes per axis, with `ntr1` type-1 and `ntr2` type-2
transforms per evaluation (complex; vesflow packs two real components into one):

- replicated (vesflow.layerpot.ewald under MPI): every rank runs the full type-1 NUFFT on its
  own points (its FFTs: ntr1 full transforms of the fine grid), the mode grids (modes^3 per
  transform) are summed by one Allreduce, and every rank runs the full type-2 NUFFT (ntr2 full
  transforms);
- distributed (what mpi4py-fft would do, built here with scipy.fft and mpi4py): the spread
  fine grids are summed into z-slabs (Reduce_scatter), each rank transforms its slab along x, y,
  the slabs are transposed to y-slabs (Alltoall), transformed along z, and back for the
  inverse transforms; the fine grid of the velocity is gathered (Allgather) for the
  interpolation at each rank's targets.

Both paths are checked to give the same transform (printed: max relative difference).

    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n 2 .venv/bin/python -m experiments.mpi_fft
    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n 2 .venv/bin/python -m experiments.mpi_fft --modes 64 146 196

Results: docs/explanation/parallel.md, "Distributed Ewald grid" (why its transposes move the kept modes only).
"""
import argparse
import os
import time

import numpy as np
import scipy.fft
from mpi4py import MPI


def fine_size(modes, upsampfac, size):
    """Fine grid per axis: >= upsampfac * modes, even and divisible by the rank count."""
    n = int(np.ceil(upsampfac * modes))
    step = 2 * size
    return ((n + step - 1) // step) * step


def replicated(comm, grids, modes, ntr2):
    """Full FFTs of every component on every rank, the mode grids summed by Allreduce; then
    ntr2 full inverse FFTs.  Returns the summed spectra (for the check) and the seconds."""
    t = {}
    t0 = time.perf_counter()
    spec = scipy.fft.fftn(grids, axes=(1, 2, 3), workers=1)
    t["fft"] = time.perf_counter() - t0
    n = grids.shape[1]
    h = modes // 2
    keep = np.r_[0:h, n - h:n]
    t0 = time.perf_counter()
    m = np.ascontiguousarray(spec[:, keep][:, :, keep][:, :, :, keep])
    comm.Allreduce(MPI.IN_PLACE, m, op=MPI.SUM)
    t["reduce"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vel = np.zeros((ntr2, n, n, n), dtype=complex)
    vel[np.ix_(range(ntr2), keep, keep, keep)] = m[:ntr2]
    scipy.fft.ifftn(vel, axes=(1, 2, 3), workers=1, overwrite_x=True)
    t["ifft"] = time.perf_counter() - t0
    return m, t


def _transpose(comm, a, split_axis, concat_axis):
    """Alltoall redistribution of a (comp, ...) array: split `split_axis` into size chunks, one
    to each rank; concatenate the received chunks along `concat_axis`."""
    size = comm.Get_size()
    chunks = np.split(a, size, axis=split_axis)
    send = np.ascontiguousarray(np.stack(chunks))
    recv = np.empty_like(send)
    comm.Alltoall(send, recv)
    return np.concatenate(list(recv), axis=concat_axis)


def distributed(comm, grids, modes, ntr2):
    """Reduce_scatter of the spread grids into z-slabs, slab FFT (x, y), transpose, FFT (z);
    the inverse in reverse order for ntr2 components, and the Allgather of the fine velocity
    grid.  Returns the mode grids on this rank's y-slab and the seconds."""
    size, rank = comm.Get_size(), comm.Get_rank()
    ntr, n = grids.shape[0], grids.shape[1]
    b = n // size
    t = {}
    t0 = time.perf_counter()
    # axis 1 is z: rank r receives z in [r b, (r + 1) b)
    send = np.ascontiguousarray(np.moveaxis(grids, 1, 0))      # (z, comp, y, x)
    slab = np.empty((b, ntr, n, n), dtype=complex)
    comm.Reduce_scatter_block(send, slab, op=MPI.SUM)
    slab = np.ascontiguousarray(np.moveaxis(slab, 0, 1))       # (comp, z_loc, y, x)
    t["reduce"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scipy.fft.fftn(slab, axes=(2, 3), workers=1, overwrite_x=True)
    t["fft"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ys = _transpose(comm, slab, 2, 1)                           # (comp, z, y_loc, x)
    t["transpose"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    spec = scipy.fft.fft(ys, axis=1, workers=1)
    t["fft"] += time.perf_counter() - t0
    # inverse for the velocity: z, transpose back, (x, y)
    t0 = time.perf_counter()
    vel = scipy.fft.ifft(spec[:ntr2], axis=1, workers=1)
    t["ifft"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    zs = _transpose(comm, vel, 1, 2)                            # (comp, z_loc, y, x)
    t["transpose"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    scipy.fft.ifftn(zs, axes=(2, 3), workers=1, overwrite_x=True)
    t["ifft"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    full = np.empty((size,) + zs.shape, dtype=complex)
    comm.Allgather(np.ascontiguousarray(zs), full)
    t["gather"] = time.perf_counter() - t0
    return spec, t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modes", type=int, nargs="+", default=[64, 146],
                    help="NUFFT modes per axis (146: the N = 512, p = 16, 1e-6 choice)")
    ap.add_argument("--upsampfac", type=float, default=1.25)
    ap.add_argument("--ntr1", type=int, default=2, help="type-1 transforms (2: Stokeslet, packed)")
    ap.add_argument("--ntr2", type=int, default=2, help="type-2 transforms (2: velocity, packed)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    comm = MPI.COMM_WORLD
    size, rank = comm.Get_size(), comm.Get_rank()
    rng = np.random.default_rng(1 + rank)
    if rank == 0:
        print(f"{size} ranks, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '-')}, "
              f"upsampfac {a.upsampfac}, {a.ntr1} type-1 + {a.ntr2} type-2 transforms; "
              "seconds per evaluation (min of repeats, slowest rank)")
        print(f"{'modes':>6} {'fine':>5} {'MB/grid':>8} | {'replicated':>10} (fft, reduce, ifft) | "
              f"{'distributed':>11} (fft, ifft, reduce, transpose, gather) | ratio | check")
    for modes in a.modes:
        n = fine_size(modes, a.upsampfac, size)
        grids = rng.standard_normal((a.ntr1, n, n, n)) + 1j * rng.standard_normal((a.ntr1, n, n, n))
        best_r, best_d = None, None
        for _ in range(a.repeat):
            comm.Barrier()
            t0 = time.perf_counter()
            mr, tr = replicated(comm, grids, modes, a.ntr2)
            tr["total"] = time.perf_counter() - t0
            comm.Barrier()
            t0 = time.perf_counter()
            sd, td = distributed(comm, grids, modes, a.ntr2)
            td["total"] = time.perf_counter() - t0
            tr = {k: comm.allreduce(v, op=MPI.MAX) for k, v in tr.items()}
            td = {k: comm.allreduce(v, op=MPI.MAX) for k, v in td.items()}
            if best_r is None or tr["total"] < best_r["total"]:
                best_r = tr
            if best_d is None or td["total"] < best_d["total"]:
                best_d = td
        # check: this rank's y-slab of the distributed spectrum against the replicated modes
        b, h = n // size, modes // 2
        keep = np.r_[0:h, n - h:n]
        ymine = np.arange(rank * b, (rank + 1) * b)
        sel = np.flatnonzero(np.isin(keep, ymine))
        ref = mr[:, :, sel, :]
        got = sd[:, :, np.searchsorted(ymine, keep[sel]), :][:, keep][:, :, :, keep]
        err = np.abs(got - ref).max() / max(np.abs(mr).max(), 1e-300) if sel.size else 0.0
        err = comm.allreduce(err, op=MPI.MAX)
        if rank == 0:
            print(f"{modes:6d} {n:5d} {16 * n ** 3 / 1e6:8.1f} | {best_r['total']:10.3f} "
                  f"({best_r['fft']:.3f}, {best_r['reduce']:.3f}, {best_r['ifft']:.3f}) | "
                  f"{best_d['total']:11.3f} ({best_d['fft']:.3f}, {best_d['ifft']:.3f}, "
                  f"{best_d['reduce']:.3f}, {best_d['transpose']:.3f}, {best_d['gather']:.3f}) | "
                  f"{best_r['total'] / best_d['total']:5.2f} | {err:.1e}")
        del grids
    if rank == 0:
        print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
