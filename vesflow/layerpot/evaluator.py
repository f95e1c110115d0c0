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
"""
from __future__ import annotations

import numpy as np

from .. import sph
from .._kernels import stokes
from . import near as nearmod
from .far import FarField, resolve_backend
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


class Settings:
    """Quadrature settings of the layer potentials (defaults of the paper: q = 2p)."""

    def __init__(self, q_self=None, q_far=None, near_factor=1.0, backend="auto", fmm_eps=1e-8, period=None,
                 near_blend=0.0, self_precision="double", ewald_own="auto", applies_per_setup=APPLIES_PER_SETUP):
        self.q_self, self.q_far = q_self, q_far
        from .ewald import OWN_MODES
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
        """surface: all vesicles.  part (vesflow.parallel.Partition, None with one process):
        only this rank's vesicles are targets and have self operators (`local`, `idx`); this
        rank holds the sources of its vesicles and of the other ranks' vesicles within its near
        zone (or Ewald cutoff), `known` (vesflow.parallel.Halo); the direct far field passes
        the other ranks' sources around the ring of ranks."""
        s = settings or Settings()
        p = surface.p
        self.part = part
        self.N_total = surface.n_vesicles
        lam_all = np.broadcast_to(np.asarray(lam, dtype=float), (self.N_total,)).copy()
        if part is None:
            self.idx = np.arange(self.N_total)
            self.local = surface
        else:
            from ..surface import Surface
            self.idx = part.idx
            self.local = Surface(surface.coeffs[part.idx], p)
        self.p, self.N = p, self.local.n_vesicles
        self.q_self = s.q_self or 2 * p
        self.q_far = s.q_far or 2 * p
        self.mu = float(viscosity)
        self.lam_all = lam_all
        self.lam = lam_all[self.idx] if part is not None else lam_all
        self.want_double = bool(np.any(lam_all != 1.0)) if want_double is None else bool(want_double)
        self.settings = s
        self.surface = surface
        self.timers = timers
        with _timed(timers, "self_setup"):
            self.self_ops = SelfOperators(self.local.coeffs, p, self.q_self, True, self.want_double, self.mu,
                                          dtype=s.self_dtype)
        # far-field sources: the upsampled grid with its quadrature weights (rows of `known`)
        gq = self.local.geometry(self.q_far)
        self.Tq = sph.transform(p, self.q_far)
        mq = self.Tq.npts
        self.Tp = sph.transform(p)
        self.halo = None
        if part is None:
            self.known = np.arange(self.N_total, dtype=np.int64)
            self.src = np.ascontiguousarray(gq.X.reshape(-1, 3))
            self.src_w = gq.dA.reshape(-1)
            self.src_nw = np.ascontiguousarray((gq.normal * gq.dA[..., None]).reshape(-1, 3))
            self.h = nearmod.near_distance(surface.area(), self.q_far, s.near_factor)
        else:
            self.src_w_local = gq.dA.reshape(-1)
        # own targets: the p-grid
        self.trg = np.ascontiguousarray(self.local.points().reshape(-1, 3))
        self.trg_id = np.repeat(np.asarray(self.idx, dtype=np.int64), self.Tp.npts)
        self.far = None
        self.near = None
        self.own_ops = None
        self.own_auto = None          # ewald_own "auto": the cost model's figures of the choice
        self.far_own = self._far_own_mode(gq)
        if part is not None:
            far_args = self._halo_setup(gq)
        self.src_id = np.repeat(self.known, mq)
        self.src_off = np.arange(len(self.known) + 1, dtype=np.int64) * mq
        # the near blocks read the sources planar, x/y/z runs per vesicle (stokes.planar)
        self.src_planar = stokes.planar(self.src, self.src_off)
        self.src_nw_planar = stokes.planar(self.src_nw, self.src_off)
        if self.N_total > 1 or s.period:    # periodic: a single vesicle sees its images
            with _timed(timers, "near_setup"):
                self.near = self._near_setup(self.trg, self.trg_id)
            with _timed(timers, "far_setup"):
                if part is None:
                    self.far = FarField(self.src, self.src_id, self.trg, self.trg_id, backend=s.backend,
                                        eps=s.fmm_eps, period=s.period, double_layer=self.want_double,
                                        own=self.far_own, own_skip=self._own_skip)
                else:
                    self.far = self._far_partitioned(*far_args)
            if self.far.smooth_own:
                with _timed(timers, "own_setup"):
                    n, mp = self.N, self.Tp.npts
                    self.own_ops = OwnSmoothOperators(
                        self.trg.reshape(n, mp, 3), gq.X.reshape(n, mq, 3), gq.dA.reshape(n, mq),
                        (gq.normal * gq.dA[..., None]).reshape(n, mq, 3), self.far.ewald.params.xi, p,
                        self.q_far, True, self.want_double, self.mu, dtype=self._own_dtype())
        self.n_near_pairs_total = (self.n_near_pairs if part is None else int(part.sum(self.n_near_pairs)))

    def _far_own_mode(self, gq):
        """The Ewald sum's own mode (Settings.ewald_own): "smooth" unless a vesicle is so large
        against the period that its own periodic images could lie within the largest cutoff
        (0.49 of the shortest period, ewald.choose_params): then "subtract"
        (ewald.own_extent_ok).  Sets ``_own_skip`` (q-grid points per vesicle, mean area) for
        the cost model."""
        s = self.settings
        area = gq.dA.reshape(self.N, -1).sum(axis=1)
        tot = float(area.sum()) if self.part is None else self.part.sum(float(area.sum()))
        self._own_skip = (self.Tq.npts, tot / max(self.N_total, 1))
        mode = s.ewald_own
        if mode == "auto":
            mode = self._own_auto(gq)
        if mode != "smooth" or s.period is None:
            return mode
        pts = np.concatenate([gq.X.reshape(self.N, -1, 3), self.local.points().reshape(self.N, -1, 3)], axis=1)
        ext = (pts.max(axis=1) - pts.min(axis=1)).max(axis=0, initial=0.0)
        if self.part is not None:
            ext = np.array([self.part.max(float(e)) for e in ext])
        from .ewald import own_extent_ok
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
        from .far import predicted_ewald
        s, N, mq, mp = self.settings, self.N_total, self.Tq.npts, self.Tp.npts
        lo = gq.X.reshape(-1, 3).min(axis=0) if gq.X.size else np.zeros(3)
        hi = gq.X.reshape(-1, 3).max(axis=0) if gq.X.size else np.zeros(3)
        if self.part is not None:
            lo = np.array([-self.part.max(float(-x)) for x in lo])
            hi = np.array([self.part.max(float(x)) for x in hi])
        corners = np.stack([lo, hi])
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

    def _halo_setup(self, gq):
        """With a partition: the far-field backend (and Ewald parameters) for the whole problem,
        so that every rank and a one-process run take the same, from the gathered bounding boxes
        of the vesicles; then the surfaces this rank needs (vesflow.parallel.Halo): those within
        the near zone h_n of one of its vesicles, within the Ewald real-space cutoff (ewald),
        all (fmm: the FMM sums over gathered sources).  Returns (backend, Ewald parameters)."""
        from ..parallel import Halo, vesicle_boxes
        part, s, N, mq, mp = self.part, self.settings, self.N_total, self.Tq.npts, self.Tp.npts
        with _timed(self.timers, "gather"):
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
        with _timed(self.timers, "gather"):
            self.halo = Halo(part, boxes, distance, s.period)
            self.known = self.halo.known
            n = self.N
            geo = self.halo.exchange(np.concatenate([gq.X.reshape(n, -1), (gq.normal * gq.dA[..., None]).reshape(n, -1),
                                                     gq.dA.reshape(n, -1)], axis=1))
        self.src = np.ascontiguousarray(geo[:, :3 * mq].reshape(-1, 3))
        self.src_nw = np.ascontiguousarray(geo[:, 3 * mq:6 * mq].reshape(-1, 3))
        self.src_w = np.ascontiguousarray(geo[:, 6 * mq:].reshape(-1))
        # this rank's source points within `known` (increasing ids: Partition.block_vesicles)
        own = self.halo.own_rows()
        self._own_src = (own[:, None] * mq + np.arange(mq)[None]).reshape(-1)
        return backend, params

    def _far_partitioned(self, backend, params):
        """direct: this rank's sources, every rank's block passed around the ring; ewald: the
        known sources (real-space part) and this rank's spread (grid Allreduced); fmm: all."""
        s, o = self.settings, self._own_src
        if backend == "direct":
            return FarField(self.src[o], self.src_id[o], self.trg, self.trg_id, backend="direct", eps=s.fmm_eps,
                            double_layer=self.want_double, ring=self.part)
        spread = (self.part, o) if backend == "ewald" else None
        return FarField(self.src, self.src_id, self.trg, self.trg_id, backend=backend, eps=s.fmm_eps,
                        period=s.period, params=params, spread=spread, double_layer=self.want_double,
                        own=self.far_own, own_skip=self._own_skip)

    # ------------------------------------------------------------------ setup helpers
    def _near_setup(self, trg, trg_id):
        """Near pairs, projections, line points and interpolation weights for targets trg."""
        hmax = float(self.h.max())
        # tpos: each pair's target, moved to its image nearest the vesicle when periodic
        pairs, tpos = nearmod.near_pairs_images(trg, trg_id, self.src, self.src_id, self.src_off, hmax,
                                                self.settings.period)
        if len(pairs):
            keep = np.zeros(len(pairs), dtype=bool)
            # exact per-vesicle width: min distance from the target to the vesicle's sources
            nearest = np.empty(len(pairs), dtype=np.int64)
            for k0 in range(0, len(pairs), 2048):
                sl = slice(k0, k0 + 2048)
                t, v = pairs[sl, 0], pairs[sl, 1]
                pts = self.src.reshape(len(self.known), -1, 3)[self._row(v)]           # (B, Mq, 3)
                d2 = np.einsum("bmk,bmk->bm", pts - tpos[sl][:, None], pts - tpos[sl][:, None])
                j = d2.argmin(axis=1)
                nearest[sl] = j
                keep[sl] = np.sqrt(d2[np.arange(len(j)), j]) < 2.0 * self.h[v]
            pairs, nearest, tpos = pairs[keep], nearest[keep], tpos[keep]
        else:
            nearest = np.zeros(0, dtype=np.int64)
        info = {"pairs": np.ascontiguousarray(pairs)}
        if not len(pairs):
            return info
        it, jp = np.divmod(nearest, self.Tq.nlon)
        # vesicles by their row in `known` (the sources this rank holds); pairs[:, 1] keeps the id
        coeffs = self.surface.coeffs if self.part is None else self.surface.coeffs[self.known]
        proj = nearmod.Projection(coeffs, self.p, tpos, self._row(pairs[:, 1]),
                                  self.Tq.theta[it], self.Tq.phi[jp])
        h = self.h[pairs[:, 1]]
        # targets farther than h (1 + blend) from their projection are in the smooth-rule zone
        blend = getattr(self.settings, "near_blend", 0.0)
        inside_zone = np.abs(proj.signed_distance) < h * (1.0 + blend)
        if blend > 0:
            info["blend"] = nearmod.blend_weight((np.abs(proj.signed_distance[inside_zone]) / h[inside_zone] - 1.0) / blend)
        info["pairs"] = np.ascontiguousarray(pairs[inside_zone])
        info["tpos"] = np.ascontiguousarray(tpos[inside_zone])
        P = len(info["pairs"])
        # (row of tpos, vesicle): the pair list of the smooth-rule kernels
        rows = self._row(info["pairs"][:, 1])
        info["rows"] = rows
        info["tpairs"] = np.ascontiguousarray(np.stack([np.arange(P), rows], axis=1))
        sel = lambda a: a[inside_zone]
        proj.theta, proj.phi, proj.point, proj.normal = map(sel, (proj.theta, proj.phi, proj.point, proj.normal))
        proj.signed_distance, proj.converged = sel(proj.signed_distance), sel(proj.converged)
        info["projection"] = proj
        side = np.where(proj.signed_distance >= 0, 1.0, -1.0)
        info["side"] = side
        oriented = _Oriented(proj, side)
        pts, _ = nearmod.line_points(oriented, h[inside_zone])
        info["line_points"] = np.ascontiguousarray(pts.reshape(-1, 3))
        info["line_pairs"] = np.ascontiguousarray(
            np.stack([np.arange(P * nearmod.L_POINTS), np.repeat(rows, nearmod.L_POINTS)], axis=1))
        # each pair's target and its line points: one block of 1 + L_POINTS targets against the
        # pair's vesicle (stokes.*_sum_blocks, vectorized across the block)
        info["blocks"] = np.ascontiguousarray(np.concatenate(
            [info["tpos"][:, None], pts.reshape(P, nearmod.L_POINTS, 3)], axis=1))
        info["block_ves"] = np.ascontiguousarray(rows, dtype=np.int64)
        info["weights"] = nearmod.interpolation_weights(oriented, h[inside_zone])
        info["basis"] = sph.evaluate(np.eye(sph.n_coeffs(self.p)), self.p, proj.theta, proj.phi).T  # (P, C)
        return info

    def _row(self, ids):
        """Rows in `known` (this rank's sources) of vesicle ids."""
        return ids if self.part is None else np.searchsorted(self.known, ids)

    # ------------------------------------------------------------------ apply
    def _densities(self, f, g):
        """Sources of the smooth rule on the q_far grid: f w / mu and (1 - lambda) g."""
        w = self.src_w if self.part is None else self.src_w_local
        fw = np.moveaxis(self.Tq.synth(f), -2, -1).reshape(-1, 3) * (w / self.mu)[:, None]
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

    def apply(self, f, g=None, parts=None):
        """Coefficients (N, 3, C) of sum_j S_j[f_j] + D_j[g_j] on every surface (pv for own D)."""
        parts = parts if parts is not None else {}
        with _timed(self.timers, "self"):
            u_self = self.self_part(f, g)
        if self.far is None:
            return u_self
        with _timed(self.timers, "far_own"):
            u_own = self.own_smooth_part(f, g)
        fw, gq = self._densities(f, g)
        u_near, g_near = u_self, g
        if self.part is not None:
            fw, gq, u_near, g_near = self._exchanged(fw, gq, u_self, g)
        with _timed(self.timers, "far"):
            vals = self._far_evaluate(fw, gq)
        with _timed(self.timers, "near"):
            vals = self._near_correct(vals, self.near, self.trg, fw, gq, u_near, g_near)
        vals = vals.reshape(self.N, -1, 3)
        out = u_self + self.Tp.analysis(np.moveaxis(vals, -1, -2))
        if u_own is not None:
            out += u_own
        return out

    def _far_evaluate(self, fw, gq):
        """The far field at this rank's targets from densities over the sources it holds (the
        ring of ranks passes only this rank's own ones: FarField.ring)."""
        nw = self.src_nw if gq is not None else None
        if getattr(self.far, "ring", None) is not None:
            o = self._own_src
            return self.far.evaluate(f_w=fw[o], nw=None if nw is None else nw[o], g=None if gq is None else gq[o])
        return self.far.evaluate(f_w=fw, nw=nw, g=gq)

    def _exchanged(self, fw, gq, u_self, g):
        """One halo exchange per GMRES iteration (vesflow.parallel.Halo): the far-field
        densities of the vesicles this rank holds sources of, and the self potentials and
        double-layer densities the near corrections start from (their source vesicle may live
        on another rank).  Rows in `known` order."""
        N, mq, C3 = self.N, self.Tq.npts, 3 * sph.n_coeffs(self.p)
        pieces = [fw.reshape(N, -1), u_self.reshape(N, -1)]
        if gq is not None:
            pieces += [gq.reshape(N, -1), g.reshape(N, -1)]
        with _timed(self.timers, "gather"):
            allg = self.halo.exchange(np.concatenate(pieces, axis=1))
        K = len(self.known)
        fw_all = np.ascontiguousarray(allg[:, :3 * mq].reshape(-1, 3))
        u_all = allg[:, 3 * mq:3 * mq + C3].reshape(K, 3, -1)
        if gq is None:
            return fw_all, None, u_all, None
        o = 3 * mq + C3
        gq_all = np.ascontiguousarray(allg[:, o:o + 3 * mq].reshape(-1, 3))
        g_all = allg[:, o + 3 * mq:].reshape(K, 3, -1)
        return fw_all, gq_all, u_all, g_all

    def _near_correct(self, vals, info, trg, fw, gq, u_self, g):
        """Replace the smooth rule of near pairs by the near-singular value."""
        if info is None or "projection" not in info:
            return vals
        pairs = info["pairs"]
        # smooth rule of each pair's vesicle at its target (column 0) and line points (1 ..)
        blk = np.zeros(info["blocks"].shape)
        fp = stokes.planar(fw, self.src_off)
        if gq is None:
            stokes.stokeslet_sum_blocks(self.src_planar, fp, self.src_off, info["blocks"], info["block_ves"], blk)
        else:                          # both layers in one pass over the sources (the same values)
            stokes.stokeslet_stresslet_sum_blocks(self.src_planar, fp, self.src_nw_planar,
                                                  stokes.planar(gq, self.src_off), self.src_off, info["blocks"],
                                                  info["block_ves"], blk)
        smooth = blk[:, 0]
        line = blk[:, 1:]
        v, rows = pairs[:, 1], info["rows"]
        # on-surface value at the projection: the self potential of vesicle v, one-sided for D
        u0 = _rows_times_vesicle(info["basis"], u_self, rows)
        if gq is not None:
            g0 = _rows_times_vesicle(info["basis"], g, rows) * (1.0 - self.lam_all[v])[:, None]
            u0 -= 0.5 * info["side"][:, None] * g0
        w = info["weights"]
        nearval = w[:, :1] * u0 + np.einsum("pl,plk->pk", w[:, 1:], line)
        if "blend" in info:
            np.add.at(vals, pairs[:, 0], info["blend"][:, None] * (nearval - smooth))
        else:
            np.add.at(vals, pairs[:, 0], nearval - smooth)
        return vals

    def evaluate_at(self, targets, f, g=None):
        """Values at free targets (T, 3) of sum_j S_j[f_j] + D_j[g_j], any distance (off-surface)."""
        if self.part is not None:
            raise ValueError("evaluate_at: free targets need the layer potentials of all vesicles "
                             "on this process (part=None); this one holds a partition")
        targets = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        tid = np.full(len(targets), -1, dtype=np.int64)
        fw, gq = self._densities(f, g)
        far = FarField(self.src, self.src_id, targets, tid, backend=self.settings.backend, eps=self.settings.fmm_eps,
                       period=self.settings.period, double_layer=gq is not None)
        vals = far.evaluate(f_w=fw, nw=self.src_nw if gq is not None else None, g=gq)
        info = self._near_setup(targets, tid)
        return self._near_correct(vals, info, targets, fw, gq, self.self_part(f, g), g)

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
        gq = np.ones((len(self.src), 3))
        vals = np.zeros((len(self.trg), 3))
        if self.part is None:
            stokes.stresslet_sum_excl(self.src, self.src_nw, gq, self.src_id, self.trg, self.trg_id, vals)
        else:                # the direct sum over every rank's sources: the ring of ranks
            o = self._own_src
            ring = FarField(self.src[o], self.src_id[o], self.trg, self.trg_id, backend="direct", ring=self.part)
            vals = ring.evaluate(nw=self.src_nw[o], g=gq[o])
        near_t = np.zeros(len(self.trg), dtype=bool)
        if self.near is not None and "projection" in self.near:
            info = self.near
            smooth = np.zeros((len(info["pairs"]), 3))
            stokes.stresslet_sum_pairs(self.src, self.src_nw, gq, self.src_off, info["tpos"], info["tpairs"], smooth)
            line = np.zeros((len(info["line_points"]), 3))
            stokes.stresslet_sum_pairs(self.src, self.src_nw, gq, self.src_off, info["line_points"],
                                       info["line_pairs"], line)
            u0 = (0.5 - 0.5 * info["side"])[:, None] * np.ones((1, 3))   # outside limit: 0, inside: 1
            line = line.reshape(len(info["pairs"]), nearmod.L_POINTS, 3)
            w = info["weights"]
            # periodic: pairs with a periodic image of the target are left out (the direct sum
            # above is over the primary images only)
            prim = np.all(info["tpos"] == self.trg[info["pairs"][:, 0]], axis=1)
            corr = w[:, :1] * u0 + np.einsum("pl,plk->pk", w[:, 1:], line) - smooth
            np.add.at(vals, info["pairs"][prim, 0], corr[prim])
            near_t[info["pairs"][prim, 0]] = True
        err = np.abs(vals).max(axis=1)
        out["near"] = float(err[near_t].max()) if near_t.any() else 0.0
        out["far"] = float(err[~near_t].max()) if (~near_t).any() else 0.0
        return self._max_over_ranks(out)

    def _max_over_ranks(self, errors):
        """The largest of each error over the ranks (every rank takes the same decision)."""
        if self.part is None:
            return errors
        return {k: self.part.max(v) for k, v in errors.items()}

    @property
    def n_near_pairs(self):
        return 0 if self.near is None else len(self.near["pairs"])

    def contacts(self):
        """Near pairs whose target lies on or behind the other surface: (target, vesicle, signed distance)."""
        if self.near is None or "projection" not in self.near:
            return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
        d = self.near["projection"].signed_distance
        bad = d <= 0
        return self.near["pairs"][bad], d[bad]


class _Oriented:
    """A projection whose normal points to the target's side (for the line points)."""

    def __init__(self, proj, side):
        self.point = proj.point
        self.normal = proj.normal * side[:, None]
        self.signed_distance = np.abs(proj.signed_distance)


class _timed:
    def __init__(self, timers, name):
        self.timers, self.name = timers, name

    def __enter__(self):
        if self.timers is not None:
            self.timers.start(self.name)

    def __exit__(self, *exc):
        if self.timers is not None:
            self.timers.stop(self.name)


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
