"""The Ewald sum's error against the NUFFT accuracy it requests (``ewald.NUFFT_EPS_FACTOR``:
NUFFT eps = factor * tol), free space and periodic, single and double layer
(docs/explanation/far_field.md, "Accuracy of the Ewald sum").

Scenes: ``spheres``, the unit spheres of benchmarks/far_field.py (--n of them, p = 16 targets,
q = 32 sources, area-weighted random densities); ``clusters``, the random point clusters of
tests/layerpot/test_ewald.py (20 clusters of 50 sources and 15 targets, radius 0.3, in a box of side 3,
plus 10 targets of no vesicle).  Free space: against the direct sum.  Periodic (``spheres``:
period 2.5 ceil(N^(1/3)); ``clusters``: period 3): against the Ewald sum at tol 1e-13 with the
NUFFT at 1e-14 (other xi, rc and grid).  Single layer: the parameters of a single layer alone
(the Stokeslet's error prefactor, as the benchmark's and a viscosity-matched suspension's);
double layer: the stresslet with the parameters of both layers.  Printed: max |u - ref| /
max |ref| as a fraction of tol, per factor.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.nufft_eps_margin
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.nufft_eps_margin --tols 1e-6 --factors 0.5 1 2 5 10
"""
import argparse

import numpy as np


from benchmarks.far_field import scene  # noqa: E402
from vesflow._kernels import stokes  # noqa: E402
from vesflow.layerpot import ewald  # noqa: E402


def clusters(rng, nclus=20, per=50, L=3.0, radius=0.3, ntrg_per=15, free_trg=10):
    """As tests/layerpot/test_ewald.py's clusters()."""
    c = rng.uniform(0, L, (nclus, 3))
    src = (c[:, None, :] + radius * rng.uniform(-1, 1, (nclus, per, 3))).reshape(-1, 3)
    trg = (c[:, None, :] + radius * rng.uniform(-1, 1, (nclus, ntrg_per, 3))).reshape(-1, 3)
    sid = np.repeat(np.arange(nclus), per)
    tid = np.repeat(np.arange(nclus), ntrg_per)
    trg = np.concatenate([trg, rng.uniform(0, L, (free_trg, 3))])
    tid = np.concatenate([tid, np.full(free_trg, -7)])
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    return src, sid, trg, tid, f, nw, g


def evaluate(src, sid, trg, tid, dens, tol, period, double_layer, factor):
    old = ewald.NUFFT_EPS_FACTOR
    ewald.NUFFT_EPS_FACTOR = factor
    try:
        es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, period=period, double_layer=double_layer, threads=1)
    finally:
        ewald.NUFFT_EPS_FACTOR = old
    return es.evaluate(*dens)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tols", type=float, nargs="+", default=[1e-4, 1e-6, 1e-8, 1e-10])
    ap.add_argument("--factors", type=float, nargs="+", default=[0.5, 1.0, 2.0])
    ap.add_argument("--n", type=int, default=8, help="spheres of the spheres scene")
    a = ap.parse_args(argv)
    print(f"# max error / max |ref| in units of tol, NUFFT eps = factor * tol; factors {a.factors}")
    print(f"{'scene':>9} {'domain':>8} {'layer':>7} {'tol':>7} " + " ".join(f"{'x' + format(f, 'g'):>8}" for f in a.factors))
    worst = {f: 0.0 for f in a.factors}
    for name in ("spheres", "clusters"):
        if name == "spheres":
            src, sid, trg, tid, f, nw, g = scene(a.n, 16, 32)
            L = 2.5 * int(np.ceil(a.n ** (1 / 3)))
        else:
            src, sid, trg, tid, f, nw, g = clusters(np.random.default_rng(1))
            L = 3.0
        for period in (None, L):
            for layer in ("single", "double"):
                dens = (f, None, None) if layer == "single" else (None, nw, g)
                dbl = layer == "double"
                if period is None:
                    ref = np.zeros(trg.shape)
                    if dbl:
                        stokes.stresslet_sum_excl(src, nw, g, sid, trg, tid, ref)
                    else:
                        stokes.stokeslet_sum_excl(src, f, sid, trg, tid, ref)
                else:
                    ref = evaluate(src, sid, trg, tid, dens, 1e-13, period, dbl, 0.1)
                for tol in a.tols:
                    errs = []
                    for fac in a.factors:
                        u = evaluate(src, sid, trg, tid, dens, tol, period, dbl, fac)
                        errs.append(np.abs(u - ref).max() / np.abs(ref).max() / tol)
                        worst[fac] = max(worst[fac], errs[-1])
                    print(f"{name:>9} {'free' if period is None else 'periodic':>8} {layer:>7} {tol:>7.0e} "
                          + " ".join(f"{e:>8.3f}" for e in errs), flush=True)
    print("# worst: " + ", ".join(f"factor {f:g}: {w:.3f} tol" for f, w in worst.items()))


if __name__ == "__main__":
    main()
