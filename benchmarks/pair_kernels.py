"""CPU time per pair of the compiled pair sums on each vector path this CPU runs (one thread).

    direct      stokes.stokeslet_sum / stresslet_sum: --targets targets against --sources sources
                (the far field's direct backend, the Ewald own-vesicle sums), ns per pair
    near        stokes.stokeslet_sum_blocks, stresslet_sum_blocks, stokeslet_stresslet_sum_blocks:
                blocks of 9 targets against one vesicle of --m sources (the near correction),
                ns per kernel evaluation (one target and one source; both layers: one evaluation
                of each)
    ewald       the real-space sum of the spectral Ewald method (EwaldSum.real_space, free space,
                --ves clusters of 600 points, single layer and both layers), ns per pair
                inside the cutoff (own vesicle excluded)

Process CPU time, best of --repeat (the machine may be loaded: take the best of several runs).
The paths (vesflow._kernels.paths): each one the CPU runs, or those given by --paths.

    flock /tmp/bench.lock .venv/bin/python benchmarks/pair_kernels.py
    .venv/bin/python benchmarks/pair_kernels.py --paths avx2 --repeat 5
"""
import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from scipy.spatial import cKDTree  # noqa: E402

from vesflow._kernels import ewald as ek  # noqa: E402
from vesflow._kernels import paths, stokes  # noqa: E402
from vesflow.layerpot import ewald  # noqa: E402


def best_cpu(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t = time.process_time()
        fn()
        best = min(best, time.process_time() - t)
    return best


def direct(n_src, n_trg, repeat, rng):
    """ns per pair of the Stokeslet and the stresslet sums, all sources to all targets."""
    src = rng.uniform(-1, 1, (n_src, 3))
    trg = rng.uniform(-1.5, 1.5, (n_trg, 3))
    f, nw, g = rng.standard_normal((3, n_src, 3))
    out = np.zeros_like(trg)
    ts = best_cpu(lambda: stokes.stokeslet_sum(src, f, trg, out), repeat)
    td = best_cpu(lambda: stokes.stresslet_sum(src, nw, g, trg, out), repeat)
    return ts / (n_src * n_trg) * 1e9, td / (n_src * n_trg) * 1e9


def near(m, n_ves, n_blocks, repeat, rng, K=9):
    """ns per kernel evaluation of the block sums: n_blocks blocks of K targets, each against
    one of n_ves vesicles of m sources (noisy unit spheres side by side)."""
    sizes = np.full(n_ves, m)
    off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    u = rng.standard_normal((n_ves * m, 3))
    src = u / np.linalg.norm(u, axis=1, keepdims=True) + np.repeat(2.2 * np.arange(n_ves), m)[:, None] * [1, 0, 0]
    f, nw, g = rng.standard_normal((3, n_ves * m, 3))
    ves = rng.integers(0, n_ves, n_blocks).astype(np.int64)
    trg = src[off[ves]][:, None, :] + rng.uniform(-0.1, 0.1, (n_blocks, K, 3))
    trg = np.ascontiguousarray(trg)
    ps, pf, pn, pg = (stokes.planar(a, off) for a in (src, f, nw, g))
    out = np.zeros_like(trg)
    evals = n_blocks * K * m
    ts = best_cpu(lambda: stokes.stokeslet_sum_blocks(ps, pf, off, trg, ves, out), repeat)
    td = best_cpu(lambda: stokes.stresslet_sum_blocks(ps, pn, pg, off, trg, ves, out), repeat)
    tb = best_cpu(lambda: stokes.stokeslet_stresslet_sum_blocks(ps, pf, pn, pg, off, trg, ves, out), repeat)
    return ts / evals * 1e9, td / evals * 1e9, tb / evals * 1e9


def real_space(n_ves, repeat, rng, per=600):
    """ns per pair inside rc of the Ewald real-space sum (single layer; both layers)."""
    c = rng.uniform(0, 4.0, (n_ves, 3))
    src = (c[:, None, :] + 0.5 * rng.uniform(-1, 1, (n_ves, per, 3))).reshape(-1, 3)
    sid = np.repeat(np.arange(n_ves), per)
    f, nw, g = rng.standard_normal((3, src.shape[0], 3))
    rc = 0.6
    params = ewald.make_params(1e-8, ewald._exponents(np.log(1e8))[0] / rc, rc, src)
    es = ewald.EwaldSum(src, sid, src, sid, params=params, double_layer=True, own="smooth")
    es.real_space(f)                                     # cell lists, once per geometry
    tree = cKDTree(src)
    pairs = tree.query_ball_point(src, rc, return_length=True).sum()
    for v in range(n_ves):                               # minus the own vesicle's pairs
        t = cKDTree(src[sid == v])
        pairs -= t.query_ball_point(src[sid == v], rc, return_length=True).sum()
    t1 = best_cpu(lambda: es.real_space(f), repeat)
    t2 = best_cpu(lambda: es.real_space(f, nw, g), repeat)
    return t1 / pairs * 1e9, t2 / pairs * 1e9


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--paths", nargs="+", default=None, choices=paths.PATHS,
                    help="vector paths to measure (default: each one this CPU runs)")
    ap.add_argument("--sources", type=int, default=4000)
    ap.add_argument("--targets", type=int, default=1000)
    ap.add_argument("--m", type=int, default=2112, help="sources per vesicle of the near blocks (q = 32)")
    ap.add_argument("--blocks", type=int, default=200)
    ap.add_argument("--ves", type=int, default=16, help="clusters of the Ewald real-space sum")
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    best = paths.PATHS.index(stokes.set_vector_path(True))
    todo = a.paths or list(paths.PATHS[:best + 1])[::-1]
    print(f"# pair kernels, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}, process CPU, best of {a.repeat}; "
          f"best path of this CPU: {paths.PATHS[best]}; load " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    print(f"# direct: {a.targets} targets x {a.sources} sources; near: {a.blocks} blocks of 9 targets x {a.m} sources")
    print(f"# {'path':8s} {'direct S':>9s} {'direct D':>9s} {'near S':>9s} {'near D':>9s} {'near S+D':>9s} {'ewald S':>9s} {'ewald S+D':>9s}   ns")
    try:
        for path in todo:
            stokes.set_vector_path(path)
            rng = np.random.default_rng(1)
            ds, dd = direct(a.sources, a.targets, a.repeat, rng)
            ns, nd, nb = near(a.m, 8, a.blocks, a.repeat, rng)
            ek.set_vector_path(path)
            es, ed = real_space(a.ves, a.repeat, rng)
            print(f"  {stokes.vector_path():8s} {ds:9.2f} {dd:9.2f} {ns:9.2f} {nd:9.2f} {nb:9.2f} {es:9.2f} {ed:9.2f}",
                  flush=True)
    finally:
        stokes.set_vector_path(True)
        ek.set_vector_path(True)


if __name__ == "__main__":
    main()
