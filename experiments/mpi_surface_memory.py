"""Surface memory per rank of the layer potentials (issue 19): the q-grid sources a rank holds,
its own vesicles' and the other ranks' within its near zone (vesflow.parallel.Halo), and the
peak of the set-up plus one application, against a layout that gathers every surface.

    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n 2 .venv/bin/python -m experiments.mpi_surface_memory --nves 64 --p 16

The scene is benchmarks/mpi_scaling.py's lattice (spacing 2.2, oblate v = 0.65, radius 0.764),
or with --spacing a denser or sparser one.  Per rank (rank 0 prints): vesicles owned, held
(`known`) and received, the bytes of the held sources (points, normals x weights, weights,
ids: 64 Mq bytes per held vesicle), the per-iteration halo buffers, the direct far field's
ring buffers (two of the largest block: points and densities), and tracemalloc's peak
(numpy's allocations) over LayerPotentials' set-up and one apply with a double layer.  Run
with PYTHONPATH pointing at a tree without the halo (every surface gathered) for the
comparison: `known` is then every vesicle.
"""
import argparse
import sys
import time
import tracemalloc

from vesflow.threads import early_environment  # noqa: E402
early_environment()

MB = 2.0 ** 20


def lattice(n, p, spacing):
    import numpy as np
    from vesflow import shapes
    k = int(round(n ** (1.0 / 3.0)))
    if k ** 3 != n:
        sys.exit(f"--nves {n}: use a cube (8, 27, 64, 125)")
    centres = [(spacing * i, spacing * j, spacing * l + 0.1 * ((i + j) % 2))
               for i in range(k) for j in range(k) for l in range(k)]
    return np.stack([shapes.make_shape("oblate", p, center=c, reduced_volume=0.65, radius=0.764,
                                       rotation=(0.0, 90.0, 0.0)) for c in centres])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--nves", type=int, default=64)
    ap.add_argument("--spacing", type=float, default=2.2)
    ap.add_argument("--far", default="direct")
    args = ap.parse_args(argv)
    from vesflow import threads
    threads.configure(1)
    import numpy as np
    from petsc4py import PETSc
    from vesflow import sph
    from vesflow.layerpot.evaluator import LayerPotentials, Settings
    from vesflow.parallel import make_partition
    from vesflow.surface import Surface

    comm = PETSc.COMM_WORLD.tompi4py()
    rank, size = comm.Get_rank(), comm.Get_size()
    c = lattice(args.nves, args.p, args.spacing)
    S = Surface(c, args.p)
    part = make_partition(S.centroid(), comm=comm) if size > 1 else None
    idx = np.arange(args.nves) if part is None else part.idx
    lam = np.where(np.arange(args.nves) % 2 == 0, 1.0, 0.5)            # a double layer: g is exchanged too
    C = sph.n_coeffs(args.p)
    rng = np.random.default_rng(0)
    f, g = rng.standard_normal((len(idx), 3, C)), rng.standard_normal((len(idx), 3, C))
    comm.Barrier()
    tracemalloc.start()
    t0 = time.perf_counter()
    lp = LayerPotentials(S, lam=lam, settings=Settings(backend=args.far), part=part)
    setup_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    held = tracemalloc.get_traced_memory()[0]
    lp.apply(f, g)
    apply_peak = tracemalloc.get_traced_memory()[1]
    wall = time.perf_counter() - t0
    tracemalloc.stop()
    known = getattr(lp, "known", np.arange(args.nves))
    halo = getattr(lp, "halo", None)
    mq = lp.Tq.npts
    src_bytes = sum(a.nbytes for a in (lp.src, lp.src_nw, lp.src_w, lp.src_id))
    per_it = len(known) * (6 * mq + 6 * C) * 8 * 2          # received rows + the assembled ones (fw, u, gq, g)
    ring = getattr(lp.far, "ring", None)
    ring_bytes = 0 if ring is None else 2 * int(part.counts.max()) * mq * 12 * 8
    line = (f"ranks={size} rank={rank} nves={args.nves} p={args.p} far={lp.far.backend} owned={len(idx)} "
            f"held={len(known)} received={halo.n_received if halo is not None else len(known) - len(idx)} "
            f"sources_MB={src_bytes / MB:.1f} ({src_bytes / len(known) / 1e3:.1f} kB per held vesicle) "
            f"per_iteration_MB={per_it / MB:.1f} ring_buffers_MB={ring_bytes / MB:.1f} "
            f"traced: held_after_setup_MB={held / MB:.1f} setup_peak_MB={setup_peak / MB:.1f} "
            f"apply_peak_MB={apply_peak / MB:.1f} wall_s={wall:.1f}")
    lines = comm.gather(line, root=0)
    if rank == 0:
        print("\n".join(lines))
        sys.stdout.flush()


if __name__ == "__main__":
    main()
