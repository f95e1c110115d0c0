"""Cost model of a scene for `vesflow check` (paper Table 2): memory, and time per GMRES
iteration and per solve set-up.

What is stored (float64, 8 bytes, unless a memory option says float32, 4 bytes):
    self operators        N x (3C)^2            (x 2 with the double layer: S and D;
                                                 float32 with -ves_self_precision single)
    block preconditioner  N x ((4C)^2 + (3C)^2) parts A0 and S Mb, and N x (4C)^2 per cached
                          dt octave (the LU factors; up to 3 are cached); float32 with
                          -ves_pc_precision single
    far/near sources      N x Mq x 7            (points, weights, normal x weight)
    near pairs            P x (C + 8 x 3 + 9)   (basis row, line points, weights)
with C = (p+1)^2 - 1 coefficients per scalar, M = 2p(p+1) grid points, Mq = 2q(q+1) on the
upsampled grid (q = -ves_q_near, 2p by default) and P the near (point, vesicle) pairs.

Time per GMRES iteration: the membrane forces and transforms (per vesicle), the self
operators (one GEMV each: they are streamed from memory), the far field (direct sum over the
(N M) x ((N-1) Mq) pairs, the FMM or the Ewald sum, as `-ves_far auto` would choose:
vesflow.layerpot.far's own model), and the near correction (9 Mq kernel evaluations per near
pair).  Time per step: the solves of one step (3 with -ves_adapt doubling), each its set-up and
ITERATIONS_PER_SOLVE GMRES iterations.  The constants
below were measured on the development machine (2 cores; docs/explanation/validation.md); expect the
right order of magnitude, not the digits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BANDWIDTH = 2e10                 # bytes/s streamed by the batched self GEMV (measured 2-5e10)
FORCE_S = (8.0e-5, 1.0e-7)       # seconds per vesicle per iteration: a + b p^3 (forces, transforms)
SELF_SETUP_S = (0.088, 4.0)      # seconds per vesicle to assemble S at p = 16, exponent in p
PC_SETUP_S = (0.26, 4.0)         # seconds per vesicle to build and factor its 4C block at p = 16
# (benchmarks/cost_model.py, CPU seconds, p = 6 / 8 / 12 / 16: S 0.0019 / 0.0050 / 0.026 / 0.097,
# block + LU 0.007 / 0.012 / 0.057 / 0.26-0.36, forces 1.6 / 2.2 / 4.3 / 7.4e-4 per iteration, then
# 1.3 / 2.4 / 4.8e-4 at p = 8 / 12 / 16 with the derivatives synthesized from the coefficients;
# before the second wave's transforms: S 0.0035 / - / 0.034 / 0.134, block + LU 0.011 / - / 0.086 / 0.29)
NEAR_EVALS = 9                   # kernel evaluations per near pair and source point (1 + 8 line points)
# seconds per (near target or line point, source) kernel evaluation of one thread, the near
# correction in blocks (stokes.*_sum_blocks): 4.24 s for 88189 pairs at p = 16, q = 32
# (benchmarks/iteration.py --n 512, docs/explanation/far_field.md); then 0.50 -> 0.32 s per iteration at
# N = 64 with the blocks summed by the vectorized range sums of pairsum.h: x 0.64
NEAR_SECONDS_PER_EVAL = 1.6e-9
# GMRES iterations per solve (block preconditioner): 5.2 in runs/taylor_green.toml (575 in 37
# doubling steps of 3 solves), 6-10 in docs/explanation/accuracy_cost.md; the paper's 1408-cell case needed
# 139 per solve with its own preconditioner (section 4.4)
ITERATIONS_PER_SOLVE = 8
SOLVES_PER_STEP = {"doubling": 3, "none": 1}       # other schemes (SDC sweeps): counted as 1 solve per sweep pass
NEAR_COUNT_MAX_POINTS = 1_200_000                 # count the near pairs when N M is below (~8 s CPU at the limit)


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
    t_setup: float               # per solve (every step: three with -ves_adapt doubling)
    t_pc: float                  # per preconditioner factorization (every -ves_pc_lag solves)
    solves_per_step: int = 3
    iterations_per_solve: int = ITERATIONS_PER_SOLVE
    threads: int = 1
    mem_own: int = 0             # the Ewald far field's own smooth operators E_v (as many as the self operators)
    t_own: float = 0.0           # their GEMV per iteration

    @property
    def t_step(self):
        """Seconds per time step: each solve's set-up and GMRES iterations (no preconditioner
        factorization: it is reused over -ves_pc_lag solves)."""
        return self.solves_per_step * (self.t_setup + self.iterations_per_solve * self.t_iteration)

    @property
    def t_iteration(self):
        return self.t_forces + self.t_self + self.t_own + self.t_far + self.t_near

    @property
    def memory(self):
        return self.mem_self + self.mem_own + self.mem_pc_parts + self.mem_pc_max + self.mem_sources + self.mem_near

    def __str__(self):
        mib = lambda b: f"{b / 2**20:.1f} MiB"
        ms = lambda s: f"{s * 1e3:.2f} ms"
        near = "not computed" if self.near_pairs < 0 else f"{self.near_pairs} near pairs at t = 0"
        return "\n".join([
            f"cost     per GMRES iteration ~ {ms(self.t_iteration)}: forces {ms(self.t_forces)}, "
            f"self {ms(self.t_self)}, far ({self.far_backend}) {ms(self.t_far + self.t_own)}, near {ms(self.t_near)} ({near})",
            f"         per solve set-up ~ {self.t_setup:.2f} s (self operators); preconditioner "
            f"factorization ~ {self.t_pc:.2f} s (every -ves_pc_lag solves)",
            f"         per time step ~ {self.t_step:.4g} s: {self.solves_per_step} solve(s) x (set-up + "
            f"{self.iterations_per_solve} GMRES iterations, an assumed typical count); {self.threads} thread(s), "
            f"from the cost model (vesflow/costs.py)",
            f"memory   ~ {mib(self.memory)}: self operators {mib(self.mem_self)} "
            f"(N (3C)^2 x {_entry(self.self_bytes)}{' x 2, S and D' if self.double_layer else ''}"
            f"{f'; the Ewald own smooth operators as many again, {mib(self.mem_own)}' if self.mem_own else ''}), block "
            f"preconditioner parts {mib(self.mem_pc_parts)} (N 25 C^2 x {_entry(self.pc_bytes)}) and LU "
            f"{mib(self.mem_pc)} per cached dt (N (4C)^2 x {_entry(self.pc_bytes)}, up to 3: {mib(self.mem_pc_max)}), "
            f"sources {mib(self.mem_sources)}, near {mib(self.mem_near)}",
            self._fits(),
        ])

    def _fits(self):
        """Whether the memory fits this machine's RAM (the minimum: one cached preconditioner)."""
        least = self.memory - self.mem_pc_max + self.mem_pc
        try:
            import os
            ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        except (ValueError, OSError, AttributeError):
            return "machine  RAM unknown"
        verdict = ("fits" if self.memory <= 0.8 * ram else
                   "fits while at most one preconditioner set is cached (fixed dt)" if least <= 0.8 * ram else
                   "does NOT fit")
        return (f"machine  {ram / 2**30:.1f} GiB RAM: {verdict} (needs {least / 2**30:.1f} GiB with one cached "
                f"preconditioner, {self.memory / 2**30:.1f} GiB with three; 80 % of the RAM usable)")


def _entry(nbytes):
    return "8 B" if nbytes == 8 else f"{nbytes} B (float32)"


def _near_pairs(scene, p, q, near_factor):
    """Near (p-grid point, other vesicle) pairs of the initial configuration."""
    from . import sph
    from ._kernels import search
    from .layerpot.near import near_distance
    from .simulation import initial_coefficients
    from .surface import Surface
    S = Surface(initial_coefficients(scene), p)
    N = scene.n_vesicles
    trg = np.ascontiguousarray(S.points().reshape(-1, 3))
    src = np.ascontiguousarray(S.points(q).reshape(-1, 3))
    trg_id = np.repeat(np.arange(N, dtype=np.int64), sph.transform(p).npts)
    src_id = np.repeat(np.arange(N, dtype=np.int64), sph.transform(p, q).npts)
    h = float(near_distance(S.area(), q, near_factor).max())
    pairs, _ = search.near_pairs(trg, trg_id, src, src_id, h)
    return int(np.asarray(pairs).reshape(-1, 2).shape[0])


def estimate(scene, opts=None, near=True):
    """Estimate of a scene's costs (an Estimate; str() gives the lines `vesflow check` prints).
    opts: resolved options (vesflow.options.read_options) for q, the far-field backend and its
    accuracy; near: count the near pairs of the initial configuration (N > 1, N M <= 1.2e6)."""
    from .layerpot import far as farmod
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
    pairs = 0
    if N > 1 and near:
        pairs = (_near_pairs(scene, p, q, float(o.get("near_factor") or 1.0)) if N * M <= NEAR_COUNT_MAX_POINTS
                 else -1)
    mem_near = max(pairs, 0) * (C + 3 * 8 + 9) * 8
    t_forces = N * (FORCE_S[0] + FORCE_S[1] * p ** 3)
    t_self = mem_self / BANDWIDTH
    backend, t_far = "none", 0.0
    if N > 1 or eff.periodic:          # periodic: a single vesicle sees its images
        nsrc, ntrg = N * Mq, N * M
        eps = float(o.get("far_tol") or farmod.DEFAULT_EPS)
        t_direct, t_fmm = farmod.predicted_seconds(nsrc, ntrg, eps)
        t_direct *= (N - 1) / N                      # a vesicle's own sources are left out
        t_ewald = _ewald_seconds(scene, p, nsrc, ntrg, N * M * Mq, eps) if farmod._have_ewald() else None
        want = o.get("far", "auto")
        if want == "auto":
            backend = farmod.choose_backend(nsrc, ntrg, "auto", eps, t_ewald, periodic=bool(eff.periodic))
        else:
            backend = want
        t_far = {"fmm": t_fmm, "ewald": t_ewald}.get(backend, t_direct) or 0.0
    # ewald: the own vesicle's smooth share removed by per-vesicle operators E_v (Settings.ewald_own
    # "smooth", vesflow.layerpot.own_smooth): as many bytes as the self operators, one more GEMV
    # (-ves_ewald_own auto, the default, may take "subtract" for a run of few GMRES iterations
    # per set-up: no E_v, a dearer far field; the memory counted here is the larger of the two)
    from .layerpot.evaluator import OWN_SINGLE_TOL
    own_bytes = 4 if (self_bytes == 4 or (backend == "ewald" and eps >= OWN_SINGLE_TOL)) else 8   # _own_dtype
    mem_own = mem_self * own_bytes // self_bytes if backend == "ewald" else 0
    t_own = mem_own / BANDWIDTH
    t_near = max(pairs, 0) * NEAR_EVALS * Mq * NEAR_SECONDS_PER_EVAL / max(1, _threads()) * (2 if dl else 1)
    t_setup = N * SELF_SETUP_S[0] * (p / 16) ** SELF_SETUP_S[1] * (q / (2 * p)) ** 2 * (1.5 if dl else 1)
    t_pc = N * PC_SETUP_S[0] * (p / 16) ** PC_SETUP_S[1]
    return Estimate(n_vesicles=N, p=p, q=q, unknowns=N * 4 * C, double_layer=dl, mem_self=mem_self,
                    mem_pc=mem_pc, mem_pc_max=3 * mem_pc, mem_pc_parts=mem_pc_parts, self_bytes=self_bytes,
                    pc_bytes=pc_bytes, mem_sources=mem_sources, mem_near=mem_near,
                    near_pairs=pairs if N > 1 and near else (0 if N == 1 else -1), far_backend=backend,
                    t_forces=t_forces, t_self=t_self, t_far=t_far, t_near=t_near, t_setup=t_setup, t_pc=t_pc,
                    solves_per_step=SOLVES_PER_STEP.get(o.get("adapt") or "doubling", 1), threads=_threads(),
                    mem_own=mem_own, t_own=t_own)


def _ewald_seconds(scene, p, nsrc, ntrg, own_pairs, eps):
    """Predicted seconds of the Ewald far field (vesflow.layerpot.far.predicted_ewald) over the
    box of the initial p-grid points (the period cell when periodic)."""
    from .layerpot import far as farmod
    from .simulation import initial_coefficients
    from .surface import Surface
    pts = Surface(initial_coefficients(scene), p).points().reshape(-1, 3)
    period = scene.domain.period if scene.domain is not None else None
    n = scene.n_vesicles
    area = float(Surface(initial_coefficients(scene), p).area().mean()) if n else 0.0
    own_skip = (nsrc // max(n, 1), area)          # Settings.ewald_own "smooth": no own real-space pairs
    return farmod.predicted_ewald(pts, nsrc, ntrg, own_pairs, eps, period=period, own_skip=own_skip)[0]


def _threads():
    try:
        from ._kernels import stokes
        return int(stokes.max_threads())
    except Exception:
        return 1


def pc_rebuild_iterations(n_vesicles, p, q, double_layer=False, near_pairs=0, far_backend="direct",
                          far_eps=1e-8):
    """The block preconditioner's rebuild (blocks and LU) in GMRES iterations of the same
    system, by the model above: what vesflow.precond's reuse rule weighs the aging blocks'
    extra iterations against.  A model, not a clock, so that the rebuilds (and with them the
    iterates) are the same in every run of the same input, restarts included."""
    from .layerpot import far as farmod
    N, C = n_vesicles, (p + 1) ** 2 - 1
    M, Mq = 2 * p * (p + 1), 2 * q * (q + 1)
    n_ops = 2 if double_layer else 1
    t_it = N * (FORCE_S[0] + FORCE_S[1] * p ** 3) + N * (n_ops * (3 * C) ** 2 + (4 * C) ** 2) * 8 / BANDWIDTH
    if N > 1:
        t_direct, t_fmm = farmod.predicted_seconds(N * Mq, N * M, far_eps, threads=1)
        t_it += t_fmm if far_backend == "fmm" else t_direct * (N - 1) / N
        t_it += near_pairs * NEAR_EVALS * Mq * farmod.DIRECT_SECONDS_PER_PAIR * n_ops
    t_pc = N * PC_SETUP_S[0] * (p / 16) ** PC_SETUP_S[1]
    return t_pc / t_it
