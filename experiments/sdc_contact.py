"""Why -ts_type sdc stops in the no-repulsion pair tests of tests/stepping/test_robustness.py (issue 18).

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.sdc_contact [--case detector-0.15]
        [-opt value ...]

Cases (the scenes and options of the tests): detector-0.15, detector-0.22
(test_collision_detector_rejects_steps_and_run_ends_without_intersection) and close-pair
(test_close_pair_without_repulsion_ends_without_contact).  Runs the case with -ts_type euler and
-ts_type sdc (plus the extra options), printing every attempted step: the min gap of the state
before it, of the raw candidate and of each post-processed variant Run._try checks
((reparam, projection its) -> gap).  Then, from the last accepted sdc state, one euler and one
sdc step of the dt the run stopped at: their candidates and gaps, and the volume change rate.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from tests import harness
from vesflow import collision, options as optmod, scene as scenemod
from vesflow.errors import NumericalFailure
from vesflow.simulation import Run
from vesflow.surface import Surface

CASES = {
    "detector-0.15": (harness.pair_scene(1.3, 0.15, 6, 6.0, every=6.0, dt=0.05), {"-ves_adapt_tol": 0.15}),
    "detector-0.22": (harness.pair_scene(1.3, 0.22, 6, 6.0, every=6.0, dt=0.05), {"-ves_adapt_tol": 0.15}),
    "close-pair": (harness.pair_scene(1.3, 0.3, 6, 5.8, every=1.0, dt=0.05),
                   {"-ves_reparam": "off", "-ves_adapt_tol": 0.05}),
}


def traced_run(text, options):
    """The run, with a line per attempted step (gaps before, raw, post-processed variants)."""
    sc = scenemod.parse_scene(text)
    opts = optmod.read_options(optmod.dict_getter(options), sc)
    run = Run(sc, opts, writer=None)
    gap = lambda c: collision.min_gap(Surface(c, run.p), run.q_near)
    plain_try, plain_post = run._try, run._post_processed
    seen = {}

    def post(coeffs, reparam, project_its=1, dt=0.0):
        out = plain_post(coeffs, reparam, project_its, dt)
        seen.setdefault("raw", coeffs.copy())
        seen.setdefault("variants", []).append(f"({int(reparam)},{project_its}) {gap(out):.3e}")
        return out

    def attempt(dt):
        seen.clear()
        g0 = gap(run.stepper.coeffs)
        out = plain_try(dt)
        run.last_attempt_dt = dt
        line = f"  t = {run.t:.6f}  dt = {dt:.3e}  {out[1]:14s}"
        if "raw" in seen:
            line += f" gap {g0:.3e}  raw {gap(seen['raw']):.3e}  post " + "  ".join(seen["variants"])
        print(line, flush=True)
        return out

    run._try, run._post_processed = attempt, post
    try:
        run.run()
        failure = None
    except NumericalFailure as e:
        failure = str(e)
    print(f"  end t = {run.t:.6g}, {run.counts}, failure: {failure}")
    return run, opts, failure


def one_step(sc, options, X0, area0, volume0, t0, dt):
    """Raw and post-processed candidates of one step of dt from X0 (no adaptivity)."""
    opts = optmod.read_options(optmod.dict_getter(dict(options, **{"-ves_adapt": "none"})), sc)
    run = Run(sc, opts, writer=None)
    run.area0, run.volume0 = area0, volume0
    st = run.stepper
    st.coeffs, st.time, st.last = X0.copy(), t0, None
    st.step(dt) if run.sdc is None else run.sdc.step(dt)
    raw = st.coeffs.copy()
    return raw, run._post_processed(raw, False, dt=dt), run


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="detector-0.15", choices=sorted(CASES))
    args, rest = ap.parse_known_args()
    extra = dict(zip(rest[::2], rest[1::2]))
    text, options = CASES[args.case]
    options = dict(options, **extra)
    for ts in ("euler", "sdc"):
        print(f"{args.case}, -ts_type {ts} {extra}")
        run, opts, failure = traced_run(text, dict(options, **{"-ts_type": ts}))
    if failure is None:
        return
    X0, dt = run.stepper.coeffs.copy(), run.last_attempt_dt
    sc = scenemod.parse_scene(text)
    p, q = run.p, run.q_near
    gap = lambda c: collision.min_gap(Surface(c, p), q)
    V = Surface(X0, p).volume()
    print(f"from the last accepted sdc state (t = {run.t:.6f}, gap {gap(X0):.3e}), one step of dt = {dt:.3e}:")
    raws = {}
    for ts in ("euler", "sdc"):
        raw, kept, _ = one_step(sc, dict(options, **{"-ts_type": ts}), X0, run.area0, run.volume0, run.t, dt)
        raws[ts] = raw
        rate = (Surface(raw, p).volume() - V) / dt / run.volume0
        print(f"  {ts:5s}: raw gap {gap(raw):.3e}, after correction (no reparameterization) {gap(kept):.3e}, "
              f"dV/dt / V0 {np.array2string(rate, precision=2)}")
    d = np.abs(raws["sdc"] - raws["euler"]).max()
    print(f"  max |X_sdc - X_euler| (coefficients) {d:.2e}; |X_sdc - X0| {np.abs(raws['sdc'] - X0).max():.2e}")


if __name__ == "__main__":
    sys.exit(main())
