"""Per-step set-up of the per-vesicle operators: ms of process CPU (and wall) per vesicle for
the self operators (vesflow.layerpot.singular.SelfOperators) and the Ewald far field's own
smooth operators (vesflow.layerpot.own_smooth.OwnSmoothOperators), docs/explanation/far_field.md
"Periodic: where the time of a large suspension goes".

N biconcave vesicles (reduced volume 0.65, random orientations), degree p, singular and far
grid q = 2p, Ewald splitting --xi; single layer alone ("S") and both layers ("S+D"); each
construction runs through threads.map_vesicles (one vesicle per Python thread, BLAS on one
thread), so OMP_NUM_THREADS sets the threads.  Best of --repeat constructions (after one
warm-up that fills the transform and Wigner-block caches).  With --profile the parts of one
vesicle's assembly (one thread) are printed instead (SelfOperators/OwnSmoothOperators
._assemble under cProfile, the top functions by own time).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/setup_operators.py --n 16
    OMP_NUM_THREADS=2 OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/setup_operators.py --n 16
"""
import argparse
import os
import time

import numpy as np


from vesflow import shapes, sph, threads  # noqa: E402
from vesflow.layerpot.own_smooth import OwnSmoothOperators  # noqa: E402
from vesflow.layerpot.singular import SelfOperators  # noqa: E402
from vesflow.surface import Surface  # noqa: E402


def scene(n, p, q, seed=0):
    """Coefficients (n, 3, C) and the own smooth operators' inputs of n rotated cells."""
    rng = np.random.default_rng(seed)
    coeffs = np.stack([shapes.make_shape("biconcave", p, center=tuple(3.0 * rng.standard_normal(3)),
                                         rotation=tuple(rng.uniform(0, np.pi, 3))) for _ in range(n)])
    S = Surface(coeffs, p)
    geo = S.geometry(q)
    x = np.ascontiguousarray(S.points().reshape(n, -1, 3))
    y = np.ascontiguousarray(geo.X.reshape(n, -1, 3))
    w = np.ascontiguousarray(geo.dA.reshape(n, -1))
    nw = np.ascontiguousarray((geo.normal * geo.dA[..., None]).reshape(n, -1, 3))
    return coeffs, (x, y, w, nw)


def timed(fn, repeat):
    """Best (process CPU, wall) seconds of fn() over repeat calls."""
    best = (np.inf, np.inf)
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        best = min(best, (time.process_time() - c0, time.perf_counter() - w0))
    return best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=16, help="vesicles (<= 128 on a shared machine)")
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--xi", type=float, default=3.0, help="Ewald splitting of the own smooth operators")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="cProfile of one vesicle's assembly instead")
    args = ap.parse_args(argv)
    p, q = args.p, 2 * args.p
    coeffs, (x, y, w, nw) = scene(args.n, p, q)
    builders = {
        "self S": lambda c, a: SelfOperators(c, p, q, True, False),
        "self S+D": lambda c, a: SelfOperators(c, p, q, True, True),
        "own S": lambda c, a: OwnSmoothOperators(*a, args.xi, p, q, True, False),
        "own S+D": lambda c, a: OwnSmoothOperators(*a, args.xi, p, q, True, True),
    }
    for b in builders.values():                     # warm-up: transforms, Wigner blocks
        b(coeffs[:1], (x[:1], y[:1], w[:1], nw[:1]))
    if args.profile:
        import cProfile
        import pstats
        for name, b in builders.items():
            pr = cProfile.Profile()
            pr.enable()
            for _ in range(args.repeat):
                b(coeffs[:1], (x[:1], y[:1], w[:1], nw[:1]))
            pr.disable()
            print(f"\n## {name}, one vesicle, {args.repeat} assemblies")
            pstats.Stats(pr).sort_stats("tottime").print_stats(12)
        return
    print(f"# per-vesicle operators, p = {p}, q = {q}, N = {args.n}, C = {sph.n_coeffs(p)}; "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, map_vesicles threads now "
          f"{min(threads.openmp_threads(), args.n, threads.free_cores())}; load average "
          + " ".join(f"{v:.2f}" for v in os.getloadavg()))
    print(f"{'operator':>10} {'CPU ms/ves':>11} {'wall ms/ves':>12}")
    for name, b in builders.items():
        cpu, wall = timed(lambda: b(coeffs, (x, y, w, nw)), args.repeat)
        print(f"{name:>10} {cpu / args.n * 1e3:>11.1f} {wall / args.n * 1e3:>12.1f}", flush=True)


if __name__ == "__main__":
    main()
