"""Memory per rank of one step, modelled (issue 19): the paper's Taylor-Green suspension,
1408 vesicles at p = 16, on 1, 2, 16 and 64 ranks, and what makes it fit in 24 GB.

    .venv/bin/python -m experiments.mpi_memory                      # the table of docs/explanation/parallel.md
    .venv/bin/python -m experiments.mpi_memory --ranks 1 2 4 16 64

Per rank = base + (vesicles it owns) x owned + (surfaces it holds) x surface
           + (all vesicles) x (replicated - surface) + Ewald grid.
With the Ewald far field's own vesicle in the set-up (--ewald-own smooth, the default of
vesflow.layerpot.own_smooth) `owned` holds one more dense 3C x 3C operator per vesicle and
layer (5.7 MB at p = 16, single layer; in the self operators' precision).
`owned` and `replicated` are the dense per-vesicle arrays counted from their shapes (self
operator 3C x 3C, preconditioner parts A0 4C x 4C and S Mb 3C x 3C, LU factors 4C x 4C per
kept dt) plus the rest, measured: the peak RSS of benchmarks/mpi_scaling.py at 8 and 64
vesicles on 1 rank and 64 on 2 (--measured, GB) fixes the base and the two slopes.
`surface` (--surface-mb, 0.44 MB at p = 16) is the part of `replicated` that the surfaces
were, measured by experiments/mpi_surface_memory.py (4 ranks, 64 vesicles: the set-up peak of
a rank holding all 64 surfaces against one holding 36, 12.4 MB / 28); since the near-zone
exchange (vesflow.parallel.Halo) a rank holds only its own surfaces and its halo's, counted
for the scene's initial vesicles and the run's Morton partition (`held_surfaces`, --scene).
The Ewald grid (periodic Taylor-Green: the only far field there) is replicated per rank: the
mode grid of the parameters vesflow would choose (3 complex components) plus the NUFFT's
upsampled grid, taken as twice the mode grid (a model, not measured at this size); with
--ewald-grid distributed (-ves_ewald_grid distributed) it is a rank's z-slab of the fine grid,
its box over its vesicles' stencils and its mode slabs, counted for the scene's vesicles and the
run's Morton partition (`distributed_grid_bytes`: grid / ranks plus the ghosts).

    .venv/bin/python -m experiments.mpi_memory --ranks 1 2 4 16 64 --ewald-grid distributed

The memory options -ves_self_precision single and -ves_pc_precision single store those dense
arrays in float32: the owned part falls by half their bytes (counted from the shapes: 15.8 MB
per vesicle with both at p = 16 and one LU; measured at 8 vesicles: peak RSS 0.50 -> 0.38 GB,
15 MB per vesicle).  The last table gives the fewest ranks of 24 GB each for every combination.

    .venv/bin/python -m experiments.mpi_memory --fit-gb 24
"""
import argparse
import math
import os


GB = 2.0 ** 30


def dense_bytes(p, double_layer=False, lu_kept=1, self_bytes=8, pc_bytes=8):
    """Per-vesicle bytes of the dense blocks: self operator(s), PC parts, LU factors
    (self_bytes / pc_bytes: 4 with -ves_self_precision / -ves_pc_precision single)."""
    C = (p + 1) ** 2 - 1
    self_ops = (2 if double_layer else 1) * (3 * C) ** 2 * self_bytes
    parts = ((4 * C) ** 2 + (3 * C) ** 2) * pc_bytes
    lu = lu_kept * (4 * C) ** 2 * pc_bytes
    return self_ops, parts, lu


def fit(traced, held2, surface, rss_base):
    """base, owned, surface, rest (bytes): base the RSS no array accounts for (ru_maxrss minus
    tracemalloc's peak, GB), and from tracemalloc's peaks (GB) of mpi_scaling.py --trace at
    64 vesicles on 1 rank (T1 = 64 (owned + surface + rest)) and on 2 ranks, each holding
    held2 surfaces (T2 = 32 owned + held2 surface + 64 rest): owned and rest, the memory per
    vesicle of the whole suspension that every rank still holds (state, gathered velocities)."""
    T1, T2 = (t * GB for t in traced)
    rest = (T2 - T1 / 2 - (held2 - 32) * surface) / 32
    owned = T1 / 64 - surface - rest
    return rss_base * GB, owned, surface, rest


def ewald_grid_bytes(n, p, L, tol=1e-8):
    """The mode grid vesflow would choose for n vesicles in the periodic cube of side L."""
    from vesflow.layerpot.ewald import choose_params
    import numpy as np
    Mq, Mp = 2 * (2 * p) * (2 * p + 1), 2 * p * (p + 1)
    prm = choose_params(tol, np.zeros((2, 3)), L, n * Mq, n * Mp, 1, 3)
    modes = float(np.prod(prm.modes))
    return prm, L, modes * 16 * 3 * 3          # F (3 comps) + the NUFFT's upsampled grid (~2x)


def distributed_grid_bytes(prm, boxes, order, L, ranks, m=3):
    """-ves_ewald_grid distributed: the most grid bytes of any rank (vesflow.layerpot.ewald_grid:
    its z-slab of the fine grid, its box over the stencils of its vesicles' points, the mode
    slabs; `slab_bytes`) for each rank count, the vesicles' bounding boxes ``boxes`` (N, 2, 3)
    over the ranks by the Morton order ``order`` (the run's partition), period L."""
    import numpy as np
    from vesflow.layerpot.ewald_grid import cover, es_kernel, fine_size, slab_bytes, upsample_for
    from vesflow.parallel import balanced_blocks
    ups = upsample_for(prm.nufft_eps)
    w = es_kernel(prm.nufft_eps, ups)[0]
    K = [int(k) for k in prm.modes]
    n = [fine_size(k, ups) for k in K]
    out = {}
    for R in ranks:
        starts = balanced_blocks(np.ones(len(order)), R)
        most = 0
        for r in range(R):
            mine = order[starts[r]:starts[r + 1]]
            blen = []
            for a in range(3):
                h = L / n[a]
                u = np.concatenate([np.arange(np.floor(lo / h), np.ceil(hi / h) + 1)
                                    for lo, hi in boxes[mine][:, :, a]])
                blen.append(cover(np.mod(u, n[a]), n[a], w)[1])
            zl = (r + 1) * n[2] // R - r * n[2] // R
            yl = (r + 1) * (K[1] - 1) // R - r * (K[1] - 1) // R
            most = max(most, slab_bytes(m, n, blen, zl, yl, K, R)["total"])
        out[R] = most
    return out


def held_surfaces(scene_path, ranks, distance=None, tol=1e-8):
    """Most surfaces any rank holds (its own and those of its halo, vesflow.parallel.Halo) for
    each rank count, from the scene's initial vesicles (wrapped into the periodic cell): the
    Morton partition of the run, the bounding boxes of the p- and q-grid points, the halo
    distance of the far field the run would take: max(h_n, Ewald real-space cutoff) (periodic:
    ewald); free space: h_n (direct).  Returns ({ranks: held}, distance, owned per rank,
    (the vesicles' boxes, their Morton order, the period))."""
    import numpy as np
    from vesflow import scene as S
    from vesflow.layerpot.ewald import choose_params
    from vesflow.layerpot.near import near_distance
    from vesflow.parallel import balanced_blocks, box_gaps, morton_order, vesicle_boxes
    from vesflow.simulation import initial_coefficients, wrap_into_cell
    from vesflow.surface import Surface
    sc = S.parse_scene(open(scene_path).read())
    p, L = sc.p, sc.periodic_length or None
    c = initial_coefficients(sc)
    if L:
        c = wrap_into_cell(c, p, L)[0]
    boxes, cent, area = [], [], []
    for k in range(0, len(c), 128):
        s = Surface(c[k:k + 128], p)
        boxes.append(vesicle_boxes(s.points(2 * p), s.points()))
        cent.append(s.centroid())
        area.append(s.area())
    boxes, cent = np.concatenate(boxes), np.concatenate(cent)
    N = len(c)
    if distance is None:
        distance = float(near_distance(np.concatenate(area), 2 * p).max())
        if L:
            Mq, Mp = 2 * (2 * p) * (2 * p + 1), 2 * p * (p + 1)
            distance = max(distance, choose_params(tol, np.zeros((2, 3)), L, N * Mq, N * Mp, 1, 3).rc)
    order = morton_order(cent)
    held, owned = {}, {}
    for R in ranks:
        starts = balanced_blocks(np.ones(N), R)
        most = 0
        for r in range(R):
            mine = order[starts[r]:starts[r + 1]]
            others = np.setdiff1d(order, mine)
            hit = np.zeros(len(others), dtype=bool)
            for k in range(0, len(others), 512):
                hit[k:k + 512] = (box_gaps(boxes[mine], boxes[others[k:k + 512]], L) <= distance).any(axis=0)
            most = max(most, len(mine) + int(hit.sum()))
        held[R], owned[R] = most, int(np.diff(starts).max())
    return held, distance, owned, (boxes, order, L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 16, 64])
    ap.add_argument("--traced", type=float, nargs=2, default=[3.119, 1.578],
                    help="tracemalloc peak (GB) of mpi_scaling.py --trace at p = 16, 64 vesicles: on 1 rank, on 2")
    ap.add_argument("--held2", type=int, default=48, help="surfaces each of the 2 ranks held in that run")
    ap.add_argument("--rss-base", type=float, default=0.14, help="peak RSS minus tracemalloc's peak (GB; "
                    "0.13-0.15 in those runs and at 8 vesicles)")
    ap.add_argument("--period", type=float, default=17.0, help="side of the periodic cube (runs/taylor_green_1408.toml: "
                    "1408 cells of radius 0.766, v = 0.65, volume fraction 0.35)")
    ap.add_argument("--surface-mb", type=float, default=0.19, help="memory per held surface at a step's peak, "
                    "p = 16 (MB): mpi_scaling.py --trace on 2 ranks, 64 surfaces held (before the halo) against "
                    "48, 1.581 - 1.578 GB")
    ap.add_argument("--scene", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "runs",
                    "taylor_green_1408.toml"), help="scene whose halo sizes are counted (its vesicle count "
                    "replaces --nves)")
    ap.add_argument("--fit-gb", type=float, default=24.0, help="memory per rank to fit in (GB)")
    ap.add_argument("--ewald-own", choices=("smooth", "subtract"), default="smooth",
                    help="the Ewald far field's own vesicle (Settings.ewald_own): smooth keeps one more dense "
                         "3C x 3C operator per owned vesicle and layer (vesflow.layerpot.own_smooth)")
    ap.add_argument("--ewald-grid", choices=("replicated", "distributed"), default="replicated",
                    help="-ves_ewald_grid: the Ewald grid on every rank (replicated) or in z-slabs over the ranks "
                         "(distributed: grid / ranks plus the ghost planes of a rank's box, distributed_grid_bytes)")
    ap.add_argument("--lu-kept", type=int, default=2, help="LU factors per vesicle kept (precond.MAX_DT_FACTORS 3; "
                    "fixed or slowly varying dt: 1-2)")
    args = ap.parse_args(argv)
    held, distance, _, layout = held_surfaces(args.scene, sorted(set(args.ranks) | set(range(1, 9)) | {16, 32, 64}))
    p, N = args.p, held[1]
    surf = args.surface_mb * 2 ** 20
    s, parts, lu = dense_bytes(p, lu_kept=args.lu_kept)
    base, owned, surf, rest = fit(args.traced, args.held2, surf, args.rss_base)
    # the fit's runs (mpi_scaling.py) had no Ewald far field: the own smooth operators E_v of the
    # periodic Taylor-Green run (as many bytes as the self operators, single layer) come on top
    own_smooth = args.ewald_own == "smooth"
    repl = surf + rest
    print(f"p = {p}: dense per vesicle: self operator {s / 2**20:.1f} MB, PC parts {parts / 2**20:.1f} MB, "
          f"LU {lu / 2**20:.1f} MB ({args.lu_kept} kept), Ewald own smooth operator "
          f"{(s if own_smooth else 0) / 2**20:.1f} MB (--ewald-own {args.ewald_own})")
    print(f"measured (mpi_scaling.py --trace, 1 LU kept): base {base / GB:.2f} GB, per owned vesicle "
          f"{owned / 2**20:.1f} MB, per vesicle of the suspension {repl / 2**20:.2f} MB before the halo, of which "
          f"the surface {surf / 2**20:.2f} MB (now per held surface) and the rest {rest / 2**20:.2f} MB")
    owned += s if own_smooth else 0
    print(f"surfaces held per rank (own + halo within {distance:.3f}, the most over the ranks): "
          + ", ".join(f"{R} ranks {held[R]}" for R in sorted(held)))

    def replicated(R):
        return held[R] * surf + N * rest
    extra_lu = (args.lu_kept - 1) * dense_bytes(p)[2]
    prm, L, grid_repl = ewald_grid_bytes(N, p, args.period)
    print(f"Taylor-Green box L = {L:.1f}: Ewald modes {prm.modes} at tol 1e-8, replicated grid ~{grid_repl / GB:.2f} GB "
          "per rank")
    if args.ewald_grid == "distributed":
        grids = distributed_grid_bytes(prm, layout[0], layout[1], layout[2] or L, sorted(set(args.ranks) | set(held)))
        print("-ves_ewald_grid distributed, grid per rank (largest): "
              + ", ".join(f"{R} ranks {grids[R] / GB:.3f} GB" for R in sorted(set(args.ranks))))
        gridf = grids.__getitem__
    else:
        gridf = lambda R: grid_repl          # noqa: E731
    grid = gridf(1)
    print(f"{'ranks':>6} {'owned':>6} {'held':>6} {'per rank GB':>12} {'all surfaces gathered':>22} "
          f"{'node total GB (all ranks)':>26}")
    for R in args.ranks:
        n_own = math.ceil(N / R)
        per = base + n_own * (owned + extra_lu) + replicated(R) + gridf(R)
        gathered = base + n_own * (owned + extra_lu) + N * repl + gridf(R)
        print(f"{R:6d} {n_own:6d} {held[R]:6d} {per / GB:12.2f} {gathered / GB:22.2f} {per * R / GB:26.1f}")
    # the options that bring one node's total under 24 GB (16 ranks, say)
    print("options (per owned vesicle; the dense arrays each removes, counted from their shapes: the measured\n"
          "peak falls less, SphereSpectral at 8 vesicles by 11 MB per vesicle, not 26; docs/explanation/parallel.md):")
    opts = {
        "as is": owned + extra_lu,
        "SphereSpectral PC (no per-vesicle blocks)": owned + extra_lu - parts - (args.lu_kept) * dense_bytes(p)[2],
        "single-precision PC parts and LU": owned + extra_lu - (parts + args.lu_kept * dense_bytes(p)[2]) / 2,
        "single-precision self operators too": owned + extra_lu - (parts + args.lu_kept * dense_bytes(p)[2] + s
                                                                   + (s if own_smooth else 0)) / 2,
    }
    for name, per_ves in opts.items():
        tot = N * per_ves + base + replicated(1) + grid      # one rank
        print(f"  {name:45s} {per_ves / 2**20:7.1f} MB/vesicle, 1408 vesicles {N * per_ves / GB:6.1f} GB; "
              f"one rank {tot / GB:6.1f} GB, 16 ranks on a node "
              f"{(N * per_ves + 16 * (base + replicated(16) + gridf(16))) / GB:6.1f} GB")
    # the options of vesflow: owned bytes fall by what the float32 arrays save (from their shapes)
    print(f"vesflow's memory options: memory per rank (model) and the fewest ranks of {args.fit_gb:g} GB each")
    print(f"{'-ves_self_precision':>19} {'-ves_pc_precision':>18} {'MB/owned':>9} "
          + " ".join(f"{f'{R} ranks':>9}" for R in args.ranks) + f" {'fewest ranks':>13} {'GB/rank there':>14}")
    for sp in ("double", "single"):
        for pp in ("double", "single"):
            s_b, parts_b, lu_b = dense_bytes(p, lu_kept=args.lu_kept, self_bytes=4 if sp == "single" else 8,
                                             pc_bytes=4 if pp == "single" else 8)
            per_own = owned + extra_lu - (s + parts + lu) + (s_b + parts_b + lu_b)
            if own_smooth:                   # E_v in the self operators' precision
                per_own += s_b - s
            per_rank = lambda R: base + math.ceil(N / R) * per_own + replicated(R) + gridf(R)
            fewest = next((R for R in sorted(held) if per_rank(R) <= args.fit_gb * GB), None)
            print(f"{sp:>19} {pp:>18} {per_own / 2**20:9.1f} "
                  + " ".join(f"{per_rank(R) / GB:9.2f}" for R in args.ranks)
                  + (f" {fewest:13d} {per_rank(fewest) / GB:14.2f}" if fewest else f" {'none':>13}"))


if __name__ == "__main__":
    main()
