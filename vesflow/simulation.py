"""A run: scene -> initial state -> time steps -> HDF5 frames and checkpoints.

`Run` wires the parts of vesflow.stepping from a scene and the options: the State (from the
scene or a checkpoint), the Stepper on the partition of the vesicles, the integrator of
-ts_type with the error estimate of -ves_adapt, the Adaptor, the PostStep, the quadrature
adaptation and the monitors; the loop is vesflow.stepping.Driver (docs/explanation/stepping.md).
"""
from __future__ import annotations

import numpy as np

from . import sph
from .contact import Contacts
from .errors import NumericalFailure, SettingsError
from .layerpot.evaluator import Settings
from .layerpot.wall import Wall
from .layerpot.wall import check_degree as check_wall_degree
from .parallel import make_partition
from .setup_state import (initial_coefficients, physics, scene_period, vesicle_params,  # noqa: F401 (re-exported)
                          wall_coefficients, wrap_into_cell)
from .stepper import Stepper
from .stepping import (Adaptor, Checkpoints, Driver, Frames, PostStep, Progress, QuadratureAdaptor, State, StepLog,
                       make_integrator, next_output_time)  # noqa: F401 (next_output_time re-exported)
from .stepping.adaptor import step_q as _step_q  # noqa: F401 (re-exported)
from .surface import Surface
from .timing import Timers


class Run(Driver):
    """Steps the scene's vesicles over its horizon; writes through an io.OutputWriter (or a
    stand-in with its write_frame / write_steps / write_timings / write_checkpoint, or none).
    checkpoint: the dict of vesflow.io.read_checkpoint to continue from (a restart)."""

    def __init__(self, scene, opts, writer=None, checkpoint=None, progress=False, monitor=False, log=print):
        check_available(scene, opts)
        self.scene, self.opts, self.writer, self.p = scene, opts, writer, scene.p
        self.timers, self.period = Timers(), scene_period(scene)
        self.horizon, self.every, self.log = scene.time.horizon, scene.output.every, log
        settings = Settings(q_self=opts["q_self"], q_far=opts["q_near"], near_factor=opts["near_factor"],
                            near_blend=opts["near_blend"], backend=opts["far"], fmm_eps=opts["far_tol"],
                            period=self.period, self_precision=opts["self_precision"], ewald_own=opts["ewald_own"],
                            ewald_grid=opts["ewald_grid"], near_map_mb=opts["near_map_mb"])
        state = (State.initial(initial_coefficients(scene), sph.n_coeffs(self.p)) if checkpoint is None
                 else State.from_checkpoint(checkpoint))
        self.post = PostStep(opts, self.p, None, None, None, self.timers, self.period, lambda: self.q_near)
        self.post.wrap(state)
        self.state = state
        self.part = make_partition(Surface(state.coeffs, self.p).centroid())   # the vesicles over the ranks
        self.post.part = self.part
        self.wall = self._wall(scene, opts)
        self.post.wall = self.wall
        self.stepper = Stepper(state.coeffs, self.p, vesicle_params(scene), physics(scene), settings,
                               coupling=opts["coupling"], timers=self.timers, part=self.part,
                               pc_precision=opts["pc_precision"], pc_factors=opts["pc_factors"],
                               pc_parts=opts["pc_parts"], wall=self.wall)
        self.stepper.pin_start = opts["setup_cache"] == "start"
        if self.wall is not None and checkpoint is None and writer is not None and hasattr(writer, "write_wall"):
            writer.write_wall(self.wall.surface.points()[0], self.wall.surface.coeffs[0], self.wall.p)
        state.load(self.stepper)
        if checkpoint is None:
            S = Surface(state.coeffs, self.p)
            self.area0, self.volume0, self.n_accepted = S.area(), S.volume(), 0
        else:
            self.area0, self.volume0 = np.asarray(checkpoint["area0"]), np.asarray(checkpoint["volume0"])
            self.n_accepted = int(checkpoint["n_accepted"])
            if "q_self" in checkpoint and opts["quad_tol"] > 0:     # the adapted degrees
                settings.q_self, settings.q_far = int(checkpoint["q_self"]), int(checkpoint["q_near"])
            self.stepper.restore_preconditioner(checkpoint.get("pc"))
        self.integrator = make_integrator(opts, self.stepper, self.post)
        self.sdc = getattr(getattr(self.integrator, "base", self.integrator), "sdc", None)
        self.adaptor = Adaptor(opts, scene.time.dt, self.horizon, self.every, self.integrator.order,
                               dt=None if checkpoint is None else float(checkpoint["dt"]),
                               t=None if checkpoint is None else state.t)
        self.quadrature = QuadratureAdaptor(self.stepper, opts["quad_tol"], opts["q_max"], self.timers)
        self.contacts = (Contacts(self.p, self.period, state.coeffs, opts["q_near"])   # vesflow.contact
                         if opts["contact"] and opts["collision"] and scene.n_vesicles > 1 else None)
        if checkpoint is not None and self.contacts is not None:
            self.contacts.restore(checkpoint.get("contact"))
        self.monitors = (([StepLog(log)] if monitor else []) + ([Progress()] if progress else [])
                         + ([Frames(writer), Checkpoints(writer)] if writer is not None else []))
        self.progress, self.monitor = progress, monitor
        self._start_loop()

    # the run's figures, read where they are kept
    t = property(lambda self: self.state.t)
    u = property(lambda self: self.state.u)
    sigma = property(lambda self: self.state.sigma)
    image = property(lambda self: self.state.image)
    dt = property(lambda self: self.adaptor.dt)
    next_frame = property(lambda self: self.adaptor.next_frame)
    err_order = property(lambda self: self.integrator.order)
    reparam_skipped = property(lambda self: self.post.reparam_skipped)
    reparam_iterated = property(lambda self: self.post.reparam_iterated)
    q_self = property(lambda self: int(self.stepper.lp_settings.q_self))
    q_near = property(lambda self: int(self.stepper.lp_settings.q_far))
    area0 = property(lambda self: self.post.area0, lambda self, a: setattr(self.post, "area0", a))
    volume0 = property(lambda self: self.post.volume0, lambda self, v: setattr(self.post, "volume0", v))

    def _wall(self, scene, opts):
        """The container of a scene with [wall] (its self operator and LU built here, once), None
        without; a SettingsError before any step for what walls cannot do yet."""
        if scene.wall is None:
            return None
        if self.part.size > 1:
            raise SettingsError(f"[wall]: walls need one rank (this run has {self.part.size} MPI ranks)")
        with self.timers.stage("wall_setup"):
            return Wall(wall_coefficients(scene.wall), scene.wall.p, q_far=opts["wall_q"], near_factor=opts["near_factor"])

    @property
    def quad_errors(self):
        """The last quadrature error estimates (after an adaptation only: -ves_quad_tol > 0)."""
        if self.quadrature.errors is None:
            raise AttributeError("quad_errors: the quadrature degrees are not adapted (-ves_quad_tol 0)")
        return self.quadrature.errors

    def unwrapped_centroid(self):
        """Centroids (N, 3) with the lattice vectors taken off by the wrap added back."""
        return self.stepper.surface.centroid() + (self.period or 0.0) * self.state.image


def check_available(scene, opts):
    """Refuse what this version cannot run, before any output is created: exit status 3
    (NumericalFailure), or 2 for a [wall] it cannot take (SettingsError: explicit coupling, a
    wall degree too low for the container)."""
    if scene.wall is not None:
        if opts["coupling"] != "implicit":
            raise SettingsError(f"-ves_coupling {opts['coupling']}: a [wall] needs the implicit coupling")
        w = scene.wall
        check_wall_degree(Surface(wall_coefficients(w)[None], w.p), w.p, opts["wall_q"], opts["near_factor"])
    if scene.domain is not None and opts["far"] not in ("auto", "ewald"):
        raise NumericalFailure(f"-ves_far {opts['far']}: a periodic domain ([domain]) needs the Ewald far "
                               "field; use -ves_far ewald or auto")
