"""The cost model's constants (vesflow/calibration.py) measured on this machine, one thread.

For the accuracy-cost study's vesicle (oblate, v = 0.85, two of them in shear) at each degree
p, after one step has filled the caches:

- S set-up: the singular self operator per vesicle (SelfOperators, q = 2p);
- block + LU: the block preconditioner's rebuild per vesicle (BlockJacobi.block_parts on the
  preconditioner grid, then one LU at the step's dt);
- forces: membrane force and divergence per vesicle per GMRES iteration (StepOperator);
- direct pair: seconds per (target, source) pair of the direct Stokeslet sum of two vesicles
  (far field, and the near correction's kernel);

and prints them next to the model's values, with the fitted power laws the model uses
(self_setup_s and pc_setup_s: value at p = 16 and exponent in p; forces_s: a + b p^3).
Process CPU time, best of --repeat, so that a shared machine disturbs the figures less.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/cost_model.py
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/cost_model.py --degrees 8 12 --repeat 2
"""
import argparse
import os
import time

from vesflow.threads import early_environment  # noqa: E402
early_environment()

import numpy as np  # noqa: E402

from vesflow import calibration, costs, options as optmod, precond, scene as scenemod, study, threads  # noqa: E402
from vesflow._kernels import stokes  # noqa: E402
from vesflow.layerpot.singular import SelfOperators  # noqa: E402
from vesflow.operator import StepOperator  # noqa: E402
from vesflow.simulation import Run  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def best_cpu(fn, repeat):
    """Smallest process CPU time of `repeat` calls of fn (one warm-up call first)."""
    fn()
    best = np.inf
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def measure(p, repeat):
    scene = scenemod.load_scene(os.path.join(ROOT, "runs", "accuracy_cost.toml"))
    sc = study.case_scene(scene, study.parse_case(f"{p},0.04,0"), horizon=0.05)
    opts = optmod.read_options(optmod.dict_getter({"-ves_adapt": "none"}), sc)
    run = Run(sc, opts, writer=study.Recorder(opts["q_near"]))
    run.run()
    st = run.stepper
    lp = st.lp_current if st.lp_current is not None else st.lp_last
    op = StepOperator(lp.surface, st.params, 0.05, lp, st.q_force, st.coupling)
    coeffs = lp.surface.coeffs
    t_self = best_cpu(lambda: SelfOperators(coeffs[:1], p), repeat)
    pc = precond.BlockJacobi()

    def rebuild():
        parts = pc.block_parts(op)
        pc.parts = parts
        pc.factors = []
        pc._factors_for(op)
    t_pc = best_cpu(rebuild, repeat) / op.N
    x = np.random.default_rng(0).standard_normal(op.N * op.block)
    u, s = op.split(x)
    t_forces = best_cpu(lambda: (op.membrane_force(u, s), op.divergence(u)), 3 * repeat) / op.N
    t_apply = best_cpu(lambda: op.apply(x), 3 * repeat)
    src, trg = lp.src, lp.trg
    f = np.random.default_rng(1).standard_normal(src.shape)
    out = np.zeros(trg.shape)
    pairs = float(trg.shape[0]) * src.shape[0] * (op.N - 1) / op.N
    t_pair = best_cpu(lambda: stokes.stokeslet_sum_excl(src, f, lp.src_id, trg, lp.trg_id, out), 3 * repeat) / pairs
    return {"p": p, "self": t_self, "pc": t_pc, "forces": t_forces, "apply": t_apply, "pair": t_pair,
            "its_model": costs.pc_rebuild_iterations(op.N, p, lp.q_far), "its_measured": t_pc * op.N / t_apply}


def fit_power(ps, ts):
    """(value at p = 16, exponent) of t = c p^e, least squares in log-log."""
    e, logc = np.polyfit(np.log(ps), np.log(ts), 1)
    return float(np.exp(logc) * 16.0 ** e), float(e)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--degrees", type=int, nargs="+", default=[6, 8, 12, 16])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    threads.configure(1)
    print(f"# cost-model constants, one thread, process CPU (best of {a.repeat}); load average "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print("# p   S set-up/ves   block+LU/ves   forces/ves/it   apply/it (2 ves)   direct s/pair   "
          "rebuild in its: model / measured")
    rows = []
    for p in a.degrees:
        r = measure(p, a.repeat)
        rows.append(r)
        print(f"  {p:<3d} {r['self']:12.4f}   {r['pc']:12.4f}   {r['forces']:13.2e}   {r['apply']:16.2e}   "
              f"{r['pair']:13.2e}   {r['its_model']:6.1f} / {r['its_measured']:.1f}", flush=True)
    ps = np.array([r["p"] for r in rows], dtype=float)
    if len(ps) >= 2:
        s16, se = fit_power(ps, [r["self"] for r in rows])
        c16, ce = fit_power(ps, [r["pc"] for r in rows])
        b, a0 = np.polyfit(ps ** 3, [r["forces"] for r in rows], 1)
        cal = calibration.load()
        print(f"# fitted: self_setup_s = ({s16:.3g}, {se:.2f})   calibration {cal.self_setup_s}")
        print(f"#         pc_setup_s   = ({c16:.3g}, {ce:.2f})   calibration {cal.pc_setup_s}")
        print(f"#         forces_s     = ({a0:.2e}, {b:.2e})   calibration {cal.forces_s}")
        print(f"#         direct_s_per_pair = {np.median([r['pair'] for r in rows]):.2e}   "
              f"calibration {cal.direct_s_per_pair:.2e} ({cal.source}; benchmarks/calibrate.py writes it)")


if __name__ == "__main__":
    main()
