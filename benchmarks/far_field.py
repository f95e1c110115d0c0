"""Far-field backends: time per evaluation versus the number of vesicles (docs/far_field.md).

Unit spheres on a jittered cubic lattice (centre spacing 2.5, no overlaps), targets on the
p-grid (M = 2p(p+1) per vesicle), sources on the q-grid (2q(q+1) per vesicle) with the
Gauss-Legendre area weights of docs/conventions.md, random densities.  For each number of
vesicles N and each backend of vesflow.layerpot.far, the time of one evaluation (best of
``--repeat``; set-up of the FarField object timed separately), the FMM error against the
direct sum where both ran, and the growth exponent fitted to log(time) vs log(N).
A case is skipped (and reported) when its predicted time, extrapolated from the previous
size with N^2 (direct) or N^1.2 (FMM), exceeds ``--max-seconds`` or would take the run past
``--budget`` seconds in total.

    OMP_NUM_THREADS=2 python benchmarks/far_field.py                  # the run of docs/far_field.md
    python benchmarks/far_field.py --sizes 8 16 --layer double --eps 1e-6
"""
import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from vesflow.layerpot import far  # noqa: E402


def sphere_grid(q):
    """Unit-sphere q-grid (docs/conventions.md): points (M, 3), area weights (M,)."""
    x, w = np.polynomial.legendre.leggauss(q + 1)
    order = np.argsort(-x)
    x, w = x[order], w[order]
    theta = np.arccos(x)
    phi = np.pi * np.arange(2 * q) / q
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    pts = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    wts = np.repeat(w * np.pi / q, 2 * q)
    return pts, wts


def scene(nves, p, q, seed=0):
    """Sources/targets of ``nves`` unit spheres on a jittered lattice."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(nves ** (1 / 3)))
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:nves]
    centres = 2.5 * ijk + rng.uniform(-0.2, 0.2, (nves, 3))
    tp, _ = sphere_grid(p)
    sp, sw = sphere_grid(q)
    trg = (centres[:, None, :] + tp[None]).reshape(-1, 3)
    src = (centres[:, None, :] + sp[None]).reshape(-1, 3)
    trg_id = np.repeat(np.arange(nves), tp.shape[0])
    src_id = np.repeat(np.arange(nves), sp.shape[0])
    w = np.tile(sw, nves)
    f_w = rng.standard_normal(src.shape) * w[:, None]
    nw = (src - np.repeat(centres, sp.shape[0], axis=0)) * w[:, None]
    g = rng.standard_normal(src.shape)
    return src, src_id, trg, trg_id, f_w, nw, g


def _loadavg():
    try:
        return " ".join(open("/proc/loadavg").read().split()[:3])
    except OSError:
        return "n/a"


def fit_exponent(ns, ts):
    if len(ns) < 2:
        return float("nan")
    return float(np.polyfit(np.log(ns), np.log(ts), 1)[0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64, 128, 256])
    ap.add_argument("-p", type=int, default=16)
    ap.add_argument("-q", type=int, default=32)
    ap.add_argument("--eps", type=float, nargs="+", default=[far.DEFAULT_EPS],
                    help="FMM accuracies to time (one FMM column each)")
    ap.add_argument("--layer", choices=["single", "double", "both"], default="single")
    ap.add_argument("--repeat", type=int, default=2, help="timed evaluations per case (best kept) when cheap")
    ap.add_argument("--max-seconds", type=float, default=200.0,
                    help="skip a case whose predicted time per evaluation exceeds this")
    ap.add_argument("--budget", type=float, default=540.0,
                    help="skip a case that would take the whole run past this many seconds")
    args = ap.parse_args(argv)

    def densities(f_w, nw, g):
        if args.layer == "single":
            return dict(f_w=f_w)
        if args.layer == "double":
            return dict(nw=nw, g=g)
        return dict(f_w=f_w, nw=nw, g=g)

    backends = [("direct", None)] + [("fmm", e) for e in args.eps]
    names = ["direct"] + [f"fmm eps={e:g}" for e in args.eps]
    M, Q = 2 * args.p * (args.p + 1), 2 * args.q * (args.q + 1)
    print(f"# far field, {args.layer} layer, p = {args.p} (M = {M} targets/vesicle), "
          f"q = {args.q} ({Q} sources/vesicle), OMP_NUM_THREADS = {os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"{os.cpu_count()} cpus")
    print(f"# load average at start: {_loadavg()}")
    print("# times in seconds per evaluation (set-up of FarField in brackets); err = max|fmm - direct| / max|direct|")
    header = f"{'N':>5} {'targets':>8} {'sources':>8} " + " ".join(f"{n:>24}" for n in names) + "  errors"
    print(header)
    times = {n: [] for n in names}
    sizes_done = {n: [] for n in names}
    skipped = []
    t_start = time.perf_counter()
    for nves in args.sizes:
        src, src_id, trg, trg_id, f_w, nw, g = scene(nves, args.p, args.q)
        dens = densities(f_w, nw, g)
        row = f"{nves:>5} {trg.shape[0]:>8} {src.shape[0]:>8} "
        ref = None
        errs = []
        for (backend, eps), name in zip(backends, names):
            prev_n, prev_t = (sizes_done[name][-1], times[name][-1]) if times[name] else (None, None)
            if prev_n is not None:
                expo = 2.0 if backend == "direct" else 1.2
                pred = prev_t * (nves / prev_n) ** expo
                if pred > args.max_seconds or time.perf_counter() - t_start + pred > args.budget:
                    row += f"{'skipped (~%.0f s)' % pred:>24} "
                    skipped.append((nves, name, pred))
                    continue
            t0 = time.perf_counter()
            ff = far.FarField(src, src_id, trg, trg_id, backend=backend, eps=eps or far.DEFAULT_EPS)
            t_setup = time.perf_counter() - t0
            best = np.inf
            for k in range(args.repeat):
                t0 = time.perf_counter()
                u = ff.evaluate(**dens)
                dt = time.perf_counter() - t0
                best = min(best, dt)
                if dt > 5.0:
                    break
            times[name].append(best)
            sizes_done[name].append(nves)
            row += f"{'%.4g [%.2g]' % (best, t_setup):>24} "
            if backend == "direct":
                ref = u
            elif ref is not None:
                errs.append(f"{np.abs(u - ref).max() / np.abs(ref).max():.1e}")
        print(row + " " + " ".join(errs), flush=True)
    print("# fitted growth exponent t ~ N^a (all measured sizes; sizes >= 32), and the cost constants")
    threads = far._stokes.max_threads()
    for (backend, eps), name in zip(backends, names):
        ns, ts = np.array(sizes_done[name], float), np.array(times[name])
        if ns.size == 0:
            continue
        big = ns >= 32
        line = f"#   {name:>16}: a = {fit_exponent(ns, ts):.2f}; a(N>=32) = {fit_exponent(ns[big], ts[big]):.2f}; "
        if backend == "direct":
            c = ts[-1] * threads / (ns[-1] ** 2 * M * Q)
            line += f"{c * 1e9:.2f} ns per pair per thread (largest N, {threads} threads)"
        else:
            c = ts[-1] / (ns[-1] * (M + Q))
            line += f"{c * 1e6:.0f} us per point (largest N; model constant of far.py: " \
                    f"{far.predicted_seconds(Q, M, eps, 1)[1] / (M + Q) * 1e6:.0f} us)"
        print(line)
    # crossover of the fitted power laws (largest sizes) for this p, q
    if len(sizes_done["direct"]) >= 2:
        for (backend, eps), name in list(zip(backends, names))[1:]:
            if len(sizes_done[name]) < 2:
                continue
            nd, td = np.array(sizes_done["direct"], float), np.array(times["direct"])
            nf, tf = np.array(sizes_done[name], float), np.array(times[name])
            ad, af = fit_exponent(nd[-3:], td[-3:]), fit_exponent(nf[-3:], tf[-3:])
            if ad > af:
                ncross = np.exp((np.log(tf[-1]) - af * np.log(nf[-1]) - np.log(td[-1]) + ad * np.log(nd[-1])) / (ad - af))
                txt = f"{ncross:.0f}" if ncross < 1e5 else "> 1e5"
                print(f"# crossover direct / {name}: N ~ {txt} vesicles (fits over the 3 largest sizes)")
    nmodel = next((n for n in range(1, 100000)
                   if far.choose_backend(n * Q, n * M, "auto", far.DEFAULT_EPS) == "fmm"), None)
    print(f"# far.py 'auto' (eps {far.DEFAULT_EPS:g}, {threads} threads) switches to the FMM at N = {nmodel}")
    for nves, name, pred in skipped:
        print(f"# skipped N = {nves} {name}: predicted {pred:.0f} s per evaluation > --max-seconds {args.max_seconds:g}")
    print(f"# load average at end: {_loadavg()}; total benchmark time {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
