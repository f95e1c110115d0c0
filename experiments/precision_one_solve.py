"""One solve with the memory options against double (issue 19): the accuracy-cost pair
(runs/accuracy_cost.toml, p = 12), dt = 0.05 from the initial shapes, for several -ksp_rtol;
prints per variant (dd, sd = self single, ds = pc single, ss = both) the GMRES iterations and the
velocity's largest difference from double's relative to its largest value.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.precision_one_solve            # vesflow's KSP
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.precision_one_solve gmres      # -ksp_type gmres
"""
import os
import sys

from vesflow.threads import early_environment  # noqa: E402
early_environment()

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    import numpy as np
    from petsc4py import PETSc
    from vesflow import options as O, scene as S, threads
    from vesflow.simulation import Run
    threads.configure(1)
    if len(sys.argv) > 1:
        PETSc.Options().setValue("ksp_type", sys.argv[1])
    for rtol in (1e-6, 1e-8, 1e-10, 1e-12):
        PETSc.Options().setValue("ksp_rtol", rtol)
        out = {}
        for sp, pp in (("double", "double"), ("single", "double"), ("double", "single"), ("single", "single")):
            sc = S.load_scene(os.path.join(HERE, "..", "runs", "accuracy_cost.toml"))
            opts = {"ves_self_precision": sp, "ves_pc_precision": pp}
            run = Run(sc, O.read_options(O.dict_getter(opts), sc), log=lambda *a, **k: None)
            sol = run.stepper.solve(0.05)
            out[sp[0] + pp[0]] = (sol.u, sol.its)
        ud = out["dd"][0]
        print(f"rtol={rtol:g} " + " ".join(f"{k}: its={its} du={np.abs(u - ud).max() / np.abs(ud).max():.1e}"
                                           for k, (u, its) in out.items()), flush=True)


if __name__ == "__main__":
    main()
