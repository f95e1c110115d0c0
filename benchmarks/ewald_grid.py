"""The Ewald Fourier grid over MPI ranks: replicated (NUFFT) against distributed (z-slabs),
grid bytes per rank, bytes sent per rank and seconds per evaluation (docs/explanation/parallel.md,
"Distributed Ewald grid").

The scene of benchmarks/far_field.py (unit spheres on a jittered lattice of spacing 2.5, p-grid
targets, q-grid sources, random densities) in its periodic cube, the vesicles over the ranks by
the Morton partition (vesflow.parallel), each rank holding every source for the real-space part
and spreading its own; both grids on the same Ewald parameters (chosen from --tol for the whole
problem, or --modes K per axis to force a grid size).

    # memory only (tiny problem, a 128^3 mode grid), oversubscribed ranks are fine:
    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n {1,2,4,8,16} .venv/bin/python benchmarks/ewald_grid.py --nves 16 --p 4 --q 8 --modes 128 --memory
    # time of one evaluation (Fourier part and whole sum), 1 and 2 ranks:
    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n {1,2} .venv/bin/python benchmarks/ewald_grid.py --nves 64 --p 16 --q 32 --tol 1e-8

Printed by rank 0: per grid path the grid bytes per rank (largest over the ranks: distributed:
its box, slab and mode arrays, vesflow.layerpot.ewald_grid.DistributedFourier.grid_bytes;
replicated: the mode grids P and W and the NUFFT's fine grid, ducc0's oversampling
1.3 .. 1.6 counted at 1.45 per axis), tracemalloc's peak during one evaluation (the numpy
arrays: every distributed array, not ducc0's own), the bytes sent per rank per evaluation
(distributed: the box planes and transposes; replicated: the Allreduce of the mode grid,
counted as 2 (P - 1) / P of it, the ring algorithm), and (without --memory) the CPU and wall
seconds of the Fourier part and the whole sum (best of --repeat, largest over the ranks), and
the largest difference of the two paths' velocities.  (mpich's ranks busy-poll while they
wait in a collective: a rank's CPU time includes its waits for the slowest rank.)
"""
import argparse
import dataclasses
import os
import resource
import time
import tracemalloc

from vesflow.threads import early_environment  # noqa: E402  (before numpy: the run's thread policy)
early_environment()

import numpy as np  # noqa: E402

from far_field import scene  # noqa: E402
from vesflow.layerpot import ewald  # noqa: E402
from vesflow.parallel import make_partition, world_comm  # noqa: E402


def timed(fn, repeat, comm):
    """(result, (wall, CPU) seconds of the repeat of least CPU time); the ranks start each
    repeat together (a Barrier outside the timing)."""
    best = None
    for _ in range(repeat):
        comm.Barrier()
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        t = (time.perf_counter() - w, time.process_time() - c)
        best = t if best is None or t[1] < best[1] else best
    return out, best


def replicated_bytes(es, m):
    """The replicated path's grids: P ((m + 1) / 2 packed transforms) and W (2) on the modes,
    and the NUFFT's fine grid of one transform (oversampling 1.45 per axis, complex)."""
    modes = float(np.prod(es.params.modes))
    return int(16 * modes * ((m + 1) // 2 + 2) + 16 * modes * 1.45 ** 3)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--nves", type=int, default=64)
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--q", type=int, default=32)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--modes", type=int, default=0, help="force the mode grid to K^3 (0: the chosen one)")
    ap.add_argument("--layer", choices=("single", "double", "both"), default="single")
    ap.add_argument("--memory", action="store_true", help="grid bytes only (one evaluation, no timing)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--grids", nargs="+", default=["replicated", "distributed"])
    a = ap.parse_args(argv)
    comm = world_comm()
    rank, size = comm.Get_rank(), comm.Get_size()
    src, sid, trg, tid, f_w, nw, g = scene(a.nves, a.p, a.q)
    side = 2.5 * int(np.ceil(a.nves ** (1 / 3)))
    src, trg = src + 1.25, trg + 1.25                     # the lattice inside its cube [0, side)
    part = make_partition(np.stack([src[sid == v].mean(axis=0) for v in range(a.nves)]), comm=comm)
    mine_s = np.flatnonzero(np.isin(sid, part.idx))
    mine_t = np.flatnonzero(np.isin(tid, part.idx))
    m = {"single": 3, "double": 6, "both": 9}[a.layer]
    p = ewald.choose_params(a.tol, np.concatenate([src, trg]), side, len(src), len(trg), 1, 9 if m > 3 else 3)
    if a.modes:
        p = dataclasses.replace(p, modes=(a.modes,) * 3)
    dens = {"single": dict(f_w=f_w), "double": dict(nw=nw, g=g), "both": dict(f_w=f_w, nw=nw, g=g)}[a.layer]
    if rank == 0:
        print(f"{size} ranks, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', '-')}; {a.nves} vesicles "
              f"p {a.p} q {a.q}, {len(src)} sources, {len(trg)} targets, periodic cube {side:g}, tol {a.tol:g}, "
              f"modes {'x'.join(map(str, p.modes))}, rc {p.rc:.3g}, {a.layer} layer ({m} components)", flush=True)
    results = {}
    for grid in a.grids:
        es = ewald.EwaldSum(src, sid, trg[mine_t], tid[mine_t], period=side, params=p, threads=1,
                            spread=(part, mine_s), double_layer=m > 3, grid=grid)
        comm.Barrier()
        tracemalloc.start()
        u = es.fourier(**dens)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        if grid == "distributed":
            d = es._dist
            gb = d.grid_bytes(m)["total"]
            sent = d.bytes_sent / d.evaluations
            extra = f"fine {'x'.join(map(str, d.n))}, w {d.w}, box {'x'.join(map(str, d.blen))}, slab z {d.z1 - d.z0}"
        else:
            gb = replicated_bytes(es, m)
            modes = float(np.prod(p.modes))
            sent = 0.0 if size == 1 else 2.0 * (size - 1) / size * 16 * modes * ((m + 1) // 2)
            extra = "modes + ducc0 fine grid (1.45^3 modes, modelled)"
        row = {"grid_bytes": gb, "traced": peak, "sent": sent, "extra": extra, "u": u}
        if not a.memory:
            comm.Barrier()
            _, tf = timed(lambda: es.fourier(**dens), a.repeat, comm)
            _, te = timed(lambda: es.evaluate(**dens), a.repeat, comm)
            row["fourier"], row["evaluate"] = tf, te
        rows = comm.gather({k: v for k, v in row.items() if k != "u"}, root=0)
        results[grid] = u
        if rank == 0:
            gbm = max(r["grid_bytes"] for r in rows)
            tr = max(r["traced"] for r in rows)
            se = max(r["sent"] for r in rows)
            line = (f"{grid:>11}: grid bytes per rank {gbm / 1e6:9.1f} MB (rank 0: {rows[0]['extra']}), "
                    f"traced peak {tr / 1e6:8.1f} MB, sent per rank {se / 1e6:8.2f} MB")
            if not a.memory:
                f_c = max(r["fourier"][1] for r in rows)
                f_w_ = max(r["fourier"][0] for r in rows)
                e_c = max(r["evaluate"][1] for r in rows)
                e_w = max(r["evaluate"][0] for r in rows)
                line += f"; Fourier part {f_c:.3f} s CPU ({f_w_:.3f} wall), whole sum {e_c:.3f} s CPU ({e_w:.3f} wall)"
            print(line, flush=True)
        del es
    if len(results) == 2:
        d = max(float(np.abs(results["replicated"] - results["distributed"]).max()) / max(float(np.abs(results["replicated"]).max()), 1e-300), 0.0)
        d = comm.allreduce(d, op=__import__("mpi4py").MPI.MAX)
        if rank == 0:
            print(f"largest difference of the Fourier parts (relative to the largest value): {d:.2e}")
    rss = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6, root=0)
    if rank == 0:
        print(f"peak RSS per rank (both paths in one process): max {max(rss):.2f} GB; load average "
              f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
