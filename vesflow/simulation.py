"""A run: scene -> initial state -> time steps (adaptive, with rejection) -> HDF5 frames and checkpoints.

Adaptive stepping (paper 3.7): the error e = max |X(two steps of dt/2) - X(one step of dt)|
(-ts_type sdc: by default the difference of its last two sweeps, vesflow/sdc.py) is accepted
when e / dt <= E/T (-ves_adapt_tol); the next step is dt (beta (E/T) dt / e)^(1/k) (k = 1 for
the first-order step; for sdc the order of e / dt), within [dt_min, dt_max] and at most doubling.  A step is also rejected (dt halved)
on a GMRES failure, a non-finite result or a collision (paper 3.3).
"""
from __future__ import annotations

import sys
import time as _time

import numpy as np

from . import collision, sph
from .contact import Contacts
from .correction import correct_area_volume, restore_spheres
from .reparam import reparameterize
from .errors import ConvergenceError, NumericalFailure
from .layerpot.evaluator import Settings
from .operator import VesicleParams
from .shapes import make_shape
from .stepper import Physics, Stepper
from .surface import Surface
from .timing import Timers


def initial_coefficients(scene):
    """Position coefficients (N, 3, C) of the scene's vesicles."""
    p = scene.p
    out = np.empty((scene.n_vesicles, 3, sph.n_coeffs(p)))
    for k, v in enumerate(scene.vesicles):
        out[k] = make_shape(v.shape, p, radius=v.radius, center=v.center, rotation=v.rotation,
                            reduced_volume=v.reduced_volume if v.shape in ("oblate", "prolate", "biconcave") else None,
                            axes=v.axes)
    return out


def vesicle_params(scene):
    ves = scene.vesicles
    return VesicleParams([v.bending_modulus for v in ves], [v.viscosity_contrast for v in ves],
                         [v.excess_density for v in ves], scene.fluid.viscosity)


def physics(scene):
    flow, args = None, {}
    if scene.flow is not None and (scene.flow.rate or scene.flow.amplitude):   # rate 0: no flow, no cost
        flow = scene.flow.type
        if flow == "taylor_green":
            args = {"amplitude": scene.flow.amplitude, "period": scene.periodic_length}
        elif flow == "poiseuille":
            args = {"rate": scene.flow.rate, "radius": scene.flow.radius}
        else:
            args = {"rate": scene.flow.rate}
    g = scene.gravity.g if scene.gravity is not None else None
    R = scene.repulsion.radius if scene.repulsion is not None else 0.0
    return Physics(flow, args, g, R or 0.0, scene.fluid.viscosity)


class Run:
    """Drives a Stepper over the scene's horizon; writes through an io.OutputWriter (or none)."""

    def __init__(self, scene, opts, writer=None, checkpoint=None, progress=False, monitor=False, log=print):
        check_available(scene, opts)
        self.scene, self.opts, self.writer = scene, opts, writer
        self.p = scene.p
        self.timers = Timers()
        settings = Settings(q_self=opts["q_self"], q_far=opts["q_near"], near_factor=opts["near_factor"], near_blend=opts["near_blend"],
                            backend=_backend(opts["far"]), fmm_eps=opts["far_tol"],
                            period=scene.periodic_length or None, self_precision=opts["self_precision"],
                            ewald_own=opts["ewald_own"])
        params = vesicle_params(scene)
        phys = physics(scene)
        coeffs = initial_coefficients(scene) if checkpoint is None else np.asarray(checkpoint["coeffs"])
        # periodic: lattice vectors / L taken off each vesicle so far (the unwrapped position is
        # the stored one + L image); a checkpoint without them (free space, older files) has none
        self.image = np.zeros((scene.n_vesicles, 3), dtype=np.int64)
        if checkpoint is not None and "image" in checkpoint:
            self.image = np.asarray(checkpoint["image"], dtype=np.int64).reshape(-1, 3).copy()
        period = scene_period(scene)
        if period is not None:
            coeffs, moved = wrap_into_cell(coeffs, self.p, period)
            self.image += moved
        from .parallel import make_partition, world_size
        # the vesicles over the MPI ranks (None with one process: nothing gathered)
        self.part = make_partition(Surface(coeffs, self.p).centroid()) if world_size() > 1 else None
        self.contacts = None              # touching steps in contact (vesflow/contact.py)
        if opts["contact"] and opts["collision"] and scene.n_vesicles > 1:
            self.contacts = Contacts(self.p, period, coeffs, opts["q_near"])
        self.stepper = Stepper(coeffs, self.p, params, phys, settings, coupling=opts["coupling"],
                               timers=self.timers, part=self.part, pc_precision=opts["pc_precision"])
        self.sdc = None                   # -ts_type sdc: the SDC steps of the stepper
        self.err_order = 1                # k of the step update dt (beta tol dt / err)^(1/k)
        if opts["ts_type"] == "sdc":
            from .sdc import SDC
            from .sdc import collocation_order
            self.sdc = SDC(self.stepper, opts["ts_sdc_nodes"], opts["ts_sdc_sweeps"], opts["ts_sdc_quadrature"])
            K, top = opts["ts_sdc_sweeps"], collocation_order(opts["ts_sdc_nodes"], opts["ts_sdc_quadrature"])
            # sweeps: d_K, the local error of K - 1 sweeps, dt^(K + 1); contraction: the estimate of
            # the kept K-sweep state (sdc.error_estimate), dt^(K + 2) for K >= 2 (one sweep: d_1)
            self.err_order = {"doubling": min(K + 1, top), "sweeps": min(K, top),
                              "contraction": min(K + 1, top) if K >= 2 else 1}.get(opts["adapt"], 1)
        if phys.repulsion_radius > 0:
            from .repulsion import repulsion_force
            R = phys.repulsion_radius
            self.stepper.extra_force = lambda surf, geo: repulsion_force(surf, self.stepper.lp_current, R,
                                                                         self.stepper.q_force)
        self.horizon = scene.time.horizon
        self.every = scene.output.every
        self.progress, self.monitor, self.log = progress, monitor, log
        self.counts = {"accepted": 0, "rejected": 0}
        self.reparam_skipped = 0          # accepted steps whose reparameterization would have made contact
        self.reparam_iterated = 0         # accepted steps kept out of contact by the iterated projection
        self.rows = []
        self.iterations = 0               # GMRES iterations of every solve of this process
        self.first_step_at = None         # perf_counter() when the first step began
        self.last_failure = ""            # the message of the last failed solve (for -ts_monitor)
        if checkpoint is None:
            S = Surface(coeffs, self.p)
            self.area0, self.volume0 = S.area(), S.volume()
            self.t, self.dt, self.next_frame, self.n_accepted = 0.0, scene.time.dt, 0.0, 0
            self.sigma = np.zeros((scene.n_vesicles, sph.n_coeffs(self.p)))
            self.u = np.zeros_like(coeffs)
        else:
            self.area0, self.volume0 = np.asarray(checkpoint["area0"]), np.asarray(checkpoint["volume0"])
            self.t, self.dt = float(checkpoint["time"]), float(checkpoint["dt"])
            self.n_accepted = int(checkpoint["n_accepted"])
            # the frame sequence continues at the next multiple of `every` (the checkpoint's
            # next_frame unless the restart changes -ves_output_every): a checkpoint is written
            # after the frame of its time, if that time is an output time
            self.next_frame = next_output_time(self.t, self.every)
            self.sigma, self.u = np.asarray(checkpoint["sigma"]), np.asarray(checkpoint["u"])
            if int(checkpoint["has_last"]):
                from .stepper import Solution
                self.stepper.last = Solution(self.u.copy(), self.sigma.copy(), 0, 0)
            self.stepper.time = self.t
            if "q_self" in checkpoint and opts["quad_tol"] > 0:     # the adapted degrees
                settings.q_self, settings.q_far = int(checkpoint["q_self"]), int(checkpoint["q_near"])

    # ------------------------------------------------------------------ one attempted step
    def _try(self, dt):
        """Candidate state after dt (adaptive or not) or a rejection reason."""
        st = self.stepper
        saved = (st.coeffs.copy(), st.time, st.last)
        adapt = self.opts["adapt"]
        advance = st.step if self.sdc is None else (lambda h: self.sdc.step(h)[0])
        try:
            sol = advance(dt)
            its = sol.its
            err = 0.0
            if adapt == "doubling":
                one = st.coeffs.copy()
                st.coeffs, st.time, st.last = saved[0].copy(), saved[1], saved[2]
                s1 = advance(0.5 * dt)
                if self.opts["correct"] == "area_volume":   # a sphere stays the standard sphere
                    st.coeffs = restore_spheres(st.coeffs, self.p, self.area0, self.volume0)[0]
                s2 = advance(0.5 * dt)
                its += s1.its + s2.its
                sol = s2
                err = self._doubling_error(one, st.coeffs)
            elif adapt == "sweeps":
                err = self.sdc.error
            elif adapt == "contraction":
                err = self.sdc.contraction_error
            elif adapt == "invariants":
                S = st.surface
                err = float(max(np.abs(S.area() / self.area0 - 1).max(), np.abs(S.volume() / self.volume0 - 1).max()))
            if not (np.all(np.isfinite(st.coeffs)) and np.isfinite(err)):   # NaN in either candidate
                raise ConvergenceError("non-finite state", reason="nan", iterations=its)
        except ConvergenceError as e:
            self.last_failure = str(e)
            st.coeffs, st.time, st.last = saved
            reason = "nonfinite" if e.reason == "nan" else "ksp"
            return None, reason, getattr(e, "iterations", 0) or 0, np.inf
        tol = self.opts["adapt_tol"]
        if adapt != "none" and err / dt > tol:
            st.coeffs, st.time, st.last = saved
            return None, "error_estimate", its, err
        # the post-step (reparameterize, correct) changes the surface between grid points at
        # the truncation error, which near contact is the size of the gap: check collisions on
        # the state that will be kept, and drop the reparameterization of this step if it
        # alone brings the surfaces into contact.  In between, the reparameterization with its
        # projection iterated (`reparam.project_onto`: shape change below the truncation error,
        # not used everywhere because it keeps the descent from converging, docs/robustness.md)
        raw = st.coeffs.copy()
        st.coeffs = self._post_processed(raw, self.opts["reparam"], dt=dt)
        check = self.opts["collision"] and st.surface.n_vesicles > 1
        if check and self._touching():
            touching = True
            if self.opts["reparam"]:
                st.coeffs = self._post_processed(raw, True, project_its=10, dt=dt)
                touching = self._touching()
                self.reparam_iterated += int(not touching)
                if touching:
                    st.coeffs = self._post_processed(raw, False)
                    touching = self._touching()
                    self.reparam_skipped += int(not touching)
            if touching and self.contacts is not None:      # in contact: separate (vesflow/contact.py)
                separated = self.contacts.resolve(st.coeffs, saved[0], self.q_near)
                if separated is not None:
                    st.coeffs = separated
                    touching = self._touching()
            if touching:
                st.coeffs, st.time, st.last = saved
                return None, "collision", its, err
        if check and self.contacts is not None:           # in contact: not closer than the target
            st.coeffs = self.contacts.keep_apart(st.coeffs, self.q_near)
        return sol, "accepted", its, err

    def _touching(self):
        with self.timers.stage("collision"):
            if self.part is None:
                return collision.contacts(self.stepper.surface, self.q_near, scene_period(self.scene)) > 0
            # this rank's points against every surface, the counts summed over the ranks
            mine = collision.contacts(self.stepper.surface, self.q_near, scene_period(self.scene), part=self.part)
            return self.part.sum(mine) > 0

    def _attempt(self, dt):
        """_try(dt), noting the attempt (for `position`); if it raises, the stepper is put back
        to the last accepted state first."""
        st = self.stepper
        saved = (st.coeffs.copy(), st.time, st.last)
        self.attempt = (self.counts["accepted"] + self.counts["rejected"] + 1, self.t, dt)
        try:
            out = self._try(dt)
        except BaseException:
            st.coeffs, st.time, st.last = saved
            raise
        self.attempt = None
        return out

    def position(self):
        """Where the run is, for an error message: 'step 3 (t = 0.1, dt = 0.05)'."""
        a = getattr(self, "attempt", None)
        if a is not None:
            return f"step {a[0]} (t = {a[1]:.6g}, dt = {a[2]:.3g})"
        n = self.counts["accepted"] + self.counts["rejected"]
        return f"after step {n} (t = {self.t:.6g})" if n else f"before the first step (t = {self.t:.6g})"

    def save_last_good_state(self):
        """Write the steps so far, the timings and a checkpoint of the last accepted state
        (after an unexpected error: `_attempt` has put the stepper back to it)."""
        if self.writer is None:
            return
        self._flush_steps()
        self.writer.write_timings(self.timers.as_dict())
        if self.writer.last_checkpoint_time != self.t:
            self.writer.write_checkpoint(self.checkpoint(), force=True)

    def _landing_dt(self):
        """The step to take from t and the time it lands on (or None): the adaptive proposal
        self.dt, shortened to end exactly at the next output time or the horizon when it would
        pass it (or stretched by at most 1% to reach it, so no sliver steps are left)."""
        target = min(self.next_frame, self.horizon)
        gap = target - self.t
        if self.dt >= gap / (1.0 + _STRETCH):
            return gap, target
        return self.dt, None

    def _doubling_error(self, one, two):
        """max |n . (X(two steps of dt/2) - X(one step of dt))| on the grid: the difference of
        the shapes, both candidates first moved onto the area/volume constraint set (the
        correction the post-step applies).  Tangential differences are left out as the
        reparameterization leaves them out: it moves the points tangentially at will.

        A sphere of fixed area and volume cannot deform, yet the linearized inextensibility
        lets the step deform it at O(dt) (the l = 2 velocity of a sphere in a strain,
        docs/dynamics.md): one step deforms by dt u, two half steps by less (the first half
        step leaves a near-sphere whose tension locks the deformation), and the raw difference
        is O(dt), driving dt to dt_min.  After the correction (for a sphere: the sphere of volume
        V0) both candidates differ by the O(dt^2) truncation error as for any other shape, in
        their normal part (measured, p = 12, rate 1: err / dt = 0.038 dt normal; the tangential
        part is 0.27 dt whatever dt: the locked sphere's tank-treading differs between them).

        Only for (near-)spheres, reduced volume above 1 - NEAR_SPHERE: every other vesicle keeps
        the raw difference of the candidates (the estimate of paper 3.7).  Applied to all shapes,
        the corrected normal part let the accuracy-cost study's steps grow (p = 12, E = 0.07:
        219 solves instead of 306) and its error stall near 4e-3 whatever E (E^0.37).
        """
        area0, volume0 = self.area0, self.volume0
        if self.part is not None:         # this rank's vesicles, the largest error over the ranks
            idx = self.part.idx
            one, two, area0, volume0 = one[idx], two[idx], _rows(area0, idx), _rows(volume0, idx)
            return self.part.max(self._vesicle_doubling_error(one, two, area0, volume0))
        return self._vesicle_doubling_error(one, two, area0, volume0)

    def _vesicle_doubling_error(self, one, two, area0, volume0):
        """_doubling_error of the vesicles of one and two (area0, volume0 theirs)."""
        raw = np.linalg.norm(np.moveaxis(Tgrid(self.p, two - one), -2, -1), axis=-1).max(axis=1)
        near_sphere = Surface(one, self.p).reduced_volume() > 1.0 - NEAR_SPHERE
        if not near_sphere.any():
            return float(raw.max())
        if self.opts["correct"] == "area_volume":
            with self.timers.stage("other"):
                o = self.opts
                one = correct_area_volume(one, self.p, area0, volume0,
                                          tol=o["correct_tol"], max_its=o["correct_max_its"])[0]
                two = correct_area_volume(two, self.p, area0, volume0,
                                          tol=o["correct_tol"], max_its=o["correct_max_its"])[0]
        d = np.moveaxis(Tgrid(self.p, two - one), -2, -1)                  # (N, M, 3) on the p-grid
        normal = Surface(one, self.p).geometry(self.p).normal
        locked = np.abs(np.einsum("vmk,vmk->vm", d, normal)).max(axis=1)
        return float(np.where(near_sphere, locked, raw).max())

    def _next_dt(self, dt, err):
        o = self.opts
        if o["adapt"] == "none":
            return self.scene.time.dt
        if err <= 0:
            new = 2.0 * dt
        else:
            new = dt * min(2.0, o["adapt_beta"] * (o["adapt_tol"] * dt / err) ** (1.0 / self.err_order))
        if o["dt_max"] is not None:
            new = min(new, o["dt_max"])
        return max(new, o["dt_min"])

    # ------------------------------------------------------------------ the loop
    def run(self):
        st = self.stepper
        t_start = _time.perf_counter()
        if self.first_step_at is None:
            self.first_step_at = t_start
        if self.n_accepted == 0 and self.t == 0.0:             # frame 0 (without a writer: the next output time)
            self._frame()
        rejects_in_row = 0
        max_steps = self.opts["ts_max_steps"]
        while self.t < self.horizon * (1 - 1e-12):
            if max_steps is not None and self.n_accepted >= max_steps:
                break
            dt, target = self._landing_dt()
            q_used = (self.q_self, self.q_near)
            sol, reason, its, err = self._attempt(dt)
            accepted = sol is not None
            self.rows.append((self.t, dt, int(accepted), its, err, reason) + q_used)
            self.iterations += its
            if self.monitor:
                self.log(f"step {self.counts['accepted'] + self.counts['rejected']:5d} t={self.t:.6g} dt={dt:.3e} its={its} err={err:.2e} q={q_used[0]}/{q_used[1]} {reason}"
                         + (f" ({self.last_failure})" if reason in ("ksp", "nonfinite") else ""))
            if accepted:
                rejects_in_row = 0
                self.counts["accepted"] += 1
                self.n_accepted += 1
                if target is not None:           # landed on an output time or the horizon
                    st.time = target
                self.t = st.time
                self.u, self.sigma = sol.u, sol.sigma
                self._wrap()
                if self.opts["quad_tol"] > 0:
                    self._adapt_quadrature()
                proposal = self._next_dt(dt, err)
                # a step shortened to land keeps the proposal of the step it replaced
                self.dt = max(self.dt, proposal) if dt < self.dt else proposal
                if self.t >= self.next_frame - _time_tol(self.t) or self.t >= self.horizon * (1 - 1e-12):
                    self._frame()
            else:
                self.counts["rejected"] += 1
                rejects_in_row += 1
                self.dt = 0.5 * dt if reason != "error_estimate" else max(self._next_dt(dt, err), 0.0)
                if reason == "error_estimate":
                    self.dt = min(self.dt, 0.9 * dt)
                if self.dt < self.opts["dt_min"] or rejects_in_row >= self.opts["max_rejects"]:
                    self._flush_steps()
                    if self.writer is not None:      # the last good (accepted) state, for --restart
                        self.writer.write_timings(self.timers.as_dict())
                        self.writer.write_checkpoint(self.checkpoint())
                    raise NumericalFailure(
                        f"step at t = {self.t:.6g} rejected {rejects_in_row} times in a row (last: {reason}, "
                        f"dt = {dt:.3e}); the last good state is saved" +
                        (" in the checkpoint" if self.writer is not None else "") +
                        (f"; error per unit time {err / dt:.3g} > -ves_adapt_tol {self.opts['adapt_tol']:g} even "
                         "at this dt: a floor of spatial error (p, q) that smaller steps cannot reduce"
                         if reason == "error_estimate" and dt > 0 else ""))
            if self.progress:
                self._progress(t_start)
        if self.progress:
            sys.stderr.write("\n")
        self._flush_steps()
        if self.writer is not None:
            self.writer.write_timings(self.timers.as_dict())
        return self

    @property
    def q_self(self):
        return int(self.stepper.lp_settings.q_self)

    @property
    def q_near(self):
        return int(self.stepper.lp_settings.q_far)

    def _adapt_quadrature(self):
        """Paper 3.2.4: the double-layer identity sum_j D_j[1] = 1, 1/2, 0 inside / on / outside,
        checked on the layer potentials of the last solve (self regime -> q_self; near and far
        regimes, which share one grid -> q_near).  q + 1 above -ves_quad_tol, q - 1 below a tenth
        of it (the dead band keeps q from flipping every step), within [p (p + 1 for q_self), -ves_q_max]."""
        lp = self.stepper.lp_last
        if lp is None:
            return
        with self.timers.stage("quad_adapt"):
            e = lp.error_estimate()
        tol, lo, hi = self.opts["quad_tol"], self.p, self.opts["q_max"]
        s = self.stepper.lp_settings
        s.q_self = _step_q(self.q_self, e["self"], tol, lo + 1, hi)      # Graham-Sloan needs q > p
        s.q_far = _step_q(self.q_near, max(e["near"], e["far"]), tol, lo, hi)
        self.quad_errors = e

    def _post_processed(self, coeffs, reparam, project_its=1, dt=0.0):
        """Reparameterize (if reparam), then restore area and volume (the reparameterization
        moves points tangentially but changes A and V at the discretization error, ~1e-6; the
        correction after it leaves them at -ves_correct_tol).  With a partition each rank
        processes its vesicles (both act per vesicle) and the results are gathered."""
        if self.part is None:
            return self._post_process(coeffs, reparam, project_its, self.area0, self.volume0, dt)
        idx = self.part.idx
        mine = self._post_process(coeffs[idx], reparam, project_its, _rows(self.area0, idx), _rows(self.volume0, idx), dt)
        with self.timers.stage("gather"):
            return self.part.gather(mine)

    def _post_process(self, coeffs, reparam, project_its, area0, volume0, dt=0.0):
        """Reparameterize, correct area and volume, then (-ves_keep_centroid) translate each
        vesicle back to the centroid the step gave it.  Neither part is motion: the
        reparameterization moves points tangentially (its shape change is the truncation error),
        the correction is a normal move psi n (3.20); on a sheared, asymmetric shape both shift
        the volume centroid, by 2e-6 ... 2e-5 per step in the accuracy-cost pair (p = 8, sdc),
        as much as the step's own error and not seen by any step-error estimate.  A rigid
        translation changes neither area, volume nor parameterization.

        The reparameterization takes up to max(-ves_reparam_max_its, -ves_reparam_rate dt)
        descent steps: the grid distorts at a rate per unit simulated time, so the descent's
        budget is per unit time too.  With a fixed budget per step (20), a run of 20 sdc steps
        reparameterized 15x less than one of 300 euler steps: every call stopped at the cap and
        the mesh energy rose to 22 instead of 16 (accuracy-cost pair, p = 8), a spatial error
        set by the number of steps, not by the tolerance."""
        o = self.opts
        if o["keep_centroid"]:
            c0 = Surface(coeffs, self.p).centroid()
        if reparam:
            with self.timers.stage("reparam"):
                coeffs, _, _, _ = reparameterize(coeffs, self.p, dtau_max=o["reparam_dtau_max"],
                                                 tol=o["reparam_tol"],
                                                 max_its=max(o["reparam_max_its"], int(np.ceil(o["reparam_rate"] * dt))),
                                                 attenuation=o["reparam_attenuation"],
                                                 project_its=project_its)
        if o["correct"] == "area_volume":
            with self.timers.stage("correction"):
                coeffs, _, _ = correct_area_volume(coeffs, self.p, area0, volume0,
                                                   tol=o["correct_tol"], max_its=o["correct_max_its"])
        if o["keep_centroid"]:
            coeffs = Surface(coeffs, self.p).translated(c0 - Surface(coeffs, self.p).centroid()).coeffs
        return coeffs

    def _wrap(self):
        """Periodic runs, at a step boundary: a vesicle whose centroid left the cell [0, L)^3
        is moved back by a lattice vector (exact for the periodic sums, the minimum-image near
        field and the periodic background flow), counted in self.image."""
        L = scene_period(self.scene)
        if L is None:
            return
        st = self.stepper
        with self.timers.stage("other"):
            coeffs, moved = wrap_into_cell(st.coeffs, self.p, L, centroid=st.surface.centroid())
        if np.any(moved):
            st.coeffs = coeffs
            self.image += moved

    def unwrapped_centroid(self):
        """Centroids (N, 3) with the lattice vectors taken off by the wrap added back."""
        L = scene_period(self.scene) or 0.0
        return self.stepper.surface.centroid() + L * self.image

    # ------------------------------------------------------------------ output
    def _frame(self):
        with self.timers.stage("output"):
            self._write_frame()

    def _write_frame(self):
        if self.writer is None:
            self.next_frame = next_output_time(self.t, self.every)
            return
        if self.part is not None and _is_peer(self.writer):     # an MPI rank other than 0: rank 0 writes
            self.next_frame = next_output_time(self.t, self.every)
            self.rows = []
            self.writer.write_checkpoint(self.checkpoint())
            return
        p = self.p
        S = self.stepper.surface
        Tp = sph.transform(p)
        kappa = self.stepper.params.kappa
        periodic = {"image": self.image} if scene_period(self.scene) is not None else {}
        self.writer.write_frame(
            time=self.t, points=S.points(), coefficients=S.coeffs, tension=Tp.synth(self.sigma),
            area=S.area(), volume=S.volume(), centroid=self.unwrapped_centroid(),
            bending_energy=S.bending_energy(kappa), velocity=np.moveaxis(Tp.synth(self.u), -2, -1),
            poles=S.pole_points(), **periodic)
        self.next_frame = next_output_time(self.t, self.every)
        self._flush_steps()
        self.writer.write_timings(self.timers.as_dict())
        self.writer.write_checkpoint(self.checkpoint())

    def checkpoint(self):
        return {"time": self.t, "dt": self.dt, "coeffs": self.stepper.coeffs, "area0": self.area0,
                "volume0": self.volume0, "next_frame": self.next_frame, "n_accepted": self.n_accepted,
                "sigma": self.sigma, "u": self.u, "has_last": int(self.stepper.last is not None),
                "q_self": self.q_self, "q_near": self.q_near, "image": self.image}

    def _flush_steps(self):
        if self.writer is not None and self.rows:
            self.writer.write_steps(self.rows)
        self.rows = []

    def _progress(self, t0):
        last = self.rows[-1] if self.rows else (0, 0, 0, 0, 0, "")
        sys.stderr.write(f"\r t = {self.t:9.4f} / {self.horizon:g}  dt = {self.dt:.2e}  its = {last[3]:3d}  "
                         f"accepted {self.counts['accepted']}  rejected {self.counts['rejected']}  "
                         f"wall {_time.perf_counter() - t0:7.1f} s ")
        sys.stderr.flush()


def check_available(scene, opts):
    """Refuse (exit status 3) what this version cannot run, before any output is created."""
    if scene.domain is not None and opts["far"] not in ("auto", "ewald"):
        raise NumericalFailure(f"-ves_far {opts['far']}: a periodic domain ([domain]) needs the Ewald far "
                               "field; use -ves_far ewald or auto")
    _backend(opts["far"])


_STRETCH = 0.01     # a step may grow by this fraction to land on an output time
NEAR_SPHERE = 2e-3  # reduced volume above 1 - NEAR_SPHERE: the doubling error's normal part only


def _time_tol(t):
    return 1e-9 * max(1.0, abs(t))


def next_output_time(t, every):
    """The first multiple k * every (k integer) after t (by more than the rounding of t):
    frames are due at 0, every, 2 every, ..., whatever steps were taken (also after a restart,
    or a restart with another -ves_output_every)."""
    k = np.floor(t / every + _time_tol(t / every)) + 1.0
    return float(k * every)


def _step_q(q, err, tol, lo, hi):
    if not np.isfinite(err) or err > tol:
        return min(q + 1, hi)
    if err < 0.1 * tol:
        return max(q - 1, lo)
    return q


def _is_peer(writer):
    from .io.peer import PeerWriter
    return isinstance(writer, PeerWriter)


def _rows(a, idx):
    """a[idx] for a per-vesicle array, a itself for a scalar."""
    a = np.asarray(a)
    return a[idx] if a.ndim else a


def Tgrid(p, c):
    return sph.transform(p).synth(c)


def wrap_into_cell(coeffs, p, period, centroid=None):
    """Move each vesicle by the lattice vector -L k, k = floor(centroid / L), so that its
    centroid lies in [0, L)^3: the l = 0 coefficient of x, y, z changes by -sqrt(4 pi) L k.
    Returns (coefficients, k (N, 3) integers); the input is not changed."""
    if centroid is None:
        centroid = Surface(coeffs, p).centroid()
    k = np.floor(np.asarray(centroid) / period).astype(np.int64)
    if not np.any(k):
        return coeffs, k
    out = np.array(coeffs, dtype=float)
    out[:, :, 0] -= np.sqrt(4.0 * np.pi) * period * k
    return out, k


def scene_period(scene):
    """The period of a triply periodic scene, None in free space."""
    return scene.periodic_length or None


def _backend(name):
    return name
