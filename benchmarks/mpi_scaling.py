"""Seconds per GMRES iteration and per time step on 1 and 2 MPI ranks (issue 19), memory per rank.

The scene: a cubic lattice of N oblate vesicles (v = 0.65, area radius 0.764, spacing 2.2, as
benchmarks/step_cost.py --nves) in shear, repulsion radius 0.05, fixed steps dt = 0.1
(-ves_adapt none: one solve per step, -ksp_rtol 1e-6), the direct far field by default.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/mpi_scaling.py --nves 64 --p 16 --steps 2
    OMP_NUM_THREADS=1 .venv/bin/mpiexec -n 2 .venv/bin/python benchmarks/mpi_scaling.py --nves 64 --p 16 --steps 2

One line per rank (rank 0 prints them): wall and CPU seconds of the stepping, seconds per step
and per GMRES iteration (the time inside KSPSolve over its iterations), the split by stage,
and the peak resident memory (ru_maxrss) of each rank; then the load average (the machine is
shared: with one thread per rank the CPU time is what an idle core's wall time would be).
--trace adds tracemalloc's peak per rank (the arrays alone) and the surfaces the last layer
potentials held (own + halo, vesflow.parallel.Halo): the figures of docs/explanation/parallel.md "Memory".
"""
import argparse
import os
import resource
import sys
import time

from vesflow.threads import early_environment  # noqa: E402  (before numpy: the run's thread policy)
early_environment()

SCENE = """
title = "mpi scaling (issue 19)"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = {p}
[time]
horizon = {T}
dt = {dt}
[output]
every = {T}
[repulsion]
radius = 0.05
{vesicles}
"""

VESICLE = """[[vesicle]]
shape = "oblate"
reduced_volume = 0.65
radius = 0.764
rotation = [0.0, 90.0, 0.0]
bending_modulus = 0.01
center = [{x}, {y}, {z}]
"""


def vesicle_blocks(n):
    k = int(round(n ** (1.0 / 3.0)))
    if k ** 3 != n:
        sys.exit(f"--nves {n}: use a cube (8, 27, 64)")
    h = 2.2
    centres = [(h * i, h * j, h * l + 0.1 * ((i + j) % 2)) for i in range(k) for j in range(k) for l in range(k)]
    return "".join(VESICLE.format(x=x, y=y, z=z) for x, y, z in centres)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--nves", type=int, default=64)
    ap.add_argument("--steps", type=int, default=2)
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--far", default="direct", help="-ves_far (direct, fmm, ewald, auto)")
    ap.add_argument("--pc", default=None, help="-pc_python_type (default: the run's choice, BlockJacobi)")
    ap.add_argument("--trace", action="store_true", help="also tracemalloc's peak per rank (numpy's allocations; "
                    "slower): the memory the arrays need, without the MPI library's and allocator's share of the RSS")
    ap.add_argument("extra", nargs="*", help="more vesflow options as name=value (e.g. ves_pc_lag=1)")
    args = ap.parse_args(argv)

    from vesflow import threads
    threads.configure(1)
    from petsc4py import PETSc
    from vesflow import options as O, scene as S
    from vesflow.simulation import Run
    from vesflow.timing import STAGES

    comm = PETSc.COMM_WORLD.tompi4py()
    rank, size = comm.Get_rank(), comm.Get_size()
    text = SCENE.format(p=args.p, T=args.steps * args.dt, dt=args.dt, vesicles=vesicle_blocks(args.nves))
    opts = {"ves_adapt": "none", "ts_max_steps": args.steps, "ves_far": args.far}
    for kv in args.extra:
        k, v = kv.split("=", 1)
        opts[k] = v
    PETSc.Options().setValue("ksp_rtol", 1e-6)
    if args.pc:
        PETSc.Options().setValue("pc_type", "python")
        PETSc.Options().setValue("pc_python_type", args.pc)
    sc = S.parse_scene(text)
    run = Run(sc, O.read_options(O.dict_getter(opts), sc))
    comm.Barrier()
    if args.trace:
        import tracemalloc
        tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    run.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    traced = ""
    if args.trace:
        cur, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        lp = run.stepper.lp_last
        traced = (f" traced_peak_gb={peak / 2 ** 30:.3f} traced_after_gb={cur / 2 ** 30:.3f} held_surfaces="
                  f"{len(getattr(lp, 'known', range(args.nves)))}")
    st = run.stepper
    tot = run.timers.as_dict()
    steps = max(run.counts["accepted"], 1)
    rss_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20       # kB -> GB
    nloc = len(st.part.idx) if st.part is not None else args.nves
    line = (f"ranks={size} rank={rank} nves={args.nves} local={nloc} p={args.p} far={st.lp_last.far.backend} "
            f"pc={args.pc or 'default'} "
            f"steps={steps} its={st.ksp_its} wall_s={wall:.2f} cpu_s={cpu:.2f} s_per_step={wall / steps:.3f} "
            f"cpu_per_step={cpu / steps:.3f} s_per_gmres_it={st.ksp_seconds / max(st.ksp_its, 1):.4f} "
            f"peak_rss_gb={rss_gb:.2f}{traced}\n  stages (s): " + " ".join(f"{s}={tot[s]:.2f}" for s in STAGES)
            + " " + " ".join(f"{s}={run.timers.detail[s]:.2f}" for s in ("self_setup", "near_setup", "far_setup",
                                                                         "pc_blocks", "pc_lu", "gather")))
    lines = comm.gather(line, root=0)
    if rank == 0:
        print("\n".join(lines))
        print(f"load average (1, 5, 15 min): {' '.join(f'{x:.2f}' for x in os.getloadavg())} on "
              f"{os.cpu_count()} cores")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
