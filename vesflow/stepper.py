"""One semi-implicit step and the first-order stepper (docs/explanation/method.md, section 6; paper 3.6).

    alpha u - sum_j [S_ij(dt B_j[u_j] + f_sigma(sigma_j)) - D_ij u_j]   (sign of D: see operator.py)
          = u_inf(X^n) + sum_j S_ij (f_b(X_j^n) + f_g,j + f_r,j),      div u = 0,
    X^{n+1} = X^n + dt u.

The linear system is a petsc4py Mat of type python (operator.StepOperator) solved by KSP
(GMRES by default, every -ksp_* option honoured); the default preconditioner is the
block-Jacobi PC context unless the command line names another.  One Mat and one KSP per
stepper, made at the first solve and reused (the Mat takes each solve's operator as its
context); `close` destroys them.  The vesicles are those of a `vesflow.parallel.Partition`
(one process: the one-rank partition, every vesicle).
"""
from __future__ import annotations

import copy
import time

import numpy as np

from . import forces, repulsion, sph
from .errors import ConvergenceError
from .flows import background_velocity
from .layerpot.evaluator import LayerPotentials, Settings
from .layerpot.wall import WallCoupling
from .operator import StepOperator
from .parallel import Partition
from .precond import PC_DTYPES, BlockJacobi, _PerVesicle
from .setup_state import Physics  # noqa: F401  (re-exported: vesflow.stepper.Physics)
from .solver import configure_ksp
from .surface import Surface
from .threads import adapt_openmp
from .timing import Timers


class Solution:
    """Velocity u (N, 3, C) and tension sigma (N, C) coefficients, with the KSP record; wall:
    the container's density coefficients (3 C_w,) or None."""

    def __init__(self, u, sigma, its, reason, wall=None):
        self.u, self.sigma, self.its, self.reason, self.wall = u, sigma, its, reason, wall


class Stepper:
    """Holds the state (position coefficients) and advances it with first-order steps."""

    def __init__(self, coeffs, p, params, physics=None, lp_settings=None, coupling="implicit",
                 q_force=None, timers=None, ksp_prefix=None, part=None, pc_precision=None, pc_factors=None,
                 pc_parts=None, wall=None):
        self.coeffs = np.array(coeffs, dtype=float)
        self.wall = wall            # a container (vesflow.layerpot.wall.Wall) or None
        # vesflow.parallel.Partition of the vesicles (None: this process owns every vesicle)
        self.part = part if part is not None else Partition.single(len(self.coeffs))
        self.params_local = params.take(self.part.idx)
        self.p = p
        self.params = params
        self.physics = physics or Physics(viscosity=params.mu)
        self.lp_settings = lp_settings or Settings()
        self.coupling = coupling
        self.q_force = q_force or 2 * p
        self.timers = timers or Timers()
        self.ksp_prefix = ksp_prefix
        self.pc_precision = pc_precision   # of the default block-Jacobi PC (None: -ves_pc_precision)
        self.pc_factors, self.pc_parts = pc_factors, pc_parts   # its kept LU sets and parts (None: the options)
        self.time = 0.0
        self.last = None            # last Solution: initial guess of the next solve
        self.lock_spheres = True    # a sphere's normal velocity of degree >= 2 held at 0 (sphere_constraints)
        self.cond_estimate = None   # of the last solve's preconditioned operator (_condition_estimate)
        self.cond_max = 0.0         # the largest of them so far
        self.lp_cache_size = 1      # layer potentials kept for this many surfaces (the most recent)
        self.lp_pinned = None       # a Surface whose layer potentials are kept besides them (SDC: the step's start)
        self.pin_start = True       # SDC may pin its step's start (-ves_setup_cache start; current: no pin)
        self.lp_last = self.lp_current = None
        self.ksp_seconds = 0.0      # wall seconds inside KSPSolve, and its iterations, summed over the solves
        self.ksp_its = 0
        self._lp_cache = []
        self._ksp = None            # the one KSP (with its Mat and vectors), made at the first solve
        self._pc_record = None      # a preconditioner_state to rebuild at the next solve (a restart)
        self._pc_adopted = False    # the first KSP's PC context became _pc_context

    @property
    def surface(self):
        """The Surface of the current coefficients; the same object (with its cached geometry)
        while they do not change, so that the solves of one step share their set-up."""
        cached = getattr(self, "_surface", None)
        if cached is None or not np.array_equal(cached.coeffs, self.coeffs):
            cached = self._surface = Surface(self.coeffs.copy(), self.p)
        return cached

    def close(self):
        """Destroy the KSP, its Mat and vectors (made again by a later solve)."""
        if self._ksp is not None:
            for obj in self._ksp[:5]:
                obj.destroy()
        self._ksp = None

    def preconditioner_state(self):
        """What rebuilds the default preconditioner as it is now (a checkpoint entry): the
        coefficients and quadrature degrees its block parts were built at, the dt of each kept LU
        factorization (oldest first) and its reuse counters.  {"built": 0} before any (or for a
        context without reuse state)."""
        ctx = getattr(self, "_pc_context", None)
        if not isinstance(ctx, _PerVesicle) or ctx.parts_record is None:
            return {"built": 0}
        rec = ctx.parts_record
        return {"built": 1, "coeffs": np.array(rec["coeffs"]), "q_self": rec["q_self"], "q_far": rec["q_far"],
                "factor_dt": np.array([dt for dt, _ in ctx.factors], dtype=float),
                "base_its": -1 if ctx.base_its is None else int(ctx.base_its), "uses": int(ctx.uses),
                "stale": int(ctx.stale), "rebuilds": int(ctx.rebuilds), "rebuild_its": float(ctx.rebuild_its),
                "excess_its": int(ctx.excess_its)}

    def restore_preconditioner(self, state):
        """Rebuild the preconditioner of preconditioner_state() `state` at the next solve: the
        same parts and factors from the same coefficients, so that a restart takes the iterates
        of the uninterrupted run."""
        self._pc_record = state if state is not None and int(state.get("built", 0)) else None

    def _rebuild_preconditioner(self, ctx, rec):
        if not isinstance(ctx, _PerVesicle):
            return
        settings = copy.copy(self.lp_settings)
        settings.q_self, settings.q_far = int(rec["q_self"]), int(rec["q_far"])
        lp = LayerPotentials(Surface(np.asarray(rec["coeffs"], dtype=float), self.p), lam=self.params.lam,
                             viscosity=self.params.mu, settings=settings, timers=self.timers, part=self.part)
        dts = np.atleast_1d(np.asarray(rec["factor_dt"], dtype=float))
        op = sphere_constraints(lp.local, StepOperator(lp.local, self.params_local, dts[0] if len(dts) else 0.0,
                                                       lp, self.q_force, self.coupling), self.lock_spheres)
        ctx.parts, ctx.factors, ctx.lu = None, [], None
        ctx.build_parts(op)
        for dt in dts:
            op.dt = float(dt)
            ctx._factors_for(op)
        if not ctx.keep_parts:
            ctx.parts = None
        base = int(rec["base_its"])
        ctx.base_its, ctx.uses, ctx.stale = (None if base < 0 else base), int(rec["uses"]), bool(rec["stale"])
        ctx.rebuilds, ctx.rebuild_its, ctx.excess_its = int(rec["rebuilds"]), float(rec["rebuild_its"]), int(rec["excess_its"])

    def reset_preconditioner(self):
        """Forget the preconditioner's parts and factors (a checkpoint: restarts take the same steps)."""
        ctx = getattr(self, "_pc_context", None)
        if ctx is not None and hasattr(ctx, "reset"):
            ctx.reset()
        else:
            self._pc_context = None

    # ------------------------------------------------------------------ pieces of one solve
    def _setup(self, surface, dt):
        """Layer potentials of the surface (kept while the surface and the quadrature degrees do
        not change: the step and half step of step doubling share them; the last lp_cache_size
        surfaces) and the step operator."""
        key = (id(surface), self.lp_settings.q_self, self.lp_settings.q_far)
        cache = self._lp_cache
        lp = next((c[1] for c in cache if c[0] == key and c[1].surface is surface), None)
        if lp is None:
            self._evict(self.lp_cache_size - 1)  # room first: the evicted are freed before the new set-up
            lp = LayerPotentials(surface, lam=self.params.lam, viscosity=self.params.mu,
                                 settings=self.lp_settings, timers=self.timers, part=self.part)
        else:
            cache.remove((key, lp))
        cache.append((key, lp))                 # most recently used last
        self._evict(self.lp_cache_size)
        op = StepOperator(lp.local, self.params_local, dt, lp, self.q_force, self.coupling, self._wall_coupling(lp))
        return lp, op

    def _evict(self, keep):
        """Keep the layer potentials of the `keep` most recent surfaces and of lp_pinned; drop the
        other references to those evicted (the last solve's, the Mat's operator), so that they
        are freed now."""
        cache = self._lp_cache
        pinned = [c for c in cache if self.lp_pinned is not None and c[1].surface is self.lp_pinned]
        rest = [c for c in cache if c not in pinned]
        cache[:] = pinned + (rest[len(rest) - keep:] if keep > 0 else [])
        alive = [c[1] for c in cache]
        for _, lp in rest:                      # the geometries of the surfaces evicted (not the stepper's own)
            if all(lp is not a for a in alive) and lp.surface is not getattr(self, "_surface", None):
                lp.surface.release_geometry()
        if all(self.lp_last is not lp for lp in alive):
            self.lp_last = None
        if all(self.lp_current is not lp for lp in alive):
            self.lp_current = None
        old = self._ksp[0].getPythonContext() if self._ksp is not None else None
        if old is not None and all(getattr(old, "lp", None) is not lp for lp in alive):
            old.lp = None                       # that operator is replaced at this solve (_solver)

    def _wall_coupling(self, lp):
        """The container's coupling to the vesicles of lp's geometry (kept with lp), None without a wall."""
        if self.wall is None:
            return None
        if getattr(lp, "wall_coupling", None) is None:
            with self.timers.stage("wall_setup"):
                lp.wall_coupling = WallCoupling(self.wall, lp)
        return lp.wall_coupling

    def explicit_traction(self, surface, geo):
        """f_b(X^n) + f_g + f_r (3.13, with the near pairs of the solve's layer potentials) on the
        force grid (N, npts, 3)."""
        prm = self.params_local
        f = forces.bending_force(geo, prm.kappa)
        if self.physics.gravity is not None and np.any(self.params.drho != 0):
            f = f + forces.gravity_force(geo, prm.drho, self.physics.gravity)
        if self.physics.repulsion_radius > 0:
            f = f + repulsion.repulsion_force(surface, self.lp_current, self.physics.repulsion_radius, self.q_force)
            if self.wall is not None:          # and from a container's wall
                f = f + repulsion.wall_repulsion_force(surface, self.lp_current.wall_coupling.at_vesicle_points,
                                                       self.physics.repulsion_radius, self.q_force)
        return f

    def rhs(self, surface, lp, op):
        """Right side of the step for the vesicles of surface (op.surface: this rank's)."""
        self.timers.start("rhs")
        Tp = sph.transform(self.p)
        X = surface.points()
        if self.physics.flow is None:                     # no [flow]: nothing to evaluate
            b1 = np.zeros(surface.coeffs.shape)
        else:
            uinf = background_velocity(self.physics.flow, X, **self.physics.flow_args)
            b1 = Tp.analysis(np.moveaxis(uinf, -1, -2))
        f = op.coeffs_vec(self.explicit_traction(surface, op.geo))
        self.timers.stop("rhs")
        bw = None
        if op.wall is not None:              # the wall rows: -u_ves of the explicit forces (W.2)
            v, at_wall = lp.apply(f, None, targets=op.wall.at_wall)
            b1, bw = b1 + v, op.wall.rhs(at_wall)
        else:
            b1 = b1 + lp.apply(f, None)
        if self.coupling == "explicit" and self.last is not None and lp.N_total > 1:
            # inter-vesicle terms of the previous solution moved to the right side
            fi = op.membrane_force(_mine(self.last.u, lp), _mine(self.last.sigma, lp))
            g = -_mine(self.last.u, lp) if lp.want_double else None
            b1 = b1 + lp.apply(fi, g) - lp.self_part(fi, g)
        return op.join(b1, np.zeros((surface.n_vesicles, sph.n_coeffs(self.p))), bw)

    def correction_rhs(self, lp, op, displacement):
        """Right side S[B[e]] of the correction equation for a displacement e (N, 3, C):
        the single layer of its linearized bending force (3.12) on the frozen geometry."""
        f = forces.linearized_bending_force(op.geo, self.params_local.kappa, op.grid_vec(_mine(displacement, lp)))
        if op.wall is None:
            return op.join(lp.apply(op.coeffs_vec(f), None), np.zeros((op.N, sph.n_coeffs(self.p))))
        b1, at_wall = lp.apply(op.coeffs_vec(f), None, targets=op.wall.at_wall)
        return op.join(b1, np.zeros((op.N, sph.n_coeffs(self.p))), op.wall.rhs(at_wall))

    def solve(self, dt, surface=None, displacement=None):
        """Velocity and tension at the current (or given) configuration for a step dt.

        With a displacement e, the same operator with the right side S[B[e]] (correction_rhs)
        and a zero initial guess: the response w of the spectral deferred correction sweep
        (vesflow.stepping.sdc), e + dt w = e + dt V[B[e + dt w]].
        """
        from petsc4py import PETSc
        surface = self.surface if surface is None else surface
        q = self.lp_settings.q_far or 2 * self.p
        adapt_openmp(pairs=(surface.n_vesicles * 2 * q * (q + 1)) * (surface.n_vesicles * 2 * self.p * (self.p + 1)))
        lp, op = self._setup(surface, dt)
        self.lp_current = lp
        A, ksp, b, x, r = self._solver(op, surface.n_vesicles * op.block + op.n_wall)
        b.setArray(self.rhs(op.surface, lp, op) if displacement is None else self.correction_rhs(lp, op, displacement))
        if (displacement is None and self.last is not None
                and self.last.u.shape == (surface.n_vesicles, 3, sph.n_coeffs(self.p))):
            x.setArray(op.join(_mine(self.last.u, lp), _mine(self.last.sigma, lp), self.last.wall))
        else:
            x.set(0.0)
        with self.timers.stage("setup"):
            ksp.setUp()
        t_solve = time.perf_counter()
        ksp.solve(b, x)
        t_solve = time.perf_counter() - t_solve
        self.timers.count("solve")
        reason, its = ksp.getConvergedReason(), ksp.getIterationNumber()
        self.ksp_seconds += t_solve
        self.ksp_its += its
        pc = ksp.getPC()
        observe = getattr(pc.getPythonContext() if pc.getType() == "python" else None, "observe", None)
        self.cond_estimate = _condition_estimate(ksp)
        if np.isfinite(self.cond_estimate):
            self.cond_max = max(self.cond_max, self.cond_estimate)
        rtol = ksp.getTolerances()[0]
        if reason < 0:
            if observe is not None:
                observe(its, failed=True)
            raise ConvergenceError(f"GMRES did not converge: reason {_reason_name(reason)} after {its} iterations",
                                   reason=reason, iterations=its)
        # GMRES tests the preconditioned residual: a (near-)singular preconditioner can report
        # convergence with a wrong solution.  One more matvec checks the true residual.
        A.mult(x, r)
        r.aypx(-1.0, b)
        relres = r.norm() / max(b.norm(), 1e-300)
        if observe is not None:
            observe(its, failed=not relres <= max(1e-6, 1e4 * rtol), seconds=t_solve)
        if not relres <= max(1e-6, 1e4 * rtol):
            raise ConvergenceError(f"GMRES reported {_reason_name(reason)} after {its} iterations but the true "
                                   f"relative residual is {relres:.2e} (a singular preconditioner?): "
                                   + residual_modes(op, r.getArray(), b.norm(), x.getArray()),
                                   reason=reason, iterations=its)
        u, s = op.split(x.getArray().copy())
        q_wall = None if op.wall is None else op.wall_part(x.getArray()).copy()
        self.lp_last = lp
        with self.timers.stage("gather"):     # every rank keeps the velocity of every vesicle
            both = self.part.gather(np.concatenate([u.reshape(op.N, -1), s], axis=1))
        u, s = both[:, :3 * op.C].reshape(-1, 3, op.C), both[:, 3 * op.C:]
        return Solution(u.copy(), s.copy(), its, reason, q_wall)

    def _solver(self, op, n):
        """(Mat, KSP, b, x, r) of this stepper with op as the Mat's context: made and configured
        at the first solve (and when the system's size changes), then reused; the Mat's state is
        increased so that the KSP sets its preconditioner up again (the PC context decides what
        it reuses).  A preconditioner to rebuild (restore_preconditioner) is rebuilt here."""
        from petsc4py import PETSc   # here, not at import: the caller initializes PETSc with its options first
        sizes = (op.size, n)                  # the rows of this rank's vesicles (and of a container's wall)
        if self._ksp is not None and self._ksp[5] == sizes:
            A, ksp = self._ksp[0], self._ksp[1]
            A.setPythonContext(sphere_constraints(op.surface, op, self.lock_spheres))
            A.stateIncrease()
        else:
            self.close()
            comm = PETSc.COMM_SELF if self.part.comm is None else PETSc.Comm(self.part.comm)   # Partition.single: serial
            A = PETSc.Mat().createPython([sizes, sizes], sphere_constraints(op.surface, op, self.lock_spheres), comm=comm)
            A.setUp()
            ksp = PETSc.KSP().create(comm=comm)
            configure_ksp(ksp, A, self.ksp_prefix, default_pc=self.default_pc_context, ksp_type=self.default_ksp_type())
            ksp.setComputeSingularValues(True)       # the condition estimate of M^-1 A (_condition_estimate)
            self._ksp = (A, ksp, A.createVecRight(), A.createVecLeft(), A.createVecRight(), sizes)
            if not self._pc_adopted and ksp.getPC().getType() == "python":
                self._pc_context = ksp.getPC().getPythonContext()    # the default, or -pc_python_type's
                self._pc_adopted = True                               # kept by the later KSPs
        pc = ksp.getPC()
        if pc.getType() == "python":                 # the context kept across solves (and KSPs)
            ctx = getattr(self, "_pc_context", None)
            if ctx is None:
                ctx = self._pc_context = pc.getPythonContext() or self.default_pc_context()
            if pc.getPythonContext() is not ctx:
                pc.setPythonContext(ctx)
            if self._pc_record is not None:
                self._rebuild_preconditioner(ctx, self._pc_record)
        self._pc_record = None
        return self._ksp[:5]

    def default_pc_context(self):
        """The block-Jacobi PC context, kept across solves (it reuses LU factors, -ves_pc_lag)."""
        if getattr(self, "_pc_context", None) is None:
            self._pc_context = _default_pc(self.pc_precision, self.pc_factors, self.pc_parts)
        return self._pc_context

    def default_ksp_type(self):
        """gmres; fgmres when the default block-Jacobi PC is float32 (-ves_pc_precision single):
        left-preconditioned GMRES with a float32 PC leaves the solution 1.3e-7 (relative) from
        double's at any rtol, fgmres within 3e-14 at rtol 1e-8 in the same iterations (one
        solve of the accuracy-cost pair, p = 12; docs/explanation/parallel.md)."""
        if self.pc_precision is not None:
            dtype = PC_DTYPES[self.pc_precision]
        else:                                # a context of another kind (tests): its own precision, or double
            dtype = getattr(self.default_pc_context(), "dtype", np.float64)
        return "fgmres" if dtype == np.float32 else "gmres"

    def velocity(self):
        """Instantaneous velocity and tension (one solve with dt = 0: no implicit bending)."""
        return self.solve(0.0)

    def step(self, dt):
        """One first-order step: solve, then X^{n+1} = X^n + dt u.  Returns the Solution."""
        sol = self.solve(dt)
        if not np.all(np.isfinite(sol.u)):
            raise ConvergenceError("the solve returned NaN or Inf", reason="nan", iterations=sol.its)
        self.coeffs = self.coeffs + dt * sol.u
        self.time += dt
        self.last = sol
        return sol


def _mine(a, lp):
    """The rows of per-vesicle array a (all vesicles) that belong to lp's vesicles."""
    return a[lp.idx]


SPHERE_TOL = 1e-6     # reduced volume above 1 - SPHERE_TOL: a sphere (as correction.py)
LOCK_STIFFNESS = 1e3  # K of the locking force -K (mu / R) (u.n)_{n >= 2} n on spheres


def sphere_constraints(surface, op, lock=True):
    """op with the two constraints of a sphere (reduced volume above 1 - SPHERE_TOL) set in it:
    StepOperator.gauge and .lock, which its apply, membrane_force and block parts include
    (docs/explanation/dynamics.md, "Spheres and near-spheres", "Locked shape").

    Gauge.  On a sphere a constant tension exerts no force (2 H sigma n with H constant; the
    single layer of n vanishes on and off a closed surface): its column is zero and the n = 0
    divergence row is the flux of the velocity rows times 2/R, so the system is singular and
    GMRES broke down on the quadrature-size inconsistency of the right side (measured:
    DIVERGED_BREAKDOWN, two sedimenting spheres, p = 8).  The term c sigma_0 added to the n = 0
    divergence row (c < 0, the scale of a sphere's tension Schur complement in degree 1,
    0.4 / (R mu alpha); the rank-one update of precond.regularize_tension_mode) picks the
    solution with sigma_0 = 0: that row is redundant on a sphere, nothing physical changes.

    Lock (lock=True).  A sphere of fixed area and volume cannot deform; the linearized
    constraint div u = 0 lets it (its normal velocity of degree 2 in a strain is
    60 / (23 lambda + 32) a n.E.n, tests/stepping/test_dynamics.py), and that instantaneous motion
    changes its stresslet to (80 - 115 lambda) / (23 lambda + 32) times a rigid sphere's -5
    (0.13 of it at lambda = 1): two spheres sedimenting along their line of centres fall 1.8%
    (3 radii apart) and 2.8% (2.5) faster than rigid spheres.  The locked limit of a
    quasi-spherical vesicle (excess area -> 0, tension -> infinity) keeps its normal velocity of
    degree >= 2 at zero; the implicit force -K (mu / R) P_{n >= 2}(u . n) n, K = LOCK_STIFFNESS,
    imposes it to 1 / (1 + K m), m ~ 0.1 the sphere's normal mobility: rigid-sphere
    hydrodynamics for the translation, while the membrane still tank-treads (div-free
    tangential motion)."""
    v = surface.reduced_volume()
    spheres = np.nonzero(v > 1.0 - SPHERE_TOL)[0]
    if len(spheres) == 0:
        return op
    R = surface.effective_radius()
    op.gauge[spheres] = -0.4 / (R[spheres] * op.params.mu * op.params.alpha[spheres])
    if lock:
        op.lock[spheres] = LOCK_STIFFNESS * op.params.mu / R[spheres]
    return op


def _condition_estimate(ksp):
    """sigma_max / sigma_min of the preconditioned operator from the Krylov method's Hessenberg
    matrix (an estimate from the space GMRES built; NaN if the method gives none)."""
    try:
        smax, smin = ksp.computeExtremeSingularValues()
    except Exception:                  # e.g. a -ksp_type without the estimate
        return float("nan")
    return float(smax / smin) if smin > 0 else float("inf")


def _split_by_degree(op, a):
    """{(vesicle, "velocity" | "tension", degree n): norm} of a vector in the system's layout
    (the tension part of a residual holds the divergence rows)."""
    ns = sph.index_tables(op.p)[0][:op.C]
    av = np.asarray(a)[:op.N * op.block].reshape(op.N, op.block)
    vel = av[:, :3 * op.C].reshape(op.N, 3, op.C)
    ten = av[:, 3 * op.C:]
    out = {}
    for n in range(op.p + 1):
        sel = ns == n
        for v in range(op.N):
            out[(v, "velocity", n)] = np.sqrt((vel[v][:, sel] ** 2).sum())
            out[(v, "tension", n)] = np.sqrt((ten[v][sel] ** 2).sum())
    return out, np.linalg.norm(vel), np.linalg.norm(ten)


def residual_modes(op, r, bnorm, x=None):
    """Which mode failed: the residual r (relative to the right side's norm) in its velocity
    and divergence rows and its largest (vesicle, rows, degree n) part, and the largest part of
    the solution x, e.g. "residual: velocity rows 1.0e+00, divergence rows 2.0e-06, largest
    vesicle 1 velocity rows degree 0 (6.4e-01); solution: largest vesicle 0 tension degree 0
    (100% of its norm: the constant-tension mode)"."""
    b = max(bnorm, 1e-300)
    ids = getattr(op.lp, "idx", None)        # with a partition: this rank's vesicles (their scene numbers)
    name = (lambda v: v) if ids is None else (lambda v: int(ids[v]))
    parts, nv, nt = _split_by_degree(op, r)
    (v, rows, n), worst = max(parts.items(), key=lambda kv: kv[1])
    v = name(v)
    rows = "divergence" if rows == "tension" else rows
    out = (f"residual: velocity rows {nv / b:.1e}, divergence rows {nt / b:.1e}, largest vesicle {v} {rows} "
           f"rows degree {n} ({worst / b:.1e})")
    if x is not None:
        parts, _, _ = _split_by_degree(op, x)
        total = np.sqrt(sum(w ** 2 for w in parts.values()))
        (v, kind, n), big = max(parts.items(), key=lambda kv: kv[1])
        v = name(v)
        what = ": the constant-tension mode" if (kind, n) == ("tension", 0) else ""
        out += (f"; solution: largest vesicle {v} {kind} degree {n} "
                f"({100 * big ** 2 / max(total ** 2, 1e-300):.0f}% of its norm{what})")
    return out


def _default_pc(precision=None, factors=None, parts=None):
    return BlockJacobi(precision=precision, factors=factors, parts=parts)


def _reason_name(reason):
    try:
        from petsc4py import PETSc
        for k, v in vars(PETSc.KSP.ConvergedReason).items():
            if v == reason and not k.startswith("_"):
                return f"{k} ({reason})"
    except Exception:
        pass
    return str(reason)
