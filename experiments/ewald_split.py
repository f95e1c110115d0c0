"""The Ewald far field (periodic, or free space with --free) split into its parts, and the cost model re-fitted from them
(docs/explanation/far_field.md, "Periodic: where the time of a large suspension goes").

The scene of benchmarks/far_field.py (unit spheres on a jittered lattice of spacing 2.5 in
their periodic cube), single layer, parameters from --tol; per part the best of --repeat
process-CPU (and wall) seconds: real space (--own subtract: own-vesicle subtraction included;
smooth, the default as in LayerPotentials: the own vesicle left out), type-1 NUFFT, k-space
multiplication, type-2 NUFFT; then the counts the cost model uses (pairs inside rc of the
uniform-density estimate, with --own smooth minus the own ones of ewald.own_pairs_inside; own
pairs; NUFFT points, modes) and the constants they imply.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.ewald_split --n 64 512 --tol 1e-6
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.ewald_split --n 512 --rc auto 1.2 1.5   # given cutoffs
"""
import argparse
import math
import os
import time

import numpy as np


from benchmarks.far_field import scene  # noqa: E402
from vesflow.layerpot import ewald  # noqa: E402


def best(fn, repeat):
    out, bw, bc = None, math.inf, math.inf
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        bw, bc = min(bw, time.perf_counter() - w), min(bc, time.process_time() - c)
    return out, bw, bc


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, nargs="+", default=[64])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--q", type=int, default=32)
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--rc", type=lambda v: None if v == "auto" else float(v), nargs="+", default=[None],
                    help="real-space cutoffs (auto: the cost model's choice)")
    ap.add_argument("--nufft", choices=ewald.NUFFT_LIBS, default=ewald.DEFAULT_NUFFT)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--free", action="store_true", help="free space (the lattice without its box)")
    ap.add_argument("--own", choices=ewald.OWN_MODES, default="smooth",
                    help="the own vesicle: left out of the real space (smooth, as LayerPotentials) or summed "
                         "and its full kernel subtracted (subtract)")
    ap.add_argument("--nufft-eps-factor", type=float, default=ewald.NUFFT_EPS_FACTOR,
                    help="NUFFT accuracy over tol (ewald.NUFFT_EPS_FACTOR)")
    a = ap.parse_args(argv)
    ewald.NUFFT_EPS_FACTOR = a.nufft_eps_factor
    print(f"# {'free-space' if a.free else 'periodic'} Ewald split, p = {a.p}, q = {a.q}, tol {a.tol:g}, nufft {a.nufft} "
          f"(eps {a.nufft_eps_factor:g} tol), "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; load {os.getloadavg()[0]:.2f}")
    for n in a.n:
        src, sid, trg, tid, f_w, nw, g = scene(n, a.p, a.q)
        period = None if a.free else 2.5 * int(np.ceil(n ** (1 / 3)))
        if period is not None:                   # the jittered lattice inside [0, period)^3
            src, trg = src + 1.25, trg + 1.25
        for rc in a.rc:
            run(a, n, src, sid, trg, tid, f_w, period, rc)


def run(a, n, src, sid, trg, tid, f_w, period, rc):
    """One cutoff (None: the cost model's), single layer: the parts, best of --repeat."""
    params = None
    if rc is not None:
        params = ewald.make_params(a.tol, ewald._exponents(math.log(1 / a.tol), False)[0] / rc, rc,
                                   np.concatenate([src, trg]), period, double_layer=False)
    own_skip = (src.shape[0] // n, 4.0 * math.pi)             # unit spheres
    es = ewald.EwaldSum(src, sid, trg, tid, tol=a.tol, period=period, nufft=a.nufft, params=params, own=a.own,
                        own_skip=own_skip)
    pr = es.params
    es.evaluate(f_w=f_w)                                     # cell lists, plans
    _, rw, rcpu = best(lambda: es.real_space(f_w), a.repeat)
    c = np.zeros((2, src.shape[0]), dtype=np.complex128)      # packed as EwaldSum.fourier
    c.real = f_w.T[0::2]
    c.imag[:1] = f_w.T[1::2]
    P, t1w, t1c = best(lambda: es._nufft.type1(c), a.repeat)
    P = P.reshape((-1,) + tuple(pr.modes))
    W = np.empty((2,) + P.shape[1:], dtype=np.complex128)
    scale = 1.0 / float(np.prod(pr.period))
    _, kw, kc = best(lambda: ewald._kernels.kspace_apply(P, es._psi, es._k[0], es._k[1], es._k[2], True, False,
                                                        scale, W), a.repeat)
    _, t2w, t2c = best(lambda: es._nufft.type2(W), a.repeat)
    vol = float(np.prod(pr.box))
    pairs = trg.shape[0] * src.shape[0] * ewald._pair_fraction(pr)
    own = n * (trg.shape[0] // n) * (src.shape[0] // n)
    if a.own == "smooth":                      # the model's pairs: the other vesicles' only
        pairs = max(pairs - trg.shape[0] * ewald.own_pairs_inside(pr.rc, *own_skip), 1.0)
        own = 0
    m = float(np.prod(pr.modes))
    tot = rcpu + t1c + kc + t2c
    mp = ewald._predicted_parts(pr, src.shape[0], trg.shape[0], 3, own, own_skip if a.own == "smooth" else None)
    print(f"N {n:4d} xi {pr.xi:.2f} rc {pr.rc:.3f} modes {pr.modes}: real {rw:.2f} / {rcpu:.2f}  "
          f"type1 {t1w:.2f} / {t1c:.2f}  kspace {kw:.2f} / {kc:.2f}  type2 {t2w:.2f} / {t2c:.2f}  "
          f"total cpu {tot:.2f}; model{' (own incl.)' if a.own == 'subtract' else ''} {sum(mp.values()):.2f} = {mp['real']:.2f} + {mp['type1']:.2f} + "
          f"{mp['kspace']:.2f} + {mp['type2']:.2f}; "
          f"{pairs:.3g} model pairs ({rcpu / pairs * 1e9:.2f} ns each), {own:.3g} own pairs, "
          f"{m:.3g} modes  (load {os.getloadavg()[0]:.2f})", flush=True)


if __name__ == "__main__":
    main()
