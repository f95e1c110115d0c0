"""Can the near correction's line points use a coarser grid than the far field's q grid?
(docs/explanation/far_field.md, "The near part").

The near-singular value at a target (paper 3.2.2) interpolates the on-surface value and the
smooth rule at L = 8 line points at distances s h_n, s = 1, 8/7, ..., 2 (h_n = sqrt(A / q)).
The paper's heuristic says a degree-q' grid is accurate beyond sqrt(A / q'), so the farther
line points could use a coarser grid (fewer sources per point).  This script measures what
that does: the line values of the current scheme (every line point on the q grid) are
replaced by the smooth rule on the grids of a scheme (one degree per line point), and the
change of the near-corrected velocity is reported next to the scheme's own error.  The
target itself always keeps the q grid (it cancels the far field's value).

- ``--case identity``: the double layer of the density 1 (lambda = 0 kernel) of one vesicle
  (sphere, ellipsoid 1:1:3, biconcave) at 30 targets at 1e-1, 1e-3, 1e-5 R outside: the exact
  value is 0 (docs/explanation/validation.md; tests/layerpot/test_layerpot.py::test_double_layer_identity_near_targets).
- ``--case lattice``: 8 vesicles (benchmarks/iteration.py's lattice, free space, direct sum)
  or a biconcave pair at a gap, random densities (smooth: exp(-0.3 k) in the flat index k;
  rough: exp(-0.5 n) in the degree n), single layer (and double, lambda = 0.3, with
  --double); error = max over near targets of the interaction velocity against q = 96,
  relative to its largest value.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.near_line_grid --case identity
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.near_line_grid --case lattice --spacing 2.3 --double
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.near_line_grid --case lattice --biconcave-gap 0.03
"""
import argparse

import numpy as np


from vesflow import shapes, sph  # noqa: E402
from vesflow._kernels import stokes  # noqa: E402
from vesflow.layerpot import near as nearmod  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials, Settings  # noqa: E402
from vesflow.surface import Surface  # noqa: E402

P = 16
Q = 32
SCHEMES = {"current": [32] * 8, "sqrt rule": [32, 25, 20, 16, 16, 16, 16, 16],
           "p grid s>=1.43": [32, 32, 32, 16, 16, 16, 16, 16], "q/s": [32, 28, 25, 23, 21, 19, 18, 16],
           "24 s>=1.14": [32] + [24] * 7, "24 s>=1.43": [32] * 3 + [24] * 5, "28 s>=1.29": [32] * 2 + [28] * 6,
           "28/26/24 s>=1.71": [32] * 5 + [28, 26, 24]}


def cost(grids):
    """Kernel evaluations per near pair relative to the current scheme (target + 8 line points)."""
    n = lambda q: sph.transform(P, q).npts
    return (n(Q) + sum(n(q) for q in grids)) / (9 * n(Q))


def line_changes(lp, surf, info, f, g, lam, schemes):
    """Per scheme: sum_l w_l (line value on its grid - line value on the q grid), per pair (P, 3)."""
    N = surf.n_vesicles
    pts = info.blocks[:, 1:]                                             # (pairs, L, 3)
    rows = info.rows
    values = {}
    for q in sorted(set(sum(schemes.values(), []))):
        geo, T = surf.geometry(q), sph.transform(P, q)
        src = np.ascontiguousarray(geo.X.reshape(-1, 3))
        nw = np.ascontiguousarray((geo.normal * geo.dA[..., None]).reshape(-1, 3))
        off = np.arange(N + 1, dtype=np.int64) * T.npts
        fw = np.ascontiguousarray(np.moveaxis(T.synth(f), -2, -1).reshape(-1, 3) * geo.dA.reshape(-1)[:, None])
        out = np.zeros(pts.shape)
        src_p = stokes.planar(src, off)
        stokes.stokeslet_sum_blocks(src_p, stokes.planar(fw, off), off, np.ascontiguousarray(pts), rows, out)
        if g is not None:
            gq = np.ascontiguousarray(np.moveaxis(T.synth(g * (1 - lam)[:, None, None]), -2, -1).reshape(-1, 3))
            stokes.stresslet_sum_blocks(src_p, stokes.planar(nw, off), stokes.planar(gq, off), off,
                                        np.ascontiguousarray(pts), rows, out)
        values[q] = out
    w = info.weights[:, 1:]
    res = {}
    for name, grids in schemes.items():
        lv = np.stack([values[q][:, l] for l, q in enumerate(grids)], axis=1)
        res[name] = np.einsum("pl,plk->pk", w, lv - values[Q])
    return res


def identity(schemes):
    axes = {"sphere": {}, "ellipsoid": {"axes": (1, 1, 3)}, "biconcave": {}}
    print("D[1] at 30 targets outside one vesicle (exact 0), max error, p = 16, q = 32")
    print("| shape | distance / R | " + " | ".join(f"{k} ({cost(v):.2f})" for k, v in schemes.items()) + " |")
    print("|---" * (2 + len(schemes)) + "|")
    for shape, kw in axes.items():
        surf = Surface(shapes.make_shape(shape, P, rotation=(10, 20, 30), **kw)[None], P)
        lp = LayerPotentials(surf, lam=0.0, settings=Settings(q_self=Q, q_far=Q))
        geo = surf.geometry(P)
        idx = np.random.default_rng(3).choice(geo.X.shape[1], 30, replace=False)
        R0 = surf.effective_radius()[0]
        g = np.zeros((1, 3, sph.n_coeffs(P)))
        g[0, 0, 0] = np.sqrt(4 * np.pi)
        for dist in (1e-1, 1e-3, 1e-5):
            trg = np.ascontiguousarray(geo.X[0, idx] + dist * R0 * geo.normal[0, idx])
            u = lp.evaluate_at(trg, 0 * g, g)
            info = lp._near_setup(trg, np.full(len(trg), -1, dtype=np.int64))
            ch = line_changes(lp, surf, info, 0 * g, g, np.zeros(1), schemes)
            errs = []
            for name in schemes:
                v = u.copy()
                np.add.at(v, info.pairs[:, 0], ch[name])
                errs.append(np.abs(v).max())
            print(f"| {shape} | {dist:g} | " + " | ".join(f"{e:.1e}" for e in errs) + " |", flush=True)


def lattice_surface(spacing, n=8):
    rng = np.random.default_rng(0)
    side = int(round(n ** (1 / 3)))
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    centres = spacing * (ijk + 0.5) + rng.uniform(-0.1, 0.1, (n, 3))
    return Surface(np.stack([shapes.make_shape("sphere", P, center=tuple(c), rotation=tuple(rng.uniform(0, 3, 3)))
                             for c in centres]), P)


def biconcave_pair(gap):
    """Two biconcave cells (reduced volume 0.65) stacked along z, the second tilted by 0.15,
    moved until the smallest distance between their q = 48 points is `gap`."""
    a = shapes.make_shape("biconcave", P, reduced_volume=0.65)
    X = Surface(a[None], P).points(48)[0]
    lo, hi = 0.0, 3.0
    for _ in range(50):
        mid = (lo + hi) / 2
        if np.min(np.linalg.norm(X[:, None] - (X[None] + [0.3, 0.1, mid]), axis=-1)) < gap:
            lo = mid
        else:
            hi = mid
    b = shapes.make_shape("biconcave", P, reduced_volume=0.65, center=(0.3, 0.1, hi), rotation=(0.0, 0.15, 0.0))
    return Surface(np.stack([a, b]), P)


def lattice(a, schemes):
    surf = biconcave_pair(a.biconcave_gap) if a.biconcave_gap else lattice_surface(a.spacing)
    N = surf.n_vesicles
    double = a.double or bool(a.biconcave_gap)
    lam = np.full(N, 0.3 if double else 1.0)
    lps = {q: LayerPotentials(surf, lam=lam, settings=Settings(backend="direct", q_far=q)) for q in (Q, 64, 96)}
    info = lps[Q].near
    near_t = np.unique(info.pairs[:, 0])
    what = f"biconcave pair, gap {a.biconcave_gap}" if a.biconcave_gap else f"8 spheres, spacing {a.spacing}"
    print(f"{what}: {len(info.pairs)} near pairs, {'single and double layer' if double else 'single layer'}")
    print("| density | q = 32 error vs 96 | q = 64 vs 96 | " + " | ".join(f"{k} ({cost(v):.2f})" for k, v in schemes.items())
          + " |")
    print("|---" * (3 + len(schemes)) + "|")
    C = sph.n_coeffs(P)
    for kind in ("smooth", "rough"):
        rng = np.random.default_rng(5)
        decay = np.exp(-0.3 * np.arange(C)) if kind == "smooth" else np.exp(-0.5 * np.floor(np.sqrt(np.arange(C) + 1)))
        f = rng.standard_normal((N, 3, C)) * decay
        g = rng.standard_normal((N, 3, C)) * decay if double else None
        u = {}
        for q, lp in lps.items():
            ui = lp.Tp.synth(lp.apply(f, g)) - lp.Tp.synth(lp.self_part(f, g))
            u[q] = np.moveaxis(ui, -1, -2).reshape(-1, 3)
        scale = np.abs(u[96]).max()
        err = lambda v: np.abs(v - u[96])[near_t].max() / scale
        ch = line_changes(lps[Q], surf, info, f, g, lam, schemes)
        cells = []
        for name in schemes:
            v = u[Q].copy()
            np.add.at(v, info.pairs[:, 0], ch[name])
            cells.append(f"{err(v):.2e} (change {np.abs(v - u[Q]).max() / scale:.0e})")
        print(f"| {kind} | {err(u[Q]):.2e} | {err(u[64]):.2e} | " + " | ".join(cells) + " |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", choices=("identity", "lattice"), default="identity")
    ap.add_argument("--spacing", type=float, default=2.3)
    ap.add_argument("--double", action="store_true")
    ap.add_argument("--biconcave-gap", type=float, default=None)
    ap.add_argument("--schemes", nargs="+", default=None, help=f"names among {', '.join(SCHEMES)}")
    a = ap.parse_args(argv)
    schemes = SCHEMES if not a.schemes else {k: SCHEMES[k] for k in ["current"] + a.schemes}
    w = nearmod.lagrange_weights(np.r_[0.0, 1 + np.arange(nearmod.L_POINTS) / (nearmod.L_POINTS - 1)],
                                 np.linspace(0, 1, 201))
    print(f"# largest |interpolation weight| of line points 0..7 for targets within h_n: "
          f"{' '.join(f'{x:.0f}' for x in np.abs(w[:, 1:]).max(0))} (Lebesgue constant {np.abs(w).sum(1).max():.0f})")
    if a.case == "identity":
        identity(schemes)
    else:
        lattice(a, schemes)


if __name__ == "__main__":
    main()
