"""The time loop (like PETSc's TSSolve) over an integrator, an adaptor, the post-step and monitors.

Each attempt: the adaptor's dt (landing on output times), the integrator's candidate and error
estimate, the adaptor's error test, the post-step (reparameterization, area/volume correction,
collision check); an accepted candidate becomes the state (wrapped into the periodic cell, the
quadrature degrees adapted), a rejected one leaves the state as it was.  The state between
steps is a `State`; the stepper is put at it before every attempt.
"""
from __future__ import annotations

import time as _time

import numpy as np

from ..errors import ConvergenceError, NumericalFailure


class Driver:
    """Set up by a subclass (vesflow.simulation.Run): state, stepper, integrator, adaptor, post
    (PostStep), quadrature (QuadratureAdaptor), contacts (vesflow.contact.Contacts or None), monitors,
    writer (or None), timers, and
    area0 / volume0 / n_accepted."""

    def _start_loop(self):
        self.counts = {"accepted": 0, "rejected": 0}
        self.rows = []
        self.iterations = 0               # GMRES iterations of every solve of this process
        self.first_step_at = None         # perf_counter() when the first step began
        self.last_failure = ""            # the message of the last failed solve (for -ts_monitor)
        self.attempt = None
        self.stop = None                  # polled at each step boundary: a vesflow.signals.StopRequest

    # ------------------------------------------------------------------ one attempted step
    def _try(self, dt):
        """(candidate State or None, reason, GMRES iterations, error estimate) of a step of dt."""
        try:
            cand, err, its = self.integrator.step(self.state, dt)
            if not (np.all(np.isfinite(cand.coeffs)) and np.isfinite(err)):   # NaN in either candidate
                raise ConvergenceError("non-finite state", reason="nan", iterations=its)
        except ConvergenceError as e:
            self.last_failure = str(e)
            return None, "nonfinite" if e.reason == "nan" else "ksp", getattr(e, "iterations", 0) or 0, np.inf
        reason = self.adaptor.check(dt, err)
        if reason != "accepted":
            return None, reason, its, err
        # the post-step (reparameterize, correct) changes the surface between grid points at
        # the truncation error, which near contact is the size of the gap: check collisions on
        # the state that will be kept, and drop the reparameterization of this step if it
        # alone brings the surfaces into contact.  In between, the reparameterization with its
        # projection iterated (`reparam.project_onto`: shape change below the truncation error,
        # not used everywhere because it keeps the descent from converging, docs/explanation/robustness.md)
        raw, post, reparam = cand.coeffs, self.post, self.opts["reparam"]
        cand.coeffs = self._post_processed(raw, reparam, dt=dt)
        walled = getattr(post, "wall", None) is not None          # a container: one vesicle can touch it
        if self.opts["collision"] and (len(raw) > 1 or walled) and post.touching(cand.coeffs):
            touching = True
            if reparam:
                cand.coeffs = self._post_processed(raw, True, project_its=10, dt=dt)
                touching = post.touching(cand.coeffs)
                post.reparam_iterated += int(not touching)
                if touching:
                    cand.coeffs = self._post_processed(raw, False)
                    touching = post.touching(cand.coeffs)
                    post.reparam_skipped += int(not touching)
            if touching and self.contacts is not None:      # in contact: separate (vesflow.contact)
                separated = self.contacts.resolve(cand.coeffs, self.state.coeffs, self.q_near)
                if separated is not None:
                    cand.coeffs = separated
                    touching = post.touching(cand.coeffs)
            if touching:
                return None, "collision", its, err
        if self.opts["collision"] and len(raw) > 1 and self.contacts is not None:   # in contact: not closer than the target
            cand.coeffs = self.contacts.keep_apart(cand.coeffs, self.q_near)
        return cand, "accepted", its, err

    def _post_processed(self, coeffs, reparam, project_its=1, dt=0.0):
        return self.post.processed(coeffs, reparam, project_its, dt)

    def _attempt(self, dt):
        """_try(dt), noting the attempt (for `position`); the stepper is put back at the state
        whatever happens."""
        self.attempt = (self.counts["accepted"] + self.counts["rejected"] + 1, self.t, dt)
        try:
            out = self._try(dt)
        finally:
            self.state.load(self.stepper)
        self.attempt = None
        return out

    def position(self):
        """Where the run is, for an error message: 'step 3 (t = 0.1, dt = 0.05)'."""
        a = self.attempt
        if a is not None:
            return f"step {a[0]} (t = {a[1]:.6g}, dt = {a[2]:.3g})"
        n = self.counts["accepted"] + self.counts["rejected"]
        return f"after step {n} (t = {self.t:.6g})" if n else f"before the first step (t = {self.t:.6g})"

    # ------------------------------------------------------------------ the loop
    def run(self):
        if self.first_step_at is None:
            self.first_step_at = _time.perf_counter()
        if self.n_accepted == 0 and self.t == 0.0:             # frame 0
            self._output()
        try:
            while not self.adaptor.done(self.t, self.n_accepted):
                if self.stop is not None and self.stop.poll():     # a signal: stop at this step boundary
                    break
                dt, target = self.adaptor.landing(self.t)
                q_used = (self.q_self, self.q_near)
                cand, reason, its, err = self._attempt(dt)
                row = (self.t, dt, int(cand is not None), its, err, reason) + q_used
                self.rows.append(row)
                self.iterations += its
                for m in self.monitors:
                    m.attempt(self, row)
                if cand is not None:
                    self._accept(cand, target, dt, err)
                else:
                    self._reject(dt, err, reason)
                for m in self.monitors:
                    m.stepped(self, row)
            for m in self.monitors:
                m.end(self)
            self.flush_steps()
            if self.writer is not None:
                self.writer.write_timings(self.timers.as_dict())
        finally:
            self.stepper.close()
        return self

    def _accept(self, cand, target, dt, err):
        self.counts["accepted"] += 1
        self.n_accepted += 1
        if target is not None:           # landed on an output time or the horizon
            cand.t = target
        self.post.wrap(cand)
        self.state = cand
        self.state.load(self.stepper)
        self.quadrature.after_step()
        self.adaptor.accept(dt, err)
        if self.adaptor.output_due(self.t):
            self._output()

    def _reject(self, dt, err, reason):
        self.counts["rejected"] += 1
        if not self.adaptor.reject(dt, err, reason):
            return
        n = self.adaptor.rejects_in_row
        self.flush_steps()
        if self.writer is not None:      # the last good (accepted) state, for --restart
            self.writer.write_timings(self.timers.as_dict())
            self.writer.write_checkpoint(self.checkpoint())
        raise NumericalFailure(
            f"step at t = {self.t:.6g} rejected {n} times in a row (last: {reason}, dt = {dt:.3e}); the last good "
            "state is saved" + (" in the checkpoint" if self.writer is not None else "") +
            (f"; error per unit time {err / dt:.3g} > -ves_adapt_tol {self.opts['adapt_tol']:g} even "
             "at this dt: a floor of spatial error (p, q) that smaller steps cannot reduce"
             if reason == "error_estimate" and dt > 0 else ""))

    def _output(self):
        self.adaptor.output_written(self.t)
        for m in self.monitors:
            m.output(self)

    # ------------------------------------------------------------------ output
    def checkpoint(self):
        """Everything a restart needs to take the steps this run takes from here: the state, the
        step-size proposal, the constraints, the quadrature degrees and the preconditioner's
        record (vesflow.stepper.Stepper.preconditioner_state) and the contact state
        (vesflow.contact.Contacts.as_checkpoint)."""
        ck = dict(self.state.as_checkpoint(), dt=self.dt, area0=self.area0, volume0=self.volume0,
                  next_frame=self.next_frame, n_accepted=self.n_accepted, q_self=self.q_self,
                  q_near=self.q_near, pc=self.stepper.preconditioner_state())
        if self.contacts is not None:
            ck["contact"] = self.contacts.as_checkpoint()
        return ck

    def flush_steps(self):
        if self.writer is not None and self.rows:
            self.writer.write_steps(self.rows)
        self.rows = []

    def save_last_good_state(self):
        """Write the steps so far, the timings and a checkpoint of the last accepted state
        (after an unexpected error: the state is the last accepted one)."""
        if self.writer is None:
            return
        self.flush_steps()
        self.writer.write_timings(self.timers.as_dict())
        if self.writer.last_checkpoint_time != self.t:
            self.writer.write_checkpoint(self.checkpoint(), force=True)
