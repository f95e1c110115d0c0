"""One GMRES iteration of a periodic suspension, split into its parts (docs/explanation/far_field.md,
"A whole GMRES iteration").

N vesicles (unit-radius spheres, or biconcave cells of reduced volume 0.65 with --shape
biconcave, random orientations) on a jittered cubic lattice of spacing --spacing in their
periodic cube, p = --p, far-field and near sources on the degree-q grid (--q, default 2p;
``Settings(q_far=...)``), Ewald far field at --tol.  Set-up
once (self operators, near pairs, Ewald cell lists and NUFFT plans: the first apply), then
--repeat applications of ``LayerPotentials.apply`` (one per GMRES iteration), each split into
self (batched GEMV of the dense self operators), far (Ewald; far_own: the GEMV of the own
vesicle's smooth-share operators, vesflow.layerpot.own_smooth), near (pair corrections) and the
rest (q-grid synthesis of the densities, analysis of the result); wall and process-CPU seconds
per iteration, best of the repeats.  Memory: the self operators alone are N (3C)^2 x 8 bytes
(5.7 MB per vesicle at p = 16), the own smooth operators (--own smooth, the default) as many
again.  The biconcave cells (2.38 wide) in random orientations touch or
intersect at spacings 2.2 and 2.5 (minimum distance 0.001 / 0.005 between their q = 48 points):
such a scene times the iteration but its velocities are meaningless (docs/explanation/far_field.md, "The
far/near grid degree q").

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/iteration.py --n 64
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/iteration.py --n 64 --shape biconcave --spacing 2.2
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/iteration.py --n 512 --q 24 --repeat 3
"""
import argparse
import os
import time

import numpy as np


from vesflow import shapes  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials, Settings  # noqa: E402
from vesflow.surface import Surface  # noqa: E402
from vesflow.timing import Timers  # noqa: E402


class CpuTimers(Timers):
    """vesflow.timing.Timers recording (wall, process CPU) per name."""

    def __init__(self):
        super().__init__(use_petsc=False)
        self.t = {}
        self._t0 = {}

    def start(self, name):
        self._t0[name] = (time.perf_counter(), time.process_time())

    def stop(self, name):
        w, c = self._t0.pop(name)
        a, b = self.t.get(name, (0.0, 0.0))
        self.t[name] = (a + time.perf_counter() - w, b + time.process_time() - c)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--q", type=int, default=None, help="far/near upsampled grid degree (default 2p)")
    ap.add_argument("--tol", type=float, default=1e-6)
    ap.add_argument("--spacing", type=float, default=2.5)
    ap.add_argument("--shape", choices=("sphere", "biconcave"), default="sphere")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--own", choices=("smooth", "subtract"), default="smooth",
                    help="the Ewald sum's own vesicle: removed by set-up operators (smooth) or in the iteration")
    a = ap.parse_args(argv)
    q = a.q or 2 * a.p
    if q < a.p:
        ap.error(f"--q {q}: the far/near grid degree must be >= p = {a.p}")
    rng = np.random.default_rng(0)
    side = int(np.ceil(a.n ** (1 / 3)))
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:a.n]
    centres = a.spacing * (ijk + 0.5) + rng.uniform(-0.1, 0.1, (a.n, 3))
    period = a.spacing * side
    kw = dict(reduced_volume=0.65) if a.shape == "biconcave" else {}
    coeffs = np.stack([shapes.make_shape(a.shape, a.p, center=tuple(c), rotation=tuple(rng.uniform(0, 3, 3)), **kw)
                       for c in centres])
    surf = Surface(coeffs, a.p)
    print(f"# N = {a.n} {a.shape}s, p = {a.p}, q = {q}, period {period:g}, tol {a.tol:g}, "
          f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; load {os.getloadavg()[0]:.2f}", flush=True)
    tm = CpuTimers()
    w0, c0 = time.perf_counter(), time.process_time()
    lp = LayerPotentials(surf, settings=Settings(backend="ewald", fmm_eps=a.tol, period=period, q_far=q,
                                                 ewald_own=a.own), timers=tm)
    f = rng.standard_normal((a.n, 3, (a.p + 1) ** 2 - 1)) * np.exp(-0.3 * np.arange((a.p + 1) ** 2 - 1))
    lp.apply(f)                                  # first apply: cell lists, NUFFT plans
    sw, sc = time.perf_counter() - w0, time.process_time() - c0
    pr = lp.far.ewald.params
    npairs = lp.n_near_pairs
    own = f", own smooth operators {tm.t['own_setup'][1]:.1f} s CPU" if "own_setup" in tm.t else ""
    print(f"# set-up incl. first apply {sw:.1f} / {sc:.1f} s (self operators {tm.t['self_setup'][1]:.1f} s CPU{own}); "
          f"{npairs} near pairs; ewald xi {pr.xi:.2f} rc {pr.rc:.2f} modes {pr.modes}", flush=True)
    best = None
    for _ in range(a.repeat):
        tm.t = {}
        w, c = time.perf_counter(), time.process_time()
        lp.apply(f)
        tot = (time.perf_counter() - w, time.process_time() - c)
        if best is None or tot[1] < best[0][1]:
            best = (tot, dict(tm.t))
    tot, parts = best
    rest = tuple(tot[i] - sum(v[i] for v in parts.values()) for i in range(2))
    line = "  ".join(f"{k} {v[0]:.2f} / {v[1]:.2f}" for k, v in list(parts.items()) + [("rest", rest)])
    print(f"N {a.n:5d} q {q}  iteration {tot[0]:.2f} / {tot[1]:.2f} s (wall / cpu): {line}  (load {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
