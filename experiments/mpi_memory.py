"""Memory per rank of one step, modelled: the paper's Taylor-Green suspension, 1408 vesicles at
p = 16, on 1 ... 64 ranks, with vesflow's memory options one after the other.

    .venv/bin/python -m experiments.mpi_memory                      # the table of docs/explanation/parallel.md
    .venv/bin/python -m experiments.mpi_memory --ranks 1 2 4 16 64

Per rank = base + Ewald grids + (vesicles it owns) x owned + (other surfaces it holds) x surface
           + (other vesicles) x rest.
`owned` is vesflow check's model (vesflow.memory_model.memory_per_vesicle: self and own smooth
operators, preconditioner parts and LU sets, near pairs, sources and geometry, measured by
benchmarks/memory_per_vesicle.py), base and the Ewald grids (replicated on every rank)
likewise; `rest` (0.50 MB per vesicle of the suspension: the replicated state at a step's peak)
and `surface` (0.19 MB per held surface) come from benchmarks/mpi_scaling.py --trace on 1 and 2
ranks (64 vesicles at p = 16); the surfaces a rank holds (its own and those of its halo,
vesflow.parallel.Halo) are counted for the scene's initial vesicles and the run's Morton
partition (`held_surfaces`).
With --ewald-grid distributed (-ves_ewald_grid distributed) a rank's Ewald grids are its z-slab
of the fine grid, its box over its vesicles' stencils and its mode slabs (`distributed_grid_bytes`,
counted for the scene's vesicles and the run's Morton partition: grid / ranks plus the ghosts),
in the same proportion to the replicated grids as one evaluation's.

    .venv/bin/python -m experiments.mpi_memory --ranks 1 2 4 16 64 --ewald-grid distributed
"""
import argparse
import math
import os


GB = 2.0 ** 30


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
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4, 16, 64])
    ap.add_argument("--rest-mb", type=float, default=0.50, help="replicated state per vesicle of the suspension "
                    "at a step's peak (MB; mpi_scaling.py --trace on 1 and 2 ranks, 64 vesicles at p = 16)")
    ap.add_argument("--surface-mb", type=float, default=0.19, help="memory per held surface at a step's peak, "
                    "p = 16 (MB): mpi_scaling.py --trace on 2 ranks, 64 surfaces held against 48")
    ap.add_argument("--near-per-vesicle", type=float, default=540.0, help="near pairs per vesicle (vesflow check "
                    "runs/taylor_green_1408.toml: 760320 at t = 0)")
    ap.add_argument("--scene", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "runs",
                    "taylor_green_1408.toml"), help="scene whose halo sizes are counted")
    ap.add_argument("--fit-gb", type=float, default=16.0, help="memory of one node for all its ranks (GB)")
    ap.add_argument("--period", type=float, default=17.0, help="side of the periodic cube")
    ap.add_argument("--ewald-grid", choices=("replicated", "distributed"), default="replicated",
                    help="-ves_ewald_grid: the Ewald grid on every rank (replicated) or in z-slabs over the ranks "
                         "(distributed: grid / ranks plus the ghost planes of a rank's box, distributed_grid_bytes)")
    args = ap.parse_args(argv)
    from vesflow import costs, memory_model
    held, distance, _, layout = held_surfaces(args.scene, sorted(set(args.ranks) | {1}))
    p, N = args.p, held[1]
    prm, L, _ = ewald_grid_bytes(N, p, args.period)
    modes = float(prm.modes[0]) * prm.modes[1] * prm.modes[2]
    if args.ewald_grid == "distributed":     # a rank's share of the grids: its slab over the whole grid
        dist = distributed_grid_bytes(prm, layout[0], layout[1], layout[2] or L, sorted(set(args.ranks) | {1}))
        share = {R: dist[R] / dist[1] for R in dist}
        print("-ves_ewald_grid distributed, grid per rank (largest) over the whole grid: "
              + ", ".join(f"{R} ranks {share[R]:.3f}" for R in sorted(args.ranks)))
    else:
        share = {R: 1.0 for R in set(args.ranks) | {1}}
    print(f"{N} vesicles, p = {p}, Taylor-Green box L = {L:.1f}: Ewald modes {prm.modes} at tol 1e-8; surfaces held "
          f"per rank (own + halo within {distance:.3f}): " + ", ".join(f"{R} ranks {held[R]}" for R in sorted(held)))
    base = {"ts_type": "sdc", "ewald_own": "smooth"}
    sets = [("defaults", dict(base))]
    o = dict(base)
    for k, v in [("pc_precision", "single"), ("ewald_own", "subtract"), ("pc_factors", 1), ("setup_cache", "current"),
                 ("pc_parts", "drop"), ("self_precision", "single")]:
        o = dict(o, **{k: v})
        sets.append((f"+ -ves_{k} {v}", dict(o)))
    print("per owned vesicle: memory_model.memory_per_vesicle; per rank: costs.BASE_BYTES, the Ewald grids "
          f"({args.ewald_grid}), {args.rest_mb} MB per other vesicle of the suspension and {args.surface_mb} MB per other "
          "surface held")
    print(f"{'options (cumulative)':44} {'MB/owned':>9} " + " ".join(f"{f'{R} ranks':>9}" for R in args.ranks)
          + f" {'node total (GB) at the most ranks':>34}")
    for name, o in sets:
        own_bytes = 4 if o.get("self_precision") == "single" else 8
        per = sum(memory_model.memory_per_vesicle(p, 2 * p, o, False, args.near_per_vesicle, o["ewald_own"] == "smooth",
                                           own_bytes, N).values())
        grids = 16 * modes * (memory_model.EWALD_GRIDS * memory_model.layer_potentials_held(o) + memory_model.EWALD_GRIDS_APPLY)
        per_rank = lambda R: (costs.BASE_BYTES + grids * share[R] + math.ceil(N / R) * per
                              + (N - math.ceil(N / R)) * args.rest_mb * 2 ** 20
                              + (held[R] - math.ceil(N / R)) * args.surface_mb * 2 ** 20)
        R = max(args.ranks)
        print(f"{name:44} {per / 2**20:9.1f} " + " ".join(f"{per_rank(R) / GB:9.2f}" for R in args.ranks)
              + f" {R * per_rank(R) / GB:34.1f}")


if __name__ == "__main__":
    main()
