"""Singular self operators: set-up and apply time per vesicle, and the apply's memory bandwidth (docs/explanation/performance.md).

For each degree p (q = 2p, the default singular order) one oblate vesicle (reduced volume 0.85)
is assembled by vesflow.layerpot.singular.SelfOperators, single layer alone ("S") and single
plus double layer ("S+D"), ``--setup-ves`` times each after one first assembly that fills the
Wigner-block cache (sph.wigner_blocks, once per run and p): the first and the means of the others
(what each vesicle of a run costs) are printed.

The apply is timed as a GMRES iteration does it, through LayerPotentials.self_part (one batched
SelfOperators.apply per layer: np.matmul of (N, 3C, 3C) float64 operators with the (N, 3C, 1)
densities, i.e. N matrix-vector products), for N vesicles whose operators are copies of the
assembled one in separate memory (the values do not change the time).  Two batch sizes per p:
the one given by --nves (default 64, 16, 4 for p = 8, 16, 32) and, with --stream-mb, the
smallest N whose operators fill that many MB (default 256 MB, 8x the 32 MB L3 of the machine of
docs/explanation/performance.md, so every apply streams from DRAM).

Bandwidth: bytes of operator matrices read per apply (N (3C)^2 8 per layer; the densities and
results add < 1%) / apply time, as a fraction of the copy bandwidth measured in the same process,
interleaved with the apply (best of --rounds rounds each; np.copyto of two --copy-mb MB arrays, (bytes read + bytes written) / time, best
of 5; the write-allocate read of the destination is NOT counted, as is usual, so a read-only
stream such as GEMV can exceed 100%).  For reference also the read bandwidth of one large GEMV
(a --copy-mb MB matrix times a vector), the best a bandwidth-bound apply can do.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/self_operator.py             # docs/explanation/performance.md
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/self_operator.py --degrees 8 16 --setup-ves 2 --stream-mb 0
"""
import argparse
import os
import time
from types import SimpleNamespace

import numpy as np


from vesflow import shapes, sph  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials  # noqa: E402
from vesflow.layerpot.singular import SelfOperators  # noqa: E402

DEFAULT_NVES = {8: 64, 16: 16, 32: 4}


def best(fn, repeat, min_time=0.2):
    """Best wall time of fn() over max(repeat, enough calls to fill min_time)."""
    t, total, k = np.inf, 0.0, 0
    while k < repeat or total < min_time:
        t0 = time.perf_counter()
        fn()
        dt = time.perf_counter() - t0
        t, total, k = min(t, dt), total + dt, k + 1
        if k >= 1000:
            break
    return t


class Bandwidth:
    """Copy and GEMV-read bandwidth of large arrays (bytes / s)."""

    def __init__(self, mb):
        n = int(mb * 1e6 / 8)
        self.a = np.random.default_rng(0).standard_normal(n)
        self.b = np.empty_like(self.a)
        np.copyto(self.b, self.a)
        cols = 1000
        self.mat = self.a[: n - n % cols].reshape(-1, cols)
        self.x = np.ones(cols)

    def copy(self, repeat=5):
        return 2 * self.a.nbytes / best(lambda: np.copyto(self.b, self.a), repeat, 0.0)

    def gemv(self, repeat=5):
        return self.mat.nbytes / best(lambda: self.mat @ self.x, repeat, 0.0)

    def paired(self, fn, rounds, repeat):
        """Best copy, GEMV and fn() times over ``rounds`` interleaved rounds (the load of a shared
        machine changes within seconds; interleaving keeps the ratio honest)."""
        cb, gb, t = 0.0, 0.0, np.inf
        for _ in range(rounds):
            cb, gb = max(cb, self.copy(1)), max(gb, self.gemv(1))
            t = min(t, best(fn, repeat, 0.05))
        return cb, gb, t


def loadavg():
    return "load average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--degrees", type=int, nargs="+", default=[8, 16, 32])
    ap.add_argument("--nves", type=int, nargs="+", default=None,
                    help="vesicles per batched apply, one per degree (default 64, 16, 4 for p = 8, 16, 32)")
    ap.add_argument("--stream-mb", type=float, default=256.0,
                    help="also apply with enough vesicles to fill this many MB of operators (0: no)")
    ap.add_argument("--setup-ves", type=int, default=3, help="assemblies timed per degree and layer set (>= 1)")
    ap.add_argument("--repeat", type=int, default=3, help="applies timed per round (best kept)")
    ap.add_argument("--rounds", type=int, default=6, help="interleaved rounds of copy, GEMV and apply per case")
    ap.add_argument("--copy-mb", type=float, default=400.0, help="size of each array of the copy benchmark")
    args = ap.parse_args(argv)
    nves = args.nves or [DEFAULT_NVES.get(p, max(1, 64 * 8 ** 2 // p ** 2)) for p in args.degrees]
    if len(nves) != len(args.degrees):
        ap.error("--nves needs one value per degree")

    bw = Bandwidth(args.copy_mb)
    c0, g0 = bw.copy(), bw.gemv()
    print(f"# self operators, q = 2p, oblate v = 0.85; OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"{os.cpu_count()} cpus; {loadavg()}")
    print(f"# copy bandwidth (np.copyto {args.copy_mb:.0f} MB, read + written): {c0 / 1e9:.1f} GB/s; "
          f"GEMV read bandwidth ({args.copy_mb:.0f} MB matrix): {g0 / 1e9:.1f} GB/s")

    # ---------------------------------------------------------------- set-up
    print("\n# set-up per vesicle (s): the first assembly at each p also fills the Wigner-block cache (once per run"
          "\n# and p); S = single layer, S+D = single and double layer, mean of the assemblies after the first")
    print(f"{'p':>3} {'q':>3} {'3C':>5} {'MB/op':>7} {'first S':>8} {'S':>8} {'S+D':>8}")
    ops = {}
    for p in args.degrees:
        q = 2 * p
        c = shapes.make_shape("oblate", p, reduced_volume=0.85)[None]
        sph.transform(p), sph.transform(p, q)          # transforms are set up once per run, not per vesicle
        times = {}
        for key, dbl in (("S", False), ("S+D", True)):
            ts = []
            for _ in range(max(1, args.setup_ves) + (key == "S")):
                t0 = time.perf_counter()
                so = SelfOperators(c, p, q, True, dbl)
                ts.append(time.perf_counter() - t0)
            times[key] = ts
        ops[p] = (so.single[0], so.double[0])
        n3 = 3 * sph.n_coeffs(p)
        print(f"{p:>3} {q:>3} {n3:>5} {n3 * n3 * 8 / 1e6:>7.2f} {times['S'][0]:>8.3g} "
              f"{np.mean(times['S'][1:]):>8.3g} {np.mean(times['S+D']):>8.3g}   ({loadavg()})", flush=True)

    # ---------------------------------------------------------------- apply
    print("\n# apply (LayerPotentials.self_part: batched np.matmul, N GEMVs per layer), best of "
          f"{args.rounds} rounds;\n# bandwidth = operator bytes / time; fraction of the copy (GEMV) bandwidth measured in the same rounds")
    print(f"{'p':>3} {'N':>5} {'layers':>6} {'MB read':>8} {'us/vesicle':>11} {'GB/s':>6} {'copy GB/s':>9} "
          f"{'frac copy':>9} {'frac GEMV':>9}")
    rng = np.random.default_rng(1)
    for p, n in zip(args.degrees, nves):
        S1, D1 = ops[p]
        C = sph.n_coeffs(p)
        sizes = [n]
        if args.stream_mb > 0:
            ns = int(np.ceil(args.stream_mb * 1e6 / S1.nbytes))
            if ns > n:
                sizes.append(ns)
        for N in sizes:
            single = np.repeat(S1[None], N, axis=0)
            double = np.repeat(D1[None], N, axis=0)
            f = rng.standard_normal((N, 3, C))
            g = rng.standard_normal((N, 3, C))
            for layers in ("S", "S+D"):
                lp = SimpleNamespace(self_ops=SimpleNamespace(single=single, double=double),
                                     want_double=layers == "S+D", lam=np.full(N, 0.5))
                nbytes = single.nbytes * (2 if layers == "S+D" else 1)
                cb, gb, t = bw.paired(lambda: LayerPotentials.self_part(lp, f, g), args.rounds, args.repeat)
                rate = nbytes / t
                print(f"{p:>3} {N:>5} {layers:>6} {nbytes / 1e6:>8.1f} {t / N * 1e6:>11.1f} {rate / 1e9:>6.1f} "
                      f"{cb / 1e9:>9.1f} {rate / cb:>9.2f} {rate / gb:>9.2f}", flush=True)
            del single, double
    print(f"# {loadavg()}; the batches of up to 32 MB (p = 8, N = 64) fit in the L3 cache: "
          "their 'bandwidth' is partly cache bandwidth")


if __name__ == "__main__":
    main()
