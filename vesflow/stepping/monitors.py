"""Monitors (like PETSc's TSMonitor): called by the run after every attempted step, before
its outcome is applied (`attempt`) and after (`stepped`), at every output time (`output`) and
at the end (`end`).  A new output is a new
Monitor, not an edit of the loop."""
from __future__ import annotations

import sys
import time

import numpy as np

from .. import sph


class Monitor:
    def attempt(self, run, row):
        """row: (t, dt, accepted, its, err, reason, q_self, q_near) of the attempt."""

    def stepped(self, run, row):
        """After the attempt's outcome (the new state, or the rejection) is applied."""

    def output(self, run):
        """At an output time, after the accepted step that reached it."""

    def end(self, run):
        """After the last step."""


class StepLog(Monitor):
    """-ts_monitor: one line per attempted step."""

    def __init__(self, log=print):
        self.log = log

    def attempt(self, run, row):
        t, dt, _, its, err, reason, qs, qn = row
        self.log(f"step {run.counts['accepted'] + run.counts['rejected']:5d} t={t:.6g} dt={dt:.3e} its={its} "
                 f"err={err:.2e} q={qs}/{qn} {reason}"
                 + (f" ({run.last_failure})" if reason in ("ksp", "nonfinite") else ""))


class Progress(Monitor):
    """-ves_progress: a line on stderr rewritten after every attempt."""

    def __init__(self):
        self.t0 = time.perf_counter()

    def stepped(self, run, row):
        sys.stderr.write(f"\r t = {run.t:9.4f} / {run.horizon:g}  dt = {run.dt:.2e}  its = {row[3]:3d}  "
                         f"accepted {run.counts['accepted']}  rejected {run.counts['rejected']}  "
                         f"wall {time.perf_counter() - self.t0:7.1f} s ")
        sys.stderr.flush()

    def end(self, run):
        sys.stderr.write("\n")


class Frames(Monitor):
    """A frame of the state (vesflow.io.OutputWriter.write_frame) at every output time."""

    def __init__(self, writer):
        self.writer = writer

    def output(self, run):
        st, p = run.stepper, run.p
        S, Tp = st.surface, sph.transform(p)
        periodic = {"image": run.state.image} if run.period is not None else {}
        with run.timers.stage("output"):
            self.writer.write_frame(
                time=run.t, points=S.points(), coefficients=S.coeffs, tension=Tp.synth(run.state.sigma),
                area=S.area(), volume=S.volume(), centroid=run.unwrapped_centroid(),
                bending_energy=S.bending_energy(st.params.kappa), velocity=np.moveaxis(Tp.synth(run.state.u), -2, -1),
                poles=S.pole_points(), bending_energy_density=S.bending_energy_density(st.params.kappa), **periodic)


class Checkpoints(Monitor):
    """The steps so far, the timings and a checkpoint (run.checkpoint()) at every output
    time; the writer keeps one per -ves_checkpoint_every of simulated time."""

    def __init__(self, writer):
        self.writer = writer

    def output(self, run):
        with run.timers.stage("output"):
            run.flush_steps()
            self.writer.write_timings(run.timers.as_dict())
            self.writer.write_checkpoint(run.checkpoint())
