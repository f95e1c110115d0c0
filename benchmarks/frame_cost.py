"""The cost of frames and checkpoints: the same run with a frame (and a checkpoint) only at the
end against one with a frame and a checkpoint after every step.

The paper's pair (runs/accuracy_cost.toml: two oblate vesicles in shear, p = 12), fixed
dt = 0.1 (-ves_adapt none -ts_dt 0.1), 30 steps, one thread, run by the command line
(`python -m vesflow run`) of the vesflow that PYTHONPATH names, so that two trees can be
measured side by side with the same script:

    flock /tmp/bench.lock env PYTHONPATH=. OMP_NUM_THREADS=1 .venv/bin/python benchmarks/frame_cost.py

Prints, for each case, the CPU time of the run's process (user + system: the machine is
shared) and its set-up stage (/timings/setup of the run file), then the ratio of the two.
"""
import argparse
import os
import resource
import subprocess
import sys
import tempfile

import h5py

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def cpu_of_children():
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run_case(scene, out, p, dt, every, steps, env):
    args = [sys.executable, "-m", "vesflow", "run", scene, "-o", out, "-ves_p", str(p), "-ves_adapt", "none",
            "-ts_dt", str(dt), "-ts_max_time", str(steps * dt), "-ts_max_steps", str(steps),
            "-ves_output_every", str(every), "-ves_checkpoint_every", str(every)]
    c0 = cpu_of_children()
    subprocess.run(args, check=True, env=env, stdout=subprocess.DEVNULL)
    cpu = cpu_of_children() - c0
    with h5py.File(out, "r") as f:
        return cpu, float(f["timings"].attrs["setup"]), int(f["frames/time"].shape[0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=os.path.join(ROOT, "runs", "accuracy_cost.toml"))
    ap.add_argument("--p", type=int, default=12)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--dt", type=float, default=0.1)
    args = ap.parse_args(argv)
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    T = args.steps * args.dt
    with tempfile.TemporaryDirectory() as d:
        end = run_case(args.scene, os.path.join(d, "end.h5"), args.p, args.dt, T, args.steps, env)
        every = run_case(args.scene, os.path.join(d, "every.h5"), args.p, args.dt, args.dt, args.steps, env)
    print(f"PYTHONPATH={env.get('PYTHONPATH', '')}: {os.path.basename(args.scene)} p={args.p} steps={args.steps} dt={args.dt}")
    print(f"  frames at the end:  cpu_s={end[0]:.2f} setup_s={end[1]:.2f} frames={end[2]}")
    print(f"  frame every step:   cpu_s={every[0]:.2f} setup_s={every[1]:.2f} frames={every[2]}")
    print(f"  ratio every/end: {every[0] / end[0]:.3f}")


if __name__ == "__main__":
    main()
