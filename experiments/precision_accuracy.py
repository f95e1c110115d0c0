"""Accuracy cost of the memory options -ves_self_precision / -ves_pc_precision single (issue 19).

Runs the accuracy-cost study's scene (runs/accuracy_cost.toml: two vesicles in shear, p = 12)
to a short horizon with each option and with both, against double precision, and prints per
variant: the final centroid difference relative to the vesicle length (as the study measures
errors, max over vesicles), GMRES iterations per solve, accepted / rejected steps, the bytes of
the self operators and the wall time (noisy on a shared machine).

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.precision_accuracy --T 1 --rtol 1e-8
"""
import argparse
import os
import time

from vesflow.threads import early_environment  # noqa: E402
early_environment()

HERE = os.path.dirname(os.path.abspath(__file__))
VARIANTS = {"double": ("double", "double"), "self": ("single", "double"), "pc": ("double", "single"),
            "both": ("single", "single")}


def run_variant(name, args):
    import numpy as np
    from petsc4py import PETSc
    from vesflow import options as O, scene as S
    from vesflow.simulation import Run
    if args.rtol is not None:
        PETSc.Options().setValue("ksp_rtol", args.rtol)
    sc = S.load_scene(os.path.join(HERE, "..", "runs", "accuracy_cost.toml"))
    self_prec, pc_prec = VARIANTS[name]
    opts = {"ts_max_time": args.T, "ves_p": args.p, "ves_self_precision": self_prec, "ves_pc_precision": pc_prec}
    sc = O.apply_overrides(sc, O.dict_getter(opts))
    run = Run(sc, O.read_options(O.dict_getter(opts), sc), log=lambda *a, **k: None)
    t0 = time.perf_counter()
    run.run()
    wall = time.perf_counter() - t0
    st = run.stepper
    surf = st.surface
    ext = np.linalg.norm(surf.points() - surf.centroid()[:, None, :], axis=-1).max(axis=1)
    return {"centroid": surf.centroid(), "length": 2 * ext, "its": run.iterations,
            "solves": run.timers.counts.get("solve", 0),
            "accepted": run.counts["accepted"], "rejected": run.counts["rejected"],
            "self_bytes": st.lp_last.self_ops.nbytes, "wall": wall}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--T", type=float, default=1.0)
    ap.add_argument("--p", type=int, default=12)
    ap.add_argument("--rtol", type=float, default=None, help="-ksp_rtol (default: vesflow's 1e-8)")
    ap.add_argument("--variants", default="double,self,pc,both")
    args = ap.parse_args(argv)
    import numpy as np
    from vesflow import threads
    threads.configure(1)
    ref = None
    for name in args.variants.split(","):
        try:
            r = run_variant(name, args)
        except Exception as exc:             # a failed run is a result too (which option, why)
            print(f"variant={name} p={args.p} T={args.T:g} rtol={args.rtol or 1e-8:g} FAILED: {exc}", flush=True)
            continue
        if ref is None and name == "double":
            ref = r
        diff = (float((np.linalg.norm(r["centroid"] - ref["centroid"], axis=1) / ref["length"]).max())
                if ref is not None else float("nan"))
        per = r["its"] / max(r["solves"] or 1, 1)
        print(f"variant={name} p={args.p} T={args.T:g} rtol={args.rtol or 1e-8:g} centroid_diff/length={diff:.2e} "
              f"its={r['its']} solves={r['solves']} its_per_solve={per:.1f} accepted={r['accepted']} "
              f"rejected={r['rejected']} self_ops_MB={r['self_bytes'] / 2**20:.1f} wall_s={r['wall']:.1f}", flush=True)


if __name__ == "__main__":
    main()
