"""What single precision would cost (issue 19, memory options): an experiment, not an option.

vesflow stores its self operators and preconditioner blocks in double precision.  This script
patches, for one run in this process, either
  --variant pc     the preconditioner's LU factors to single precision (factor and solve in
                   float32: the preconditioner only), or
  --variant self   the self operators (S, and D with a contrast) to single precision (the
                   matvec's self interaction in float32),
and compares one step of a lattice of vesicles with the double-precision run (--variant none):
GMRES iterations, and the largest difference of the velocity and of the new positions,
relative to the largest velocity / position change.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/single_precision.py --nves 8 --p 16
"""
import argparse
import os
import resource
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from vesflow.threads import early_environment  # noqa: E402
early_environment()


def patch(variant):
    import numpy as np
    if variant == "pc":
        from vesflow import precond
        from scipy.linalg import lu_factor, lu_solve
        precond.lu_factor = lambda A, check_finite=False: lu_factor(np.asarray(A, dtype=np.float32),
                                                                    check_finite=False)
        precond.lu_solve = lambda lu, b, check_finite=False: lu_solve(lu, np.asarray(b, dtype=np.float32),
                                                                      check_finite=False).astype(np.float64)
    elif variant == "self":
        from vesflow.layerpot import singular
        init = singular.SelfOperators.__init__

        def init32(self, *a, **k):
            init(self, *a, **k)
            for name in ("single", "double"):
                if getattr(self, name) is not None:
                    setattr(self, name, getattr(self, name).astype(np.float32))
        singular.SelfOperators.__init__ = init32

        def apply32(ops, density_coeffs):
            N, _, C = density_coeffs.shape
            out = np.matmul(ops, density_coeffs.reshape(N, 3 * C, 1).astype(ops.dtype))
            return out.reshape(N, 3, C).astype(np.float64)
        singular.SelfOperators.apply = staticmethod(apply32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nves", type=int, default=8)
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--variant", choices=["none", "pc", "self", "all"], default="all")
    ap.add_argument("--rtol", type=float, default=1e-8)
    args = ap.parse_args(argv)
    if args.variant == "all":                    # each variant in its own process (patches, RSS)
        import subprocess
        out = {}
        for v in ("none", "pc", "self"):
            r = subprocess.run([sys.executable, __file__, "--nves", str(args.nves), "--p", str(args.p),
                                "--rtol", str(args.rtol), "--variant", v], capture_output=True, text=True)
            if r.returncode:
                sys.exit(r.stderr)
            out[v] = r.stdout.strip().splitlines()[-1]
            print(out[v])
        return
    import numpy as np
    from vesflow import threads
    threads.configure(1)
    patch(args.variant)
    from petsc4py import PETSc
    from vesflow import options as O, scene as S
    from vesflow.simulation import Run
    import mpi_scaling as M
    PETSc.Options().setValue("ksp_rtol", args.rtol)
    sc = S.parse_scene(M.SCENE.format(p=args.p, T=0.1, dt=0.1, vesicles=M.vesicle_blocks(args.nves)))
    run = Run(sc, O.read_options(O.dict_getter({"ves_adapt": "none", "ts_max_steps": 1, "ves_far": "direct"}), sc))
    c0 = run.stepper.coeffs.copy()
    run.run()
    st = run.stepper
    ref_path = f"/tmp/vesflow_single_precision_ref_{args.nves}_{args.p}.npz"
    if args.variant == "none":
        np.savez(ref_path, u=st.last.u, c=st.coeffs)
        du = dc = 0.0
    else:
        ref = np.load(ref_path)
        du = np.abs(st.last.u - ref["u"]).max() / np.abs(ref["u"]).max()
        dc = np.abs(st.coeffs - ref["c"]).max() / np.abs(ref["c"] - c0).max()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    print(f"variant={args.variant} nves={args.nves} p={args.p} rtol={args.rtol:g} its={st.ksp_its} "
          f"velocity_rel_diff={du:.2e} step_rel_diff={dc:.2e} peak_rss_gb={rss:.2f}")


if __name__ == "__main__":
    main()
