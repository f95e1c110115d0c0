"""GMRES iterations and time per iteration of one implicit solve, per preconditioner (docs/explanation/dynamics.md).

A suspension of N identical oblate vesicles (reduced volume --v, effective radius 1, symmetry
axis along z, the shear gradient) on a regular lattice whose surfaces are --gap apart along
each lattice axis, in shear u = (z, 0, 0) of rate 1, kappa_b = --kappa, viscosity contrast
--lam.  The scene is built with a [[lattice]] table (vesflow.scene), so overlaps are checked.
For each (N, p) the step operator of one semi-implicit step of size --dt is set up once
(singular self operators, near-zone projections, far-field sources: vesflow.stepper.Stepper
._setup) and its right-hand side formed (Stepper.rhs); then the same system is solved with
each preconditioner by a KSP configured as Stepper.solve does it (GMRES, rtol 1e-8 unless
-ksp_rtol is given, max_it 1000, zero initial guess, PETSc's default restart 30):

    none      -pc_type none
    bjacobi   vesflow.precond.BlockJacobi    (the default of Stepper.solve): dense LU of each
              vesicle's own 4C x 4C block, C = (p + 1)^2 - 1
    sphere    vesflow.precond.SphereSpectral: the block of a sphere of the same area, kappa
              and lambda, assembled once per distinct (radius, kappa, lambda)

Printed per solve: iterations, converged reason, true relative residual, preconditioner
set-up time (KSP.setUp: the LU factors), solve time, time per iteration (wall and process
CPU), and once per (N, p): operator set-up time, the time of one operator application
(one matrix-vector product), the far-field backend and the number of near pairs.
OMP_NUM_THREADS and os.getloadavg() are printed with every table: on a shared machine the
wall times are only as good as the load.

A solve whose predicted time (iterations of the same preconditioner at the largest smaller N
measured, times the measured matrix-vector time, plus the preconditioner set-up scaled by N)
exceeds --max-seconds is not run; the estimate is printed instead.  Likewise an (N, p) whose
operator set-up is predicted (by N times the per-vesicle set-up of the largest smaller N at
that p) beyond --max-seconds is skipped whole.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gmres_iterations.py                       # 2, 8, 64 x p 8, 16
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/gmres_iterations.py --sizes 2 --degrees 8 # quick (~10 s)
    ... --pcs bjacobi sphere --max-seconds 1200 -ksp_gmres_restart 100                       # PETSc options pass through
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


PCS = ("none", "bjacobi", "sphere")


def lattice_counts(n):
    """Near-cubic nx * ny * nz = n, largest along x (the flow direction)."""
    best = None
    for nx in range(1, n + 1):
        if n % nx:
            continue
        for ny in range(1, n // nx + 1):
            if (n // nx) % ny:
                continue
            nz = n // nx // ny
            key = (max(nx, ny, nz) - min(nx, ny, nz), -nx)
            if best is None or key < best[0]:
                best = (key, sorted((nx, ny, nz), reverse=True))
    return best[1]


def oblate_extents(v):
    """Semi-extents along x (= y) and z of the oblate of reduced volume v and effective radius 1."""
    from vesflow.shapes import make_shape
    from vesflow.surface import Surface
    X = Surface(make_shape("oblate", 8, reduced_volume=v)[None], 8).points(32)[0]
    return float(np.abs(X[:, 0]).max()), float(np.abs(X[:, 2]).max())


def scene_text(n, p, v, gap, kappa, lam):
    ex, ez = oblate_extents(v)
    nx, ny, nz = lattice_counts(n)
    sp = (2 * ex + gap, 2 * ex + gap, 2 * ez + gap)
    origin = tuple(-0.5 * (k - 1) * d for k, d in zip((nx, ny, nz), sp))
    return f"""title = "GMRES benchmark: {n} oblate vesicles"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = {p}
[time]
horizon = 1.0
dt = 0.01
[[lattice]]
count = [{nx}, {ny}, {nz}]
spacing = [{sp[0]!r}, {sp[1]!r}, {sp[2]!r}]
origin = [{origin[0]!r}, {origin[1]!r}, {origin[2]!r}]
vesicle = {{ shape = "oblate", reduced_volume = {v!r}, bending_modulus = {kappa!r}, viscosity_contrast = {lam!r} }}
"""


class Clock:
    def __init__(self):
        self.w, self.c = time.perf_counter(), time.process_time()

    def read(self):
        return time.perf_counter() - self.w, time.process_time() - self.c


def make_pc(ksp, name):
    from vesflow.precond import BlockJacobi, SphereSpectral
    pc = ksp.getPC()
    if name == "none":
        pc.setType("none")
    else:
        pc.setType("python")
        pc.setPythonContext({"bjacobi": BlockJacobi, "sphere": SphereSpectral}[name](lag=1))


def solve_with(op, b_arr, pc_name, max_it):
    """One KSP solve of op x = b as in Stepper.solve; returns a dict of measurements."""
    from petsc4py import PETSc
    n = op.N * op.block
    A = PETSc.Mat().createPython([n, n], op, comm=PETSc.COMM_SELF)
    A.setUp()
    b = A.createVecRight()
    x = A.createVecLeft()
    b.setArray(b_arr)
    x.set(0.0)
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("gmres")
    ksp.setTolerances(rtol=1e-8, max_it=max_it)
    ksp.setInitialGuessNonzero(True)
    make_pc(ksp, pc_name)
    ksp.setFromOptions()
    if pc_name != "none" and ksp.getPC().getType() != "python":
        raise SystemExit(f"PETSc options changed the {pc_name} preconditioner to {ksp.getPC().getType()}: "
                         "do not pass -pc_type to this benchmark")
    m0 = op.n_mult
    clk = Clock()
    ksp.setUp()
    setup = clk.read()
    clk = Clock()
    ksp.solve(b, x)
    solve = clk.read()
    its, reason = ksp.getIterationNumber(), ksp.getConvergedReason()
    mults = op.n_mult - m0
    xa = x.getArray().copy()
    r = b_arr - op.apply(xa)
    out = dict(its=its, reason=int(reason), setup=setup, solve=solve, mults=mults,
               relres=float(np.linalg.norm(r) / np.linalg.norm(b_arr)),
               rtol=ksp.getTolerances()[0], x=xa)
    ksp.destroy()
    A.destroy()
    return out


def fmt_t(w_c):
    return f"{w_c[0]:8.3f} {w_c[1]:8.3f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[2, 8, 64], help="numbers of vesicles")
    ap.add_argument("--degrees", type=int, nargs="+", default=[8, 16], help="spherical-harmonic degrees p")
    ap.add_argument("--pcs", nargs="+", default=list(PCS), choices=PCS)
    ap.add_argument("--v", type=float, default=0.9, help="reduced volume of the oblate vesicles")
    ap.add_argument("--gap", type=float, default=0.3, help="surface gap along the lattice axes (radius 1)")
    ap.add_argument("--kappa", type=float, default=0.1, help="bending modulus kappa_b")
    ap.add_argument("--lam", type=float, default=1.0, help="viscosity contrast (1: no double layer)")
    ap.add_argument("--dt", type=float, default=0.01, help="time step of the implicit system")
    ap.add_argument("--max-it", type=int, default=1000)
    ap.add_argument("--max-seconds", type=float, default=600.0,
                    help="skip (and estimate) a solve or a set-up predicted to take longer")
    ap.add_argument("--check", action="store_true",
                    help="also run Stepper.solve once per (N, p) and compare its iteration count with bjacobi")
    a, petsc_args = ap.parse_known_args(argv)

    import petsc4py
    petsc4py.init([sys.argv[0]] + petsc_args)
    from vesflow import sph
    from vesflow.layerpot.evaluator import Settings
    from vesflow.scene import parse_scene
    from vesflow.simulation import initial_coefficients, physics, vesicle_params
    from vesflow.stepper import Stepper
    from vesflow.surface import Surface
    from vesflow._kernels import stokes

    print(f"# OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')} (kernel threads {stokes.max_threads()}), "
          f"loadavg at start {tuple(round(x, 2) for x in os.getloadavg())}")
    print(f"# oblate v = {a.v}, gap {a.gap}, kappa_b = {a.kappa}, lambda = {a.lam}, shear rate 1, dt = {a.dt}, "
          f"q_self = q_near = q_far = 2p; PETSc args: {' '.join(petsc_args) or 'none'}")
    hdr = (f"{'N':>4} {'p':>3} {'pc':>8} {'its':>5} {'reason':>6} {'relres':>8} "
           f"{'pcset_w':>8} {'pcset_c':>8} {'solve_w':>8} {'solve_c':>8} {'it_w':>8} {'it_c':>8} {'mults':>5} {'load1':>5}")
    rows, per_ves_setup, mv_time = [], {}, {}
    for p in a.degrees:
        for n in sorted(a.sizes):
            sc = parse_scene(scene_text(n, p, a.v, a.gap, a.kappa, a.lam))
            smaller = [m for (m, pp) in per_ves_setup if pp == p and m < n]
            if smaller:
                pred = n * per_ves_setup[(max(smaller), p)]
                if pred > a.max_seconds:
                    print(f"\n## N = {n}, p = {p}: skipped, operator set-up predicted {pred:.0f} s > --max-seconds")
                    continue
            coeffs = initial_coefficients(sc)
            S = Surface(coeffs, p)
            settings = Settings(q_self=2 * p, q_far=2 * p, near_factor=1.0, backend="auto")
            st = Stepper(coeffs, p, vesicle_params(sc), physics(sc), settings)
            clk = Clock()
            lp, op = st._setup(S, a.dt)
            b = st.rhs(S, lp, op)
            opset = clk.read()
            per_ves_setup[(n, p)] = opset[0] / n
            x0 = np.random.default_rng(0).standard_normal(op.N * op.block)
            clk = Clock()
            for _ in range(3):
                op.apply(x0)
            mv = tuple(t / 3 for t in clk.read())
            mv_time[(n, p)] = mv
            npairs = 0 if lp.near is None else len(lp.near.pairs)
            backend = "none (one vesicle)" if lp.far is None else lp.far.backend
            C = sph.n_coeffs(p)
            gaps = _min_gap(S) if n > 1 else float("nan")
            print(f"\n## N = {n} ({'x'.join(map(str, lattice_counts(n)))} lattice), p = {p}: {n * 4 * C} unknowns, "
                  f"min surface gap {gaps:.3f}; far field {backend}, {npairs} near (target, vesicle) pairs")
            print(f"   operator set-up (self operators, near and far set-up, rhs): wall {opset[0]:.2f} s, cpu {opset[1]:.2f} s; "
                  f"one matvec: wall {mv[0]:.4f} s, cpu {mv[1]:.4f} s; loadavg {os.getloadavg()[0]:.2f}")
            print(hdr)
            xs = {}
            for pc in a.pcs:
                prev = [r for r in rows if r["p"] == p and r["pc"] == pc and r["N"] < n and r.get("its") is not None]
                if prev:
                    r0 = max(prev, key=lambda r: r["N"])
                    pred = (r0["its"] + 1) * mv[0] * 1.1 + r0["pcset"][0] * n / r0["N"]
                    if pred > a.max_seconds:
                        est_its = r0["its"]
                        rows.append(dict(N=n, p=p, pc=pc, its=None, est=pred, est_its=est_its))
                        print(f"{n:4d} {p:3d} {pc:>8}  skipped: predicted {pred:.0f} s (~{est_its} its as at N = {r0['N']}, "
                              f"{mv[0]:.2f} s per matvec, pc set-up {r0['pcset'][0] * n / r0['N']:.0f} s)")
                        continue
                res = solve_with(op, b, pc, a.max_it)
                its = res["its"]
                per = (res["solve"][0] / max(its, 1), res["solve"][1] / max(its, 1))
                rows.append(dict(N=n, p=p, pc=pc, its=its, pcset=res["setup"], solve=res["solve"], per=per,
                                 reason=res["reason"], relres=res["relres"], opset=opset, mv=mv))
                if res["relres"] < 1e-6:
                    xs[pc] = res["x"]
                print(f"{n:4d} {p:3d} {pc:>8} {its:5d} {res['reason']:6d} {res['relres']:8.1e} "
                      f"{fmt_t(res['setup'])} {fmt_t(res['solve'])} {per[0]:8.4f} {per[1]:8.4f} {res['mults']:5d} "
                      f"{os.getloadavg()[0]:5.2f}", flush=True)
            if len(xs) > 1:
                ref = next(iter(xs.values()))
                d = max(np.abs(x - ref).max() for x in xs.values()) / np.abs(ref).max()
                print(f"   solutions of {', '.join(xs)} (true relative residual < 1e-6) agree to {d:.1e} (max-norm, relative)")
            if a.check:
                clk = Clock()
                sol = Stepper(coeffs, p, vesicle_params(sc), physics(sc), settings).solve(a.dt)
                print(f"   check: Stepper.solve (default preconditioner) took {sol.its} iterations, "
                      f"{clk.read()[0]:.2f} s wall including its own set-up")
    print("\n# summary: iterations (time per iteration, wall s)")
    print(f"{'N':>4} {'p':>3} " + " ".join(f"{pc:>22}" for pc in a.pcs))
    for p in a.degrees:
        for n in sorted(a.sizes):
            cells = []
            for pc in a.pcs:
                r = next((r for r in rows if r["N"] == n and r["p"] == p and r["pc"] == pc), None)
                if r is None:
                    cells.append(f"{'-':>22}")
                elif r["its"] is None:
                    cells.append(f"{'(~' + str(r['est_its']) + ', est ' + format(r['est'], '.0f') + ' s)':>22}")
                else:
                    cells.append(f"{str(r['its']) + ' (' + format(r['per'][0], '.4f') + ')':>22}")
            print(f"{n:4d} {p:3d} " + " ".join(cells))
    print(f"# loadavg at end {tuple(round(x, 2) for x in os.getloadavg())}")


def _min_gap(S):
    """Smallest distance between p-grid points of different vesicles (an estimate of the gap)."""
    from scipy.spatial import cKDTree
    X = S.points()
    N = X.shape[0]
    best = np.inf
    for v in range(N):
        others = np.concatenate([X[:v], X[v + 1:]]).reshape(-1, 3)
        d, _ = cKDTree(others).query(X[v], k=1)
        best = min(best, float(d.min()))
    return best


if __name__ == "__main__":
    main()
