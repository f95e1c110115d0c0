"""Pairs driven into contact without repulsion (p = 6): outcome, rejections, separations, CPU time.

    PYTHONPATH=$PWD OMP_NUM_THREADS=1 .venv/bin/python benchmarks/contacts.py --case detector-0.15 \
        [--schemes euler,sdc] [-opt value ...]

Cases: detector-0.15, detector-0.22, close-pair (the no-repulsion tests of
tests/stepping/test_robustness.py, their scenes and options) and pushed-0.25, pushed-0.3 (default options,
centres (-1.3, 0, dz), (1.3, 0, -dz), T = 6, frames every 0.5: the pairs tests/stepping/test_contacts.py
drives into contact).  One line per scheme: end time, failure, accepted / rejected by reason,
separated steps (vesflow/contact.py) with their start gaps and shifts, smallest frame gap,
steps' dt range, CPU seconds.  -ves_contact off gives the behaviour without separation.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from tests import harness
from vesflow import options as O, scene as S
from vesflow.errors import NumericalFailure
from vesflow.simulation import Run

CASES = {
    "detector-0.15": (harness.pair_scene(1.3, 0.15, 6, 6.0, every=6.0, dt=0.05), {"-ves_adapt_tol": 0.15}),
    "detector-0.22": (harness.pair_scene(1.3, 0.22, 6, 6.0, every=6.0, dt=0.05), {"-ves_adapt_tol": 0.15}),
    "close-pair": (harness.pair_scene(1.3, 0.3, 6, 5.8, every=1.0, dt=0.05),
                   {"-ves_reparam": "off", "-ves_adapt_tol": 0.05}),
    "pushed-0.25": (harness.pair_scene(1.3, 0.25, 6, 6.0, every=0.5, dt=0.05), {}),
    "pushed-0.3": (harness.pair_scene(1.3, 0.3, 6, 6.0, every=0.5, dt=0.05), {}),
}


def simulate(text, options):
    """harness.simulate with the options that override scene keys (-ves_repulsion_radius) applied."""
    getter = O.dict_getter(options)
    sc = O.apply_overrides(S.parse_scene(text), getter)
    opts = O.read_options(getter, sc)
    rec = harness.Recorder(opts["q_near"])
    run = Run(sc, opts, writer=rec)
    failure = None
    try:
        run.run()
    except NumericalFailure as e:
        failure = str(e)
    return run, rec, failure


def run_case(text, options, steps=False):
    t0 = time.process_time()
    run, rec, failure = simulate(text, options)
    cpu = time.process_time() - t0
    if steps:                                   # t, dt, outcome of every attempted step
        for r in rec.steps:
            print(f"  t = {r[0]:.5f}  dt = {r[1]:.3e}  {r[5]}")
    gaps = [f["min_gap"] for f in rec.frames]
    dts = [r[1] for r in rec.steps if r[2]]
    log = run.contacts.log if run.contacts is not None else []
    return {"t_end": run.t, "failure": failure, "accepted": run.counts["accepted"],
            "rejected": harness.rejections(rec), "separated": len(log),
            "start_gaps": [float(f"{g[0]:.2g}") for g in log], "candidate_gaps": [float(f"{g[1]:.2g}") for g in log],
            "shift_max": max((g[2] for g in log), default=0.0),
            "min_frame_gap": min(gaps), "contacts": max(f["contacts"] for f in rec.frames),
            "dt_min": min(dts) if dts else np.nan, "dt_max": max(dts) if dts else np.nan, "cpu": cpu}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", default="detector-0.15", choices=sorted(CASES))
    ap.add_argument("--schemes", default="euler,sdc")
    ap.add_argument("--steps", action="store_true", help="print every attempted step")
    args, rest = ap.parse_known_args()
    extra = dict(zip(rest[::2], rest[1::2]))
    text, options = CASES[args.case]
    for ts in args.schemes.split(","):
        r = run_case(text, dict(options, **extra, **{"-ts_type": ts}), args.steps)
        fail = r.pop("failure")
        print(f"{args.case} -ts_type {ts} {extra}: " + ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items())
            + (f"; failure: {fail}" if fail else ""), flush=True)


if __name__ == "__main__":
    sys.exit(main())
