"""Measure this machine's cost-model constants (vesflow.calibration) and write its calibration file.

One thread, process CPU time, best of --repeat.  What is measured (the names of vesflow.calibration):

    forces_s, self_setup_s, pc_setup_s, direct_s_per_pair
        benchmarks/cost_model.py's measurement at each --degrees (the accuracy-cost pair after one
        step): forces per vesicle per iteration fitted a + b p^3, the self operator's and the
        block preconditioner's set-up per vesicle fitted t16 (p / 16)^e, the direct Stokeslet
        sum per pair (median)
    self_gemv_bytes_per_s
        the batched GEMV of N = 64 self operators at the largest degree (SelfOperators.apply)
    near_s_per_eval
        the near correction of two close oblate vesicles at the largest degree
        (LayerPotentials._near_correct) over its near pairs x 9 x Mq kernel evaluations
    fmm_s_per_point
        fmm3dpy's Stokes FMM (FarField backend "fmm") on 27 unit spheres at p = 8, q = 16, per point,
        at eps 1e-6, 1e-8, 1e-10 (when fmm3dpy imports; else the defaults are kept)
    ewald
        the periodic Ewald sum of 27 unit spheres (p = 8, q = 16, tol 1e-6, own vesicle "smooth")
        split into its parts at 3 cutoffs: real space = pair x pairs + target x targets, the two
        NUFFTs = nufft_point x width^3 x points + fft_point x (FFT work), k space = mode x modes,
        least squares; own_pair and fft_growth keep the defaults' ratio and exponent

The calibration changes `vesflow check`'s predicted times only, never a run's choices (docs/
explanation/calibration.md).  Run it alone on the machine:

    flock /tmp/bench.lock env OMP_NUM_THREADS=1 .venv/bin/python benchmarks/calibrate.py
    .venv/bin/python benchmarks/calibrate.py --degrees 8 12 -o /tmp/calibration.json --repeat 2
"""
import argparse
import dataclasses
import math
import os
import platform
import sys
import time

from vesflow.threads import early_environment  # noqa: E402
early_environment()

import numpy as np  # noqa: E402

import cost_model  # noqa: E402  (benchmarks/cost_model.py)
from far_field import scene as sphere_scene  # noqa: E402  (benchmarks/far_field.py)
from vesflow import calibration, costs, shapes, sph, threads  # noqa: E402
from vesflow.layerpot import ewald, far  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials  # noqa: E402
from vesflow.layerpot.singular import SelfOperators  # noqa: E402
from vesflow.surface import Surface  # noqa: E402


def best_cpu(fn, repeat):
    """Smallest process CPU seconds of `repeat` calls (one warm-up call first); and the last result."""
    out = fn()
    best = math.inf
    for _ in range(repeat):
        t = time.process_time()
        out = fn()
        best = min(best, time.process_time() - t)
    return best, out


def gemv_bytes_per_s(p, repeat, n=64):
    C3 = 3 * sph.n_coeffs(p)
    rng = np.random.default_rng(0)
    ops = rng.standard_normal((n, C3, C3))
    x = rng.standard_normal((n, 3, C3 // 3))
    t, _ = best_cpu(lambda: SelfOperators.apply(ops, x), 3 * repeat)
    return ops.nbytes / t


def near_seconds_per_eval(p, repeat):
    c = np.stack([shapes.make_shape("oblate", p, center=(x, 0.0, 0.0), reduced_volume=0.85) for x in (-1.02, 1.02)])
    lp = LayerPotentials(Surface(c, p))
    rng = np.random.default_rng(1)
    f = rng.standard_normal((2, 3, sph.n_coeffs(p)))
    u_self = lp.self_part(f)
    fw, _ = lp._densities(f, None)
    vals = np.zeros((lp.trg.shape[0], 3))
    t, _ = best_cpu(lambda: lp._near_correct(vals.copy(), lp.near, lp.trg, fw, None, u_self, None), 3 * repeat)
    return t / (lp.n_near_pairs * costs.NEAR_EVALS * lp.Tq.npts), lp.n_near_pairs


def fmm_seconds_per_point(repeat, n=27, p=8, q=16):
    src, sid, trg, tid, f_w, _, _ = sphere_scene(n, p, q)
    out = []
    for eps in (1e-6, 1e-8, 1e-10):
        ff = far.FarField(src, sid, trg, tid, backend="fmm", eps=eps, double_layer=False)
        t, _ = best_cpu(lambda: ff.evaluate(f_w=f_w), repeat)
        out.append((eps, t / (src.shape[0] + trg.shape[0])))
    return tuple(out)


def ewald_constants(repeat, n=27, p=8, q=16, tol=1e-6):
    """The Ewald weights fitted to the parts at three cutoffs (module docstring)."""
    src, sid, trg, tid, f_w, _, _ = sphere_scene(n, p, q)
    period = 2.5 * int(np.ceil(n ** (1 / 3)))
    src, trg = src + 1.25, trg + 1.25
    own_skip = (src.shape[0] // n, 4.0 * math.pi)
    rc0 = ewald.choose_params(tol, np.concatenate([src, trg]), period, src.shape[0], trg.shape[0], 1, 3, own_skip).rc
    real_rows, real_t, nufft_rows, nufft_t, kspace = [], [], [], [], []
    for rc in (0.7 * rc0, rc0, min(1.4 * rc0, 0.49 * period)):
        pr = ewald.make_params(tol, ewald._exponents(math.log(1 / tol), False)[0] / rc, rc, np.concatenate([src, trg]),
                               period, double_layer=False)
        es = ewald.EwaldSum(src, sid, trg, tid, tol=tol, period=period, params=pr, own="smooth", own_skip=own_skip,
                            threads=1)
        es.evaluate(f_w=f_w)                                     # cell lists, plans
        t_real, _ = best_cpu(lambda: es.real_space(f_w), repeat)
        c = np.zeros((2, src.shape[0]), dtype=np.complex128)     # packed as EwaldSum.fourier
        c.real = f_w.T[0::2]
        c.imag[:1] = f_w.T[1::2]
        t1, P = best_cpu(lambda: es._nufft.type1(c), repeat)
        P = P.reshape((-1,) + tuple(pr.modes))
        W = np.empty((2,) + P.shape[1:], dtype=np.complex128)
        t_k, _ = best_cpu(lambda: ewald._kernels.kspace_apply(P, es._psi, es._k[0], es._k[1], es._k[2], True, False,
                                                               1.0 / float(np.prod(pr.period)), W), repeat)
        t2, _ = best_cpu(lambda: es._nufft.type2(W), repeat)
        # the counts of ewald._predicted_parts (single layer: 2 packed type-1 transforms, 2 type-2)
        pairs = max(0.0, trg.shape[0] * src.shape[0] * ewald._pair_fraction(pr)
                    - trg.shape[0] * ewald.own_pairs_inside(pr.rc, *own_skip))
        m = float(np.prod(pr.modes))
        fine = 3.4 * m
        fft_work = fine * math.log2(max(fine, 2.0)) * (fine / 1e7) ** calibration.DEFAULTS.ewald["fft_growth"]
        wd = ewald._kernel_width(pr.nufft_eps) ** 3
        real_rows.append([pairs, trg.shape[0]])
        real_t.append(t_real)
        nufft_rows.append([wd * (2 * src.shape[0] + 2 * trg.shape[0]), 4 * fft_work])
        nufft_t.append(t1 + t2)
        kspace.append(t_k / (m * 4))
        print(f"#   ewald rc {rc:.3f} modes {pr.modes}: real {t_real:.3f} s, type 1 + 2 {t1 + t2:.3f} s, "
              f"k space {t_k:.3f} s", flush=True)
    d = calibration.DEFAULTS.ewald
    pair, target = _nonneg_lstsq(real_rows, real_t, [d["pair"], d["target"]])
    nufft_point, fft_point = _nonneg_lstsq(nufft_rows, nufft_t, [d["nufft_point"], d["fft_point"]])
    return {"pair": pair, "target": target, "own_pair": pair * d["own_pair"] / d["pair"], "nufft_point": nufft_point,
            "fft_point": fft_point, "fft_growth": d["fft_growth"], "mode": float(np.median(kspace))}


def _nonneg_lstsq(rows, t, defaults):
    """x > 0 with t ~ rows @ x, least squares relative to each t; when the fit gives a
    non-positive term (too few or too alike measurements), the defaults scaled to the data."""
    R, t = np.asarray(rows, dtype=float), np.asarray(t, dtype=float)
    x = np.linalg.lstsq(R / t[:, None], np.ones(len(t)), rcond=None)[0]
    if np.all(x > 0):
        return [float(v) for v in x]
    d = np.asarray(defaults, dtype=float)
    return [float(v) for v in d * np.median(t / (R @ d))]


def _fmt(v):
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return f"{v:.3g}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--degrees", type=int, nargs="+", default=[8, 12, 16])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("-o", "--output", default=calibration.path(), help="the calibration file (default %(default)s)")
    a = ap.parse_args(argv)
    if len(a.degrees) < 2:
        ap.error("--degrees: give at least two degrees (the fits of the set-up times)")
    threads.configure(1)
    t0 = time.process_time()
    print(f"# calibration of {platform.node()}, one thread, process CPU (best of {a.repeat}); load "
          + " ".join(f"{x:.2f}" for x in os.getloadavg()), flush=True)
    rows = []
    for p in a.degrees:
        r = cost_model.measure(p, a.repeat)
        rows.append(r)
        print(f"#   p {p:2d}: S set-up {r['self']:.4f} s, block + LU {r['pc']:.4f} s, forces {r['forces']:.2e} s "
              f"per vesicle; direct {r['pair'] * 1e9:.2f} ns per pair", flush=True)
    ps = np.array([r["p"] for r in rows], dtype=float)
    b, a0 = np.polyfit(ps ** 3, [r["forces"] for r in rows], 1)
    pmax = max(a.degrees)
    near, n_pairs = near_seconds_per_eval(pmax, a.repeat)
    print(f"#   near correction: {near * 1e9:.2f} ns per evaluation ({n_pairs} near pairs, p = {pmax})", flush=True)
    kw = dict(forces_s=(float(max(a0, 1e-7)), float(max(b, 1e-12))),
              self_setup_s=cost_model.fit_power(ps, [r["self"] for r in rows]),
              pc_setup_s=cost_model.fit_power(ps, [r["pc"] for r in rows]),
              direct_s_per_pair=float(np.median([r["pair"] for r in rows])),
              self_gemv_bytes_per_s=gemv_bytes_per_s(pmax, a.repeat), near_s_per_eval=near,
              ewald=ewald_constants(a.repeat))
    if far._have_fmm():
        kw["fmm_s_per_point"] = fmm_seconds_per_point(a.repeat)
    cal = dataclasses.replace(calibration.DEFAULTS, **kw)
    print("# constant: this machine (defaults)")
    for name, v in cal.constants().items():
        print(f"  {name}: {_fmt(v)}  ({_fmt(calibration.DEFAULTS.constants()[name])})")
    path = calibration.write(cal, a.output, machine=platform.node(), written=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                             command="benchmarks/calibrate.py " + " ".join(argv if argv is not None else sys.argv[1:]),
                             load=list(os.getloadavg()), cpu_seconds=round(time.process_time() - t0, 1))
    print(f"# written {path} ({time.process_time() - t0:.0f} s CPU): `vesflow check` predicts with it "
          f"(or with ${calibration.ENV})")


if __name__ == "__main__":
    main()
