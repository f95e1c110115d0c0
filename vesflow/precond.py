"""Preconditioners as PC python contexts (method reference 6).

    -pc_type python -pc_python_type vesflow.precond.BlockJacobi    dense LU of each vesicle's self block
    -pc_type python -pc_python_type vesflow.precond.SphereSpectral the block of a sphere of the same size

Both find the StepOperator through the operator matrix (`pc.getOperators()[0].getPythonContext()`),
factor once per step in setUp, and apply per vesicle.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import lu_factor, lu_solve


class _PerVesicle:
    """Shared machinery: one dense LU per vesicle, factored in setUp.

    The factors may be reused for `lag` solves (option -ves_pc_lag, default 5; 1 = refactor every
    solve) while dt and the number of vesicles are unchanged: a preconditioner only has to be
    close to the operator, and the geometry changes little between steps.
    """

    def __init__(self, lag=None):
        self.lag = lag
        self.age = None
        self.key = None

    def setUp(self, pc):
        A, _ = pc.getOperators()
        op = A.getPythonContext()
        self.op = op
        if self.lag is None:
            from petsc4py import PETSc
            self.lag = max(1, PETSc.Options().getInt("ves_pc_lag", 5))
        key = (op.N, op.p, int(np.round(np.log2(op.dt))) if op.dt > 0 else None)   # dt within a factor ~1.4
        cache = self.__dict__.setdefault("cache", {})
        if key in cache and cache[key][1] < self.lag:
            self.lu, age = cache[key]
            cache[key] = (self.lu, age + 1)
            return
        self.lu = [lu_factor(B, check_finite=False) for B in self.blocks(op)]
        if len(cache) >= 3:
            cache.clear()
        cache[key] = (self.lu, 1)

    def apply(self, pc, x, y):
        xa = x.getArray(readonly=True).reshape(self.op.N, self.op.block)
        out = np.empty_like(xa)
        for v, lu in enumerate(self.lu):
            out[v] = lu_solve(lu, xa[v], check_finite=False)
        y.setArray(out.ravel())

    def view(self, pc, viewer):
        viewer.printfASCII(f"vesflow {type(self).__name__}: {len(getattr(self, 'lu', []))} dense LU blocks\n")


TENSION_MODE_WEIGHT = 3.0    # |c| / (the block's estimate of the tension Schur complement scale)


def regularize_tension_mode(B, C):
    """The self block B (4C x 4C: velocity 3C component-major, then tension C; the constant
    tension at 3C, the n = 0 divergence row at 3C) with its constant-tension mode regularized:
    B + c e e^T, e = e_{3C}, c < 0 (docs/dynamics.md, "Spheres and near-spheres").

    A constant tension on a closed surface exerts 2 H sigma n, and the single layer of n
    vanishes on and off a closed surface: on a sphere (H constant) that column is zero, and the
    row combination "n = 0 divergence minus the flux of the velocity rows" is zero too (its left
    null vector).  Near a sphere the block's smallest singular value is O(1 - v) (measured,
    p = 8: 2.5e-4 at v = 0.999, 2.2e-3 at 0.99, 8.8e-3 at 0.95); it is the only small one (the
    next, tension degree 1, is ~0.1).  The tension Schur complement -div (B_uu)^-1 B_u,sigma
    is negative (semi)definite (a tension does negative work on the area), so adding c < 0 at
    (3C, 3C) keeps it definite for every shape and makes a sphere's block regular; c is the
    scale of that Schur complement in the next tension mode, estimated from the block:
    |c| = 3 max|B_d0,u| max|B_u,sigma| / max|B_uu| (its degree-1 eigenvalue is 2.7-5.4 times the
    product, measured over R, kappa, lambda, mu, dt).  The cost: the preconditioned operator
    gets the eigenvalue 1 / (1 + c gamma), gamma = (B^-1)_{3C,3C}, in this one mode (0 for a
    sphere, where the operator itself is singular: the sphere's constant tension is free).
    """
    i0 = 3 * C
    scale = np.abs(B[i0, :i0]).max() * np.abs(B[:i0, i0:]).max() / max(np.abs(B[:i0, :i0]).max(), 1e-300)
    out = np.array(B, dtype=float, copy=True)
    out[i0, i0] -= TENSION_MODE_WEIGHT * scale
    return out


class BlockJacobi(_PerVesicle):
    """Inverse of the block diagonal: each vesicle with itself (the paper's better choice), its
    constant-tension mode regularized (`regularize_tension_mode`)."""

    def blocks(self, op):
        return [regularize_tension_mode(op.self_block(v), op.C) for v in range(op.N)]


class SphereSpectral(_PerVesicle):
    """The self block of a sphere with each vesicle's area, bending modulus and contrast.

    On a sphere the operator is diagonal in the degree n (the spectrum the paper's analytic
    preconditioner uses); we assemble it once per distinct (radius, kappa, lambda) with the same
    machinery as BlockJacobi and reuse it, which is cheaper than per-vesicle blocks when many
    vesicles share their properties.

    The sphere's block is singular: a constant tension exerts no force on a sphere (its
    column is zero) and the mean normal velocity enters only the n = 0 divergence row.  Left
    as is, the LU "solves" with an exploding or arbitrary tension mode and GMRES reports
    convergence after one iteration at a true residual of 0.99 (measured, 2 vesicles, p = 8).
    `regularize_tension_mode` makes it invertible, as for BlockJacobi.
    """

    def blocks(self, op):
        from .layerpot.singular import SelfOperators
        from .operator import StepOperator, VesicleParams
        from .shapes import make_shape
        from .surface import Surface
        radii = op.surface.effective_radius()
        cache, out = {}, []
        for v in range(op.N):
            key = (round(float(radii[v]), 12), float(op.params.kappa[v]), float(op.params.lam[v]))
            if key not in cache:
                S = Surface(make_shape("sphere", op.p, radius=key[0])[None], op.p)
                lp = _SelfOnly(SelfOperators(S.coeffs, op.p, op.lp.q_self, True, op.lp.want_double, op.params.mu),
                               op.lp.want_double, np.array([key[2]]))
                prm = VesicleParams([key[1]], [key[2]], [0.0], op.params.mu)
                B = StepOperator(S, prm, op.dt, lp, op.q_force).self_block(0)
                cache[key] = regularize_tension_mode(B, op.C)
            out.append(cache[key])
        return out


class _SelfOnly:
    """The part of LayerPotentials that self_block needs."""

    def __init__(self, self_ops, want_double, lam):
        self.self_ops, self.want_double, self.lam = self_ops, want_double, lam
