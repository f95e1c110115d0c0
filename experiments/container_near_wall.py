"""A sphere settling 0.3 from the wall of a spherical container of radius 3 (no exact value): its
velocity per wall degree p_w and degree q_w of the wall's smooth and near-singular rules
(-ves_wall_q), vesicle degree p = 16, against the finest case; what set the default q_w = 4 p_w
(docs/explanation/walls.md).

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.container_near_wall [--gap 0.3]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from vesflow import shapes, sph
from vesflow.layerpot.wall import Wall
from vesflow.operator import VesicleParams
from vesflow.stepper import Physics, Stepper

CASES = [(16, 32), (16, 64), (16, 96), (24, 48), (24, 96), (32, 128)]     # (p_w, q_w), the last the reference


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gap", type=float, default=0.3)
    ap.add_argument("--p", type=int, default=16)
    args = ap.parse_args()
    R, p = 3.0, args.p
    rows = []
    for pw, qw in CASES:
        t0 = time.process_time()
        wall = Wall(shapes.make_shape("sphere", pw, radius=R), pw, q_far=qw)
        st = Stepper(shapes.make_shape("sphere", p, center=(0.0, 0.0, R - 1.0 - args.gap))[None], p,
                     VesicleParams([0.1], [1.0], [1.0]), Physics(gravity=np.array([0.0, 0.0, -1.0])), wall=wall)
        sol = st.velocity()
        rows.append((pw, qw, wall.h, sph.transform(p).synth(sol.u)[0][2].mean(), sol.its, time.process_time() - t0))
    ref = rows[-1][3]
    print("| p_w | q_w | h_w | U_z | against the last | GMRES its | CPU s |")
    print("|---|---|---|---|---|---|---|")
    for pw, qw, h, U, its, t in rows:
        print(f"| {pw} | {qw} | {h:.2f} | {U:.6f} | {U / ref - 1:+.1e} | {its} | {t:.1f} |")


if __name__ == "__main__":
    main()
