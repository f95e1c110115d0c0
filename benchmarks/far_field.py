"""Far-field backends: time per evaluation versus the number of vesicles (docs/explanation/far_field.md).

Unit spheres on a jittered cubic lattice (centre spacing 2.5, no overlaps), targets on the
p-grid (M = 2p(p+1) per vesicle), sources on the q-grid (2q(q+1) per vesicle) with the
Gauss-Legendre area weights of docs/explanation/conventions.md, random densities.  For each number of
vesicles N and each backend of vesflow.layerpot.far, the time of one evaluation (best of
``--repeat``; set-up of the FarField object timed separately), the FMM error against the
direct sum where both ran, the growth exponent fitted to log(time) vs log(N) (least squares),
and the crossover N above which the FMM is faster: from the measured wall times where both
were measured on either side, else from the power laws fitted to the 3 largest sizes (wall and
"ideal" = CPU / threads).  One evaluation is what a GMRES iteration costs in the far field
(single layer of all vesicles' q-grid sources at all p-grid targets, own vesicle excluded).
A case is skipped (and reported) when its predicted time, extrapolated from the previous
size with N^2 (direct) or N^1.2 (FMM), exceeds ``--max-seconds`` or would take the run past
``--budget`` seconds in total.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/far_field.py       # the run of docs/explanation/far_field.md
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/far_field.py       # direct on 2 threads (fmm stays serial)
    python benchmarks/far_field.py --sizes 8 16 --layer double --eps 1e-6
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/far_field.py --eps 1e-6 --sizes 8 16 32 64 128 256 512 1024

Backends: direct, fmm and ewald (free space) at each ``--eps``.  A case predicted (far.py's
cost model, scaled by measured / model of the previous size) above ``--max-seconds`` or past
``--budget`` is not run: its column shows the model, marked "(model)".
"""
import argparse
import os
import time

import numpy as np


from vesflow.layerpot import far  # noqa: E402


def sphere_grid(q):
    """Unit-sphere q-grid (docs/explanation/conventions.md): points (M, 3), area weights (M,)."""
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
    ap.add_argument("--max-seconds", type=float, default=120.0,
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

    backends = [("direct", None)] + [("fmm", e) for e in args.eps] + [("ewald", e) for e in args.eps]
    names = ["direct"] + [f"fmm eps={e:g}" for e in args.eps] + [f"ewald eps={e:g}" for e in args.eps]
    threads = far._stokes.max_threads()
    used = {"direct": threads, "fmm": 1, "ewald": threads}      # the fmm3dpy wheel is serial
    M, Q = 2 * args.p * (args.p + 1), 2 * args.q * (args.q + 1)
    print(f"# far field, {args.layer} layer, p = {args.p} (M = {M} targets/vesicle), "
          f"q = {args.q} ({Q} sources/vesicle), {threads} OpenMP threads, {os.cpu_count()} cpus")
    print(f"# load average at start: {_loadavg()}")
    print("# seconds per evaluation: wall / cpu (process CPU time; 'ideal' = cpu / threads used,")
    print("# the wall time on an otherwise idle machine); [set-up of FarField]; err = max|fmm - direct| / max|direct|")
    print(f"{'N':>5} {'targets':>8} {'sources':>8} " + " ".join(f"{n:>26}" for n in names) + "  errors")
    wall = {n: [] for n in names}
    ideal = {n: [] for n in names}
    done = {n: [] for n in names}
    model = {n: [] for n in names}
    skipped = []
    t_start = time.perf_counter()
    for nves in args.sizes:
        src, src_id, trg, trg_id, f_w, nw, g = scene(nves, args.p, args.q)
        dens = densities(f_w, nw, g)
        row = f"{nves:>5} {trg.shape[0]:>8} {src.shape[0]:>8} "
        ref = None
        errs = []
        own = nves * (trg.shape[0] // nves) * (src.shape[0] // nves)
        for (backend, eps), name in zip(backends, names):
            # far.py's cost model (one thread for direct and ewald, as the CPU column), scaled by
            # measured / model of the previous size of this backend
            e_ = eps or far.DEFAULT_EPS
            if backend == "ewald":
                pred = far.predicted_ewald(np.concatenate([src, trg]), src.shape[0], trg.shape[0], own, e_, 1)[0]
            else:
                pred = far.predicted_seconds(src.shape[0], trg.shape[0], e_, 1)[0 if backend == "direct" else 1]
            if backend == "direct":
                pred *= (nves - 1) / nves
            model[name].append((nves, pred))
            if done[name]:
                ratio = ideal[name][-1] * used[backend] / dict(model[name])[done[name][-1]]
                if pred * ratio > args.max_seconds or time.perf_counter() - t_start + pred * ratio > args.budget:
                    row += f"{'~%.3g (model)' % pred:>26} "
                    skipped.append((nves, name, pred))
                    continue
            t0 = time.perf_counter()
            ff = far.FarField(src, src_id, trg, trg_id, backend=backend, eps=eps or far.DEFAULT_EPS,
                              double_layer=args.layer != "single")
            t_setup = time.perf_counter() - t0
            best, best_cpu = np.inf, np.inf
            for _ in range(args.repeat):
                t0, c0 = time.perf_counter(), time.process_time()
                u = ff.evaluate(**dens)
                dt, dc = time.perf_counter() - t0, time.process_time() - c0
                best, best_cpu = min(best, dt), min(best_cpu, dc)
                if dt > 5.0:
                    break
            wall[name].append(best)
            ideal[name].append(best_cpu / used[backend])
            done[name].append(nves)
            row += f"{'%.3g / %.3g [%.2g]' % (best, best_cpu, t_setup):>26} "
            if backend == "direct":
                ref = u
            elif ref is not None:
                errs.append(f"{np.abs(u - ref).max() / np.abs(ref).max():.1e}")
        auto = far.FarField(src, src_id, trg, trg_id, backend="auto", eps=args.eps[0],
                            double_layer=args.layer != "single").backend
        print(row + " " + " ".join(errs) + f"  auto: {auto}  (load {_loadavg()})", flush=True)

    print("# fitted growth exponent t ~ N^a of the wall / ideal times (all sizes; sizes >= 32), cost constants")
    for (backend, eps), name in zip(backends, names):
        ns = np.array(done[name], float)
        if ns.size == 0:
            continue
        tw, ti = np.array(wall[name]), np.array(ideal[name])
        big = ns >= 32
        line = (f"#   {name:>14}: a = {fit_exponent(ns, tw):.2f} / {fit_exponent(ns, ti):.2f}; "
                f"a(N>=32) = {fit_exponent(ns[big], tw[big]):.2f} / {fit_exponent(ns[big], ti[big]):.2f}; ")
        if backend == "direct":
            c = ti[-1] * threads / (ns[-1] ** 2 * M * Q)
            line += f"{c * 1e9:.2f} ns CPU per pair (far.py model: {far.DIRECT_SECONDS_PER_PAIR * 1e9:.2f})"
        elif backend == "fmm":
            c = ti[-1] / (ns[-1] * (M + Q))
            mod = far.predicted_seconds(Q, M, eps, 1)[1] / (M + Q)
            line += f"{c * 1e6:.0f} us CPU per point (far.py model: {mod * 1e6:.0f})"
        else:
            mod = dict(model[name])[ns[-1]]
            line += f"measured / model at N = {ns[-1]:.0f}: {ti[-1] * threads / mod:.2f}"
        print(line)
    # crossover: measured (log-linear interpolation between sizes where both ran), else power laws
    # fitted to the 3 largest sizes of each backend
    nd = np.array(done["direct"], float)
    for (backend, eps), name in list(zip(backends, names))[1:]:
        nf = np.array(done[name], float)
        if backend == "ewald":
            fm = f"fmm eps={eps:g}"
            both = [n for n in done[name] if n in done[fm]]
            for n in both:
                print(f"# N = {n:.0f}: ewald {dict(zip(done[fm], ideal[fm]))[n] / dict(zip(done[name], ideal[name]))[n]:.1f}x "
                      f"faster than fmm (ideal times, eps {eps:g})")
            for n, tm in model[name]:
                if n not in both:
                    te = dict(zip(done[name], ideal[name])).get(n)
                    tf = dict(zip(done[fm], ideal[fm])).get(n, dict(model[fm])[n])
                    how = ("ewald measured, fmm " + ("measured" if n in done[fm] else "model")) if te else "models"
                    print(f"# N = {n:.0f}: ewald {tf / (te or tm):.1f}x faster than fmm ({how}, eps {eps:g})")
        if nd.size < 2 or nf.size < 2:
            continue
        both = [n for n in nd if n in nf]
        wd = dict(zip(nd, wall["direct"]))
        wf = dict(zip(nf, wall[name]))
        meas = None
        for n0, n1 in zip(both[:-1], both[1:]):
            r0, r1 = np.log(wf[n0] / wd[n0]), np.log(wf[n1] / wd[n1])
            if r0 > 0 >= r1:
                meas = np.exp(np.log(n0) + r0 / (r0 - r1) * (np.log(n1) - np.log(n0)))
        if both and wf[both[0]] <= wd[both[0]]:
            print(f"# crossover direct ({threads} threads) / {name}: {backend} is already faster at N = {both[0]:.0f}")
        elif meas is not None:
            print(f"# crossover direct ({threads} threads) / {name}, measured wall times: N ~ {meas:.0f} vesicles")
        for kind, times in (("wall", wall), ("ideal", ideal)):
            td, tf = np.array(times["direct"]), np.array(times[name])
            ad, af = fit_exponent(nd[-3:], td[-3:]), fit_exponent(nf[-3:], tf[-3:])
            if ad > af:
                lnc = (np.log(tf[-1]) - af * np.log(nf[-1]) - np.log(td[-1]) + ad * np.log(nd[-1])) / (ad - af)
                txt = f"{np.exp(lnc):.0f}" if lnc < np.log(1e5) else "> 1e5"
                print(f"# crossover direct ({threads} threads) / {name}, power laws of the {kind} times "
                      f"(3 largest sizes: a = {ad:.2f} / {af:.2f}): N ~ {txt} vesicles")
    for eps in args.eps:
        nmodel = next((n for n in range(1, 100000)
                       if far.choose_backend(n * Q, n * M, "auto", eps) == "fmm"), None)
        print(f"# far.py 'auto' at eps {eps:g} with {threads} threads, without ewald, switches to the FMM at N = {nmodel}")
        prev, switches = None, []
        for n in sorted(set(np.geomspace(2, 2048, 45).astype(int))):
            src, src_id, trg, trg_id = scene(n, args.p, args.q)[:4]
            t_e = far.predicted_ewald(np.concatenate([src, trg]), src.shape[0], trg.shape[0],
                                      n * M * Q, eps, double_layer=args.layer != "single")[0]
            b = far.choose_backend(src.shape[0], trg.shape[0], "auto", eps, t_e)
            if b != prev:
                switches.append(f"{b} from N = {n}")
            prev = b
        print(f"# far.py 'auto' at eps {eps:g} with {threads} threads (this scene): " + ", ".join(switches))
    for nves, name, pred in skipped:
        print(f"# skipped N = {nves} {name}: predicted {pred:.0f} s (limits: --max-seconds "
              f"{args.max_seconds:g} per case, --budget {args.budget:g} in total)")
    print(f"# load average at end: {_loadavg()}; total benchmark time {time.perf_counter() - t_start:.0f} s")

if __name__ == "__main__":
    main()
