"""Memory per rank of one step, modelled (issue 19): the paper's Taylor-Green suspension,
1408 vesicles at p = 16, on 1, 2, 16 and 64 ranks, and what makes it fit in 24 GB.

    .venv/bin/python benchmarks/mpi_memory.py                      # the table of docs/parallel.md
    .venv/bin/python benchmarks/mpi_memory.py --nves 64 --ranks 1 2

Per rank = base + (vesicles it owns) x owned + (all vesicles) x replicated + Ewald grid.
`owned` and `replicated` are the dense per-vesicle arrays counted from their shapes (self
operator 3C x 3C, preconditioner parts A0 4C x 4C and S Mb 3C x 3C, LU factors 4C x 4C per
kept dt) plus the rest, measured: the peak RSS of benchmarks/mpi_scaling.py at 8 and 64
vesicles on 1 rank and 64 on 2 (--measured, GB) fixes the base and the two slopes.
The Ewald grid (periodic Taylor-Green: the only far field there) is replicated per rank: the
mode grid of the parameters vesflow would choose (3 complex components) plus the NUFFT's
upsampled grid, taken as twice the mode grid (a model, not measured at this size).

The memory options -ves_self_precision single and -ves_pc_precision single store those dense
arrays in float32: the owned part falls by half their bytes (counted from the shapes: 15.8 MB
per vesicle with both at p = 16 and one LU; measured at 8 vesicles: peak RSS 0.50 -> 0.38 GB,
15 MB per vesicle).  The last table gives the fewest ranks of 24 GB each for every combination.

    .venv/bin/python benchmarks/mpi_memory.py --fit-gb 24
"""
import argparse
import math
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

GB = 2.0 ** 30


def dense_bytes(p, double_layer=False, lu_kept=1, self_bytes=8, pc_bytes=8):
    """Per-vesicle bytes of the dense blocks: self operator(s), PC parts, LU factors
    (self_bytes / pc_bytes: 4 with -ves_self_precision / -ves_pc_precision single)."""
    C = (p + 1) ** 2 - 1
    self_ops = (2 if double_layer else 1) * (3 * C) ** 2 * self_bytes
    parts = ((4 * C) ** 2 + (3 * C) ** 2) * pc_bytes
    lu = lu_kept * (4 * C) ** 2 * pc_bytes
    return self_ops, parts, lu


def fit(measured, p, lu_kept):
    """base, owned, replicated (bytes) from peak RSS (GB) at (ranks, nves) = (1, 8), (1, 64), (2, 64)."""
    r18, r164, r264 = (m * GB for m in measured)
    per_ves_1 = (r164 - r18) / 56.0                    # owned + replicated
    base = r18 - 8 * per_ves_1
    owned = (r164 - r264) / 32.0                       # 64 owned on 1 rank, 32 on 2
    return base, owned, per_ves_1 - owned


def ewald_grid_bytes(n, p, L, tol=1e-8):
    """The mode grid vesflow would choose for n vesicles in the periodic cube of side L."""
    from vesflow.layerpot.ewald import choose_params
    import numpy as np
    Mq, Mp = 2 * (2 * p) * (2 * p + 1), 2 * p * (p + 1)
    prm = choose_params(tol, np.zeros((2, 3)), L, n * Mq, n * Mp, 1, 3)
    modes = float(np.prod(prm.modes))
    return prm, L, modes * 16 * 3 * 3          # F (3 comps) + the NUFFT's upsampled grid (~2x)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--nves", type=int, default=1408)
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 16, 64])
    ap.add_argument("--measured", type=float, nargs=3, default=[0.49, 3.25, 1.74],
                    help="peak RSS (GB) of mpi_scaling.py at p = 16: 8 vesicles 1 rank, 64 on 1, 64 on 2")
    ap.add_argument("--period", type=float, default=17.0, help="side of the periodic cube (runs/taylor_green_1408.toml: "
                    "1408 cells of radius 0.766, v = 0.65, volume fraction 0.35)")
    ap.add_argument("--fit-gb", type=float, default=24.0, help="memory per rank to fit in (GB)")
    ap.add_argument("--lu-kept", type=int, default=2, help="LU factors per vesicle kept (precond.MAX_DT_FACTORS 3; "
                    "fixed or slowly varying dt: 1-2)")
    args = ap.parse_args(argv)
    p, N = args.p, args.nves
    s, parts, lu = dense_bytes(p, lu_kept=args.lu_kept)
    base, owned, repl = fit(args.measured, p, 1)
    print(f"p = {p}: dense per vesicle: self operator {s / 2**20:.1f} MB, PC parts {parts / 2**20:.1f} MB, "
          f"LU {lu / 2**20:.1f} MB ({args.lu_kept} kept)")
    print(f"measured (mpi_scaling.py, 1 LU kept): base {base / GB:.2f} GB, per owned vesicle {owned / 2**20:.1f} MB, "
          f"per replicated vesicle {repl / 2**20:.2f} MB")
    extra_lu = (args.lu_kept - 1) * dense_bytes(p)[2]
    prm, L, grid = ewald_grid_bytes(N, p, args.period)
    print(f"Taylor-Green box L = {L:.1f}: Ewald modes {prm.modes} at tol 1e-8, grid ~{grid / GB:.2f} GB per rank")
    print(f"{'ranks':>6} {'owned':>6} {'per rank GB':>12} {'node total GB (all ranks)':>26}")
    for R in args.ranks:
        n_own = math.ceil(N / R)
        per = base + n_own * (owned + extra_lu) + N * repl + grid
        print(f"{R:6d} {n_own:6d} {per / GB:12.2f} {per * R / GB:26.1f}")
    # the options that bring one node's total under 24 GB (16 ranks, say)
    print("options (per owned vesicle; the dense arrays each removes, counted from their shapes: the measured\n"
          "peak falls less, SphereSpectral at 8 vesicles by 11 MB per vesicle, not 26; docs/parallel.md):")
    opts = {
        "as is": owned + extra_lu,
        "SphereSpectral PC (no per-vesicle blocks)": owned + extra_lu - parts - (args.lu_kept) * dense_bytes(p)[2],
        "single-precision PC parts and LU": owned + extra_lu - (parts + args.lu_kept * dense_bytes(p)[2]) / 2,
        "single-precision self operators too": owned + extra_lu - (parts + args.lu_kept * dense_bytes(p)[2] + s) / 2,
    }
    for name, per_ves in opts.items():
        tot = N * per_ves + base + N * repl + grid      # one rank (the node's total is this + (R-1)(base + N repl + grid))
        print(f"  {name:45s} {per_ves / 2**20:7.1f} MB/vesicle, 1408 vesicles {N * per_ves / GB:6.1f} GB; "
              f"one rank {tot / GB:6.1f} GB, 16 ranks on a node "
              f"{(N * per_ves + 16 * (base + N * repl + grid)) / GB:6.1f} GB")
    # the options of vesflow: owned bytes fall by what the float32 arrays save (from their shapes)
    print(f"vesflow's memory options: memory per rank (model) and the fewest ranks of {args.fit_gb:g} GB each")
    print(f"{'-ves_self_precision':>19} {'-ves_pc_precision':>18} {'MB/owned':>9} "
          + " ".join(f"{f'{R} ranks':>9}" for R in args.ranks) + f" {'fewest ranks':>13} {'GB/rank there':>14}")
    for sp in ("double", "single"):
        for pp in ("double", "single"):
            s_b, parts_b, lu_b = dense_bytes(p, lu_kept=args.lu_kept, self_bytes=4 if sp == "single" else 8,
                                             pc_bytes=4 if pp == "single" else 8)
            per_own = owned + extra_lu - (s + parts + lu) + (s_b + parts_b + lu_b)
            per_rank = lambda R: base + math.ceil(N / R) * per_own + N * repl + grid
            fewest = next((R for R in range(1, N + 1) if per_rank(R) <= args.fit_gb * GB), None)
            print(f"{sp:>19} {pp:>18} {per_own / 2**20:9.1f} "
                  + " ".join(f"{per_rank(R) / GB:9.2f}" for R in args.ranks)
                  + (f" {fewest:13d} {per_rank(fewest) / GB:14.2f}" if fewest else f" {'none':>13}"))


if __name__ == "__main__":
    main()
