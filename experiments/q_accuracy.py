"""What the far/near grid degree q costs in accuracy (docs/explanation/far_field.md, "The far/near grid
degree q").

The periodic scene of benchmarks/iteration.py (same lattice, shapes, orientations and random
densities for the same arguments); one ``LayerPotentials.apply`` with the far-field and near
sources on the degree-q grid (``Settings(q_far=q)``) for each q of --qs, against the same apply
at q = --ref, at each Ewald tol of --tols.  The self part (q_self = 2p) is the same at every q.
Printed per (tol, q): the max-norm difference of the velocities on the p-grid relative to the
largest velocity (`err/|u|`; also the 99th percentile of the pointwise differences), and relative to the largest interaction velocity (far + near,
i.e. apply minus the self part: `err/|u_int|`).  The tol columns include the Ewald error of
both applies (~0.03-0.25 tol, docs/explanation/far_field.md), so differences below ~tol are not q's.

    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.q_accuracy --n 64
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.q_accuracy --n 64 --spacing 2.3 --ref 96 --tols 1e-8
    OMP_NUM_THREADS=1 .venv/bin/python -m experiments.q_accuracy --n 27 --ewald-vs-direct --qs 24 28 32 40 48 64

--ewald-vs-direct: the same scene in free space, at each q the Ewald far field (tol --tols[0])
against the direct sum, same sources, same near corrections (isolates the far-field backend).
"""
import argparse
import os
import time

import numpy as np


from vesflow import shapes  # noqa: E402
from vesflow.layerpot import evaluator  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials, Settings  # noqa: E402
from vesflow.surface import Surface  # noqa: E402


def scene(n, p, spacing, shape):
    """Surface, period and densities exactly as benchmarks/iteration.py builds them."""
    rng = np.random.default_rng(0)
    side = int(np.ceil(n ** (1 / 3)))
    ijk = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
    centres = spacing * (ijk + 0.5) + rng.uniform(-0.1, 0.1, (n, 3))
    kw = dict(reduced_volume=0.65) if shape == "biconcave" else {}
    coeffs = np.stack([shapes.make_shape(shape, p, center=tuple(c), rotation=tuple(rng.uniform(0, 3, 3)), **kw)
                       for c in centres])
    f = rng.standard_normal((n, 3, (p + 1) ** 2 - 1)) * np.exp(-0.3 * np.arange((p + 1) ** 2 - 1))
    return Surface(coeffs, p), spacing * side, f


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=64)
    ap.add_argument("--p", type=int, default=16)
    ap.add_argument("--spacing", type=float, default=2.5)
    ap.add_argument("--shape", choices=("sphere", "biconcave"), default="sphere")
    ap.add_argument("--qs", type=int, nargs="+", default=[24, 28, 32])
    ap.add_argument("--ref", type=int, default=48)
    ap.add_argument("--tols", type=float, nargs="+", default=[1e-6, 1e-8])
    ap.add_argument("--ewald-vs-direct", action="store_true")
    a = ap.parse_args(argv)
    for q in a.qs + [a.ref]:
        if q < a.p:
            ap.error(f"--qs/--ref {q}: the far/near grid degree must be >= p = {a.p}")
    surf, period, f = scene(a.n, a.p, a.spacing, a.shape)
    # the self operators (q_self = 2p) do not depend on q_far: build them once for all applies
    built = {}
    real_self = evaluator.SelfOperators

    class SharedSelf(real_self):
        def __new__(cls, *args, **kw):
            key = (id(args[0]),) + tuple(args[1:]) + tuple(sorted(kw.items()))
            if key not in built:
                built[key] = real_self(*args, **kw)
            return built[key]

        def __init__(self, *args, **kw):
            pass

    evaluator.SelfOperators = SharedSelf
    if a.ewald_vs_direct:
        print(f"# N = {a.n} {a.shape}s, p = {a.p}, free space, Ewald tol {a.tols[0]:g} against the direct sum")
        print("| q | sources per vesicle | Ewald rc | max err/|u| | rms err/|u| rms | worst target (vesicle, point) |")
        print("|---|---|---|---|---|---|")
        for q in a.qs:
            u = {}
            for backend in ("direct", "ewald"):
                lp = LayerPotentials(surf, settings=Settings(backend=backend, fmm_eps=a.tols[0], q_far=q))
                u[backend] = lp.Tp.synth(lp.apply(f))
            e = np.linalg.norm(u["ewald"] - u["direct"], axis=1)
            rms = np.sqrt((e ** 2).mean() / (np.linalg.norm(u["direct"], axis=1) ** 2).mean())
            print(f"| {q} | {lp.Tq.npts} | {lp.far.ewald.params.rc:.3f} | "
                  f"{np.abs(u['ewald'] - u['direct']).max() / np.abs(u['direct']).max():.1e} | {rms:.1e} | "
                  f"{tuple(int(i) for i in np.unravel_index(e.argmax(), e.shape))} |", flush=True)
        return
    print(f"# N = {a.n} {a.shape}s, p = {a.p}, period {period:g}, spacing {a.spacing:g}, reference q = {a.ref}; "
          f"load {os.getloadavg()[0]:.2f}", flush=True)
    X = surf.points().reshape(a.n, -1, 3)
    print("| tol | q | near pairs | max err/|u| | 99th pct err/|u| | rms err/|u| rms | err/|u_int| | worst target: vesicle, distance to other surfaces | s CPU |")
    print("|---|---|---|---|---|---|---|---|---|")
    for tol in a.tols:
        vals = {}
        for q in [a.ref] + a.qs:
            c0 = time.process_time()
            lp = LayerPotentials(surf, settings=Settings(backend="ewald", fmm_eps=tol, period=period, q_far=q))
            u = lp.Tp.synth(lp.apply(f))
            u_int = u - lp.Tp.synth(lp.self_part(f, None))
            npairs = lp.n_near_pairs
            vals[q] = (u, u_int, npairs, time.process_time() - c0)
        u_ref, ui_ref = vals[a.ref][:2]
        for q in a.qs + [a.ref]:
            u, _, npairs, sec = vals[q]
            e = np.linalg.norm(u - u_ref, axis=1)                       # (N, npts)
            d = np.abs(u - u_ref).max()
            v, k = np.unravel_index(np.argmax(e), e.shape)
            others = np.delete(X, v, axis=0).reshape(-1, 3) - X[v, k]
            others -= period * np.round(others / period)
            dist = np.sqrt((others ** 2).sum(-1)).min()
            rms = np.sqrt((e ** 2).mean() / (np.linalg.norm(u_ref, axis=1) ** 2).mean())
            print(f"| {tol:g} | {q} | {npairs} | {d / np.abs(u_ref).max():.2e} | {np.percentile(e, 99) / np.abs(u_ref).max():.2e} | {rms:.2e} | {d / np.abs(ui_ref).max():.2e} "
                  f"| {v}, {dist:.3f} | {sec:.1f} |", flush=True)


if __name__ == "__main__":
    main()
