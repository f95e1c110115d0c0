"""Memory per vesicle of one time step at p = 16: what is held after the set-up, by category, the
traced peak and the stage it falls in, and the peak resident memory (issue 28).

Two scenes: `periodic`, biconcave cells (v = 0.65, area radius 0.766, bending modulus 0.1) at
volume fraction 0.35 in a periodic cube in Taylor-Green flow (amplitude 0.1, as
runs/taylor_green_1408.toml; the cube's side follows from the count), and `free`, the oblate
lattice of benchmarks/mpi_scaling.py in shear (spacing 2.2).  Each (scene, N) runs one step of
the run's defaults (sdc, its adaptive step) in a process of its own (its ru_maxrss is its peak):

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/memory_per_vesicle.py --nves 8 16 --scenes periodic free
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/memory_per_vesicle.py --nves 8 ves_pc_precision=single

Per line: the held bytes per vesicle after the step (`memory_model.held_memory`: the arrays the
stepper, its cached layer potentials and the preconditioner hold, each array counted once),
tracemalloc's peak per vesicle and the stage it falls in, the peak RSS, and `vesflow check`'s
model (`costs.estimate`) beside it.  Extra arguments name=value are vesflow options.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import time

from vesflow.threads import early_environment  # noqa: E402  (before numpy: the run's thread policy)
early_environment()

CELL_VOLUME = 0.65 * 4.0 / 3.0 * 3.141592653589793 * 0.766 ** 3

PERIODIC = """
title = "memory per vesicle: periodic Taylor-Green box"
[flow]
type = "taylor_green"
amplitude = 0.1
[domain]
period = {L:.6f}
[discretization]
p = {p}
[time]
horizon = {T}
dt = {dt}
[output]
every = {T}
[[lattice]]
volume_fraction = 0.35
seed = 3
vesicle = {{ shape = "biconcave", reduced_volume = 0.65, radius = 0.766, bending_modulus = 0.1 }}
"""

FREE = """
title = "memory per vesicle: free-space lattice in shear"
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
[[lattice]]
count = [{k}, {k}, {m}]
spacing = 2.2
vesicle = {{ shape = "oblate", reduced_volume = 0.65, radius = 0.764, rotation = [0.0, 90.0, 0.0], bending_modulus = 0.01 }}
"""


def scene_text(kind, n, p, dt):
    if kind == "periodic":
        L = (n * CELL_VOLUME / 0.35) ** (1.0 / 3.0)
        return PERIODIC.format(L=L, p=p, T=dt, dt=dt)
    k = max(1, int(round(n ** (1.0 / 3.0))))
    while n % (k * k):
        k -= 1
    return FREE.format(p=p, T=dt, dt=dt, k=k, m=n // (k * k))


class StagePeaks:
    """tracemalloc's peak within each stage of vesflow.timing (the innermost open one), the
    largest of all and where it fell: Timers.start / stop read and reset the traced peak."""

    def __init__(self, tracemalloc):
        self.tm, self.open, self.peak, self.where, self.by_stage = tracemalloc, [], 0, "", {}

    def mark(self):
        cur, peak = self.tm.get_traced_memory()
        stage = self.open[-1] if self.open else "(outside the stages)"
        self.by_stage[stage] = max(self.by_stage.get(stage, 0), peak)
        if peak > self.peak:
            self.peak, self.where = peak, stage
        self.tm.reset_peak()

    def install(self, timers_cls):
        start, stop, me = timers_cls.start, timers_cls.stop, self

        def start_(t, name):
            me.mark()
            me.open.append(name)
            return start(t, name)

        def stop_(t, name):
            me.mark()
            if name in me.open:
                me.open.remove(name)
            return stop(t, name)
        timers_cls.start, timers_cls.stop = start_, stop_


def child(args):
    import tracemalloc
    from vesflow import threads
    threads.configure(1)
    from petsc4py import PETSc
    from vesflow import costs, memory_model, options as O, scene as S, timing
    from vesflow.simulation import Run
    text = scene_text(args.scene, args.n, args.p, args.dt)
    sc = S.parse_scene(text)
    opts, petsc = {"ts_max_steps": args.steps}, {"ksp_rtol": args.rtol}
    for kv in args.extra:
        k, v = kv.split("=", 1)
        (petsc if k.startswith("ksp_") else opts)[k] = v      # ksp_*: PETSc's options
    o = O.read_options(O.dict_getter(opts), sc)
    est = costs.estimate(sc, o)
    for k, v in petsc.items():
        PETSc.Options().setValue(k, v)
    peaks = StagePeaks(tracemalloc)
    tracemalloc.start()
    peaks.install(timing.Timers)
    t0, c0 = time.perf_counter(), time.process_time()
    run = Run(sc, o)
    run.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    peaks.mark()
    held = memory_model.held_memory(run.stepper)
    cur, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    N = sc.n_vesicles
    out = {"scene": args.scene, "n": N, "p": args.p, "wall_s": wall, "cpu_s": cpu,
           "its": run.stepper.ksp_its, "held": held, "traced_peak": peaks.peak, "peak_stage": peaks.where,
           "stage_peaks": peaks.by_stage, "traced_after": cur,
           "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
           "model": {"per_vesicle": getattr(est, "per_vesicle_bytes", est.memory / N), "base": getattr(est, "base_bytes", 0),
                     "total": getattr(est, "memory_peak", est.memory)},
           "near_pairs": int(run.stepper.lp_last.n_near_pairs_total) if run.stepper.lp_last is not None else 0,
           "near_pairs_model": int(est.near_pairs),
           "stages": dict(run.timers.as_dict(), **{k: run.timers.detail[k] for k in ("far_own", "self_setup", "own_setup",
                                                                                     "pc_blocks", "pc_lu")}),
           "far": run.stepper.lp_last.far.backend if run.stepper.lp_last is not None and run.stepper.lp_last.far
           else "none", "options": opts}
    if args.coeffs:
        import numpy as np
        np.save(args.coeffs, run.stepper.coeffs)
    print("RESULT " + json.dumps(out), flush=True)


MB = 2.0 ** 20


def report(r):
    n = r["n"]
    cats = " ".join(f"{k} {v / n / MB:.2f}" for k, v in r["held"].items() if k not in ("total", "layer_potentials"))
    cats += f"; {r['held'].get('layer_potentials', '?')} set(s) of layer potentials"
    print(f"{r['scene']:>8} N = {n:3d} far {r['far']}: held after the step {r['held']['total'] / n / MB:6.2f} MB per vesicle "
          f"({cats}); traced peak {r['traced_peak'] / n / MB:6.2f} MB per vesicle (in {r['peak_stage']}); peak RSS "
          f"{r['rss'] / 2 ** 30:.3f} GB = {r['rss'] / n / MB:.1f} MB per vesicle; model {r['model']['total'] / 2 ** 30:.3f} GB "
          f"({r['model']['per_vesicle'] / MB:.2f} MB per vesicle + {r['model']['base'] / MB:.0f} MB; "
          f"{100 * (r['model']['total'] / r['rss'] - 1):+.0f} % of the RSS); {r['its']} GMRES its, "
          f"{r['cpu_s']:.1f} s CPU", flush=True)
    st, its = r["stages"], max(r["its"], 1)
    print(f"         CPU of the step by stage (s): set-up {st['setup']:.1f} (self {st['self_setup']:.1f}, own "
          f"{st['own_setup']:.1f}, pc blocks {st['pc_blocks']:.1f}, LU {st['pc_lu']:.1f}), per GMRES iteration: far "
          f"{st['far'] / its:.3f} (own {st['far_own'] / its:.3f}), near {st['near'] / its:.3f}, self {st['self'] / its:.3f}; "
          f"near pairs {r['near_pairs']} (model {r['near_pairs_model']})", flush=True)
    top = sorted(r["stage_peaks"].items(), key=lambda kv: -kv[1])[:5]
    print("         traced peak by stage (MB per vesicle): " + ", ".join(f"{k} {v / n / MB:.2f}" for k, v in top),
          flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nves", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--scenes", nargs="+", default=["periodic", "free"], choices=("periodic", "free"))
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--steps", type=int, default=1)
    ap.add_argument("--rtol", type=float, default=1e-5, help="-ksp_rtol (the paper's case: 1e-5)")
    ap.add_argument("--json", default=None, help="also write the results here")
    ap.add_argument("--variants", nargs="+", default=None, help="option sets to compare, each name=value[,name=value] "
                    "('-' for the defaults): memory per vesicle and the step's difference from the first set")
    ap.add_argument("--child", nargs=2, metavar=("SCENE", "N"), help=argparse.SUPPRESS)
    ap.add_argument("--coeffs", default=None, help=argparse.SUPPRESS)
    ap.add_argument("extra", nargs="*", help="vesflow options as name=value (e.g. ves_pc_precision=single)")
    args = ap.parse_args(argv)
    if args.child:
        args.scene, args.n = args.child[0], int(args.child[1])
        return child(args)
    results = []
    variants = args.variants or ["-"]
    import tempfile
    import numpy as np
    tmp = tempfile.mkdtemp(prefix="memory_per_vesicle_")
    for scene in args.scenes:
        for n in args.nves:
            ref = None
            for k, var in enumerate(variants):
                extra = args.extra + ([] if var == "-" else var.split(","))
                path = os.path.join(tmp, f"{scene}_{n}_{k}.npy")
                cmd = [sys.executable, os.path.abspath(__file__), "--child", scene, str(n), "--p", str(args.p),
                       "--dt", str(args.dt), "--steps", str(args.steps), "--rtol", str(args.rtol),
                       "--coeffs", path] + extra
                proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
                lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
                if proc.returncode or not lines:
                    print(proc.stdout)
                    sys.exit(f"{scene} N = {n}: the run failed (exit status {proc.returncode})")
                r = json.loads(lines[-1][len("RESULT "):])
                r["variant"] = var
                c = np.load(path)
                if ref is None:
                    ref = c
                else:     # positions after the step(s): largest coefficient difference over the vesicle size
                    r["difference"] = float(np.abs(c - ref).max() / np.abs(ref[:, :, 1:4]).max())
                results.append(r)
                if len(variants) > 1:
                    print(f"# variant {var}" + (f": step difference {r['difference']:.2e} of the first variant's"
                                                if "difference" in r else ""), flush=True)
                report(r)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
