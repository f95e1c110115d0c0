"""Spectral Ewald sums of the Stokeslet and the stresslet (docs/explanation/method.md, section 5, regime 3).

For sources ``y_s`` (densities ``f_s`` = traction times weight; ``g_s`` with orientations
``nw_s`` = normal times weight) and targets ``x_t`` this evaluates, with the section 4
kernels (mu = 1, lambda = 0 stresslet; as :mod:`vesflow.layerpot.far`)::

    u_t = sum_{n, s; (s, n) != (own, 0)} S(x_t - y_s + n L) f_s + D(x_t - y_s + n L) g_s

over the lattice ``n`` of a periodic box (triply periodic; the k = 0 Fourier mode is left
out: zero mean velocity, i.e. the net force of the box is balanced by a mean pressure
gradient, the backflow of sedimentation theory), or ``n = 0`` only in free space; "own"
are the sources of the target's own vesicle (``src_id == trg_id``) at their given position.

Splitting (Hasimoto 1959; Lindbo and Tornberg 2010): ``G = (Lap I - grad grad) r`` with
``r = phi^R + phi^F``, ``phi^F`` having the Fourier transform::

    phi^F^(k) = -8 pi H(k) / k^4,    H(k) = (1 + k^2 / (4 xi^2)) exp(-k^2 / (4 xi^2))

so ``G^F^ = 8 pi H (k^2 I - k k^T) / k^4`` and, for the stresslet ``T_ijl = -6 r_i r_j r_l / r^5
= (delta_ij d_l + delta_jl d_i + delta_il d_j) Lap r - 2 d_i d_j d_l r``,
``T^F^_ijl = i [-k^2 (delta_ij k_l + delta_jl k_i + delta_il k_j) + 2 k_i k_j k_l] phi^F^``.
The real-space parts (exp(-xi^2 r^2) decay) are summed within a cutoff ``rc`` with cell lists
(:mod:`vesflow._kernels.ewald`, formulas there); the Fourier part is::

    u^F(x) = (1/V) sum_k [ (k^2 F - k (k.F)) + i (k^2 (2 S k + k tr S) - 2 k (k.S k)) ] Psi(k) e^{i k.x}

with ``Psi = -phi^F^ / (8 pi)``, ``F(k) = sum_s f_s e^{-i k.y_s}``, ``S(k) = sum_s sym(g_s nw_s^T)
e^{-i k.y_s}`` computed by a type-1 non-uniform FFT and the sum over k by a type-2 NUFFT
(finufft or ducc0.nufft: the NUFFT's own spreading plays the role of Lindbo and Tornberg's
Gaussian spreading; this Fourier part is vesflow.layerpot.ewald_fourier's).

Free space (af Klinteberg, Shamshirgar and Tornberg 2017 use a truncated Green's function on
a padded grid, after Vico, Greengard and Ferrando 2016; here the same idea with a smooth
window): the differences ``x - y`` of points in a box of sides ``B_a`` lie in ``(-B_a, B_a)``;
``phi^F`` times a window ``W`` (1 on that range to the tolerance, 0 beyond ``B_a + w``) is
periodized with period ``P_a = 2 B_a + w`` (the least for which the images ``d + n P_a``,
``n != 0``, of every difference ``d`` lie beyond ``B_a + w``) and ``Psi`` is its discrete Fourier
transform on the NUFFT grid, computed once per set-up (``-sum_n phi^F W (x + n P) / (8 pi)``
sampled on one octant, a type-1 DCT since the function is even, times the grid cell volume;
stored for k >= 0 only).  ``(Lap I - grad grad)(phi^F W) = G^F`` wherever ``W = 1``, and the
images vanish on ``(-B_a, B_a)``, so the periodic sum with this ``Psi`` is the free-space
``u^F`` on the box.

Parameters from the requested accuracy ``tol`` (relative to the largest velocity) by the
error estimates of Lindbo and Tornberg (2010): real space ``~ exp(-xi^2 rc^2)``, Fourier space
``~ exp(-k_max^2 / (4 xi^2))`` with ``k_max = pi K / P`` (K modes per period P), i.e.
``xi rc = sqrt(ln(1/tol) + C_REAL)`` and ``k_max = 2 xi sqrt(ln(1/tol) + C_FOURIER)``; the
cutoff ``rc`` is the one of least cost by the frozen weights :data:`COST`.  The window of the
free-space kernel: ``W = prod_a (erf((B_a + w/2 - x_a)/(sqrt 2 sigma)) + erf((B_a + w/2 +
x_a)/(sqrt 2 sigma)))/2`` with ``sigma k_max = sqrt(2 (ln(1/tol) + C_WINDOW))`` (its
spectrum has decayed at k_max) and ``w = 2 sqrt 2 sigma sqrt(ln(1/tol) + C_WINDOW)``
(``1 - W`` below tol on the box range).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vesflow._kernels import ewald as _kernels
from vesflow._kernels import stokes as _stokes
from vesflow.errors import SettingsError

from .ewald_fourier import NUFFT_LIBS, Nufft, kernel_psi, kvectors, sym6
from .ewald_grid import GRID_MODES, DistributedFourier
from .groups import group_by_vesicle

# margins added to ln(1/tol) in the error estimates (module docstring), measured so that the
# relative error stays below tol for 1e-4 .. 1e-10 (tests/layerpot/test_ewald.py)
C_REAL = 0.0
C_FOURIER = 0.0
C_WINDOW = 2.0
PREFACTOR_DOUBLE = 1.5
PREFACTOR_SINGLE = 0.5
# NUFFT accuracy requested, relative to tol: with tol itself the error stays below 0.25 tol at
# 1e-4 .. 1e-10, free and periodic, single and double layer (2 tol: 0.30, 5 tol: 1.02 tol;
# experiments/nufft_eps_margin.py, docs/explanation/far_field.md, "Accuracy of the Ewald sum"; 0.5 before)
NUFFT_EPS_FACTOR = 1.0
# weights of the cutoff rule (choose_params: the cutoff of least modelled cost), in the units of
# CPU seconds of one thread: real space per (target, source) pair inside the cutoff (the estimate
# of _pair_fraction; single layer), per target (the cell traversal) and per own-vesicle pair;
# NUFFT spreading and interpolation per point per transform per kernel width cubed; FFT per
# fine-grid point (3.4 per mode) per transform per log2(grid), times (grid / 1e7)^fft_growth;
# k-space multiplication per mode per transform.  Frozen: they are the development machine's
# figures (experiments/ewald_split.py) and part of the method, so that the cutoff, and with it
# the result, is the same on every machine; this machine's measured figures are
# vesflow.calibration's, which only `vesflow check`'s predictions read
# (docs/explanation/calibration.md)
COST = {"pair": 3.7e-9, "target": 2.3e-6, "own_pair": 1.5e-9, "nufft_point": 8.8e-10, "fft_point": 6.3e-10,
        "fft_growth": 0.3, "mode": 4.0e-9}
# memory of the Fourier grids of one pass (complex; one grid per pair of real source components
# plus two for the result, EwaldSum.fourier): a parameter choice keeps the double layer's pass
# (3 + 2 grids) within it; single and double layer share one pass (5 + 2 grids) when that fits too
MAX_GRID_BYTES = 4 * 2 ** 30
MAX_MODES = MAX_GRID_BYTES // (16 * 5)
PASS_GRIDS_BOTH = 7


def _have(lib):
    try:
        __import__(lib)
    except ImportError:
        return False
    return True


@dataclass(frozen=True)
class EwaldParams:
    """Parameters of one Ewald sum.

    ``xi`` splitting, ``rc`` real-space cutoff, ``modes`` NUFFT grid (even, per axis),
    ``period`` Fourier period per axis, ``lo`` lower corner and ``box`` side lengths of the
    point box (periodic: the period cell), ``periodic``, ``sigma`` and ``w`` the free-space
    window (0 when periodic), ``nufft_eps`` the NUFFT accuracy, ``tol`` the request.
    """
    xi: float
    rc: float
    modes: tuple
    period: tuple
    lo: tuple
    box: tuple
    periodic: bool
    sigma: float
    w: float
    nufft_eps: float
    tol: float

    def predicted_seconds(self, nsrc, ntrg, threads=1, ncomp=3, own_skip=None, cost=None):
        """Cost model of one evaluation with ``ncomp`` source components (``own_skip``: as
        :func:`choose_params`; ``cost``: the weights, default :data:`COST`)."""
        return _predicted(self, nsrc, ntrg, threads, ncomp, own_skip=own_skip, cost=cost)


def _kernel_width(eps):
    return min(16, max(2, math.ceil(-math.log10(eps)) + 1))


def own_pairs_inside(rc, per_vesicle, area):
    """Own-vesicle sources within ``rc`` of a target on a vesicle of ``per_vesicle`` sources and
    surface ``area``: the cap of a sphere cut by a ball of radius rc about a surface point has
    area pi rc^2 (any sphere radius, rc <= its diameter), i.e. ``per_vesicle min(1, pi rc^2 / area)``."""
    return per_vesicle * min(1.0, math.pi * rc * rc / area) if area > 0 else per_vesicle


_BALL_RULE = None


def _ball_rule():
    """Quadrature of the octant of the unit ball: points (n, 3), weights (n,); Gauss-Legendre
    16 in r, 12 x 12 in (cos theta, phi)."""
    global _BALL_RULE
    if _BALL_RULE is None:
        r, wr = np.polynomial.legendre.leggauss(16)
        r, wr = 0.5 * (r + 1), 0.5 * wr
        u, wu = np.polynomial.legendre.leggauss(12)
        u, wu = 0.5 * (u + 1), 0.5 * wu
        ph, wp = np.polynomial.legendre.leggauss(12)
        ph, wp = 0.25 * math.pi * (ph + 1), 0.25 * math.pi * wp
        s = np.sqrt(1 - u ** 2)
        d = np.stack([s[:, None] * np.cos(ph), s[:, None] * np.sin(ph), np.broadcast_to(u[:, None], (12, 12))], -1)
        pts = r[:, None, None, None] * d[None]
        w = (wr * r ** 2)[:, None, None] * (wu[:, None] * wp[None])[None]
        _BALL_RULE = (pts.reshape(-1, 3), w.reshape(-1))
    return _BALL_RULE


def _pair_fraction(p):
    """Expected fraction of (target, source) pairs closer than rc for points spread uniformly
    over the box: periodic ``4/3 pi rc^3 / V``; free space the box's autocorrelation
    ``prod_a (1 - |d_a| / B_a)`` integrated over the ball of radius rc, over V (the pairs near
    the faces have fewer neighbours: 0.7x the periodic estimate at N = 32 of the scene of
    benchmarks/far_field.py, within 5 % of the counted pairs at N = 32, 64)."""
    vol = float(np.prod(p.box))
    if vol <= 0:
        return 1.0
    if p.periodic:
        return min(1.0, 4.0 / 3.0 * math.pi * p.rc ** 3 / vol)
    pts, w = _ball_rule()
    g = np.prod(np.clip(1.0 - p.rc * pts / np.asarray(p.box), 0.0, None), axis=1)
    return min(1.0, 8.0 * p.rc ** 3 * float(g @ w) / vol)


def _predicted_parts(p, nsrc, ntrg, ncomp, own=0, own_skip=None, cost=None):
    """Cost model (weights ``cost``, default :data:`COST`; vesflow.costs passes the machine's,
    vesflow.calibration) of one evaluation by part, one thread: real space (with the own
    vesicle; ``own_skip`` = (sources per vesicle, mean area): without it, as
    EwaldSum(own="smooth"): no own pairs inside rc (:func:`own_pairs_inside`), no own
    subtraction), type-1 NUFFT, k-space multiplication, type-2 NUFFT (CPU seconds)."""
    c = COST if cost is None else cost
    pairs = ntrg * nsrc * _pair_fraction(p)
    if own_skip is not None:
        pairs = max(0.0, pairs - ntrg * own_pairs_inside(p.rc, *own_skip))
        own = 0
    m = float(np.prod(p.modes))
    fine = 3.4 * m
    fft = c["fft_point"] * fine * math.log2(max(fine, 2.0)) * (fine / 1e7) ** c["fft_growth"]
    wd = _kernel_width(p.nufft_eps) ** 3
    layers = 1 + (ncomp > 3)
    packed = (ncomp + 1) // 2                    # type-1 transforms; 2 type-2 (EwaldSum.fourier)
    return {"real": (pairs * c["pair"] + own * c["own_pair"]) * layers + ntrg * c["target"],
            "type1": packed * (c["nufft_point"] * wd * nsrc + fft),
            "kspace": c["mode"] * m * (packed + 2),
            "type2": 2 * (c["nufft_point"] * wd * ntrg + fft)}


def _predicted(p, nsrc, ntrg, threads, ncomp, own=0, own_skip=None, cost=None):
    """Cost model of one evaluation, seconds with ``threads`` threads (``cost``: as _predicted_parts)."""
    return sum(_predicted_parts(p, nsrc, ntrg, ncomp, own, own_skip, cost).values()) / max(1, threads)


def _exponents(lt, double_layer=True):
    """``(xi rc, k_max / (2 xi))`` for ln(1/tol) = lt: ``z^2 = lt + C + P ln(lt + C)``, the
    estimate ``exp(-z^2)`` times a prefactor ``~ z^(2P)``: the stresslet's ``P = 1.5`` (its
    real-space kernel at rc over T is ``~ (xi rc)^3 exp(-xi^2 rc^2)``; its Fourier sum carries one
    more power of k), the Stokeslet's ``P = 0.5`` when the double layer is absent (measured on
    the scene of benchmarks/far_field.py: error 0.1-0.3 tol with 0.5, 0.7-0.8 tol with 0,
    0.006-0.03 tol with 1.5; docs/explanation/far_field.md)."""
    pref = PREFACTOR_DOUBLE if double_layer else PREFACTOR_SINGLE
    zr = lt + C_REAL
    zf = lt + C_FOURIER
    return math.sqrt(zr + pref * math.log(zr)), math.sqrt(zf + pref * math.log(zf))


def _window(lt, xi, kmax, box):
    """``(sigma, w)`` of the free-space window for ln(1/tol) = lt (module docstring)."""
    aw = math.sqrt(lt + C_WINDOW + 3.0 * math.log1p(xi * float(np.max(box))))
    sigma = math.sqrt(2.0) * aw / kmax
    return sigma, 2.0 * math.sqrt(2.0) * sigma * aw


def _free_period(box, w):
    """Free-space period per axis, ``P_a = 2 B_a + w``: the differences of the points lie in
    ``(-B_a, B_a)`` and the windowed kernel vanishes (to tol) beyond ``B_a + w``, so the images
    ``d + n P_a`` (n != 0) of a difference lie beyond ``P_a - B_a = B_a + w``: outside the
    kernel's support.  (``2 (B_a + w)``, the kernel's support itself, would be w per axis longer.)"""
    return 2.0 * np.asarray(box, dtype=np.float64) + w


def _modes(period, kmax):
    # K even with pi K / P >= kmax
    return tuple(int(2 * math.ceil(P * kmax / (2 * math.pi))) for P in period)


def choose_params(tol, points, period=None, nsrc=None, ntrg=None, threads=1, ncomp=3, own_skip=None, cost=None):
    """Ewald parameters for accuracy ``tol`` (module docstring) over ``points`` (n, 3), the
    sources and targets together; ``period`` None (free space), a number (cube) or 3 numbers.
    ``nsrc``, ``ntrg``: counts for the cost model (default: half the points each);
    ``own_skip`` = (sources per vesicle, mean vesicle area): the real space leaves out every
    target's own vesicle (``EwaldSum(own="smooth")``), the model counts the other pairs only.
    ``cost``: weights other than :data:`COST` (vesflow.costs' comparison; a run takes COST's)."""
    if not (1e-15 < tol < 1.0):
        raise SettingsError(f"Ewald accuracy -ves_far_tol must lie in (1e-15, 1), got {tol}")
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = pts.shape[0]
    nsrc = n // 2 if nsrc is None else nsrc
    ntrg = n - n // 2 if ntrg is None else ntrg
    lt = math.log(1.0 / tol)
    a_real, a_four = _exponents(lt, ncomp > 3)
    nufft_eps = max(tol * NUFFT_EPS_FACTOR, 1e-14)
    if period is not None:
        L = np.broadcast_to(np.asarray(period, dtype=np.float64), (3,)).copy()
        if np.any(~np.isfinite(L)) or np.any(L <= 0):
            raise SettingsError(f"period must be positive, got {period}")
        lo, box = np.zeros(3), L
        rc_hi = 0.49 * float(L.min())
    else:
        lo = pts.min(axis=0) if n else np.zeros(3)
        box = (pts.max(axis=0) - lo) if n else np.zeros(3)
        box = np.maximum(box, 1e-3 * max(float(box.max()), 1e-300))
        rc_hi = max(float(np.linalg.norm(box)), 1e-300)
    scale = float(np.cbrt(np.prod(box) / max(nsrc + ntrg, 1)))     # mean point spacing
    rc_lo = min(rc_hi, max(0.5 * scale, 1e-3 * rc_hi))
    best = None
    for rc in np.geomspace(rc_lo, rc_hi, 48):
        xi = a_real / rc
        kmax = 2.0 * xi * a_four
        if period is not None:
            per, sigma, w = tuple(L), 0.0, 0.0
        else:
            sigma, w = _window(lt, xi, kmax, box)
            per = tuple(_free_period(box, w))
        modes = _modes(per, kmax)
        if float(np.prod(modes)) > MAX_MODES:
            continue
        p = EwaldParams(xi=float(xi), rc=float(rc), modes=modes, period=tuple(float(x) for x in per),
                        lo=tuple(float(x) for x in lo), box=tuple(float(x) for x in box),
                        periodic=period is not None, sigma=float(sigma), w=float(w),
                        nufft_eps=nufft_eps, tol=float(tol))
        t = p.predicted_seconds(nsrc, ntrg, threads, ncomp, own_skip, cost)
        if best is None or t < best[0]:
            best = (t, p)
    if best is None:
        raise SettingsError(f"Ewald sum at -ves_far_tol {tol:g}: every real-space cutoff needs a Fourier "
                            f"grid above {MAX_MODES} modes ({MAX_GRID_BYTES / 2 ** 30:g} GiB); raise -ves_far_tol "
                            "or use -ves_far direct")
    return best[1]


def make_params(tol, xi, rc, points, period=None, double_layer=True):
    """Parameters with a GIVEN splitting ``xi`` and cutoff ``rc`` (the grid from ``tol``; the
    stresslet's error prefactor unless ``double_layer`` is False): for tests of the
    independence of the result on xi and for experiments/ewald_split.py."""
    lt = math.log(1.0 / tol)
    kmax = 2.0 * xi * _exponents(lt, double_layer)[1]
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if period is not None:
        L = np.broadcast_to(np.asarray(period, dtype=np.float64), (3,)).copy()
        lo, box, per, sigma, w = np.zeros(3), L, L, 0.0, 0.0
    else:
        lo = pts.min(axis=0)
        box = np.maximum(pts.max(axis=0) - lo, 1e-12)
        sigma, w = _window(lt, xi, kmax, box)
        per = _free_period(box, w)
    return EwaldParams(xi=float(xi), rc=float(rc), modes=_modes(per, kmax), period=tuple(float(x) for x in per),
                       lo=tuple(float(x) for x in lo), box=tuple(float(x) for x in box),
                       periodic=period is not None, sigma=float(sigma), w=float(w),
                       nufft_eps=max(tol * NUFFT_EPS_FACTOR, 1e-14), tol=float(tol))


OWN_MODES = ("subtract", "smooth")


def own_extent_ok(extent, rc, period):
    """Whether own="smooth" is exact: every vesicle's extent per axis plus rc below the period
    (then no periodic image of a target's own vesicle lies within rc of it), or free space."""
    if period is None:
        return True
    L = np.broadcast_to(np.asarray(period, dtype=np.float64), (3,))
    return bool(np.all(np.asarray(extent, dtype=np.float64).reshape(-1, 3).max(axis=0, initial=0.0) + rc < L))


class EwaldSum:
    """Ewald sum over fixed sources ``src`` (S, 3) with ids ``src_id`` and targets ``trg`` (T, 3)
    with ids ``trg_id`` (module docstring); ``period`` None (free space), a number or 3 numbers;
    ``params`` an :class:`EwaldParams` (default: :func:`choose_params` for ``tol``);
    ``nufft`` "finufft" or "ducc0".  Densities per call (:meth:`evaluate`).

    ``own`` (docs/explanation/far_field.md, "Spectral Ewald" (the own vesicle)): "subtract" gives the sum of
    the module docstring (the own vesicle's pairs inside rc in the real-space sum, its full
    kernel subtracted); "smooth" leaves every target's own vesicle out of the real-space sum and
    subtracts nothing, so that the result ADDS ``sum_{s own} G^F(x_t - y_s) f_s`` (+ T^F) to the
    sum of the module docstring (the Fourier part's share of the own vesicle at its given
    position); the caller removes it (vesflow.layerpot.own_smooth).  "smooth" needs every
    vesicle's extent plus rc below the period (:func:`own_extent_ok`); ``own_skip`` = (sources
    per vesicle, mean area) for the cost model (:func:`choose_params`).

    ``grid`` (-ves_ewald_grid): "replicated", the Fourier part by the NUFFTs on the whole
    mode grid (with ``spread``: the grid summed over the ranks); "distributed", on a fine grid
    in z-slabs over the ranks of ``spread``'s partition (:mod:`vesflow.layerpot.ewald_grid`;
    the same sum to the tolerance)."""

    def __init__(self, src, src_id, trg, trg_id, tol=1e-8, period=None, params=None, nufft=None,
                 threads=None, double_layer=False, spread=None, own="subtract", own_skip=None, grid="replicated"):
        self.src = np.ascontiguousarray(src, dtype=np.float64).reshape(-1, 3)
        self.trg = np.ascontiguousarray(trg, dtype=np.float64).reshape(-1, 3)
        self.src_id = np.ascontiguousarray(src_id, dtype=np.int64).reshape(-1)
        self.trg_id = np.ascontiguousarray(trg_id, dtype=np.int64).reshape(-1)
        if self.src_id.shape[0] != self.src.shape[0] or self.trg_id.shape[0] != self.trg.shape[0]:
            raise ValueError("src_id / trg_id must have one id per point")
        self.threads = _stokes.max_threads() if threads is None else max(1, int(threads))
        self.period = period
        if own not in OWN_MODES:
            raise ValueError(f"EwaldSum own = {own!r}: must be one of {', '.join(OWN_MODES)}")
        self.own = own
        if params is None:
            params = choose_params(tol, np.concatenate([self.src, self.trg]), period, self.src.shape[0],
                                   self.trg.shape[0], self.threads, 9 if double_layer else 3,
                                   own_skip if own == "smooth" else None)
        self.params = p = params
        if nufft is None:
            nufft = DEFAULT_NUFFT if _have(DEFAULT_NUFFT) else next((n for n in NUFFT_LIBS if _have(n)), None)
            if nufft is None:
                raise SettingsError("the Ewald far field needs finufft or ducc0 (pip install finufft)")
        self.nufft_lib = nufft
        # sources sorted by vesicle id; index of each target's own vesicle (-1: none)
        self._groups = grp = group_by_vesicle(self.src, self.src_id, self.trg_id)
        ids, trg_vi = grp.ids, grp.trg_vi
        if own == "smooth" and p.periodic:
            ext = np.zeros((ids.size, 3))
            if ids.size:
                pts = np.concatenate([grp.src, self.trg[trg_vi >= 0]])
                vix = np.concatenate([np.repeat(np.arange(ids.size), np.diff(grp.off)), trg_vi[trg_vi >= 0]])
                hi = np.full((ids.size, 3), -np.inf)
                lo_ = np.full((ids.size, 3), np.inf)
                np.maximum.at(hi, vix, pts)
                np.minimum.at(lo_, vix, pts)
                ext = hi - lo_
            if not own_extent_ok(ext, p.rc, p.period):
                raise ValueError(f"EwaldSum own = 'smooth': a vesicle's extent {ext.max(axis=0)} plus rc = {p.rc:g} "
                                 f"reaches the period {p.period}, its own periodic images would be left out; "
                                 "use own = 'subtract'")
        # NUFFT points in [0, 2 pi)
        lo = np.asarray(p.lo)
        per = np.asarray(p.period)
        if p.periodic:
            s01 = 2 * math.pi * np.mod(self.src - lo, per) / per
            t01 = 2 * math.pi * np.mod(self.trg - lo, per) / per
        else:
            s01 = 2 * math.pi * (self.src - lo) / per
            t01 = 2 * math.pi * (self.trg - lo) / per
        # np.mod can return the period itself for tiny negative inputs
        s01[s01 >= 2 * math.pi] = 0.0
        t01[t01 >= 2 * math.pi] = 0.0
        self._nufft = Nufft(nufft, p.modes, s01, t01, p.nufft_eps, self.threads)
        self._psi = kernel_psi(p, self.threads)
        if grid not in GRID_MODES:
            raise SettingsError(f"-ves_ewald_grid = {grid!r}: must be one of {', '.join(GRID_MODES)}")
        self.grid = grid
        # grid = "distributed": the fine grid in z-slabs over the ranks of the partition, each
        # rank spreading its own sources and interpolating at its targets
        # (vesflow.layerpot.ewald_grid; docs/explanation/parallel.md, "Distributed Ewald grid")
        self._dist = None
        if grid == "distributed":
            part, mine = spread if spread is not None else (None, slice(None))
            self._dist_mine = np.arange(self.src.shape[0])[mine]
            self._dist = DistributedFourier(p, s01[self._dist_mine], t01, None if part is None else part.comm,
                                            self.threads, psi=self._psi)
        # spread = (partition, this rank's source indices or slice): the type-1 transform of
        # this rank's sources only, the mode grid summed over the ranks (Allreduce), the rest
        # replicated (docs/explanation/parallel.md: one node, the grid is small next to the far-field work);
        # a rank that holds no other rank's sources (one process) spreads with the plan above
        self._spread = None
        if spread is not None and grid == "replicated":
            part, mine = spread
            mine = np.arange(self.src.shape[0])[mine]
            if np.array_equal(mine, np.arange(self.src.shape[0])):
                self._spread = (part, None, self._nufft)
            else:
                self._spread = (part, mine, Nufft(nufft, p.modes, np.ascontiguousarray(s01[mine]), t01,
                                                  p.nufft_eps, self.threads))
        self._k = kvectors(p)
        self._real = None            # cell lists of the real-space part, built at the first evaluation
        self._buffers = {}

    def _buffer(self, name, shape):
        """A complex array kept between evaluations (the grids of a GMRES solve's every
        iteration: no new allocation and first-touch page faults per call), one per name."""
        b = self._buffers.get(name)
        if b is None or b.shape != tuple(shape):
            self._buffers[name] = b = np.empty(shape, dtype=np.complex128)
        return b

    def real_space(self, f_w=None, nw=None, g=None):
        """Real-space part (own="subtract": incl. the own-vesicle subtraction; "smooth": the
        own vesicle left out), (T, 3)."""
        p = self.params
        out = np.zeros((self.trg.shape[0], 3))
        empty = np.zeros((0, 3))
        f = empty if f_w is None else self._groups.sorted(np.ascontiguousarray(f_w, dtype=np.float64))
        n_ = empty if g is None else self._groups.sorted(np.ascontiguousarray(nw, dtype=np.float64))
        g_ = empty if g is None else self._groups.sorted(np.ascontiguousarray(g, dtype=np.float64))
        if self._real is None:
            box = p.period if p.periodic else tuple(np.asarray(p.box) * (1 + 1e-12) + 1e-300)
            grp = self._groups
            self._real = _kernels.RealSpace(grp.src, grp.sid, grp.off, self.trg, self.trg_id, grp.trg_vi, p.xi, p.rc,
                                            p.lo, box, bool(p.periodic), self.own == "smooth")
        self._real.apply(f, n_, g_, out)
        return out

    def fourier(self, f_w=None, nw=None, g=None):
        """Fourier-space part over all sources, (T, 3).  The real source components go two to
        a complex type-1 transform and the three real velocity components in two type-2
        transforms (:func:`vesflow._kernels.ewald.kspace_apply`): 2 + 2 transforms instead of
        3 + 3 for the single layer, 5 + 2 instead of 9 + 3 for both layers."""
        comps = []
        if f_w is not None:
            comps.append(np.asarray(f_w, dtype=np.float64).T)
        if g is not None:
            comps.append(sym6(np.asarray(nw, dtype=np.float64), np.asarray(g, dtype=np.float64)))
        real = np.concatenate(comps, axis=0)
        if self._dist is not None:
            return self._dist.apply(real[:, self._dist_mine], f_w is not None, g is not None)
        m = real.shape[0]
        c = np.zeros(((m + 1) // 2, real.shape[1]), dtype=np.complex128)
        c.real = real[0::2]
        c.imag[:m // 2] = real[1::2]
        del real
        P = self._buffer("P", (c.shape[0],) + tuple(self.params.modes))
        if self._spread is None:
            P = self._nufft.type1(c, out=P)
        else:
            part, mine, nufft = self._spread
            P = part.allreduce_inplace(nufft.type1(c if mine is None else np.ascontiguousarray(c[:, mine]), out=P))
        del c
        P = P.reshape((-1,) + tuple(self.params.modes))
        W = self._buffer("W", (2,) + P.shape[1:])
        _kernels.kspace_apply(P, self._psi, self._k[0], self._k[1], self._k[2], f_w is not None, g is not None,
                              1.0 / float(np.prod(self.params.period)), W)
        del P
        w = self._nufft.type2(W, out=self._buffer("w", (2, self.trg.shape[0])))
        out = np.empty((self.trg.shape[0], 3))
        out[:, 0] = w[0].real
        out[:, 1] = w[0].imag
        out[:, 2] = w[1].real
        return out

    def evaluate(self, f_w=None, nw=None, g=None):
        """Single layer of ``f_w`` plus double layer of ``g`` (orientations ``nw``), (T, 3)."""
        if (nw is None) != (g is None):
            raise ValueError("double layer: give both nw and g, or neither")
        out = np.zeros((self.trg.shape[0], 3))
        if self.trg.shape[0] == 0 or self.src.shape[0] == 0 or (f_w is None and g is None):
            return out
        out = self.real_space(f_w, nw, g)
        if f_w is not None and g is not None and PASS_GRIDS_BOTH * 16 * float(np.prod(self.params.modes)) > MAX_GRID_BYTES:
            out += self.fourier(f_w=f_w)                 # two passes: the grids of one fit the memory
            out += self.fourier(nw=nw, g=g)
        else:
            out += self.fourier(f_w, nw, g)
        return out


DEFAULT_NUFFT = "ducc0"
