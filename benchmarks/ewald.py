"""Spectral Ewald far field against the direct sum and the FMM (docs/explanation/far_field.md, "Spectral Ewald").

The scene of benchmarks/far_field.py (unit spheres on a jittered cubic lattice of spacing 2.5,
p-grid targets, q-grid sources with area weights, random densities); for each number of
vesicles N: seconds per evaluation (one GMRES iteration's far field, own vesicle excluded) of
the ewald backend (free space, parameters chosen from --tol), its set-up, its parts (real
space incl. the own-vesicle subtraction; Fourier: NUFFTs + k-space multiplication), its error
against the direct sum where that ran, and the direct sum and fmm where they fit in
--max-seconds (else the prediction of far.py's cost model, marked "model").  Times are wall /
process CPU.  A fitted growth exponent and the backend 'auto' picks are printed at the end.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ewald.py                  # docs/explanation/far_field.md
    python benchmarks/ewald.py --sizes 8 64 --tol 1e-6 --layer double --nufft finufft
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/ewald.py --periodic   # the lattice in its periodic cube

``--periodic``: the cube of side 2.5 ceil(N^(1/3)) (the lattice's period), ewald only.
"""
import argparse
import os
import time

import numpy as np


from far_field import fit_exponent, scene  # noqa: E402
from vesflow.layerpot import far  # noqa: E402
from vesflow.layerpot import ewald  # noqa: E402


def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32, 64, 128, 256, 512])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--q", type=int, default=32)
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--layer", choices=("single", "double"), default="single")
    ap.add_argument("--nufft", choices=ewald.NUFFT_LIBS, default=ewald.DEFAULT_NUFFT)
    ap.add_argument("--max-seconds", type=float, default=30.0, help="skip a direct / fmm case predicted longer")
    ap.add_argument("--budget", type=float, default=400.0, help="stop starting cases after this many seconds")
    ap.add_argument("--periodic", action="store_true", help="triply periodic cube of the lattice (ewald only)")
    a = ap.parse_args(argv)
    threads = far._stokes.max_threads()
    t_start = time.perf_counter()
    print(f"# far field ({a.layer} layer), p = {a.p}, q = {a.q}, tol = {a.tol:g}, nufft = {a.nufft}, "
          f"{threads} OpenMP threads, {os.cpu_count()} cpus; load {os.getloadavg()[0]:.2f}")
    print("# seconds per evaluation: wall / cpu; ewald [set-up] (real + fourier cpu) xi rc modes; "
          "err = max|ewald - direct| / max|direct|")
    rows = []
    ratio = 1.0                   # measured / model cpu of the last ewald case
    for n in a.sizes:
        if time.perf_counter() - t_start > a.budget:
            print(f"# N = {n}: budget of {a.budget:g} s used up, stopping")
            break
        src, sid, trg, tid, f_w, nw, g = scene(n, a.p, a.q)
        dens = dict(f_w=f_w) if a.layer == "single" else dict(nw=nw, g=g)
        own = n * (trg.shape[0] // n) * (src.shape[0] // n)
        period = 2.5 * int(np.ceil(n ** (1 / 3))) if a.periodic else None
        if period is not None:                   # the jittered lattice inside [0, period)^3
            src, trg = src + 1.25, trg + 1.25
        t_model, _ = far.predicted_ewald(np.concatenate([src, trg]), src.shape[0], trg.shape[0], own, a.tol, 1,
                                         period=period)
        if t_model * ratio > 4 * a.max_seconds:
            print(f"{n:5d}  ewald skipped: predicted {t_model * ratio:.0f} s")
            continue
        es, sw, sc = timed(lambda: ewald.EwaldSum(src, sid, trg, tid, tol=a.tol, nufft=a.nufft, period=period,
                                                  double_layer=a.layer == "double"))
        u, ew, ec = timed(lambda: es.evaluate(**dens))          # first call: NUFFT plans
        u, ew2, ec2 = timed(lambda: es.evaluate(**dens))
        ew, ec = min(ew, ew2), min(ec, ec2)
        _, _, rc_ = timed(lambda: es.real_space(**dens))
        _, _, fc_ = timed(lambda: es.fourier(**dens))
        ratio = ec / max(t_model, 1e-9)
        pr = es.params
        td_model, tf_model = far.predicted_seconds(src.shape[0], trg.shape[0], a.tol, threads)
        line = (f"{n:5d} {trg.shape[0]:8d} {src.shape[0]:8d}  ewald {ew:7.2f} / {ec:7.2f} [{sw:.2f}] "
                f"({rc_:.2f} + {fc_:.2f}) xi {pr.xi:.2f} rc {pr.rc:.2f} modes {pr.modes}, model {t_model:.2f}")
        err = None
        if period is not None:
            print(line + f" | period {period:g}  (load {os.getloadavg()[0]:.2f})", flush=True)
            rows.append((n, ew, ec, err))
            continue
        if td_model < a.max_seconds:
            ff = far.FarField(src, sid, trg, tid, backend="direct")
            ref, dw, dc = timed(lambda: ff.evaluate(**dens))
            err = float(np.max(np.abs(u - ref)) / np.max(np.abs(ref)))
            line += f" | direct {dw:7.2f} / {dc:7.2f} err {err:.1e}"
        else:
            dw = dc = td_model
            line += f" | direct ~{td_model:.0f} (model)"
        if far._have_fmm() and tf_model < a.max_seconds:
            ff = far.FarField(src, sid, trg, tid, backend="fmm", eps=a.tol)
            _, fw, fc = timed(lambda: ff.evaluate(**dens))
            line += f" | fmm {fw:7.2f} / {fc:7.2f}"
        else:
            fw = fc = tf_model
            line += f" | fmm ~{tf_model:.0f} (model)"
        auto = far.FarField(src, sid, trg, tid, backend="auto", eps=a.tol).backend
        line += f" | auto: {auto}  (load {os.getloadavg()[0]:.2f})"
        print(line, flush=True)
        rows.append((n, ew, ec, err))
    if len(rows) >= 2:
        ns = [r[0] for r in rows]
        print(f"# ewald growth t ~ N^a: a = {fit_exponent(ns, [r[1] for r in rows]):.2f} (wall), "
              f"{fit_exponent(ns, [r[2] for r in rows]):.2f} (cpu), N = {ns[0]}..{ns[-1]}")
    print(f"# total {time.perf_counter() - t_start:.0f} s; load at end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
