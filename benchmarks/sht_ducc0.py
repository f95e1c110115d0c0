"""Our spherical-harmonic transforms against ducc0's on the same Gauss-Legendre grid (issue 2).

For p = 8, 16, 32 (q = 2p, the upsampled grid the quadratures use) and a batch of 1 and
1000 scalar fields: time of synthesis (coefficients -> grid) and analysis (grid -> coefficients)
with vesflow.sph.Transform and with ducc0.sht (synthesis_2d / adjoint_synthesis_2d + GL
weights via analysis_2d).  Agreement: a band-limited field synthesized by ducc0 on the grid
is analysed and resynthesized by vesflow; the grids must agree to 1e-12 (same points, same
function space), which the script asserts.  Also the set-up time of vesflow's transform
(first sph.transform(p, q) call) against a cached call.

    OMP_NUM_THREADS=1 python benchmarks/sht_ducc0.py            # the run in docs/explanation/transforms.md
    python benchmarks/sht_ducc0.py --p 8 16 --batch 1 100
"""
import argparse
import os
import time

import numpy as np


import ducc0  # noqa: E402

from vesflow import sph  # noqa: E402


def best(f, repeat):
    t = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        t = min(t, time.perf_counter() - t0)
    return t


def nalm(lmax):
    return (lmax + 1) * (lmax + 2) // 2


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--p", type=int, nargs="+", default=[8, 16, 32])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 1000])
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    print(f"# ducc0 {ducc0.__version__}, nthreads = 1, OMP_NUM_THREADS = {os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"{'p':>3} {'q':>3} {'batch':>6} {'ours synth':>11} {'ducc0 synth':>12} {'ours anal':>10} "
          f"{'ducc0 anal':>11} {'agree':>8}  (seconds per batch)")
    for p in a.p:
        q = 2 * p
        sph.transform.cache_clear() if hasattr(sph.transform, "cache_clear") else None
        t0 = time.perf_counter()
        T = sph.transform(p, q)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        sph.transform(p, q)
        again = time.perf_counter() - t0
        nth, nph = T.nlat, T.nlon
        for B in a.batch:
            alm = np.zeros((B, nalm(p)), dtype=complex)
            alm[:] = rng.normal(size=(B, nalm(p))) + 1j * rng.normal(size=(B, nalm(p)))
            alm[:, :p + 1] = alm[:, :p + 1].real          # m = 0 real
            # p-th degree sine mode is not in our space: drop (l = p, m = p) imaginary part
            alm[:, -1] = alm[:, -1].real
            grid = np.empty((B, nth, nph))

            def d_synth():
                for b in range(B):
                    ducc0.sht.synthesis_2d(alm=alm[b:b + 1], spin=0, lmax=p, geometry="GL", ntheta=nth,
                                           nphi=nph, map=grid[b:b + 1])

            def d_anal():
                for b in range(B):
                    ducc0.sht.analysis_2d(map=grid[b:b + 1], spin=0, lmax=p, geometry="GL")

            d_synth()
            c = T.analysis(grid.reshape(B, -1))
            back = T.synth(c).reshape(B, nth, nph)
            agree = float(np.abs(back - grid).max() / np.abs(grid).max())
            assert agree < 1e-12, agree
            ts_d, ta_d = best(d_synth, a.repeat), best(d_anal, a.repeat)
            ts_o = best(lambda: T.synth(c), a.repeat)
            flat = grid.reshape(B, -1)
            ta_o = best(lambda: T.analysis(flat), a.repeat)
            print(f"{p:>3} {q:>3} {B:>6} {ts_o:11.2e} {ts_d:12.2e} {ta_o:10.2e} {ta_d:11.2e} {agree:8.1e}")
        print(f"#   p = {p}: set-up of sph.transform({p}, {q}) {first * 1e3:.1f} ms first call, "
              f"{again * 1e6:.1f} us cached")


if __name__ == "__main__":
    main()
