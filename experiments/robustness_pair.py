"""Exploration runs of docs/explanation/robustness.md, section 3: two oblates (v = 0.9, kappa_b = 0.05)
sheared past each other, centres (-dx, 0, dz), (dx, 0, -dz); prints the outcome, the collision
rejections and the min gap / contacts at every frame.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.robustness_pair --p 6 --dz 0.45 --T 6 -ves_reparam off
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.robustness_pair --p 8 --dz 0.45 --T 4.6 --R 0.04
"""
import argparse
import time

import petsc4py  # noqa: E402

petsc4py.init([])
from tests.harness import rejections, robustness_pair as _pair, run_pair as _run_pair  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--p", type=int, default=6)
ap.add_argument("--dx", type=float, default=1.3)
ap.add_argument("--dz", type=float, default=0.45)
ap.add_argument("--T", type=float, default=6.0)
ap.add_argument("--R", type=float, default=0.0)
ap.add_argument("--dt", type=float, default=0.05)
a, rest = ap.parse_known_args()
opts = dict(zip(rest[::2], rest[1::2]))          # -ves_... value pairs
extra = f"[repulsion]\nradius = {a.R}" if a.R > 0 else ""
t0 = time.time()
run, rec, failure = _run_pair(_pair(a.dx, a.dz, a.p, a.T, extra=extra, dt=a.dt), **opts)
print("FAILED: " + failure if failure else "ok", "t", run.t, run.counts, rejections(rec),
      "wall", round(time.time() - t0, 1))
print("collisions (t, dt):", [(round(r[0], 3), r[1]) for r in rec.steps if r[5] == "collision"][:20])
print("frames (t, min gap, contacts):",
      [(round(f["time"], 2), round(f["min_gap"], 4), f["contacts"]) for f in rec.frames])
