"""Preconditioners as PC python contexts (docs/explanation/method.md, section 6).

    -pc_type python -pc_python_type vesflow.precond.BlockJacobi    dense LU of each vesicle's self block
    -pc_type python -pc_python_type vesflow.precond.SphereSpectral the block of a sphere of the same size

Both find the StepOperator through the operator matrix (`pc.getOperators()[0].getPythonContext()`)
and apply one dense LU per vesicle.  Each block is A(dt) = A0 - dt [S Mb 0; 0 0]
(`StepOperator.self_block_parts`): the parts are built once and kept, and a block for another
dt costs a sum and an LU.

Reuse, driven by the GMRES iterations (Stepper.solve reports each solve's iterations through
`observe`): the parts are rebuilt from the current geometry once the iterations the aging
blocks cost beyond the first solve after the last rebuild, summed over the solves since,
cost as much as a rebuild (the ski-rental rule: never more than twice the best fixed
schedule).  The rebuild's price in iterations comes from the cost model
(`costs.pc_rebuild_iterations`, e.g. ~40 for two vesicles at p = 12), not from a clock, so
that every run of the same input rebuilds at the same solves and takes the same iterates
(restarts included).  Rebuilt at once when a solve needs more than
`REFRESH_FACTOR` x the first + `REFRESH_SLACK` iterations or fails, after -ves_pc_lag solves
at most, and when the number of vesicles or p changed.  The LU factors of a block are reused
for any dt within a factor `DT_MATCH` of the dt they were built for (the two half steps of
step doubling, the steps after).

Precision (-ves_pc_precision): single keeps the parts and the LU factors in float32 (factored by
scipy's lu_factor on float32 blocks, applied with float32 solves): half the memory; the
step's KSP is then fgmres (`Stepper.default_ksp_type`), whose residual is the true one, so the
solution keeps double's accuracy (docs/explanation/parallel.md).

Memory (docs/explanation/parallel.md, "Memory"): the parts are held compactly (`BlockParts`: of
A0 only its coupling blocks -S Mt and Div, its velocity block only where it is not alpha I);
-ves_pc_factors K keeps at most K sets of LU factors (one per dt); -ves_pc_parts drop frees the
parts once factored, and a dt that no kept factor matches rebuilds the blocks from the current
geometry (a rebuild).  Before a rebuild or a new factorization the parts and factors it replaces
are freed, so that the old and the new are never held together.
"""
from __future__ import annotations

import weakref

import numpy as np
from scipy.linalg import lu_factor, lu_solve

from .costs import pc_rebuild_iterations
from .layerpot.singular import SelfOperators
from .operator import StepOperator, VesicleParams
from .options import parse_value
from .shapes import make_shape
from .surface import Surface
from .threads import map_vesicles
from .timing import NullTimers

REFRESH_FACTOR, REFRESH_SLACK = 3.0, 5
DT_MATCH = 1.25
MAX_DT_FACTORS = 3
PARTS_MODES = ("keep", "drop")


PC_DTYPES = {"double": np.float64, "single": np.float32}


class _PerVesicle:
    """Shared machinery: block parts per vesicle, LU factors per dt, reuse by iterations.
    precision: "double" or "single" (None: -ves_pc_precision of the options database)."""

    def __init__(self, lag=None, precision=None, factors=None, parts=None):
        self.lag = lag
        if precision is not None and precision not in PC_DTYPES:
            raise ValueError(f"pc precision = {precision!r}: must be one of {', '.join(PC_DTYPES)}")
        if factors is not None and not 1 <= int(factors) <= MAX_DT_FACTORS:
            raise ValueError(f"pc factors = {factors!r}: must be an integer in [1, {MAX_DT_FACTORS}]")
        if parts is not None and parts not in PARTS_MODES:
            raise ValueError(f"pc parts = {parts!r}: must be one of {', '.join(PARTS_MODES)}")
        self.precision = precision
        self.max_factors = None if factors is None else int(factors)
        self.parts_mode = parts
        self.reset()

    def _option(self, name, default):
        """-ves_pc_factors / -ves_pc_parts of the options database (when not given to the constructor)."""
        from petsc4py import PETSc   # lazy: the options database is read only when no value was given
        return parse_value(f"-ves_{name}", PETSc.Options().getString(f"ves_{name}", str(default)))

    @property
    def kept_factors(self):
        """Sets of LU factors kept, one per dt (-ves_pc_factors, default MAX_DT_FACTORS)."""
        if self.max_factors is None:
            self.max_factors = int(self._option("pc_factors", MAX_DT_FACTORS))
        return self.max_factors

    @property
    def keep_parts(self):
        """Whether the parts are kept after the factorization (-ves_pc_parts keep, the default)."""
        if self.parts_mode is None:
            self.parts_mode = self._option("pc_parts", "keep")
        return self.parts_mode == "keep"

    @property
    def dtype(self):
        """Storage and solves of the parts and factors (float64, or float32 with -ves_pc_precision single)."""
        if self.precision is None:
            from petsc4py import PETSc
            self.precision = parse_value("-ves_pc_precision", PETSc.Options().getString("ves_pc_precision", "double"))
        return PC_DTYPES[self.precision]

    def reset(self):
        """Forget every part and factor (rebuilt at the next setUp)."""
        self.parts = None          # per vesicle BlockParts (None once dropped: -ves_pc_parts drop)
        self.parts_key = None      # (N, p) they were built for
        self.parts_lp = None       # weak reference to the LayerPotentials (the geometry) they were built from
        self.parts_record = None   # what rebuilds them: {"coeffs", "q_self", "q_far"} of that geometry
        self.factors = []          # [(dt, [LU per vesicle])], newest last
        self.lu = None
        self._just_rebuilt = False
        self.base_its = None       # iterations of the first solve after the last rebuild
        self.uses = 0              # solves since the last rebuild
        self.stale = False
        self.rebuilds = 0
        self.rebuild_its = np.inf  # a rebuild's cost in iterations (costs.pc_rebuild_iterations)
        self.excess_its = 0        # iterations beyond base_its since the last rebuild

    # ------------------------------------------------------------------ reuse policy
    def observe(self, its, failed=False, seconds=None):
        """The iterations of the solve just done with these blocks (seconds: for the log only)."""
        if failed:
            self.stale = True
            return
        if self.base_its is None:
            self.base_its = its
            return
        self.excess_its += max(its - self.base_its, 0)
        self.stale = (its > REFRESH_FACTOR * self.base_its + REFRESH_SLACK
                      or self.excess_its >= self.rebuild_its)

    def _max_uses(self):
        if self.lag is None:
            from petsc4py import PETSc
            self.lag = max(1, PETSc.Options().getInt("ves_pc_lag", 50))
        return self.lag

    # ------------------------------------------------------------------ PC python interface
    def setUp(self, pc):
        A, _ = pc.getOperators()
        op = A.getPythonContext()
        self.shape = (op.N, op.block)      # not the operator: it holds the layer potentials
        self.wall = op.wall.wall if op.wall is not None else None    # a container's Wall (its LU), or None
        key = (op.N, op.p)
        fresh_geometry = self.built_from() is not op.lp
        if (self.parts_key is None or key != self.parts_key or self.stale
                or (fresh_geometry and self.uses >= self._max_uses())):
            self.rebuild(op)
        self.lu = self._factors_for(op)
        self.uses += 1

    def built_from(self):
        """The LayerPotentials the parts were built from, if they are still alive (else None)."""
        return None if self.parts_lp is None else self.parts_lp()

    def rebuild(self, op, parts=True):
        """New parts from op's geometry (parts False: none, -ves_pc_parts drop builds and factors
        them vesicle by vesicle), the reuse counters reset; the old parts and factors are freed
        first (never held together with the new ones)."""
        self.parts, self.factors, self.lu = None, [], None
        if parts and self.keep_parts:
            self.build_parts(op)
        else:
            self.note_parts(op)
        self._just_rebuilt = True
        self.base_its, self.uses, self.stale = None, 0, False
        self.excess_its = 0
        self.rebuild_its = self.rebuild_cost(op)
        self.rebuilds += 1

    def build_parts(self, op):
        """The parts of op's geometry, and what identifies them (a weak reference to op.lp and
        the record `Stepper.preconditioner_state` stores)."""
        with op.lp.timers.stage("pc_blocks"):
            self.parts = self.block_parts(op)
        self.note_parts(op)

    def note_parts(self, op):
        """Record the geometry the blocks come from (parts_key, parts_lp, parts_record)."""
        self.parts_key = (op.N, op.p)
        self.parts_lp = weakref.ref(op.lp)
        self.parts_record = {"coeffs": op.lp.surface.coeffs, "q_self": int(op.lp.q_self), "q_far": int(op.lp.q_far)}

    @staticmethod
    def rebuild_cost(op):
        """A rebuild in GMRES iterations of this system (costs.pc_rebuild_iterations), for the
        whole system (all ranks' vesicles and near pairs): every rank, and one process, decide alike."""
        lp = op.lp
        far = getattr(getattr(lp, "far", None), "backend", "direct")
        return pc_rebuild_iterations(getattr(lp, "N_total", op.N), op.p, getattr(lp, "q_far", 2 * op.p),
                                     bool(lp.want_double),
                                     getattr(lp, "n_near_pairs_total", getattr(lp, "n_near_pairs", 0)), far,
                                     getattr(getattr(lp, "settings", None), "fmm_eps", 1e-8))

    def _factors_for(self, op):
        """The LU factors for op.dt: a kept set within DT_MATCH, else a new one (the oldest kept
        set freed first when -ves_pc_factors are kept; with the parts dropped, the blocks are
        built again from op's geometry first: a rebuild)."""
        dt = op.dt
        for dt_f, kept in self.factors:
            if (dt_f == dt) or (dt_f > 0 and dt > 0 and max(dt / dt_f, dt_f / dt) <= DT_MATCH):
                return kept
        kept = self.lu = None             # (the loop's last set would stay referenced here)
        del self.factors[:len(self.factors) - self.kept_factors + 1]
        dtype = self.dtype
        factor = lambda parts: lu_factor(self.finish_block(parts.at(dt), op).astype(dtype, copy=False),
                                         check_finite=False)
        if self.parts is None and not self.keep_parts:
            # the blocks of this geometry, each factored as soon as built (no parts of all vesicles held)
            if not self._just_rebuilt:
                if self.factors:          # other dts' factors stay
                    self.rebuilds += 1
                else:
                    self.rebuild(op, parts=False)
            self._just_rebuilt = False
            with op.lp.timers.stage("pc_blocks"):
                lu = map_vesicles(lambda v: factor(self.block_part(op, v)), range(op.N), op.p)
            self.note_parts(op)
        else:
            if self.parts is None:
                self.build_parts(op)
            with op.lp.timers.stage("pc_lu"):
                lu = map_vesicles(lambda k: factor(self.parts[k]), range(len(self.parts)), op.p)
        self.factors.append((dt, lu))
        return lu

    def blocks(self, op):
        """The blocks as factored, at the operator's dt (for inspection and tests)."""
        return [self.finish_block(parts.at(op.dt), op) for parts in self.block_parts(op)]

    def finish_block(self, A, op):
        """Each assembled block, before its factorization: its constant-tension mode regularized
        (`regularize_tension_mode`; it depends on dt through the velocity block's scale)."""
        return regularize_tension_mode(A, op.C)

    def apply(self, pc, x, y):
        """The blocks' LU solves; with a container's wall, its rows by the LU of its self block
        (1/2 I + pv D_w + N, vesflow.layerpot.wall.Wall: built once, walls do not move)."""
        xall = x.getArray(readonly=True)
        n = self.shape[0] * self.shape[1]
        xa = xall[:n].reshape(self.shape)
        out = np.empty_like(xa)
        if self.dtype != np.float64:       # float32 factors: float32 solves
            xa = xa.astype(self.dtype)
        for v, lu in enumerate(self.lu):
            out[v] = lu_solve(lu, xa[v], check_finite=False)
        if self.wall is None:
            y.setArray(out.ravel())
        else:
            y.setArray(np.concatenate([out.ravel(), self.wall.solve(xall[n:])]))

    def view(self, pc, viewer):
        viewer.printfASCII(f"vesflow {type(self).__name__}: {len(getattr(self, 'lu', []))} dense LU blocks, "
                           f"rebuilt {self.rebuilds} times\n")


TENSION_MODE_WEIGHT = 3.0    # |c| / (the block's estimate of the tension Schur complement scale)


def regularize_tension_mode(B, C):
    """The self block B (4C x 4C: velocity 3C component-major, then tension C; the constant
    tension at 3C, the n = 0 divergence row at 3C) with its constant-tension mode regularized:
    B + c e e^T, e = e_{3C}, c < 0 (docs/explanation/dynamics.md, "Spheres and near-spheres").

    A constant tension on a closed surface exerts 2 H sigma n, and the single layer of n
    vanishes on and off a closed surface: on a sphere (H constant) that column is zero, and the
    row combination "n = 0 divergence minus the flux of the velocity rows" is zero too (its left
    null vector).  Near a sphere the block's smallest singular value is O(1 - v) (measured,
    p = 8: 2.5e-4 at v = 0.999, 2.2e-3 at 0.99, 8.8e-3 at 0.95); it is the only small one (the
    next, tension degree 1, is ~0.1).  The tension Schur complement -div (B_uu)^-1 B_u,sigma
    is negative (semi)definite (a tension does negative work on the area), so adding c < 0 at
    (3C, 3C) keeps it definite for every shape and makes a sphere's block regular; c is the
    scale of that Schur complement in the next tension mode, estimated from the block:
    |c| = 3 max|B_d0,u| max|B_u,sigma| / max|B_uu| (its degree-1 eigenvalue is 2.7-5.4 times the
    product, measured over R, kappa, lambda, mu, dt).  The cost: the preconditioned operator
    gets the eigenvalue 1 / (1 + c gamma), gamma = (B^-1)_{3C,3C}, in this one mode (0 for a
    sphere, where the operator itself is singular: the sphere's constant tension is free).
    """
    i0 = 3 * C
    scale = np.abs(B[i0, :i0]).max() * np.abs(B[:i0, i0:]).max() / max(np.abs(B[:i0, :i0]).max(), 1e-300)
    out = np.array(B, dtype=float, copy=True)
    out[i0, i0] -= TENSION_MODE_WEIGHT * scale
    return out


def pc_grid(p, q_force):
    """The grid degree of the blocks' force matrices: min(q_force, max(ceil(3p/2), p + 6)).

    A preconditioner only has to be close to the operator; the forces formed on a coarser grid
    than the operator's (2p) change the GMRES iterations by nothing measurable at p >= 12 and
    cost about half (lag 1, 20 steps of the issue-16 pair: p = 12, q 24 / 18 / 15: 62 / 63 / 85
    iterations, block CPU 22.5 / 12.1 / 6.3 s; p = 16, q 32 / 24: 62 / 62, 61 / 46 s); at p = 6
    a 9-grid costs iterations (106 vs 62), hence p + 6 at least."""
    return min(q_force, max(-(-3 * p // 2), p + 6))


class BlockParts:
    """One vesicle's block parts, A(dt) = A0 - dt [S Mb 0; 0 0] (`StepOperator.self_block_parts`),
    held compactly: of A0 (4C x 4C) its coupling blocks -S Mt (3C x C) and Div (C x 3C), its
    velocity block only where it is not alpha I (a viscosity contrast, a locked sphere), the
    tension gauge; S Mb (3C x 3C).  15 C^2 entries instead of 25 C^2 for lambda = 1; `at(dt)`
    is the block of block_at(A0, SMb, dt), entry for entry.  Iterating gives the arrays held."""

    def __init__(self, A0, SMb, dtype=np.float64):
        n = SMb.shape[0]
        uu = A0[:n, :n]
        alpha = float(uu[0, 0])
        plain = np.count_nonzero(uu) == np.count_nonzero(uu.diagonal()) and np.all(uu.diagonal() == alpha)
        self.n, self.alpha = n, alpha
        self.uu = None if plain else np.array(uu, dtype=dtype)
        self.us = np.array(A0[:n, n:], dtype=dtype)
        self.su = np.array(A0[n:, :n], dtype=dtype)
        self.ss = np.array(A0[n:, n:], dtype=dtype) if np.count_nonzero(A0[n + 1:, n:]) or np.count_nonzero(A0[n, n + 1:]) \
            else None
        self.gauge = float(A0[n, n])
        self.SMb = np.array(SMb, dtype=dtype)

    def __iter__(self):
        return iter([a for a in (self.uu, self.us, self.su, self.ss, self.SMb) if a is not None])

    @property
    def nbytes(self):
        return sum(a.nbytes for a in self)

    def at(self, dt):
        """The block A0 - dt [S Mb 0; 0 0] (a new array, in the parts' dtype)."""
        n, dtype = self.n, self.SMb.dtype
        A = np.zeros((n + self.su.shape[0],) * 2, dtype=dtype)
        if self.uu is None:
            A[np.arange(n), np.arange(n)] = self.alpha
        else:
            A[:n, :n] = self.uu
        A[:n, :n] -= dt * self.SMb
        A[:n, n:] = self.us
        A[n:, :n] = self.su
        if self.ss is not None:
            A[n:, n:] = self.ss
        else:
            A[n, n] = self.gauge
        return A


class BlockJacobi(_PerVesicle):
    """Inverse of the block diagonal: each vesicle with itself (the paper's better choice), its
    constant-tension mode regularized (`regularize_tension_mode`)."""

    def block_part(self, op, v):
        """Vesicle v's BlockParts, stored in the preconditioner's dtype as soon as built."""
        return BlockParts(*op.self_block_parts(v, pc_grid(op.p, op.q_force)), dtype=self.dtype)

    def block_parts(self, op):
        return map_vesicles(lambda v: self.block_part(op, v), range(op.N), op.p)


class SphereSpectral(_PerVesicle):
    """The self block of a sphere with each vesicle's area, bending modulus and contrast.

    On a sphere the operator is diagonal in the degree n (the spectrum the paper's analytic
    preconditioner uses); we assemble it once per distinct (radius, kappa, lambda) with the same
    machinery as BlockJacobi and reuse it, which is cheaper than per-vesicle blocks when many
    vesicles share their properties.  Radii are matched to 4 significant digits (the area
    correction holds them to ~1e-10, which must not make a new sphere every step).

    The sphere's block is singular: a constant tension exerts no force on a sphere (its
    column is zero) and the mean normal velocity enters only the n = 0 divergence row.  Left
    as is, the LU "solves" with an exploding or arbitrary tension mode and GMRES reports
    convergence after one iteration at a true residual of 0.99 (measured, 2 vesicles, p = 8).
    `regularize_tension_mode` makes it invertible, as for BlockJacobi.
    """

    def __init__(self, lag=None, precision=None, factors=None, parts=None):
        super().__init__(lag, precision, factors, parts)
        self.spheres = {}

    def observe(self, its, failed=False, seconds=None):
        """The blocks depend on the radii only: nothing goes stale with the shapes."""

    @property
    def keep_parts(self):
        """The spheres' parts are shared by the vesicles: always kept."""
        return True

    def block_parts(self, op):
        radii = op.surface.effective_radius()
        out = []
        for v in range(op.N):
            key = (float(f"{radii[v]:.4g}"), float(op.params.kappa[v]), float(op.params.lam[v]), op.p)
            if key not in self.spheres:
                S = Surface(make_shape("sphere", op.p, radius=key[0])[None], op.p)
                lp = _SelfOnly(SelfOperators(S.coeffs, op.p, op.lp.q_self, True, op.lp.want_double, op.params.mu),
                               op.lp.want_double, np.array([key[2]]))
                prm = VesicleParams([key[1]], [key[2]], [0.0], op.params.mu)
                self.spheres[key] = BlockParts(*StepOperator(S, prm, op.dt, lp, op.q_force).self_block_parts(0),
                                               dtype=self.dtype)
            out.append(self.spheres[key])
        return out


class _SelfOnly:
    """The part of LayerPotentials that self_block needs."""

    def __init__(self, self_ops, want_double, lam):
        self.self_ops, self.want_double, self.lam = self_ops, want_double, lam
        self.timers = NullTimers()
