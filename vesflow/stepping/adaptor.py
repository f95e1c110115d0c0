"""Step-size control (like PETSc's TSAdapt) and the adaptation of the quadrature degrees.

Adaptive stepping (paper 3.7): a candidate with error e is accepted when e / dt <= E/T
(-ves_adapt_tol); the next step is dt (beta (E/T) dt / e)^(1/k) (k: the integrator's order),
within [dt_min, dt_max] and at most doubling.  A step is also rejected (dt halved) on a GMRES
failure, a non-finite result or a collision (paper 3.3).  Steps land on the output times
k * every and on the horizon.
"""
from __future__ import annotations

import numpy as np

STRETCH = 0.01     # a step may grow by this fraction to land on an output time


def time_tol(t):
    return 1e-9 * max(1.0, abs(t))


def next_output_time(t, every):
    """The first multiple k * every (k integer) after t (by more than the rounding of t):
    frames are due at 0, every, 2 every, ..., whatever steps were taken (also after a restart,
    or a restart with another -ves_output_every)."""
    k = np.floor(t / every + time_tol(t / every)) + 1.0
    return float(k * every)


class Adaptor:
    """Accept or reject, propose the next dt, land on output times.  dt: the proposal of the
    next step; next_frame: the next output time (0 before the first frame of a run)."""

    def __init__(self, opts, dt0, horizon, every, order, dt=None, t=None):
        self.opts, self.dt0, self.horizon, self.every, self.order = opts, dt0, horizon, every, order
        self.dt = dt0 if dt is None else dt
        self.next_frame = 0.0 if t is None else next_output_time(t, every)
        self.rejects_in_row = 0

    def done(self, t, n_accepted):
        n = self.opts["ts_max_steps"]
        return t >= self.horizon * (1 - 1e-12) or (n is not None and n_accepted >= n)

    def landing(self, t):
        """The step to take from t and the time it lands on (or None): the proposal, shortened
        to end exactly at the next output time or the horizon when it would pass it (or
        stretched by at most 1% to reach it, so no sliver steps are left)."""
        target = min(self.next_frame, self.horizon)
        gap = target - t
        if self.dt >= gap / (1.0 + STRETCH):
            return gap, target
        return self.dt, None

    def check(self, dt, err):
        """The error test: "accepted" or "error_estimate"."""
        if self.opts["adapt"] != "none" and err / dt > self.opts["adapt_tol"]:
            return "error_estimate"
        return "accepted"

    def next_dt(self, dt, err):
        o = self.opts
        if o["adapt"] == "none":
            return self.dt0
        if err <= 0:
            new = 2.0 * dt
        else:
            new = dt * min(2.0, o["adapt_beta"] * (o["adapt_tol"] * dt / err) ** (1.0 / self.order))
        if o["dt_max"] is not None:
            new = min(new, o["dt_max"])
        return max(new, o["dt_min"])

    def accept(self, dt, err):
        self.rejects_in_row = 0
        proposal = self.next_dt(dt, err)
        # a step shortened to land keeps the proposal of the step it replaced
        self.dt = max(self.dt, proposal) if dt < self.dt else proposal

    def reject(self, dt, err, reason):
        """The next dt after a rejection; True when the run gives up (dt below -ves_dt_min or
        -ves_max_rejects rejections in a row)."""
        self.rejects_in_row += 1
        self.dt = 0.5 * dt if reason != "error_estimate" else max(self.next_dt(dt, err), 0.0)
        if reason == "error_estimate":
            self.dt = min(self.dt, 0.9 * dt)
        return self.dt < self.opts["dt_min"] or self.rejects_in_row >= self.opts["max_rejects"]

    def output_due(self, t):
        return t >= self.next_frame - time_tol(t) or t >= self.horizon * (1 - 1e-12)

    def output_written(self, t):
        self.next_frame = next_output_time(t, self.every)


class QuadratureAdaptor:
    """Paper 3.2.4: the double-layer identity sum_j D_j[1] = 1, 1/2, 0 inside / on / outside,
    checked on the layer potentials of the last solve (self regime -> q_self; near and far
    regimes, which share one grid -> q_near).  q + 1 above -ves_quad_tol, q - 1 below a tenth
    of it (the dead band keeps q from flipping every step), within [p (p + 1 for q_self), -ves_q_max]."""

    def __init__(self, stepper, tol, q_max, timers):
        self.stepper, self.tol, self.q_max, self.timers = stepper, tol, q_max, timers
        self.errors = None

    def after_step(self):
        lp = self.stepper.lp_last
        if self.tol <= 0 or lp is None:
            return
        with self.timers.stage("quad_adapt"):
            e = lp.error_estimate()
        s, lo = self.stepper.lp_settings, self.stepper.p
        s.q_self = step_q(int(s.q_self), e["self"], self.tol, lo + 1, self.q_max)      # Graham-Sloan needs q > p
        s.q_far = step_q(int(s.q_far), max(e["near"], e["far"]), self.tol, lo, self.q_max)
        self.errors = e


def step_q(q, err, tol, lo, hi):
    if not np.isfinite(err) or err > tol:
        return min(q + 1, hi)
    if err < 0.1 * tol:
        return max(q - 1, lo)
    return q
