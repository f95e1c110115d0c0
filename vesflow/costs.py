"""Cost model of a scene for `vesflow check` (paper Table 2): memory, and time per GMRES
iteration and per solve set-up; and the fixed rules of the numerical choices that depend on the
problem's size (`decision_rules`, `decisions`).

What is stored (float64, 8 bytes, unless a memory option says float32, 4 bytes), per vesicle
(`memory_per_vesicle`; a step's peak is that times N plus BASE_BYTES, `Estimate.memory_peak`):
    self operators        (3C)^2 per held set of layer potentials (2 with sdc: the step's start
                          and the current one; 1 with euler), x 2 with the double layer (S, D);
                          float32 with -ves_self_precision single
    Ewald own operators   as many as the self operators (-ves_ewald_own smooth)
    block preconditioner  parts 15 C^2 (24 C^2 with a contrast; none with -ves_pc_parts drop) and
                          (4C)^2 per LU set (`factor_sets`: sdc 3, euler with doubling 2; at most
                          -ves_pc_factors); float32 with -ves_pc_precision single
    near pairs            (C x 8 + NEAR_PAIR_EXTRA_BYTES) per pair and held set, and the maps
                          of the pairs within -ves_near_map_mb: 6 C per pair and layer
    sources, geometry     SOURCE_POINT_BYTES per q-grid point and held set, GEOMETRY_POINT_BYTES
                          per point of the cached surface grids
with C = (p+1)^2 - 1 coefficients per scalar, M = 2p(p+1) grid points, Mq = 2q(q+1) on the
upsampled grid (q = -ves_q_near, 2p by default) and P the near (point, vesicle) pairs.  The
constants (vesflow.memory_model) are measured by benchmarks/memory_per_vesicle.py.  `fit_memory` picks the memory
options a run takes when the defaults would not fit (-ves_memory_limit, or MemAvailable).

Time per GMRES iteration: the membrane forces and transforms (per vesicle), the self
operators (one GEMV each: they are streamed from memory), the far field (direct sum over the
(N M) x ((N-1) Mq) pairs, the FMM or the Ewald sum, the backend and Ewald parameters the run
takes: the rules below), and the near correction (per near pair with a map: its 6 C entries
streamed, vesflow.layerpot.nearmap; without: 9 Mq kernel evaluations); the set-up of a solve:
the self operators and the near pairs (search, projection, basis, maps).
Time per step: the solves of one step (3 with -ves_adapt doubling), each its set-up and
ITERATIONS_PER_SOLVE GMRES iterations.  The seconds per unit of work are this machine's
calibration (vesflow.calibration: a file written by benchmarks/calibrate.py, else the
development machine's figures): expect the right order of magnitude, not the digits.

The choices that change results (far-field backend, Ewald cutoff, own-vesicle mode,
preconditioner rebuild) are fixed rules of the options and the problem with frozen weights
(`decision_rules`): they never read the calibration (docs/explanation/calibration.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import calibration as calmod, sph
from ._kernels import stokes
from .layerpot import ewald as ewaldmod, far as farmod
from .layerpot.evaluator import (APPLIES_PER_SETUP, NEAR_MAP_MB, OWN_GEMV_BYTE, OWN_SETUP_PAIR, OWN_SINGLE_TOL,
                                 LayerPotentials, Settings)
from .layerpot.nearmap import map_bytes_per_pair
from .layerpot.near import near_distance, near_pairs_images
from .layerpot.wall import Q_FACTOR as WALL_Q_FACTOR
from .memory_model import (EWALD_GRIDS, EWALD_GRIDS_APPLY, MEMORY_OPTIONS, NEAR_PAIRS_ASSUMED, SETUP_THREAD_BYTES,
                           available_memory, factor_sets, layer_potentials_held, memory_choices, memory_per_vesicle)
from .parallel import Partition
from .scene.geometry import _ellipsoid_area
from .scene.packing import wall_distance
from .setup_state import initial_coefficients
from .surface import Surface

NEAR_EVALS = 9                   # kernel evaluations per near pair and source point (1 + 8 line points)
# The near pairs, seconds of one thread per pair (benchmarks/near_field.py, 32 biconcave cells at
# 35 %, p = 16, q = 32, 540 pairs per cell; docs/explanation/performance.md "Near field"):
# set-up (search, nearest source, projection, weights, basis) at p = 16, ~p^2; the maps' set-up
# per pair, layer and q-grid source (the combined kernel and the transposed synthesis); per
# iteration, every pair (on-surface value, interpolation, scatter) at p = 16, ~p^2, plus the
# maps' entries streamed at the self operators' GEMV bandwidth or 9 Mq kernel evaluations
NEAR_SETUP_S_PER_PAIR = 5.0e-5
NEAR_MAP_SETUP_S_PER_SOURCE = 3.5e-8
NEAR_ITERATION_S_PER_PAIR = 4.2e-7
# GMRES iterations per solve (block preconditioner): 5.2 in runs/taylor_green.toml (575 in 37
# doubling steps of 3 solves), 6-10 in docs/explanation/accuracy_cost.md; the paper's 1408-cell case needed
# 139 per solve with its own preconditioner (section 4.4)
ITERATIONS_PER_SOLVE = 8
SOLVES_PER_STEP = {"doubling": 3}                 # step attempts per step: one, or one and two halves
BASE_BYTES = 150 * 2 ** 20       # a process's peak RSS besides its vesicles (memory_per_vesicle)
NEAR_COUNT_MAX_POINTS = 1_200_000                 # count the near pairs when N M is below (~8 s CPU at the limit)
# Weights of the preconditioner's rebuild rule (pc_rebuild_iterations), in seconds of one thread:
# forces a + b p^3 per vesicle and iteration, bytes per second of the GEMVs, block and LU per
# vesicle t16 (p / 16)^e, near kernel evaluation; the far field by the backend rule's weights
# (vesflow.layerpot.far).  Frozen: the development machine's figures (benchmarks/cost_model.py),
# part of the method, so that the rebuilds, and with them the iterates, are the same on every machine.
REBUILD_WEIGHTS = {"forces_s": (8.0e-5, 1.0e-7), "bytes_per_s": 2e10, "pc_setup_s": (0.26, 4.0),
                   "near_s_per_eval": 1.4e-9}


@dataclass(frozen=True)
class Estimate:
    """Bytes and seconds of one scene (see the module docstring)."""

    n_vesicles: int
    p: int
    q: int
    unknowns: int
    double_layer: bool
    mem_self: int
    mem_pc: int                  # one cached set of LU factors
    mem_pc_max: int              # up to 3 cached sets
    mem_pc_parts: int            # the blocks' dt-independent parts A0 and S Mb
    self_bytes: int              # bytes per entry of the self operators (8, or 4: -ves_self_precision single)
    pc_bytes: int                # of the preconditioner's parts and LU factors
    mem_sources: int
    mem_near: int
    near_pairs: int              # at t = 0 (-1: not computed)
    far_backend: str
    t_forces: float
    t_self: float
    t_far: float
    t_near: float
    t_setup: float               # per solve (every step: three with -ves_adapt doubling): self operators, near pairs
    t_pc: float                  # per preconditioner factorization (every -ves_pc_lag solves)
    solves_per_step: int = 3
    iterations_per_solve: int = ITERATIONS_PER_SOLVE
    threads: int = 1
    mem_own: int = 0             # the Ewald far field's own smooth operators E_v (as many as the self operators)
    t_own: float = 0.0           # their GEMV per iteration
    calibration: str = "defaults"  # where the seconds per unit of work came from (vesflow.calibration)
    options: dict = None         # the memory options of the estimate (memory_per_vesicle)
    near_per_vesicle: float = 0.0  # near pairs per vesicle (counted at t = 0, or NEAR_PAIRS_ASSUMED)
    base_bytes: int = BASE_BYTES
    ewald_modes: float = 0.0     # modes of the Ewald grid (0: not ewald)
    decisions: dict = None       # the rules' choices at t = 0 (`decisions`)
    ewald_best: tuple = None     # (rc, seconds) of the cutoff this calibration would find fastest (ewald)
    wall_p: int = 0              # a container's wall ([wall]): its degree (0: no wall)
    t_wall: float = 0.0          # its share of a GMRES iteration (`_wall_cost`)
    t_wall_once: float = 0.0     # its operators, built once per run
    mem_wall: int = 0            # their bytes
    wall_near_points: int = 0    # vesicle grid points within its near zone at t = 0
    t_near_setup: float = 0.0    # the near pairs' part of t_setup
    near_mapped: int = 0         # near pairs with a map (-ves_near_map_mb)

    @property
    def t_step(self):
        """Seconds per time step: each solve's set-up and GMRES iterations (no preconditioner
        factorization: it is reused over -ves_pc_lag solves)."""
        return self.solves_per_step * (self.t_setup + self.iterations_per_solve * self.t_iteration)

    @property
    def t_iteration(self):
        return self.t_forces + self.t_self + self.t_own + self.t_far + self.t_near + self.t_wall

    @property
    def memory(self):
        return (self.mem_self + self.mem_own + self.mem_pc_parts + self.mem_pc_max + self.mem_sources + self.mem_near
                + self.mem_wall)

    def memory_per_vesicle(self, o=None):
        """Bytes per vesicle at a step's peak by category (memory_model.memory_per_vesicle) with the
        options o (default: the estimate's own)."""
        o = dict(self.options or {}) if o is None else o
        smooth = bool(self.mem_own) and o.get("ewald_own") != "subtract"
        own_bytes = 4 if o.get("self_precision") == "single" or self.own_bytes == 4 else 8
        return memory_per_vesicle(self.p, self.q, o, self.double_layer, self.near_per_vesicle, smooth, own_bytes,
                                  self.n_vesicles)

    @property
    def own_bytes(self):
        return 0 if not self.mem_own else int(round(self.mem_own / max(self.mem_self // self.self_bytes, 1)))

    @property
    def per_vesicle_bytes(self):
        return sum(self.memory_per_vesicle().values())

    def far_bytes(self, o=None):
        """The Ewald far field's grids (per rank, replicated): EWALD_GRIDS per held set of layer
        potentials and EWALD_GRIDS_APPLY more while one is applied, complex (16 B per mode)."""
        o = dict(self.options or {}) if o is None else o
        return int(16 * self.ewald_modes * (EWALD_GRIDS * layer_potentials_held(o) + EWALD_GRIDS_APPLY))

    def memory_peak_with(self, o, ranks=1):
        """Modelled peak of the whole run (every rank on this machine) with the options o."""
        setup = self.threads * SETUP_THREAD_BYTES * (self.p / 16) ** 4
        return int(ranks * (self.base_bytes + self.far_bytes(o) + setup)
                   + self.n_vesicles * sum(self.memory_per_vesicle(o).values()))

    @property
    def memory_peak(self):
        """Modelled peak resident memory of one process holding every vesicle."""
        return self.memory_peak_with(self.options or {})

    def __str__(self):
        mib = lambda b: f"{b / 2**20:.1f} MiB"
        ms = lambda s: f"{s * 1e3:.2f} ms"
        near = "not computed" if self.near_pairs < 0 else f"{self.near_pairs} near pairs at t = 0"
        return "\n".join([
            f"cost     per GMRES iteration ~ {ms(self.t_iteration)}: forces {ms(self.t_forces)}, "
            f"self {ms(self.t_self)}, far ({self.far_backend}) {ms(self.t_far + self.t_own)}, near {ms(self.t_near)} ({near})",
            f"         per solve set-up ~ {self.t_setup:.2f} s (self operators {self.t_setup - self.t_near_setup:.2f}, "
            f"near pairs {self.t_near_setup:.2f}, {self.near_mapped} of them with a map); preconditioner "
            f"factorization ~ {self.t_pc:.2f} s (every -ves_pc_lag solves)",
            f"         per time step ~ {self.t_step:.4g} s: {self.solves_per_step} solve(s) x (set-up + "
            f"{self.iterations_per_solve} GMRES iterations, an assumed typical count); {self.threads} thread(s), "
            f"calibration: {self.calibration}",
            self._memory_line(),
            self._fits(),
        ] + ([f"wall     p_w = {self.wall_p}: {ms(self.t_wall)} of each GMRES iteration (in the figure above; "
              f"{self.wall_near_points} vesicle points within its near zone at t = 0), its operators "
              f"~ {self.t_wall_once:.2f} s once and {mib(self.mem_wall)} (3 (3 C_w)^2 x 8 B: D_w, the wall block, "
              f"its LU)"] if self.wall_p else [])
          + ([f"choices  {describe_decisions(self.decisions)} (fixed rules, the same on every machine)"]
             if self.decisions else [])
          + ([self._ewald_line()] if self.ewald_best and self.t_far > 0 else []))

    def _ewald_line(self):
        rc, t = self.ewald_best
        if rc == self.decisions["ewald"]["rc"]:
            return "         the rule's Ewald cutoff is also the fastest by this calibration"
        return (f"         by this calibration the fastest Ewald cutoff would be rc = {rc:.4g}, "
                f"{100 * (1 - t / self.t_far):.1f} % less far-field time than the rule's")

    def _memory_line(self):
        mb = lambda b: f"{b / 2**20:.1f}"
        m = self.memory_per_vesicle()
        o = self.options or {}
        return (f"memory   ~ {self.memory_peak / 2**30:.2f} GiB at a step's peak: {mb(sum(m.values()))} MB per vesicle "
                f"(self operators {mb(m['self'])}, Ewald own smooth operators {mb(m['own'])}, preconditioner parts "
                f"{mb(m['pc_parts'])} and LU {mb(m['pc_factors'])} ({factor_sets(o)} set(s), {_entry(self.pc_bytes)}), "
                f"near {mb(m['near'])} and its maps {mb(m['near_maps'])}, sources and geometry {mb(m['sources'])}; {layer_potentials_held(o)} set(s) of "
                f"layer potentials) + {mb(self.base_bytes)} MB + Ewald grids {mb(self.far_bytes())} MB; arrays: self operators {mb(self.mem_self)} MiB "
                f"(N (3C)^2 x {_entry(self.self_bytes)}{' x 2, S and D' if self.double_layer else ''})")

    def _fits(self):
        """Whether the modelled peak fits the memory available (-ves_memory_limit or MemAvailable)."""
        avail, source = available_memory((self.options or {}).get("memory_limit"))
        if avail is None:
            return "machine  memory unknown"
        peak = self.memory_peak
        return (f"machine  {avail / 2**30:.1f} GiB RAM: {'fits' if peak <= avail else 'does NOT fit'} (needs "
                f"~{peak / 2**30:.2f} GiB; {source})")


def _entry(nbytes):
    return "8 B" if nbytes == 8 else f"{nbytes} B (float32)"


def _state(scene, p, q):
    """The initial surface, its q-grid geometry and its p-grid points (N, M, 3)."""
    S = Surface(initial_coefficients(scene), p)
    return S, S.geometry(q), S.points()


def _near_pairs(S, p, q, near_factor, period=None):
    """Near (p-grid point, vesicle) pairs of the initial configuration (periodic: with the images;
    the candidates of LayerPotentials' near set-up)."""
    N = S.n_vesicles
    trg = np.ascontiguousarray(S.points().reshape(-1, 3))
    src = np.ascontiguousarray(S.points(q).reshape(-1, 3))
    trg_id = np.repeat(np.arange(N, dtype=np.int64), sph.transform(p).npts)
    src_id = np.repeat(np.arange(N, dtype=np.int64), sph.transform(p, q).npts)
    src_off = np.arange(N + 1, dtype=np.int64) * sph.transform(p, q).npts
    h = float(near_distance(S.area(), q, near_factor).max())
    pairs, _ = near_pairs_images(trg, trg_id, src, src_id, src_off, h, period)
    return int(np.asarray(pairs).reshape(-1, 2).shape[0])


def _settings(scene, o):
    """The layer potentials' Settings a run of these options takes (vesflow.simulation.Run)."""
    return Settings(q_self=o.get("q_self"), q_far=o.get("q_near"), near_factor=float(o.get("near_factor") or 1.0),
                    backend=o.get("far") or "auto", fmm_eps=float(o.get("far_tol") or farmod.DEFAULT_EPS),
                    period=scene.periodic_length or None, self_precision=o.get("self_precision") or "double",
                    ewald_own=o.get("ewald_own") or "auto")


class _OwnModeInputs:
    """What the layer potentials' own-vesicle rule reads (LayerPotentials._far_own_mode, the one
    implementation of the rule), for a surface at t = 0 without the set-up of its operators."""

    _far_own_mode = LayerPotentials._far_own_mode
    _own_auto = LayerPotentials._own_auto
    _own_dtype = LayerPotentials._own_dtype

    def __init__(self, surface, settings, q, want_double):
        self.settings, self.local, self.p = settings, surface, surface.p
        self.part = Partition.single(surface.n_vesicles)
        self.N = self.N_total = surface.n_vesicles
        self.Tq, self.Tp = sph.transform(surface.p, q), sph.transform(surface.p)
        self.want_double = bool(want_double)
        self.own_auto = None


def decisions(scene, opts=None, state=None, near_pairs=None):
    """The numerical choices a run of this scene and these options makes at its first set-up, by
    the fixed rules (`decision_rules`; no calibration is read): far-field backend, Ewald
    parameters (xi, rc, modes), own-vesicle mode, and the preconditioner rebuild's price in GMRES
    iterations (None when the near pairs are not counted: N M above NEAR_COUNT_MAX_POINTS).  A
    JSON-ready dict.  state: (surface, q-grid geometry, p-grid points) of t = 0; near_pairs:
    their count (default: counted; negative: not counted)."""
    o = dict(opts) if opts is not None else {}
    p, N = scene.p, scene.n_vesicles
    st = _settings(scene, o)
    q = int(st.q_far or 2 * p)
    S, gq, pts = state if state is not None else _state(scene, p, q)
    dl = bool(scene.effects().double_layer)
    out = {"far_backend": "none", "ewald_own": None, "ewald": None}
    backend = "direct"
    if N > 1 or st.period:
        own = _OwnModeInputs(S, st, q, dl)
        mode = own._far_own_mode(gq)
        nsrc, ntrg = N * own.Tq.npts, N * own.Tp.npts
        points = np.concatenate([gq.X.reshape(-1, 3), pts.reshape(-1, 3)])
        backend, params = farmod.resolve_backend(st.backend, st.fmm_eps, st.period, nsrc, ntrg, points,
                                                 N * own.Tq.npts * own.Tp.npts, dl,
                                                 own._own_skip if mode == "smooth" else None)
        out["far_backend"] = backend
        if backend == "ewald":
            out["ewald_own"] = mode
            out["ewald"] = {"xi": params.xi, "rc": params.rc, "modes": list(params.modes)}
    if near_pairs is None:
        near_pairs = (0 if N == 1 else _near_pairs(S, p, q, st.near_factor, st.period) if N * 2 * p * (p + 1) <= NEAR_COUNT_MAX_POINTS
                      else -1)
    out["pc_rebuild_iterations"] = (None if near_pairs < 0 else
                                    float(pc_rebuild_iterations(N, p, q, dl, near_pairs, backend, st.fmm_eps)))
    return out


def describe_decisions(d):
    """One line of `decisions`."""
    far = d["far_backend"]
    if d.get("ewald"):
        e = d["ewald"]
        far += f" (rc = {e['rc']:.4g}, xi = {e['xi']:.4g}, modes {'x'.join(map(str, e['modes']))}, own vesicle {d['ewald_own']})"
    its = d["pc_rebuild_iterations"]
    return (f"far field {far}; preconditioner rebuilt after "
            + (f"{its:.3g} excess GMRES iterations" if its is not None else "its price in iterations (near pairs not counted)"))


def decision_rules():
    """The fixed rules of the choices that change results, with their frozen weights (JSON-ready;
    recorded in a run file's attributes as `decision_rules`)."""
    return {
        "far_backend": {"rule": "-ves_far auto: the least cost, one thread, of direct (per pair), fmm (per point, "
                                "interpolated in log eps) and ewald (ewald_cutoff's weights, at its cutoff); "
                                "periodic: ewald",
                        "direct_s_per_pair": farmod.DIRECT_SECONDS_PER_PAIR,
                        "fmm_s_per_point": [[e, t] for e, t in sorted(farmod.FMM_SECONDS_PER_POINT.items())]},
        "ewald_cutoff": {"rule": "the real-space cutoff rc of 48 log-spaced in [max(0.5 spacing, 1e-3 rc_max), rc_max] "
                                 "of least cost by these weights (vesflow.layerpot.ewald.choose_params); xi and the grid "
                                 "follow from rc and -ves_far_tol",
                         "weights": dict(ewaldmod.COST)},
        "ewald_own": {"rule": "-ves_ewald_own auto: smooth when (Ewald cost without the own pairs less the E_v GEMV) "
                              "x applies_per_setup exceeds the E_v set-up, else subtract; subtract when a vesicle's "
                              "extent plus 0.49 L reaches the period L",
                      "applies_per_setup": APPLIES_PER_SETUP, "own_setup_s_per_pair": OWN_SETUP_PAIR,
                      "own_gemv_s_per_byte": OWN_GEMV_BYTE},
        "pc_rebuild": {"rule": "rebuild the block preconditioner once the iterations beyond the first solve's, summed "
                               "since the last rebuild, reach its price in iterations: block and LU time over one "
                               "GMRES iteration's time, both by these weights (one thread)",
                       **{k: list(v) if isinstance(v, tuple) else v for k, v in REBUILD_WEIGHTS.items()}},
    }


def estimate(scene, opts=None, near=True, calibration=None):
    """Estimate of a scene's costs (an Estimate; str() gives the lines `vesflow check` prints).
    opts: resolved options (vesflow.options.read_options) for q, the far-field backend and its
    accuracy; near: count the near pairs of the initial configuration (N > 1, N M <= 1.2e6);
    calibration: the seconds per unit of work (default: vesflow.calibration.load(), this machine's)."""
    cal = calibration if calibration is not None else calmod.load()
    p, N = scene.p, scene.n_vesicles
    o = dict(opts) if opts is not None else {}
    q = int(o.get("q_near") or 2 * p)
    C, M, Mq = (p + 1) ** 2 - 1, 2 * p * (p + 1), 2 * q * (q + 1)
    eff = scene.effects()
    dl = bool(eff.double_layer)
    n_ops = 2 if dl else 1
    self_bytes = 4 if o.get("self_precision") == "single" else 8
    pc_bytes = 4 if o.get("pc_precision") == "single" else 8
    mem_self = N * n_ops * (3 * C) ** 2 * self_bytes
    mem_pc = N * (4 * C) ** 2 * pc_bytes
    mem_pc_parts = N * ((4 * C) ** 2 + (3 * C) ** 2) * pc_bytes
    mem_sources = N * Mq * 7 * 8 if N > 1 else 0
    state = _state(scene, p, q) if N > 1 or eff.periodic else None
    pairs = 0
    if N > 1 and near:
        pairs = (_near_pairs(state[0], p, q, float(o.get("near_factor") or 1.0), scene.periodic_length or None)
                 if N * M <= NEAR_COUNT_MAX_POINTS else -1)
    layers = 2 if dl else 1
    budget = float(o.get("near_map_mb") if o.get("near_map_mb") is not None else NEAR_MAP_MB)
    mapped = min(max(pairs, 0), int(budget * 1e6 // map_bytes_per_pair(C, layers)))
    mem_near = max(pairs, 0) * (C + 3 * 8 + 9) * 8 + mapped * map_bytes_per_pair(C, layers)
    threads = _threads()
    t_forces = N * (cal.forces_s[0] + cal.forces_s[1] * p ** 3)
    t_self = mem_self / cal.self_gemv_bytes_per_s
    chosen, ewald_best = None, None
    backend, t_far, eps = "none", 0.0, float(o.get("far_tol") or farmod.DEFAULT_EPS)
    if N > 1 or eff.periodic:          # periodic: a single vesicle sees its images
        chosen = decisions(scene, o, state=state, near_pairs=pairs if near else -1)
        backend = chosen["far_backend"]
        nsrc, ntrg = N * Mq, N * M
        t_direct, t_fmm = farmod.predicted_seconds(nsrc, ntrg, eps, threads, cal.direct_s_per_pair,
                                                   dict(cal.fmm_s_per_point))
        t_direct *= (N - 1) / N                      # a vesicle's own sources are left out
        t_far = {"fmm": t_fmm, "direct": t_direct}.get(backend, 0.0)
        if backend == "ewald":
            S, gq, pts = state
            points = np.concatenate([gq.X.reshape(-1, 3), pts.reshape(-1, 3)])
            smooth = chosen["ewald_own"] == "smooth"
            own_skip = (Mq, float(gq.dA.sum()) / N) if smooth else None
            period = scene.periodic_length or None
            t_far = farmod.predicted_ewald(points, nsrc, ntrg, 0 if smooth else N * M * Mq, eps, threads,
                                           period, dl, own_skip, cost=cal.ewald)[0]
            best = ewaldmod.choose_params(eps, points, period, nsrc, ntrg, threads, 9 if dl else 3, own_skip, cal.ewald)
            ewald_best = (best.rc, ewaldmod._predicted(best, nsrc, ntrg, threads, 3, 0 if smooth else N * M * Mq,
                                                       own_skip, cal.ewald))
    # ewald, own vesicle "smooth": its smooth share removed by per-vesicle operators E_v
    # (vesflow.layerpot.own_smooth): as many entries as the self operators, one more GEMV
    smooth_own = backend == "ewald" and chosen["ewald_own"] == "smooth"
    own_bytes = 4 if (self_bytes == 4 or eps >= OWN_SINGLE_TOL) else 8   # LayerPotentials._own_dtype
    mem_own = mem_self * own_bytes // self_bytes if smooth_own else 0
    t_own = mem_own / cal.self_gemv_bytes_per_s
    n_near = max(pairs, 0)
    t_near = (n_near * NEAR_ITERATION_S_PER_PAIR * (p / 16) ** 2 + mapped * map_bytes_per_pair(C, layers)
              / cal.self_gemv_bytes_per_s + (n_near - mapped) * NEAR_EVALS * Mq * cal.near_s_per_eval * layers) / max(1, threads)
    t_near_setup = (n_near * NEAR_SETUP_S_PER_PAIR * (p / 16) ** 2
                    + mapped * layers * Mq * NEAR_MAP_SETUP_S_PER_SOURCE) / max(1, threads)
    t_setup = (N * cal.self_setup_s[0] * (p / 16) ** cal.self_setup_s[1] * (q / (2 * p)) ** 2 * (1.5 if dl else 1)
               + t_near_setup)
    t_pc = N * cal.pc_setup_s[0] * (p / 16) ** cal.pc_setup_s[1]
    wall = (_wall_cost(scene, p, q, cal, threads, float(o.get("near_factor") or 1.0), dl, o.get("wall_q"))
            if scene.wall else {})
    near_per = (pairs / N if near and pairs >= 0 else NEAR_PAIRS_ASSUMED) if N > 1 else 0.0
    modes = float(np.prod(chosen["ewald"]["modes"])) if chosen is not None and chosen.get("ewald") else 0.0
    memo = {k: o.get(k) for k in MEMORY_OPTIONS + ("memory_limit", "ts_type", "coupling", "adapt", "ts_sdc_nodes", "ts_sdc_quadrature")}
    return Estimate(options=memo, near_per_vesicle=near_per, ewald_modes=modes, n_vesicles=N, p=p, q=q, unknowns=N * 4 * C, double_layer=dl, mem_self=mem_self,
                    mem_pc=mem_pc, mem_pc_max=3 * mem_pc, mem_pc_parts=mem_pc_parts, self_bytes=self_bytes,
                    pc_bytes=pc_bytes, mem_sources=mem_sources, mem_near=mem_near,
                    near_pairs=pairs if N > 1 and near else (0 if N == 1 else -1), far_backend=backend,
                    t_forces=t_forces, t_self=t_self, t_far=t_far, t_near=t_near, t_setup=t_setup, t_pc=t_pc,
                    solves_per_step=solves_per_step(o), threads=threads,
                    mem_own=mem_own, t_own=t_own, calibration=cal.source, decisions=chosen, ewald_best=ewald_best,
                    t_near_setup=t_near_setup, near_mapped=mapped, **wall)


def _wall_cost(scene, p, q, cal, threads, near_factor, double_layer, wall_q=None):
    """A container's share (docs/explanation/walls.md): per GMRES iteration the vesicles' layers
    at the wall's M_w points (direct, N Mq M_w pairs, x 2 with the double layer), the wall's
    smooth rule at the vesicles' points (Q_w N M pairs), the near blocks of the vesicle points
    within h_w (9 Q_w evaluations each) and the wall block's GEMV; once: its self operator
    (one vesicle's set-up at degree p_w) and LU; memory: D_w, the block and its LU."""
    w, N = scene.wall, scene.n_vesicles
    pw = w.p
    Cw, Mw, qw = (pw + 1) ** 2 - 1, 2 * pw * (pw + 1), int(wall_q or WALL_Q_FACTOR * pw)
    Qw, M, Mq = 2 * qw * (qw + 1), 2 * p * (p + 1), 2 * q * (q + 1)
    h_w = float(near_distance([_ellipsoid_area(w.axes)], qw, near_factor)[0])
    pts = Surface(initial_coefficients(scene), p).points().reshape(-1, 3)
    n_near = int(np.count_nonzero(-wall_distance(w, pts) < h_w))
    pairs = N * Mq * Mw * (2 if double_layer else 1) + Qw * N * M
    mem = 3 * (3 * Cw) ** 2 * 8
    t_it = (pairs * cal.direct_s_per_pair + n_near * NEAR_EVALS * Qw * cal.near_s_per_eval) / threads \
        + (3 * Cw) ** 2 * 8 / cal.self_gemv_bytes_per_s
    return {"wall_p": pw, "t_wall": t_it, "mem_wall": mem, "wall_near_points": n_near,
            "t_wall_once": cal.self_setup_s[0] * (pw / 16) ** cal.self_setup_s[1]}


def solves_per_step(o):
    """Solves of one step attempt: euler 1, sdc (vesflow.sdc) M (2K + 1), + 1 with Lobatto nodes
    (M = nodes - 1, K sweeps); x 3 with -ves_adapt doubling.  o: options, the defaults for what
    it lacks (sdc with 3 Radau nodes and 2 sweeps: 10; -ves_coupling explicit: euler)."""
    ts = o.get("ts_type") or ("euler" if o.get("coupling") == "explicit" else "sdc")
    adapt = o.get("adapt") or ("sweeps" if ts == "sdc" else "doubling")
    n = 1
    if ts == "sdc":
        n = (int(o.get("ts_sdc_nodes") or 3) - 1) * (2 * int(o.get("ts_sdc_sweeps") or 2) + 1) + (
            (o.get("ts_sdc_quadrature") or "radau") == "lobatto")
    return n * SOLVES_PER_STEP.get(adapt, 1)



def _threads():
    return max(1, int(stokes.max_threads()))


def pc_rebuild_iterations(n_vesicles, p, q, double_layer=False, near_pairs=0, far_backend="direct",
                          far_eps=1e-8):
    """The block preconditioner's rebuild (blocks and LU) in GMRES iterations of the same
    system, by the rule's frozen weights (REBUILD_WEIGHTS; the far field by the backend rule's,
    vesflow.layerpot.far): what vesflow.precond's reuse rule weighs the aging blocks' extra
    iterations against.  Weights, not a clock nor this machine's calibration, so that the
    rebuilds (and with them the iterates) are the same in every run of the same input, on any
    machine, restarts included."""
    w = REBUILD_WEIGHTS
    N, C = n_vesicles, (p + 1) ** 2 - 1
    M, Mq = 2 * p * (p + 1), 2 * q * (q + 1)
    n_ops = 2 if double_layer else 1
    t_it = N * (w["forces_s"][0] + w["forces_s"][1] * p ** 3) + N * (n_ops * (3 * C) ** 2 + (4 * C) ** 2) * 8 / w["bytes_per_s"]
    if N > 1:
        t_direct, t_fmm = farmod.predicted_seconds(N * Mq, N * M, far_eps, threads=1)
        t_it += t_fmm if far_backend == "fmm" else t_direct * (N - 1) / N
        t_it += near_pairs * NEAR_EVALS * Mq * w["near_s_per_eval"] * n_ops
    t_pc = N * w["pc_setup_s"][0] * (p / 16) ** w["pc_setup_s"][1]
    return t_pc / t_it


def fit_memory(scene, opts, ranks=1, near=None, est=None):
    """The options a run of `scene` takes so that its modelled peak (Estimate.memory_peak, all
    `ranks` on this machine) fits the memory available (available_memory: -ves_memory_limit or
    MemAvailable).  Returns (options, line): the options unchanged and line None when the
    defaults fit; else the first cumulative set of memory_choices that fits and the one line
    saying so.  Raises NumericalFailure (one line, naming what would fit) when nothing does.
    near: count the near pairs (default: when cheap, N M <= 2e5; else 500 per vesicle, a dense
    suspension's figure); est: the Estimate of these options, if the caller has it."""
    from .errors import NumericalFailure  # lazy: only the refusal needs it
    avail, source = available_memory(opts.get("memory_limit"))
    if avail is None:
        return opts, None
    N, p = scene.n_vesicles, scene.p
    count = near if near is not None else N * 2 * p * (p + 1) <= 200_000
    ests = {opts.get("ewald_own"): estimate(scene, opts, near=count) if est is None else est}

    def need(o):
        """The modelled peak with options o; the Ewald parameters follow -ves_ewald_own (a new estimate)."""
        mode = o.get("ewald_own")
        if mode not in ests:
            ests[mode] = estimate(scene, o, near=count)
        return ests[mode].memory_peak_with(o, ranks)

    first = need(opts)
    if first <= avail:
        return opts, None
    o, chosen, total = opts, [], first
    for k, v in memory_choices(opts):
        trial = o.replaced({k: v})
        if need(trial) >= total:         # saves nothing here (e.g. no Ewald own operators)
            continue
        o, total = trial, need(trial)
        chosen.append(f"-ves_{k} {v}")
        if total <= avail:
            return o, (f"memory: the defaults need ~{first / 2**30:.2f} GiB, {source} {avail / 2**30:.2f} GiB: "
                       f"using {' '.join(chosen)} (~{total / 2**30:.2f} GiB)")
    est = ests[o.get("ewald_own")]
    per = sum(est.memory_per_vesicle(o).values())
    most = int(max(avail - (need(o) - N * per), 0) // max(per, 1))
    raise NumericalFailure(
        f"memory: {N} vesicles at p = {p} need ~{need(o) / 2**30:.2f} GiB even with "
        f"{' '.join(chosen) or 'the options given'}, more than {source} {avail / 2**30:.2f} GiB: "
        f"at most {most} vesicles fit at p = {p} with these options (-ves_memory_limit sets the memory)")
