"""Observed order in dt of the first-order step (euler) and of SDC (vesflow/sdc.py), fixed steps.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python benchmarks/sdc_order.py [--p 6] [--case prolate,pair]

Cases: a relaxing prolate (reduced volume 0.85, kappa 1, no flow, T = 0.4) and a sheared pair
(two oblates, reduced volume 0.85, kappa 0.1, shear rate 1, T = 0.4).  The error is the largest
grid-point distance at T to a reference of 4 Gauss-Lobatto nodes and 4 sweeps at dt = T / 64
(order 5: below 1e-9 here); no reparameterization or area/volume correction (they are per
accepted step of a run, not part of the integrator).  GMRES rtol 1e-11 (-ksp_rtol).
"""
from __future__ import annotations

import argparse
import time

import numpy as np


def case_setup(name, p):
    """(coefficients, VesicleParams, Physics, T) of a case."""
    from vesflow import shapes
    from vesflow.operator import VesicleParams
    from vesflow.stepper import Physics
    if name == "prolate":
        c = shapes.make_shape("prolate", p, reduced_volume=0.85)[None]
        return c, VesicleParams([1.0], [1.0], [0.0]), Physics(), 0.4
    if name == "pair":
        c = np.stack([shapes.make_shape("oblate", p, reduced_volume=0.85, center=(-1.5, 0, 0.4)),
                      shapes.make_shape("oblate", p, reduced_volume=0.85, center=(1.5, 0, -0.4))])
        return (c, VesicleParams([0.1] * 2, [1.0] * 2, [0.0] * 2),
                Physics(flow="shear", flow_args={"rate": 1.0}), 0.4)
    raise ValueError(f"case = {name!r}: must be prolate or pair")


def final_state(name, p, dt, scheme, nodes=3, sweeps=2, near_factor=1.0, quadrature="lobatto"):
    """Position coefficients at T after fixed steps dt (scheme euler or sdc); and the solves' GMRES iterations."""
    from vesflow.layerpot.evaluator import Settings
    from vesflow.sdc import SDC
    from vesflow.stepper import Stepper
    c, params, phys, T = case_setup(name, p)
    st = Stepper(c, p, params, phys, Settings(near_factor=near_factor))
    sdc = SDC(st, nodes, sweeps, quadrature) if scheme == "sdc" else None
    its = 0
    for _ in range(int(round(T / dt))):
        its += (sdc.step(dt)[0] if sdc else st.step(dt)).its
    return st.coeffs, its


def order_table(name, p, dts, schemes, ref_dt_div=64, near_factor=1.0):
    """Rows (scheme, dt, error, order vs the previous dt, seconds) against the fine reference."""
    from vesflow import sph
    T = case_setup(name, p)[3]
    ref, _ = final_state(name, p, T / ref_dt_div, "sdc", nodes=4, sweeps=4, near_factor=near_factor)
    Tp = sph.transform(p)
    rows = []
    for label, scheme, nodes, sweeps in schemes:
        prev = None
        for dt in dts:
            t0 = time.perf_counter()
            X, its = final_state(name, p, dt, scheme, nodes, sweeps, near_factor)
            sec = time.perf_counter() - t0
            err = float(np.abs(Tp.synth(X - ref)).max())
            order = np.log(prev[1] / err) / np.log(prev[0] / dt) if prev else float("nan")
            rows.append((label, dt, err, order, its, sec))
            prev = (dt, err)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--p", type=int, default=6)
    ap.add_argument("--case", default="prolate,pair")
    ap.add_argument("--dts", default="0.1,0.05,0.025,0.0125")
    ap.add_argument("--near-factor", type=float, default=1.0, help="-ves_near_factor (0.01: no near zone)")
    ap.add_argument("--schemes", default="euler,sdc3x1,sdc3x2,sdc3x3,sdc4x3")
    args = ap.parse_args(argv)
    import petsc4py
    petsc4py.init([])
    from petsc4py import PETSc
    PETSc.Options()["ksp_rtol"] = 1e-11
    schemes = []
    for s in args.schemes.split(","):
        if s == "euler":
            schemes.append(("euler", "euler", 0, 0))
        else:
            n, k = (int(x) for x in s[3:].split("x"))
            schemes.append((f"sdc {n} nodes, {k} sweep{'s' if k > 1 else ''}", "sdc", n, k))
    dts = [float(x) for x in args.dts.split(",")]
    for name in args.case.split(","):
        print(f"\n{name}, p = {args.p}, near factor {args.near_factor:g}")
        print(f"| scheme | dt | error at T | observed order | GMRES its | wall s |\n|---|---|---|---|---|---|")
        for label, dt, err, order, its, sec in order_table(name, args.p, dts, schemes, near_factor=args.near_factor):
            print(f"| {label} | {dt:g} | {err:.2e} | {'' if np.isnan(order) else f'{order:.2f}'} | {its} | {sec:.1f} |",
                  flush=True)


if __name__ == "__main__":
    main()
