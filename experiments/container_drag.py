"""The sphere settling at the centre of a spherical container (docs/explanation/walls.md): its
velocity against Happel and Brenner's wall-corrected drag, per radius ratio lambda = a / b,
vesicle degree p and wall degree p_w, with the GMRES iterations and the CPU time of the solve.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.container_drag [--lam 0.2 0.4 0.6 0.8] [--p 8 12 16] [--pw 12 16 24]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from vesflow import shapes, sph
from vesflow.layerpot.wall import Wall
from vesflow.operator import VesicleParams
from vesflow.stepper import Physics, Stepper


def K(lam):
    """Happel & Brenner (1965), section 4-22: the drag factor of a sphere at the centre of a sphere."""
    return (1 - lam ** 5) / (1 - 9 / 4 * lam + 5 / 2 * lam ** 3 - 9 / 4 * lam ** 5 + lam ** 6)


def case(lam, p, pw, a=1.0):
    t0 = time.process_time()
    wall = Wall(shapes.make_shape("sphere", pw, radius=a / lam), pw)
    t_wall = time.process_time() - t0
    st = Stepper(shapes.make_shape("sphere", p, radius=a)[None], p, VesicleParams([0.1], [1.0], [1.0]),
                 Physics(gravity=np.array([0.0, 0.0, -1.0])), wall=wall)
    t0 = time.process_time()
    sol = st.velocity()
    t_solve = time.process_time() - t0
    U = sph.transform(p).synth(sol.u)[0][2].mean()
    exact = -(4 / 3 * np.pi * a ** 3) / (6 * np.pi * a * K(lam))
    return abs(U / exact - 1), sol.its, t_wall, t_solve


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lam", type=float, nargs="+", default=[0.2, 0.4, 0.6, 0.8])
    ap.add_argument("--p", type=int, nargs="+", default=[8, 12, 16])
    ap.add_argument("--pw", type=int, nargs="+", default=[12, 16, 24])
    args = ap.parse_args()
    print("| lambda | p | p_w | relative error | GMRES its | wall set-up (CPU s) | solve (CPU s) |")
    print("|---|---|---|---|---|---|---|")
    for lam in args.lam:
        for p in args.p:
            for pw in args.pw:
                err, its, tw, ts = case(lam, p, pw)
                print(f"| {lam:g} | {p} | {pw} | {err:.1e} | {its} | {tw:.2f} | {ts:.2f} |", flush=True)


if __name__ == "__main__":
    main()
