"""Cost model of a scene for `vesflow check` (paper Table 2): memory and time per GMRES iteration.

The constants are this machine's measured rates (docs/results.md): a dense GEMV of the self
operators streams memory at about BANDWIDTH bytes/s and a direct Stokeslet pair costs PAIR_S.
"""
from __future__ import annotations

BANDWIDTH = 5e9        # bytes/s, measured copy bandwidth order of magnitude (2 cores)
PAIR_S = 4e-9          # seconds per Stokeslet source-target pair (Cython direct, 2 threads)
TRANSFORM_S = 2e-9     # seconds per flop-ish unit of the spherical-harmonic transforms


def estimate(scene):
    p = scene.p
    N = scene.n_vesicles
    C = (p + 1) ** 2 - 1
    q = 2 * p
    eff = scene.effects()
    n_ops = 2 if eff.double_layer else 1
    mem_self = N * n_ops * (3 * C) ** 2 * 8
    mem_pc = N * (4 * C) ** 2 * 8
    t_self = mem_self / BANDWIDTH
    M, Mq = 2 * p * (p + 1), 2 * q * (q + 1)
    t_far = (N * M) * (N - 1) * Mq * PAIR_S if N > 1 else 0.0
    t_forces = N * 30 * (p * p * q + p * q * q) * TRANSFORM_S
    lines = [f"estimate per GMRES iteration: self {t_self * 1e3:.2f} ms, far (direct) {t_far * 1e3:.2f} ms, "
             f"forces {t_forces * 1e3:.2f} ms",
             f"memory: self operators {mem_self / 2**20:.1f} MiB, block preconditioner {mem_pc / 2**20:.1f} MiB"]
    return "\n".join(lines)
