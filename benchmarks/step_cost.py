"""Time per step and its split (issue 16): the set-up stages against the GMRES iterations.

The scene of the issue: two oblate vesicles (v = 0.65, thin axis along x, area radius 0.764,
centres (-1.5, 0, 0.25) and (1.5, 0, -0.25), kappa_b = 0.01, shear rate 1, repulsion radius
0.05), fixed steps dt = 0.1 (-ves_adapt none -ksp_rtol 1e-6); `--study` runs the accuracy-cost
study's scene (runs/accuracy_cost.toml) instead, `--nves` replaces the pair by a cubic lattice
of N such vesicles (spacing 2.2) to see how the split grows with N.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/step_cost.py --p 6 --steps 20
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/step_cost.py --p 12 --steps 300
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/step_cost.py --p 12 --steps 20 --nves 8

The machine is shared: besides the wall time the process's CPU time is printed (with one
thread it is what an idle machine's wall time would be, to within cache effects).
Prints the time to the first step (imports, shapes, caches), the stepping time, seconds per
step, GMRES iterations per solve and the split by stage (vesflow.timing.STAGES and the fine
set-up stages of vesflow.timing.DETAIL): one line per configuration, machine-readable.
"""
import argparse
import os
import sys
import time

T_START = time.perf_counter()
from vesflow.threads import early_environment  # noqa: E402  (before numpy: the run's thread policy)
early_environment()

SCENE = """
title = "step cost (issue 16)"
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
    if n == 2:
        centres = [(-1.5, 0.0, 0.25), (1.5, 0.0, -0.25)]
    else:
        k = int(round(n ** (1.0 / 3.0)))
        if k ** 3 != n:
            sys.exit(f"--nves {n}: use 2 or a cube (8, 27, 64)")
        h = 2.2
        centres = [(h * i, h * j, h * l + 0.1 * ((i + j) % 2)) for i in range(k) for j in range(k) for l in range(k)]
    return "".join(VESICLE.format(x=x, y=y, z=z) for x, y, z in centres)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--p", type=int, nargs="+", default=[6])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--nves", type=int, default=2)
    ap.add_argument("--dt", type=float, default=0.1)
    ap.add_argument("--study", action="store_true", help="the accuracy-cost study's scene, adaptive")
    ap.add_argument("--blas-threads", type=int, default=1, help="-ves_blas_threads of the run")
    ap.add_argument("--pc", default=None, help="-pc_python_type (default: the run's choice)")
    ap.add_argument("extra", nargs="*", help="more options as name=value (e.g. ves_pc_lag=1)")
    args = ap.parse_args(argv)

    from vesflow import threads
    threads.configure(args.blas_threads)          # the run's thread policy, before the kernels load
    from petsc4py import PETSc
    from vesflow import options as O, scene as S
    from vesflow.simulation import Run
    from vesflow.timing import DETAIL, STAGES

    for p in args.p:
        if args.study:
            here = os.path.dirname(os.path.abspath(__file__))
            text = open(os.path.join(here, "..", "runs", "accuracy_cost.toml")).read()
            opts = {"ves_p": p}
        else:
            text = SCENE.format(p=p, T=args.steps * args.dt, dt=args.dt, vesicles=vesicle_blocks(args.nves))
            opts = {"ves_adapt": "none", "ts_max_steps": args.steps}
        for kv in args.extra:
            k, v = kv.split("=", 1)
            opts[k] = v
        po = PETSc.Options()
        po.setValue("ksp_rtol", 1e-6)
        if args.pc:
            po.setValue("pc_type", "python")
            po.setValue("pc_python_type", args.pc)
        sc = S.parse_scene(text)
        run = Run(sc, O.read_options(O.dict_getter(opts), sc))
        t_first = time.perf_counter() - T_START
        t0, c0 = time.perf_counter(), time.process_time()
        run.run()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        tot = run.timers.as_dict()
        steps = run.counts["accepted"]
        solves = max(1, run.timers.counts.get("solve", 0))
        its = run.iterations / solves
        setup = tot["setup"]
        print(f"p={p} nves={args.nves} threads={os.environ.get('OMP_NUM_THREADS', '?')} "
              f"first_step_s={t_first:.2f} stepping_s={wall:.2f} cpu_s={cpu:.2f} steps={steps} "
              f"s_per_step={wall / max(steps, 1):.4f} solves={solves} its_per_solve={its:.2f} "
              f"setup_frac={setup / wall:.3f} load={os.getloadavg()[0]:.2f}")
        print("  stages (s): " + " ".join(f"{s}={tot[s]:.3f}" for s in STAGES))
        print("  set-up detail (s): " + " ".join(f"{s}={run.timers.detail[s]:.3f}" for s in DETAIL
                                                 if run.timers.detail.get(s, 0) > 0))
        sys.stdout.flush()
        T_reset()


def T_reset():
    global T_START
    T_START = time.perf_counter()
from vesflow.threads import early_environment  # noqa: E402  (before numpy: the run's thread policy)
early_environment()


if __name__ == "__main__":
    main()
