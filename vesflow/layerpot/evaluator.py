"""sum_j S_j[f] + D_j[g] at the surface points of all vesicles, or at free targets (docs/explanation/method.md, section 5).

Per step (geometry frozen) `LayerPotentials.__init__` does the setup: the self operators,
the upsampled far-field sources, the near pairs (cell lists), their projections and
interpolation weights, the far field's own smooth operators (Ewald).  `apply` is then called once per GMRES iteration:

    self      S_hat f + D_hat g                  (per-vesicle dense operators, batched GEMM)
    far       smooth rule over every other vesicle (direct, FMM or Ewald backend; Ewald with
              Settings.ewald_own "smooth": plus E_v f_v, per-vesicle operators of the set-up that
              remove the own vesicle's smooth share the Ewald sum keeps, vesflow.layerpot.own_smooth)
    near      for each near (target, vesicle) pair: minus that pair's smooth rule, plus the
              near-singular value (line extrapolation through the projection)

Densities and results are degree-p coefficients (N, 3, C).  The double-layer density g is
scaled by (1 - lambda_j) here; the caller passes the plain velocity.

Over MPI ranks (vesflow.parallel) each rank's vesicles are the targets and the sources it holds
are its own and those of the other ranks' vesicles within its near zone or Ewald cutoff (a
Halo, exchanged once in the set-up and once per application); a serial run is the one-rank
partition (Partition.single, whose halo is empty), the same code.
"""
from __future__ import annotations

import numpy as np

from .. import sph
from .._kernels import stokes
from ..parallel import Halo, Partition, vesicle_boxes
from ..surface import Surface
from ..timing import NullTimers
from . import near as nearmod
from .ewald import OWN_MODES, own_extent_ok
from .far import FarField, predicted_ewald, resolve_backend
from .own_smooth import OwnSmoothOperators
from .singular import SelfOperators


# applications of the layer potentials per set-up that ewald_own "auto" weighs the set-up of E_v
# against (the GMRES iterations of the solves sharing a set-up plus their right-hand sides):
# 18.5 in the periodic Taylor-Green run of 64 cells (docs/explanation/periodic.md: 2777 applications, 150
# set-ups), 7-12 in the dilute runs of docs/explanation/accuracy_cost.md.  A constant, not the run's own
# count, so that a restarted run makes the same choices as an uninterrupted one (as
# costs.pc_rebuild_iterations)
APPLIES_PER_SETUP = 15.0
# cost of the own smooth operators E_v (ewald_own "auto"), CPU seconds of one thread: set-up per
# (p-grid target, q-grid source) pair of a vesicle and layer; the GEMV per byte of the operators
# (p = 16, q = 32: 27-31 ms per vesicle, single layer, benchmarks/setup_operators.py, i.e. 2.5e-8
# per pair of 544 x 2112; 0.20 s for 2.9 GB at N = 512, benchmarks/iteration.py; docs/explanation/far_field.md
# "The own vesicle in the set-up", "Set-up of the self and own smooth operators")
OWN_SETUP_PAIR = 2.5e-8
# E_v in float32 from this far-field tolerance up (LayerPotentials._own_dtype)
OWN_SINGLE_TOL = 1e-6
OWN_GEMV_BYTE = 7.0e-11
NEAR_CHUNK = 256           # near pairs per block of the nearest-source search (set-up memory)


class Settings:
    """Quadrature settings of the layer potentials (defaults of the paper: q = 2p)."""

    def __init__(self, q_self=None, q_far=None, near_factor=1.0, backend="auto", fmm_eps=1e-8, period=None,
                 near_blend=0.0, self_precision="double", ewald_own="auto", applies_per_setup=APPLIES_PER_SETUP):
        self.q_self, self.q_far = q_self, q_far
        if ewald_own not in OWN_MODES + ("auto",):
            raise ValueError(f"ewald_own = {ewald_own!r}: must be one of auto, {', '.join(OWN_MODES)}")
        # the Ewald far field's own vesicle: "smooth" (its Fourier share removed by per-vesicle
        # operators built in the set-up, vesflow.layerpot.own_smooth), "subtract" (in the GMRES
        # iteration) or "auto": smooth when the cost model says the set-up pays for itself over
        # `applies_per_setup` applications; docs/explanation/far_field.md, "Spectral Ewald" (the own vesicle)
        self.ewald_own = ewald_own
        self.applies_per_setup = float(applies_per_setup)
        self.near_blend = float(near_blend)   # width of the near/smooth blend beyond h_n, in units of h_n
        self.near_factor, self.backend, self.fmm_eps = near_factor, backend, fmm_eps
        self.period = period or None     # triply periodic cube (or box) side, None: free space
        if self_precision not in SELF_DTYPES:
            raise ValueError(f"self_precision = {self_precision!r}: must be one of {', '.join(SELF_DTYPES)}")
        self.self_precision = self_precision   # storage and GEMM of the self operators (-ves_self_precision)

    @property
    def self_dtype(self):
        return SELF_DTYPES[self.self_precision]


SELF_DTYPES = {"double": np.float64, "single": np.float32}


class LayerPotentials:
    """Setup once per step for a Surface; apply many times (see module docstring)."""

    def __init__(self, surface, lam=1.0, viscosity=1.0, settings=None, want_double=None, timers=None, part=None):
        """surface: all vesicles.  part (vesflow.parallel.Partition; default Partition.single, a
        serial run): only this rank's vesicles are targets and have self operators (`local`,
        `idx`); this rank holds the sources of its vesicles and of the other ranks' vesicles
        within its near zone (or Ewald cutoff), `known` (vesflow.parallel.Halo); the direct far
        field passes the other ranks' sources around the ring of ranks.  timers: the stages'
        vesflow.timing.Timers (default NullTimers)."""
        s = settings or Settings()
        p = surface.p
        self.N_total = surface.n_vesicles
        self.part = Partition.single(self.N_total) if part is None else part
        self.idx = self.part.idx
        self.local = vesicles_of(surface, self.idx)
        self.p, self.N = p, self.local.n_vesicles
        self.q_self = s.q_self or 2 * p
        self.q_far = s.q_far or 2 * p
        self.mu = float(viscosity)
        self.lam_all = np.broadcast_to(np.asarray(lam, dtype=float), (self.N_total,)).copy()
        self.lam = self.lam_all[self.idx]
        self.want_double = bool(np.any(self.lam_all != 1.0)) if want_double is None else bool(want_double)
        self.settings = s
        self.surface = surface
        self.timers = NullTimers() if timers is None else timers
        with self.timers.stage("self_setup"):
            self.self_ops = SelfOperators(self.local.coeffs, p, self.q_self, True, self.want_double, self.mu,
                                          dtype=s.self_dtype)
        gq = self.local.geometry(self.q_far)
        self.Tq = sph.transform(p, self.q_far)
        self.Tp = sph.transform(p)
        self.src_w_local = gq.dA.reshape(-1)       # quadrature weights of this rank's q-grid points
        # own targets: the p-grid
        self.trg = np.ascontiguousarray(self.local.points().reshape(-1, 3))
        self.trg_id = np.repeat(np.asarray(self.idx, dtype=np.int64), self.Tp.npts)
        self.far = None
        self.near = None
        self.own_ops = None
        self.own_auto = None          # ewald_own "auto": the cost model's figures of the choice
        self.far_own = self._far_own_mode(gq)
        backend, params = self._sources(gq)
        if self.N_total > 1 or s.period:    # periodic: a single vesicle sees its images
            with self.timers.stage("near_setup"):
                self.near = self._near_setup(self.trg, self.trg_id)
            with self.timers.stage("far_setup"):
                self.far = self._far_field(backend, params)
            if self.far.smooth_own:
                with self.timers.stage("own_setup"):
                    n, mp, mq = self.N, self.Tp.npts, self.Tq.npts
                    self.own_ops = OwnSmoothOperators(
                        self.trg.reshape(n, mp, 3), gq.X.reshape(n, mq, 3), gq.dA.reshape(n, mq),
                        (gq.normal * gq.dA[..., None]).reshape(n, mq, 3), self.far.ewald.params.xi, p,
                        self.q_far, True, self.want_double, self.mu, dtype=self._own_dtype())
        self.n_near_pairs_total = int(self.part.sum(self.n_near_pairs))

    def _far_own_mode(self, gq):
        """The Ewald sum's own mode (Settings.ewald_own): "smooth" unless a vesicle is so large
        against the period that its own periodic images could lie within the largest cutoff
        (0.49 of the shortest period, ewald.choose_params): then "subtract"
        (ewald.own_extent_ok).  Sets ``_own_skip`` (q-grid points per vesicle, mean area) for
        the cost model."""
        s = self.settings
        area = gq.dA.reshape(self.N, -1).sum(axis=1)
        self._own_skip = (self.Tq.npts, self.part.sum(float(area.sum())) / max(self.N_total, 1))
        mode = s.ewald_own
        if mode == "auto":
            mode = self._own_auto(gq)
        if mode != "smooth" or s.period is None:
            return mode
        pts = np.concatenate([gq.X.reshape(self.N, -1, 3), self.local.points().reshape(self.N, -1, 3)], axis=1)
        ext = (pts.max(axis=1) - pts.min(axis=1)).max(axis=0, initial=0.0)
        ext = np.array([self.part.max(float(e)) for e in ext])
        L = np.broadcast_to(np.asarray(s.period, dtype=float), (3,))
        return "smooth" if own_extent_ok(ext, 0.49 * float(L.min()), s.period) else "subtract"

    def _own_dtype(self):
        """Storage of E_v: float32 when the far field is asked for no better than OWN_SINGLE_TOL
        (or the self operators are float32), else float64.  Measured (27 spheres / biconcave
        cells at p = 16, tol 1e-6): float32 E_v moves the velocities by 0.8-1.9e-7 of the largest,
        against 1-2e-8 for float64, within the tol with the NUFFT's <= 0.25 tol; it halves the
        operators' memory and the GEMV's memory traffic (0.10 of 2.10 s per iteration at N = 512)."""
        s = self.settings
        if s.self_dtype == np.float32 or s.fmm_eps >= OWN_SINGLE_TOL:
            return np.float32
        return np.float64

    def _own_auto(self, gq):
        """ewald_own "auto": "smooth" when the cost model's saving per application (the Ewald
        sum without the own pairs and subtraction, less the E_v GEMV) times the expected
        applications per set-up exceeds the set-up of E_v, else "subtract".  Figures of the
        whole problem (every rank decides the same)."""
        s, N, mq, mp = self.settings, self.N_total, self.Tq.npts, self.Tp.npts
        lo = gq.X.reshape(-1, 3).min(axis=0) if gq.X.size else np.zeros(3)
        hi = gq.X.reshape(-1, 3).max(axis=0) if gq.X.size else np.zeros(3)
        corners = np.stack([[-self.part.max(float(-x)) for x in lo], [self.part.max(float(x)) for x in hi]])
        nsrc, ntrg = N * mq, N * mp
        try:
            t_sub, _ = predicted_ewald(corners, nsrc, ntrg, N * mp * mq, s.fmm_eps, threads=1, period=s.period,
                                       double_layer=self.want_double)
            t_smooth, _ = predicted_ewald(corners, nsrc, ntrg, 0, s.fmm_eps, threads=1, period=s.period,
                                          double_layer=self.want_double, own_skip=self._own_skip)
        except Exception:            # no Ewald grid fits: the backend will not be ewald either
            return "subtract"
        layers = 1 + self.want_double
        C3 = 3 * sph.n_coeffs(self.p)
        gemv = N * layers * C3 * C3 * np.dtype(self._own_dtype()).itemsize * OWN_GEMV_BYTE
        setup = N * layers * mp * mq * OWN_SETUP_PAIR
        saving = layers * (t_sub - t_smooth) - gemv       # the own pairs are real-space work, per layer
        self.own_auto = {"saving": saving, "setup": setup, "applies": s.applies_per_setup}
        return "smooth" if saving * s.applies_per_setup > setup else "subtract"

    def _sources(self, gq):
        """The far-field backend (and Ewald parameters) for the whole problem, from the gathered
        bounding boxes of the vesicles, so that every rank and a serial run take the same; then
        the sources this rank holds (vesflow.parallel.Halo, `known`): its own vesicles and those
        within the near zone h_n of one of them, within the Ewald real-space cutoff (ewald), all
        (fmm: the FMM sums over gathered sources), with their q-grid points, normals times
        weights and weights.  Returns (backend, Ewald parameters or None)."""
        part, s, N, mq, mp = self.part, self.settings, self.N_total, self.Tq.npts, self.Tp.npts
        with self.timers.stage("gather"):
            boxes = part.gather(vesicle_boxes(gq.X, self.local.points()))
            area_max = part.max(float(self.local.area().max()))
        self.h = nearmod.near_distance(np.full(N, area_max), self.q_far, s.near_factor)
        backend, params = "direct", None
        if N > 1 or s.period:
            corners = np.stack([boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)])
            backend, params = resolve_backend(s.backend, s.fmm_eps, s.period, N * mq, N * mp, corners,
                                              N * mq * mp, self.want_double,
                                              self._own_skip if self.far_own == "smooth" else None)
        distance = float(self.h.max()) * (1.0 + 1e-6)
        if backend == "ewald":
            distance = max(distance, params.rc * (1.0 + 1e-6))
        elif backend == "fmm":
            distance = np.inf
        with self.timers.stage("gather"):
            self.halo = Halo(part, boxes, distance, s.period)
            self.known = self.halo.known
            x, nw, w = self.halo.exchange_rows(gq.X, gq.normal * gq.dA[..., None], gq.dA)
        self.src = np.ascontiguousarray(x.reshape(-1, 3))
        self.src_nw = np.ascontiguousarray(nw.reshape(-1, 3))
        self.src_w = w.reshape(-1)
        self.src_id = np.repeat(self.known, mq)
        self.src_off = np.arange(len(self.known) + 1, dtype=np.int64) * mq
        # the near blocks read the sources planar, x/y/z runs per vesicle (stokes.planar)
        self.src_planar = stokes.planar(self.src, self.src_off)
        self.src_nw_planar = stokes.planar(self.src_nw, self.src_off)
        # this rank's source points within `known` (increasing ids: Partition.block_vesicles)
        self._own_src = _point_rows(self.halo.own_rows(), mq)
        return backend, params

    def _far_field(self, backend, params):
        """direct: this rank's sources, every rank's block passed around the ring; ewald: the
        known sources (real-space part) and this rank's spread (grid summed over the ranks);
        fmm: all."""
        s, o = self.settings, self._own_src
        if backend == "direct":
            return FarField(self.src[o], self.src_id[o], self.trg, self.trg_id, backend="direct", eps=s.fmm_eps,
                            double_layer=self.want_double, ring=self.part)
        return FarField(self.src, self.src_id, self.trg, self.trg_id, backend=backend, eps=s.fmm_eps,
                        period=s.period, params=params, spread=(self.part, o), double_layer=self.want_double,
                        own=self.far_own, own_skip=self._own_skip)

    # ------------------------------------------------------------------ setup helpers
    def _near_setup(self, trg, trg_id):
        """Near pairs of the targets trg with their projections, line points and interpolation
        weights (vesflow.layerpot.near.NearPairs; None when there is none)."""
        p, h_all = self.p, self.h
        # tpos: each pair's target, moved to its image nearest the vesicle when periodic
        pairs, tpos = nearmod.near_pairs_images(trg, trg_id, self.src, self.src_id, self.src_off, float(h_all.max()),
                                                self.settings.period)
        # exact per-vesicle width: min distance from the target to the vesicle's sources
        keep = np.zeros(len(pairs), dtype=bool)
        nearest = np.empty(len(pairs), dtype=np.int64)
        srcv = self.src.reshape(len(self.known), -1, 3)
        for k0 in range(0, len(pairs), NEAR_CHUNK):       # (NEAR_CHUNK, Mq, 3) at a time: 13 MB at q = 32
            sl = slice(k0, k0 + NEAR_CHUNK)
            v = pairs[sl, 1]
            d = srcv[self._row(v)] - tpos[sl][:, None]                          # (B, Mq, 3)
            d2 = np.einsum("bmk,bmk->bm", d, d)
            j = d2.argmin(axis=1)
            nearest[sl] = j
            keep[sl] = np.sqrt(d2[np.arange(len(j)), j]) < 2.0 * h_all[v]
        pairs, nearest, tpos = pairs[keep], nearest[keep], tpos[keep]
        if not len(pairs):
            return None
        it, jp = np.divmod(nearest, self.Tq.nlon)
        # vesicles by their row in `known` (the sources this rank holds); pairs[:, 1] keeps the id
        proj = nearmod.Projection(self.surface.coeffs[self.known], p, tpos, self._row(pairs[:, 1]),
                                  self.Tq.theta[it], self.Tq.phi[jp])
        h = h_all[pairs[:, 1]]
        # targets farther than h (1 + blend) from their projection are in the smooth-rule zone
        blend = self.settings.near_blend
        zone = np.abs(proj.signed_distance) < h * (1.0 + blend)
        weight = None
        if blend > 0:
            weight = nearmod.blend_weight((np.abs(proj.signed_distance[zone]) / h[zone] - 1.0) / blend)
        pairs, tpos, h = np.ascontiguousarray(pairs[zone]), np.ascontiguousarray(tpos[zone]), h[zone]
        sel = lambda a: a[zone]
        proj.theta, proj.phi, proj.point, proj.normal = map(sel, (proj.theta, proj.phi, proj.point, proj.normal))
        proj.signed_distance, proj.converged = sel(proj.signed_distance), sel(proj.converged)
        side = np.where(proj.signed_distance >= 0, 1.0, -1.0)
        oriented = _Oriented(proj, side)
        line, _ = nearmod.line_points(oriented, h)
        # each pair's target and its line points: one block of 1 + L_POINTS targets against the
        # pair's vesicle (stokes.*_sum_blocks, vectorized across the block)
        blocks = np.ascontiguousarray(np.concatenate([tpos[:, None], line.reshape(len(pairs), nearmod.L_POINTS, 3)],
                                                     axis=1))
        return nearmod.NearPairs(
            pairs=pairs, tpos=tpos, rows=np.ascontiguousarray(self._row(pairs[:, 1]), dtype=np.int64),
            projection=proj, side=side, blocks=blocks, weights=nearmod.interpolation_weights(oriented, h),
            basis=sph.basis_values(p, proj.theta, proj.phi), blend=weight)

    def _row(self, ids):
        """Rows in `known` (this rank's sources) of vesicle ids."""
        return np.searchsorted(self.known, ids)

    # ------------------------------------------------------------------ apply
    def _densities(self, f, g):
        """Sources of the smooth rule on the q_far grid: f w / mu and (1 - lambda) g."""
        fw = np.moveaxis(self.Tq.synth(f), -2, -1).reshape(-1, 3) * (self.src_w_local / self.mu)[:, None]
        gq = None
        if g is not None and self.want_double:
            gq = np.moveaxis(self.Tq.synth(g * (1.0 - self.lam)[:, None, None]), -2, -1).reshape(-1, 3)
        return np.ascontiguousarray(fw), (None if gq is None else np.ascontiguousarray(gq))

    def self_part(self, f, g=None):
        """Coefficients of S_i[f_i] + (1 - lambda_i) pv D_i[g_i] on each vesicle's own surface."""
        u = SelfOperators.apply(self.self_ops.single, f)
        if g is not None and self.want_double:
            u += SelfOperators.apply(self.self_ops.double, g * (1.0 - self.lam)[:, None, None])
        return u

    def own_smooth_part(self, f, g=None):
        """Coefficients E_v f_v (+ E_v^D (1 - lambda_v) g_v) that remove the own vesicle's
        smooth share from the Ewald far field (vesflow.layerpot.own_smooth); None without it."""
        if self.own_ops is None:
            return None
        gl = g * (1.0 - self.lam)[:, None, None] if (g is not None and self.want_double) else None
        return self.own_ops.apply(f, gl)

    def apply(self, f, g=None):
        """Coefficients (N, 3, C) of sum_j S_j[f_j] + D_j[g_j] on every surface (pv for own D)."""
        with self.timers.stage("self"):
            u_self = self.self_part(f, g)
        if self.far is None:
            return u_self
        with self.timers.stage("far_own"):
            u_own = self.own_smooth_part(f, g)
        fw, gq = self._densities(f, g)
        fw, gq, u_near, g_near = self._exchanged(fw, gq, u_self, g)
        with self.timers.stage("far"):
            vals = self._far_evaluate(fw, gq)
        with self.timers.stage("near"):
            vals = self._near_correct(vals, self.near, fw, gq, u_near, g_near)
        vals = vals.reshape(self.N, -1, 3)
        out = u_self + self.Tp.analysis(np.moveaxis(vals, -1, -2))
        if u_own is not None:
            out += u_own
        return out

    def _far_evaluate(self, fw, gq):
        """The far field at this rank's targets from densities over the sources it holds (the
        ring of ranks passes only this rank's own ones: FarField.ring)."""
        nw = self.src_nw if gq is not None else None
        if self.far.ring is not None:
            o = self._own_src
            return self.far.evaluate(f_w=fw[o], nw=None if nw is None else nw[o], g=None if gq is None else gq[o])
        return self.far.evaluate(f_w=fw, nw=nw, g=gq)

    def _exchanged(self, fw, gq, u_self, g):
        """One halo exchange per GMRES iteration (vesflow.parallel.Halo): the far-field
        densities of the vesicles this rank holds sources of, and the self potentials and
        double-layer densities the near corrections start from (their source vesicle may live
        on another rank).  Rows in `known` order."""
        N = self.N
        rows = [fw.reshape(N, -1), u_self] + ([] if gq is None else [gq.reshape(N, -1), g])
        with self.timers.stage("gather"):
            rows = self.halo.exchange_rows(*rows)
        fw_all = np.ascontiguousarray(rows[0].reshape(-1, 3))
        if gq is None:
            return fw_all, None, rows[1], None
        return fw_all, np.ascontiguousarray(rows[2].reshape(-1, 3)), rows[1], rows[3]

    def _near_correct(self, vals, near, fw, gq, u_self, g):
        """Replace the smooth rule of the near pairs by the near-singular value, in vals (T, 3);
        the on-surface value at the projection is the self potential of the pair's vesicle,
        one-sided for D."""
        if near is None:
            return vals
        u0 = _rows_times_vesicle(near.basis, u_self, near.rows)
        if gq is not None:
            g0 = _rows_times_vesicle(near.basis, g, near.rows) * (1.0 - self.lam_all[near.pairs[:, 1]])[:, None]
            u0 -= 0.5 * near.side[:, None] * g0
        corr = self._near_minus_smooth(near, u0, fw, gq)
        np.add.at(vals, near.pairs[:, 0], corr if near.blend is None else near.blend[:, None] * corr)
        return vals

    def _near_minus_smooth(self, near, u0, fw=None, gq=None):
        """Per near pair (P, 3): the near-singular value (the line extrapolation from the
        on-surface value u0 at the projection through the smooth rule at the line points) less
        the smooth rule at the target, for the single layer of the far-field densities fw and
        the double layer of gq (either may be None)."""
        blk = np.zeros(near.blocks.shape)
        src, off = self.src_planar, self.src_off
        if gq is None:
            stokes.stokeslet_sum_blocks(src, stokes.planar(fw, off), off, near.blocks, near.rows, blk)
        elif fw is None:
            stokes.stresslet_sum_blocks(src, self.src_nw_planar, stokes.planar(gq, off), off, near.blocks,
                                        near.rows, blk)
        else:                          # both layers in one pass over the sources (the same values)
            stokes.stokeslet_stresslet_sum_blocks(src, stokes.planar(fw, off), self.src_nw_planar,
                                                  stokes.planar(gq, off), off, near.blocks, near.rows, blk)
        w = near.weights
        return w[:, :1] * u0 + np.einsum("pl,plk->pk", w[:, 1:], blk[:, 1:]) - blk[:, 0]

    def evaluate_at(self, targets, f, g=None):
        """Values at free targets (T, 3) of sum_j S_j[f_j] + D_j[g_j], any distance (off-surface)."""
        if not np.array_equal(self.idx, np.arange(self.N_total)):
            raise ValueError("evaluate_at: free targets need the layer potentials of all vesicles "
                             f"on this process; this one holds {self.N} of {self.N_total} (a partition)")
        targets = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        tid = np.full(len(targets), -1, dtype=np.int64)
        fw, gq = self._densities(f, g)
        far = FarField(self.src, self.src_id, targets, tid, backend=self.settings.backend, eps=self.settings.fmm_eps,
                       period=self.settings.period, double_layer=gq is not None)
        vals = far.evaluate(f_w=fw, nw=self.src_nw if gq is not None else None, g=gq)
        return self._near_correct(vals, self._near_setup(targets, tid), fw, gq, self.self_part(f, g), g)

    # ------------------------------------------------------------------ error estimate (3.2.4)
    def error_estimate(self):
        """Errors of D[1] (lambda = 0 kernel) per regime: self vs 1/2, near and far vs 0."""
        C = sph.n_coeffs(self.p)
        if self.self_ops.double is None:
            dl = SelfOperators(self.local.coeffs, self.p, self.q_self, False, True,
                               dtype=self.settings.self_dtype).double
        else:
            dl = self.self_ops.double
        one = np.zeros((self.N, 3, C))
        one[:, :, 0] = np.sqrt(4.0 * np.pi)
        self_vals = self.Tp.synth(SelfOperators.apply(dl, one))
        out = {"self": float(np.abs(self_vals - 0.5).max()), "near": 0.0, "far": 0.0}
        if self.N_total == 1:
            return self._max_over_ranks(out)
        ones = np.ones((len(self.src), 3))
        o = self._own_src              # the direct sum over every rank's sources: the ring of ranks
        ring = FarField(self.src[o], self.src_id[o], self.trg, self.trg_id, backend="direct", ring=self.part)
        vals = ring.evaluate(nw=self.src_nw[o], g=ones[o])
        near_t = np.zeros(len(self.trg), dtype=bool)
        if self.near is not None:
            near = self.near
            u0 = (0.5 - 0.5 * near.side)[:, None] * np.ones((1, 3))   # outside limit: 0, inside: 1
            corr = self._near_minus_smooth(near, u0, gq=ones)
            # periodic: pairs with a periodic image of the target are left out (the direct sum
            # above is over the primary images only)
            prim = np.all(near.tpos == self.trg[near.pairs[:, 0]], axis=1)
            np.add.at(vals, near.pairs[prim, 0], corr[prim])
            near_t[near.pairs[prim, 0]] = True
        err = np.abs(vals).max(axis=1)
        out["near"] = float(err[near_t].max()) if near_t.any() else 0.0
        out["far"] = float(err[~near_t].max()) if (~near_t).any() else 0.0
        return self._max_over_ranks(out)

    def _max_over_ranks(self, errors):
        """The largest of each error over the ranks (every rank takes the same decision)."""
        return {k: self.part.max(v) for k, v in errors.items()}

    @property
    def n_near_pairs(self):
        return 0 if self.near is None else len(self.near.pairs)

    def contacts(self):
        """Near pairs whose target lies on or behind the other surface: (target, vesicle, signed distance)."""
        if self.near is None:
            return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
        d = self.near.projection.signed_distance
        bad = d <= 0
        return self.near.pairs[bad], d[bad]


class _Oriented:
    """A projection whose normal points to the target's side (for the line points)."""

    def __init__(self, proj, side):
        self.point = proj.point
        self.normal = proj.normal * side[:, None]
        self.signed_distance = np.abs(proj.signed_distance)


def vesicles_of(surface, idx):
    """The Surface of the vesicles idx: `surface` itself (and its cached geometry) when idx are
    all of its vesicles in order."""
    if np.array_equal(idx, np.arange(surface.n_vesicles)):
        return surface
    return Surface(surface.coeffs[idx], surface.p)


def _point_rows(rows, m):
    """The indices of the m points of each vesicle row in `rows`: a slice when the rows are
    consecutive (indexing then makes views, not copies)."""
    rows = np.asarray(rows, dtype=np.int64)
    if len(rows) and np.array_equal(rows, np.arange(rows[0], rows[0] + len(rows))):
        return slice(int(rows[0]) * m, (int(rows[-1]) + 1) * m)
    return (rows[:, None] * m + np.arange(m)[None]).reshape(-1)


def _rows_times_vesicle(basis, coeffs, v):
    """``out[p, k] = sum_c basis[p, c] coeffs[v[p], k, c]``: one GEMM per vesicle over its rows
    (the same as ``np.einsum("pc,pkc->pk", basis, coeffs[v])`` without gathering a (P, 3, C)
    copy: 1.67 -> 0.06 s for 88189 near pairs at p = 16)."""
    out = np.empty((basis.shape[0], coeffs.shape[1]))
    if basis.shape[0] == 0:
        return out
    order = np.argsort(v, kind="stable")
    bounds = np.searchsorted(v[order], np.arange(coeffs.shape[0] + 1))
    for j in np.flatnonzero(np.diff(bounds)):
        rows = order[bounds[j]:bounds[j + 1]]
        out[rows] = basis[rows] @ coeffs[j].T
    return out
