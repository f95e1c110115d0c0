"""One sdc step of the accuracy-cost scene against a fine solution of the same step (issue 18).

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.sdc_local_error \
        [--p 8] [--t0 7] [--dts 0.125,0.25,0.5,1] [--sweeps 1,2,3,5,8] [--quadrature lobatto,radau]

The state at t0 comes from fixed sdc steps of 0.25 (runs/accuracy_cost.toml, no output).  From
it, for each dt and quadrature: the step with 3 nodes and K sweeps (K = --sweeps), against 8
steps of dt/8 with 4 Radau nodes and 6 sweeps (L-stable, converged).  Printed per K: the true error (largest grid-point
distance), d_K = |X^K - X^{K-1}| (the estimate of K - 1 sweeps) and sdc.error_estimate (of the
kept K-sweep state, from d_{K-1} and d_K).  No reparameterization or correction inside the step.
"""
from __future__ import annotations

import argparse

import numpy as np


def state_at(p, t0):
    from vesflow import options as optmod, scene as scenemod, study
    from vesflow.simulation import Run
    scene = scenemod.load_scene("runs/accuracy_cost.toml")
    sc = study.case_scene(scene, study.Case(p, 1e-2, 0.0, "sdc"), horizon=t0)
    opts = optmod.read_options(optmod.dict_getter({"-ts_type": "sdc", "-ves_adapt": "none", "-ts_dt": 0.25}), sc)
    run = Run(sc, opts, writer=None)
    run.run()
    return run.stepper


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--p", type=int, default=8)
    ap.add_argument("--t0", type=float, default=7.0)
    ap.add_argument("--dts", default="0.125,0.25,0.5,1")
    ap.add_argument("--sweeps", default="1,2,3,5,8")
    ap.add_argument("--quadrature", default="lobatto,radau")
    a = ap.parse_args()
    from vesflow import sph
    from vesflow.sdc import SDC, error_estimate
    st = state_at(a.p, a.t0)
    X0, t0, T = st.coeffs.copy(), st.time, sph.transform(a.p)

    def step(nodes, K, dt, n=1, quadrature="radau"):
        st.coeffs, st.time, st.last = X0.copy(), t0, None
        s = SDC(st, nodes, K, quadrature)
        for _ in range(n):
            s.step(dt / n)
        return st.coeffs.copy(), s.differences

    print(f"p = {a.p}, t0 = {t0:g}")
    print("| dt | nodes | K | true error | d_K | error_estimate |\n|---|---|---|---|---|---|")
    for dt in (float(x) for x in a.dts.split(",")):
        ref, _ = step(4, 6, dt, 8)
        for quad in a.quadrature.split(","):
            for K in (int(k) for k in a.sweeps.split(",")):
                X, d = step(3, K, dt, 1, quad)
                print(f"| {dt:g} | {quad} | {K} | {np.abs(T.synth(X - ref)).max():.2e} | {d[-1]:.2e} | "
                      f"{error_estimate(d):.2e} |", flush=True)


if __name__ == "__main__":
    main()
