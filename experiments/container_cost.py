"""What a container costs: one step of runs/container.toml's vesicles (dt 0.05, first order) with
the wall and without it (free space), CPU seconds of the wall's operators (built once) and of the step, the
step's stages in wall-clock seconds (vesflow.timing: the wall's coupling to the geometry
"wall_setup", the wall rows and D_w at the vesicles "wall"), GMRES iterations and applications.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.container_cost [--p 12] [--pw 16]
"""
from __future__ import annotations

import argparse
import dataclasses
import time

from tests.harness import ROOT
from vesflow.layerpot.wall import Wall
from vesflow.scene import load_scene
from vesflow.setup_state import initial_coefficients, physics, vesicle_params, wall_coefficients
from vesflow.stepper import Stepper
from vesflow.timing import Timers


def one(scene, p, pw, with_wall):
    sc = scene.replace(**{"discretization.p": p})
    timers = Timers(use_petsc=False)
    wall, t_wall = None, 0.0
    if with_wall:                       # once per run: the self operator, completion and LU of (W.2)
        t0 = time.process_time()
        wall = Wall(wall_coefficients(dataclasses.replace(sc.wall, p=pw)), pw)
        t_wall = time.process_time() - t0
    t0 = time.process_time()
    st = Stepper(initial_coefficients(sc), p, vesicle_params(sc), physics(sc), timers=timers, wall=wall)
    sol = st.step(0.05)
    total = time.process_time() - t0
    A = st._ksp[0].getPythonContext() if st._ksp else None
    return total, sol.its, timers, None if A is None else A.n_mult, t_wall


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--p", type=int, default=12)
    ap.add_argument("--pw", type=int, default=16)
    args = ap.parse_args()
    scene = load_scene(ROOT / "runs" / "container.toml")
    one(scene, args.p, args.pw, True)            # warm the caches (transform tables) of both cases
    for with_wall in (False, True):
        total, its, tm, n_mult, t_wall = one(scene, args.p, args.pw, with_wall)
        det = {k: round(v, 3) for k, v in tm.detail.items() if v > 0.005}
        col = {k: round(v, 3) for k, v in tm.total.items() if v > 0.005}
        print(f"{'wall p_w = ' + str(args.pw) if with_wall else 'free space':>14}: the wall's operators {t_wall:.2f} s "
              f"CPU (once); the step {total:.2f} s CPU, GMRES its {its}, "
              f"operator applications {n_mult}; columns {col}; detail {det}", flush=True)


if __name__ == "__main__":
    main()
