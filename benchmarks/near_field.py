"""The near field of a dense suspension: CPU microseconds per near (target, vesicle) pair, per
phase, in the set-up and per GMRES iteration (docs/explanation/performance.md, "Near field").

The scene is a piece of the paper's 1408-cell Taylor-Green suspension (runs/taylor_green_1408.toml):
biconcave cells (reduced volume 0.65, area radius 0.766, thin axis along z) on the lattice of
spacing (2.125, 2.125, 0.7727), --cells nx ny nz of them in their periodic box (35 % volume
fraction; 2 2 8: 32 cells), p = --p, far/near grid degree q = --q (default 2p), Ewald far field.
The layer potentials are set up --repeat times and applied --its times per set-up (one
application per GMRES iteration); printed, per near pair (CPU of the process, best repeat):

    set-up   search (cell lists and the nearest q-grid source), projection (Gauss-Newton on the
             series), weights (line points and Lagrange weights), basis (the on-surface limit's
             spherical harmonics at the projection), map (the precomputed near maps,
             vesflow.layerpot.nearmap; absent where the code has none)
    iteration  on-surface limit (u0 from the self potential), check points (the smooth rule at
             the target and its 8 line points: the block sums) or map (the maps' product),
             interpolation and scatter (the rest of the near stage)

and the near maps' memory per pair; then the collision check's near pairs (vesflow.collision:
the same search and projection), CPU us per pair.  Works on any vesflow version that has the near stages (it
times module functions by wrapping them), so that an old checkout is measured beside a new one:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/near_field.py
    OMP_NUM_THREADS=1 VESFLOW_SIMD=avx2 .venv/bin/python benchmarks/near_field.py
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/near_field.py --map-mb 0      # without the near maps
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/near_field.py --save out.npy   # the applied velocities
"""
import argparse
import os
import resource
import time

import numpy as np

from vesflow import collision, shapes, sph
from vesflow._kernels import stokes
from vesflow.layerpot import evaluator as ev
from vesflow.layerpot import near as nearmod
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.surface import Surface
from vesflow.timing import Timers

SPACING = np.array([2.125, 2.125, 0.7727])      # runs/taylor_green_1408.toml


class CpuTimers(Timers):
    """vesflow.timing.Timers recording process CPU seconds per stage name."""

    def __init__(self):
        super().__init__(use_petsc=False)
        self.t, self._t0 = {}, {}

    def start(self, name):
        self._t0[name] = time.process_time()

    def stop(self, name):
        self.t[name] = self.t.get(name, 0.0) + time.process_time() - self._t0.pop(name)


class Clock:
    """CPU seconds spent in wrapped functions, by label (nested calls counted once, outermost)."""

    def __init__(self):
        self.t, self.depth, self.active = {}, 0, True

    def wrap(self, owner, name, label):
        fn = getattr(owner, name, None)
        if fn is None:
            return

        def timed(*a, **k):
            if self.depth or not self.active:
                return fn(*a, **k)
            self.depth += 1
            t0 = time.process_time()
            try:
                return fn(*a, **k)
            finally:
                self.t[label] = self.t.get(label, 0.0) + time.process_time() - t0
                self.depth -= 1
        setattr(owner, name, timed)


def scene(cells, p):
    n = np.asarray(cells)
    ijk = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, 3)
    centres = SPACING * (ijk + 0.5)
    coeffs = np.stack([shapes.make_shape("biconcave", p, radius=0.766, center=tuple(c), reduced_volume=0.65)
                       for c in centres])
    return Surface(coeffs, p), tuple(float(x) for x in SPACING * n)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, nargs=3, default=[2, 2, 8])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--q", type=int, default=None)
    ap.add_argument("--its", type=int, default=3, help="applications per set-up")
    ap.add_argument("--repeat", type=int, default=2, help="set-ups")
    ap.add_argument("--contrast", action="store_true", help="viscosity contrast 5 (both layers)")
    ap.add_argument("--save", default=None, help="write the last application's result (.npy)")
    ap.add_argument("--map-mb", type=float, default=None, help="-ves_near_map_mb (0: no near maps; default: the default)")
    a = ap.parse_args(argv)
    surf, period = scene(a.cells, a.p)
    N, C = surf.n_vesicles, sph.n_coeffs(a.p)
    q = a.q or 2 * a.p
    vol = float(surf.volume().sum()) / float(np.prod(period))
    path = stokes.vector_path() if hasattr(stokes, "vector_path") else "?"
    print(f"# {N} biconcave cells, p = {a.p}, q = {q}, period {period}, volume fraction {vol:.3f}; vector path "
          f"{path}; OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}; load {os.getloadavg()[0]:.2f}",
          flush=True)
    clock = Clock()
    clock.wrap(nearmod, "near_pairs_images", "search")
    clock.wrap(nearmod, "interpolation_weights", "weights")
    clock.wrap(nearmod, "line_points", "weights")
    clock.wrap(sph, "evaluate", "basis")
    clock.wrap(sph, "basis_at", "basis")
    setup_fn = LayerPotentials._near_setup

    def near_setup(self, *args):          # the set-up's phases counted inside the near set-up only
        clock.active = True
        try:
            return setup_fn(self, *args)
        finally:
            clock.active = False
    LayerPotentials._near_setup = near_setup
    clock.wrap(ev, "_rows_times_vesicle", "u0")
    for name in ("stokeslet_sum_blocks", "stresslet_sum_blocks", "stokeslet_stresslet_sum_blocks"):
        clock.wrap(stokes, name, "checkpoints")
    # the projection: counted by a subclass (it is constructed, not called)
    clock.wrap(stokes, "near_map_apply", "map_apply")
    base_proj = nearmod.Projection

    class TimedProjection(base_proj):
        def __init__(self, *args, **kw):
            t0 = time.process_time()
            super().__init__(*args, **kw)
            clock.t["projection"] = clock.t.get("projection", 0.0) + time.process_time() - t0
    nearmod.Projection = TimedProjection

    rng = np.random.default_rng(1)
    f = rng.standard_normal((N, 3, C)) * np.exp(-0.3 * np.arange(C))
    g = rng.standard_normal((N, 3, C)) * np.exp(-0.3 * np.arange(C)) if a.contrast else None
    lam = 5.0 if a.contrast else 1.0
    best_setup, best_it, out = None, None, None
    for _ in range(a.repeat):
        tm, clock.t, clock.active = CpuTimers(), {}, False
        kw = {} if a.map_mb is None else {"near_map_mb": a.map_mb}
        lp = LayerPotentials(surf, lam=lam, settings=Settings(backend="ewald", fmm_eps=1e-6, period=period, q_far=q,
                                                               ewald_own="subtract", **kw), timers=tm)
        setup = dict(clock.t)
        setup["total"] = tm.t.get("near_setup", 0.0) + tm.t.get("near_map", 0.0)
        setup["map"] = tm.t.get("near_map", 0.0)
        setup["search"] = tm.t["near_setup"] - sum(setup.get(k, 0.0) for k in ("projection", "weights", "basis"))
        if best_setup is None or setup["total"] < best_setup["total"]:
            best_setup = setup
        clock.active = True                   # the near stage of an iteration calls only near kernels
        for _ in range(a.its):
            tm.t, clock.t = {}, {}
            out = lp.apply(f, g)
            it = dict(clock.t)
            it["total"] = tm.t["near"]
            if best_it is None or it["total"] < best_it["total"]:
                best_it = it
    P = lp.n_near_pairs
    us = lambda t: 1e6 * t / max(P, 1)
    maps = getattr(lp, "near_maps", None)
    mem = 0 if maps is None else maps.nbytes
    mapped = 0 if maps is None else len(maps.index)
    s_parts = ["search", "projection", "weights", "basis", "map"]
    i_parts = ["u0", "checkpoints", "map_apply"]
    it_rest = best_it["total"] - sum(best_it.get(k, 0.0) for k in i_parts)
    print(f"# {P} near pairs ({P / N:.0f} per cell), {mapped} with a map ({mem / max(mapped, 1) / 1e3:.1f} KB per "
          f"pair, {mem / 1e6:.0f} MB); peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB")
    print("set-up    us/pair: " + "  ".join(f"{k} {us(best_setup.get(k, 0.0)):.2f}" for k in s_parts)
          + f"  | total {us(best_setup['total']):.2f}")
    print("iteration us/pair: " + "  ".join(f"{k} {us(best_it.get(k, 0.0)):.2f}" for k in i_parts)
          + f"  interpolation+scatter {us(it_rest):.2f}  | total {us(best_it['total']):.2f}")
    t0 = time.process_time()
    pairs, _ = collision.signed_gaps(surf, q, period)
    t_col = time.process_time() - t0
    print(f"collision check (vesflow.collision.signed_gaps, {len(pairs)} pairs): {1e6 * t_col / max(len(pairs), 1):.2f} "
          f"us/pair; peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB")
    for n_it in (8, 15):
        print(f"per set-up of {n_it} iterations: {us(best_setup['total'] + n_it * best_it['total']):.1f} us/pair")
    if a.save:
        np.save(a.save, out)


if __name__ == "__main__":
    main()
