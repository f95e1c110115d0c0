"""Far-field layer potentials over many vesicles (docs/explanation/method.md, section 5, regime 3).

For targets ``x_t`` carrying a group id ``trg_id[t]`` (the vesicle the target lies on, or
any id that no source uses for a free target) and source points ``y_s`` (q-grid points)
with vesicle id ``src_id[s]``, this module evaluates the smooth-rule sums over all sources
of OTHER vesicles::

    single layer  u_t = sum_{s: src_id[s] != trg_id[t]} S(x_t, y_s) f_s w_s
    double layer  u_t = sum_{s: src_id[s] != trg_id[t]} D(x_t, y_s) g_s      (nw_s = n_s w_s)

with the kernels of section 4 (mu = 1, lambda = 0 stresslet; the caller divides by mu and
multiplies ``g`` by ``(1 - lambda_j)`` of the source vesicle).  The near pairs still have to
be corrected by the caller: subtract the smooth rule of those pairs
(:func:`vesflow._kernels.stokes.stokeslet_sum_pairs`) and add the near-singular values.

Backends
--------
``"direct"``
    The Cython kernels ``stokeslet_sum_excl`` / ``stresslet_sum_excl``: exact to rounding,
    O(T S), OpenMP over targets.
``"fmm"``
    fmm3dpy's ``stfmm3d`` (Stokes FMM, O(T + S) at fixed accuracy ``eps``).  The FMM cannot
    leave out the target's own vesicle, so the sum over ALL sources is computed and the
    self part (target t against the sources of vesicle ``trg_id[t]``) is subtracted with the
    direct kernel ``stokeslet_sum_pairs`` / ``stresslet_sum_pairs``: O(N M Q) for N vesicles
    of M targets and Q sources each (0.3-0.6 s per call at N = 256, p = 16, q = 32 on
    this machine; see docs/explanation/far_field.md).  Conventions (docs/explanation/far_field.md, "fmm"): the
    FMM stresslet is ``+(3/4pi)(r.mu)(r.nu) r / r^5``, so the orientation passed is
    ``strsvec = -n w``; ``pottarg`` comes back as (1, 3, T).
    Targets that coincide with a source of their own vesicle up to rounding (the p-grid and
    the q-grid share the equator when p and q are both even) are snapped exactly onto that
    source (distance below ``SNAP_TOL`` times the size of the point cloud): the FMM skips
    a pair below its own threshold (~1e-15 relative) but evaluates a pair at 1e-13 with
    huge, badly rounded values, which the subtraction would not cancel.  The far field of
    the other vesicles moves by O(SNAP_TOL) relative.
``"ewald"``
    The spectral Ewald sum of :mod:`vesflow.layerpot.ewald` (free space, or triply periodic
    with ``period``): O((T + S) log) at accuracy ``eps`` (relative to the largest velocity),
    plus the O(N M Q) own-vesicle subtraction (the FMM's cost too) with ``own="subtract"``;
    ``own="smooth"`` leaves the own vesicle out of the real-space sum and keeps its smooth
    Fourier share, which the caller removes (LayerPotentials: vesflow.layerpot.own_smooth).
``"auto"``
    The backend of least cost by the frozen weights of :func:`predicted_seconds` and
    :data:`vesflow.layerpot.ewald.COST`, on one thread (fmm only if fmm3dpy imports, ewald
    only if ducc0 or finufft does and the points are given); periodic: always ewald.

FMM accuracy: ``eps`` (default ``DEFAULT_EPS = 1e-8``) is fmm3dpy's requested precision;
the error measured against the direct sum, relative to the largest velocity, is below
``eps`` (docs/explanation/far_field.md).  1e-8 rather than 1e-6: the far field enters every GMRES
matrix-vector product and the singular/near quadratures are accurate to 1e-6 .. 1e-10, so an
FMM error of 1e-6 would dominate them, for a measured cost of only about 1.3x.
"""
from __future__ import annotations

from functools import cached_property

import numpy as np

from vesflow._kernels import search as _search
from vesflow._kernels import stokes as _stokes
from vesflow.errors import NumericalFailure, SettingsError

from . import ewald

from .groups import group_by_vesicle

BACKENDS = ("direct", "fmm", "ewald", "auto")
DEFAULT_EPS = 1e-8
# Weights of the "auto" rule (choose_backend: the backend of least modelled cost, every backend
# on ONE thread, so that the choice does not depend on OMP_NUM_THREADS or the machine's load):
# seconds per (target, source) pair of the direct sum; FMM (fmm3dpy, serial) seconds per point
# (sources + targets) at the listed eps, interpolated in log(eps), clamped outside.  Frozen: the
# development machine's figures (benchmarks/far_field.py, benchmarks/cost_model.py) and part of
# the method, so that the backend, and with it the result, is the same on every machine; this
# machine's measured figures are vesflow.calibration's, which only `vesflow check` reads
# (docs/explanation/calibration.md).
DIRECT_SECONDS_PER_PAIR = 1.4e-9
FMM_SECONDS_PER_POINT = {1e-6: 1.65e-4, 1e-8: 2.35e-4, 1e-10: 2.5e-4}
# targets within SNAP_TOL * (size of the point cloud) of a source of their own vesicle are
# moved onto it (FMM backend only)
SNAP_TOL = 1e-10


def _have_fmm():
    try:
        import fmm3dpy  # noqa: F401
    except ImportError:
        return False
    return True


def _have_ewald():
    return any(ewald._have(lib) for lib in ewald.NUFFT_LIBS)


def predicted_seconds(nsrc, ntrg, eps=DEFAULT_EPS, threads=None, per_pair=None, per_point=None):
    """Predicted seconds per evaluation ``(direct, fmm)`` of the single layer: by the rule's
    weights above, or by ``per_pair`` (seconds) and ``per_point`` ({eps: seconds}) if given
    (vesflow.costs: this machine's, vesflow.calibration)."""
    threads = _stokes.max_threads() if threads is None else max(int(threads), 1)
    per_pair = DIRECT_SECONDS_PER_PAIR if per_pair is None else per_pair
    per_point = FMM_SECONDS_PER_POINT if per_point is None else per_point
    t_direct = float(nsrc) * float(ntrg) * per_pair / threads
    le = sorted(per_point)
    t_point = float(np.exp(np.interp(np.log(eps), np.log(le), np.log([per_point[e] for e in le]))))
    return t_direct, (float(nsrc) + float(ntrg)) * t_point


def predicted_ewald(points, nsrc, ntrg, own_pairs, eps=DEFAULT_EPS, threads=None, period=None,
                    double_layer=False, own_skip=None, cost=None):
    """``(seconds, params)`` of the Ewald sum (single layer) over ``points`` (sources and
    targets, or any points spanning their box), ``own_pairs`` target-source pairs of the
    same vesicle (the O(N M Q) subtraction); the parameters from
    :func:`vesflow.layerpot.ewald.choose_params`; ``double_layer``: parameters accurate for
    the stresslet too (the time is still that of the single layer); ``own_skip``: the
    own="smooth" mode (:func:`vesflow.layerpot.ewald.choose_params`); ``cost``: the weights of
    the time (default the rule's, :data:`vesflow.layerpot.ewald.COST`; the parameters are the
    rule's whatever ``cost`` is)."""
    threads = _stokes.max_threads() if threads is None else max(int(threads), 1)
    p = ewald.choose_params(eps, points, period, nsrc, ntrg, threads, 9 if double_layer else 3, own_skip)
    return ewald._predicted(p, nsrc, ntrg, threads, 3, own_pairs, own_skip, cost), p


def choose_backend(nsrc, ntrg, backend="auto", eps=DEFAULT_EPS, t_ewald=None, periodic=False):
    """Resolve ``backend`` ("direct", "fmm", "ewald" or "auto") for S sources and T targets.

    "auto" takes the backend of least cost by the rule's weights (:func:`predicted_seconds`,
    one thread) among those available (ewald only when its prediction ``t_ewald``, one thread,
    is given); periodic: ewald, the only one.
    """
    if backend not in BACKENDS:
        raise SettingsError(f"far-field backend {backend!r} is not one of {', '.join(BACKENDS)}")
    if periodic and backend not in ("ewald", "auto"):
        raise SettingsError(f"far-field backend {backend!r} cannot sum over a periodic box; "
                            "use -ves_far ewald or auto")
    if backend == "auto":
        if periodic:
            backend = "ewald"
        else:
            t_direct, t_fmm = predicted_seconds(nsrc, ntrg, eps, threads=1)
            cands = [(t_direct, "direct")]
            if _have_fmm():
                cands.append((t_fmm, "fmm"))
            if t_ewald is not None and _have_ewald():
                cands.append((t_ewald, "ewald"))
            return min(cands)[1]
    if backend == "fmm" and not _have_fmm():
        raise SettingsError("far-field backend 'fmm' needs fmm3dpy (pip install fmm3dpy); "
                            "use backend 'direct' or 'auto'")
    if backend == "ewald" and not _have_ewald():
        raise SettingsError("far-field backend 'ewald' needs ducc0 or finufft (pip install finufft); "
                            "use backend 'direct' or 'auto'")
    return backend


def resolve_backend(backend, eps, period, nsrc, ntrg, points, own_pairs, double_layer=True, own_skip=None):
    """``(backend, Ewald parameters or None)`` for ``nsrc`` sources and ``ntrg`` targets
    spanning the box of ``points`` (any points spanning it), ``own_pairs`` target-source pairs
    of the same vesicle: "auto" resolved by the cost model, the Ewald parameters chosen when
    the backend is ewald (vesflow.layerpot.ewald.choose_params; ``own_skip``: for the
    own="smooth" Ewald sum)."""
    t_ewald, params = None, None
    if backend == "auto" and period is None and nsrc and ntrg and _have_ewald():
        try:
            t_ewald, params = predicted_ewald(points, nsrc, ntrg, own_pairs, eps, threads=1,
                                              double_layer=double_layer, own_skip=own_skip)
        except SettingsError:               # no grid fits the memory: not a candidate
            t_ewald, params = None, None
    backend = choose_backend(nsrc, ntrg, backend, eps, t_ewald, periodic=period is not None)
    if backend != "ewald":
        return backend, None
    if params is None:
        params = ewald.choose_params(eps, points, period, nsrc, ntrg, _stokes.max_threads(), 9 if double_layer else 3,
                               own_skip)
    return backend, params


def _own_pairs(src_id, trg_id):
    """Number of (target, source) pairs with the same id."""
    ids, cnt = np.unique(src_id, return_counts=True)
    if not ids.size:
        return 0
    vi = np.minimum(np.searchsorted(ids, trg_id), ids.size - 1)
    return int(np.where(ids[vi] == trg_id, cnt[vi], 0).sum())


def _points(name, a):
    a = np.ascontiguousarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {a.shape}")
    return a


def _ids(name, a, n):
    a = np.ascontiguousarray(a, dtype=np.int64)
    if a.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {a.shape}")
    return a


class FarField:
    """Far field of a fixed geometry: sources ``src`` (S, 3) grouped by ``src_id`` (S,),
    targets ``trg`` (T, 3) with ``trg_id`` (T,).  Densities are given per call, so one
    object serves every GMRES iteration of a time step.  ``double_layer``: the double layer
    will be evaluated too (the Ewald parameters then meet ``eps`` for the stresslet; False
    allows a cheaper choice for the single layer alone).

    Attributes: ``backend`` (resolved), ``eps``, ``ids`` (the distinct source vesicle ids,
    sorted), ``src_off`` (offsets of each vesicle's sources in the id-sorted order),
    ``n_snapped`` (targets moved onto a coincident own source, fmm and ewald).
    """

    def __init__(self, src, src_id, trg, trg_id, backend="auto", eps=DEFAULT_EPS, period=None,
                 params=None, spread=None, double_layer=True, ring=None, own="subtract", own_skip=None,
                 grid="replicated"):
        """params: the Ewald parameters (ewald backend; default: chosen for these sources and
        targets, `resolve_backend`).  With the vesicle partition (vesflow.parallel; trg are this
        rank's): the caller resolves the backend and parameters for the whole problem;
        spread = (partition, indices of this rank's sources): the Ewald sum spreads only those
        (EwaldSum); ring = partition (direct backend): src are this rank's sources, in the
        order of `Partition.block_vesicles`, and every rank's block is passed around the ring.
        double_layer: the Ewald parameters are made accurate for the stresslet too.
        own: the ewald backend's treatment of a target's own vesicle (EwaldSum): "subtract"
        (the sum over other vesicles, as every backend) or "smooth" (ewald only: the result
        then also holds the own vesicle's smooth Fourier share, which the caller removes,
        vesflow.layerpot.own_smooth; ``smooth_own`` tells whether it does); own_skip: (sources
        per vesicle, mean area) for the cost model of "smooth"; grid: the Ewald Fourier grid,
        "replicated" or "distributed" (EwaldSum, vesflow.layerpot.ewald_grid)."""
        self.src = _points("src", src)
        self.trg = _points("trg", trg)
        self.src_id = _ids("src_id", src_id, self.src.shape[0])
        self.trg_id = _ids("trg_id", trg_id, self.trg.shape[0])
        if not (0.0 < eps < 1.0):
            raise SettingsError(f"far-field accuracy eps (-ves_far_tol) must lie in (0, 1), got {eps}")
        self.eps = float(eps)
        self.period = period
        if own not in ewald.OWN_MODES:
            raise ValueError(f"FarField own = {own!r}: must be one of {', '.join(ewald.OWN_MODES)}")
        skip = own_skip if own == "smooth" else None
        if backend == "auto" or (backend == "ewald" and params is None):
            backend, params = resolve_backend(backend, self.eps, period, self.src.shape[0], self.trg.shape[0],
                                              np.concatenate([self.src, self.trg]),
                                              _own_pairs(self.src_id, self.trg_id), double_layer, skip)
        self.backend = choose_backend(self.src.shape[0], self.trg.shape[0], backend, self.eps,
                                      periodic=period is not None)
        self.ring = ring
        if ring is not None:
            if self.backend != "direct":
                raise ValueError(f"FarField: the ring of ranks is for the direct backend, not {self.backend!r}")
            per = self.src.shape[0] // max(ring.n_local, 1)
            if not np.array_equal(self.src_id, np.repeat(ring.block_vesicles(ring.rank), per)):
                raise ValueError("FarField: with the ring, src must be this rank's sources, its vesicles in "
                                 "increasing id order (Partition.block_vesicles), the same count each")
        self.n_snapped = 0
        self.ewald = None
        self.smooth_own = False
        if self.backend == "fmm":
            self._setup_fmm()
        elif self.backend == "ewald":
            # own="subtract": the own vesicle's pairs are summed inside rc and its full kernel
            # subtracted: a target a rounding error away from an own source (p- and q-grid
            # longitudes that coincide only up to rounding, e.g. q = 24 at p = 16) would cancel
            # two 1/r ~ 1e16 terms; snapped onto the source, the pair is an exact coincidence,
            # which both sums skip (their difference, the Fourier part's self term, is
            # subtracted).  own="smooth" has no own pair (G^F is smooth): targets as given, the
            # positions the caller's correction is built at
            trg = self.trg if own == "smooth" else self._snapped_targets()
            self.ewald = ewald.EwaldSum(self.src, self.src_id, trg, self.trg_id, tol=self.eps, period=period,
                                        params=params, spread=spread, double_layer=double_layer, own=own,
                                        own_skip=skip, grid=grid)
            self.smooth_own = own == "smooth"

    @cached_property
    def _groups(self):
        """The sources sorted by vesicle id, each target's vesicle among them (vesflow.layerpot.groups)."""
        return group_by_vesicle(self.src, self.src_id, self.trg_id)

    def _snapped_targets(self):
        """The targets, those within SNAP_TOL * (size of the point cloud) of a source of their
        own vesicle moved exactly onto it (``n_snapped`` counts them)."""
        grp = self._groups
        allp = np.concatenate([self.src, self.trg])
        size = float(np.max(np.ptp(allp, axis=0))) if allp.shape[0] > 1 else 0.0
        tol = SNAP_TOL * (size if size > 0.0 else 1.0)
        hit = _search.coincident_sources(grp.src, grp.off, self.trg, grp.trg_vi, tol)
        moved = np.flatnonzero(hit >= 0)
        self.n_snapped = int(moved.size)
        if not moved.size:
            return self.trg
        trg = self.trg.copy()
        trg[moved] = grp.src[hit[moved]]
        return trg

    # ------------------------------------------------------------------ set-up (FMM)
    def _setup_fmm(self):
        grp = self._groups
        self.ids, self.src_off = grp.ids, grp.off
        # each target against the sources of its own vesicle (index into ids; -1: none)
        tsel = np.flatnonzero(grp.trg_vi >= 0)
        self._self_pairs = np.ascontiguousarray(np.stack([tsel, grp.trg_vi[tsel]], axis=1), dtype=np.int64)
        # snap targets that coincide with an own source up to rounding
        self._trg_fmm = self._snapped_targets()
        self._srcT = np.ascontiguousarray(self.src.T)
        self._trgT = np.ascontiguousarray(self._trg_fmm.T)

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, f_w=None, nw=None, g=None):
        """Single layer of ``f_w`` plus double layer of ``g`` with orientations ``nw``, (T, 3).

        ``f_w``: traction times quadrature weight (S, 3) or None; ``nw``: normal times
        weight and ``g``: density (S, 3), both or neither.  With the FMM both layers cost
        one FMM call.
        """
        ns, nt = self.src.shape[0], self.trg.shape[0]
        if (nw is None) != (g is None):
            raise ValueError("double layer: give both nw and g, or neither")
        f_w = None if f_w is None else _points("f_w", f_w)
        nw = None if nw is None else _points("nw", nw)
        g = None if g is None else _points("g", g)
        for name, a in (("f_w", f_w), ("nw", nw), ("g", g)):
            if a is not None and a.shape[0] != ns:
                raise ValueError(f"{name} has {a.shape[0]} rows, src has {ns} points")
        out = np.zeros((nt, 3))
        if nt == 0 or ns == 0 or (f_w is None and g is None):
            return out
        if self.backend == "ewald":
            return self.ewald.evaluate(f_w, nw, g)
        if self.backend == "direct" and self.ring is not None:
            return self._evaluate_ring(f_w, nw, g, out)
        if self.backend == "direct":
            if f_w is not None:
                _stokes.stokeslet_sum_excl(self.src, f_w, self.src_id, self.trg, self.trg_id, out)
            if g is not None:
                _stokes.stresslet_sum_excl(self.src, nw, g, self.src_id, self.trg, self.trg_id, out)
            return out
        return self._evaluate_fmm(f_w, nw, g, out)

    def _evaluate_ring(self, f_w, nw, g, out):
        """Direct sum over every rank's sources: this rank's block (points and densities) is
        passed around the ring of ranks (vesflow.parallel.Partition.ring) and each block is
        summed at this rank's targets as it passes."""
        part = self.ring
        cols = [self.src] + [a for a in (f_w, nw, g) if a is not None]
        k = 3 * len(cols)
        per = self.src.shape[0] // max(part.n_local, 1)           # sources per vesicle
        lengths = part.counts * per * k

        def add(data, r):
            ids = np.repeat(part.block_vesicles(r), per)
            a = data.reshape(len(cols), -1, 3)
            src = a[0]
            j = 1
            if f_w is not None:
                _stokes.stokeslet_sum_excl(src, a[j], ids, self.trg, self.trg_id, out)
                j += 1
            if g is not None:
                _stokes.stresslet_sum_excl(src, a[j], a[j + 1], ids, self.trg, self.trg_id, out)

        part.ring(np.concatenate([c.reshape(-1) for c in cols]), lengths, add)
        return out

    def _evaluate_fmm(self, f_w, nw, g, out):
        import fmm3dpy

        kw = {}
        if f_w is not None:
            kw["stoklet"] = np.ascontiguousarray(f_w.T)
        if g is not None:
            kw["strslet"] = np.ascontiguousarray(g.T)
            kw["strsvec"] = np.ascontiguousarray(-nw.T)     # fmm3dpy's stresslet = -D
        res = fmm3dpy.stfmm3d(eps=self.eps, sources=self._srcT, targets=self._trgT,
                              ifppregtarg=1, **kw)
        ier = getattr(res, "ier", 0)
        if ier not in (0, None):
            raise NumericalFailure(f"fmm3dpy.stfmm3d failed with ier = {ier} "
                                   f"({self.src.shape[0]} sources, {self.trg.shape[0]} targets); "
                                   "use the far-field backend 'direct'")
        out += np.asarray(res.pottarg).reshape(3, -1).T
        # subtract the self part (target against the sources of its own vesicle): O(N M Q)
        pairs = self._self_pairs
        if pairs.shape[0]:
            selfv = np.zeros((pairs.shape[0], 3))
            grp = self._groups
            if f_w is not None:
                _stokes.stokeslet_sum_pairs(grp.src, grp.sorted(f_w), self.src_off, self._trg_fmm, pairs, selfv)
            if g is not None:
                _stokes.stresslet_sum_pairs(grp.src, grp.sorted(nw), grp.sorted(g), self.src_off,
                                            self._trg_fmm, pairs, selfv)
            out[pairs[:, 0]] -= selfv
        return out

    def single_layer(self, f_w):
        """``sum over other vesicles of S[f w]`` at the targets, (T, 3)."""
        return self.evaluate(f_w=f_w)

    def double_layer(self, nw, g):
        """``sum over other vesicles of D[g]`` (lambda = 0 kernel) at the targets, (T, 3)."""
        return self.evaluate(nw=nw, g=g)


def far_single_layer(src, f_w, src_id, trg, trg_id, backend="auto", eps=DEFAULT_EPS):
    """Single layer of all OTHER vesicles at the targets (section 4 kernel, mu = 1), (T, 3).

    ``u_t = sum_{src_id[s] != trg_id[t]} (1/(8 pi)) (f_s/r + r (r.f_s)/r^3)``, r = x_t - y_s,
    ``f_w`` = traction times quadrature weight.  See :class:`FarField` for the backends.
    """
    return FarField(src, src_id, trg, trg_id, backend, eps, double_layer=False).evaluate(f_w=f_w)


def far_double_layer(src, nw, g, src_id, trg, trg_id, backend="auto", eps=DEFAULT_EPS):
    """Double layer (lambda = 0 stresslet) of all OTHER vesicles at the targets, (T, 3).

    ``u_t = sum_{src_id[s] != trg_id[t]} -(3/(4 pi)) (r.nw_s)(r.g_s) r / r^5``, r = x_t - y_s.
    """
    return FarField(src, src_id, trg, trg_id, backend, eps).evaluate(nw=nw, g=g)
