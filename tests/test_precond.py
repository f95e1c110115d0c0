"""Preconditioners (method reference 6): both PC python contexts solve the step system to its
true residual, and they cut GMRES iterations (block-Jacobi most, as in the paper)."""
import numpy as np
import pytest

petsc4py = pytest.importorskip("petsc4py")
petsc4py.init([])
from petsc4py import PETSc  # noqa: E402

from vesflow import shapes  # noqa: E402
from vesflow.errors import ConvergenceError  # noqa: E402
from vesflow.operator import VesicleParams  # noqa: E402
from vesflow.precond import BlockJacobi, SphereSpectral  # noqa: E402
from vesflow.stepper import Physics, Stepper  # noqa: E402
from vesflow.surface import Surface  # noqa: E402

P = 6


def _pair_system():
    c = np.stack([shapes.make_shape("oblate", P, reduced_volume=0.9, center=(-1.3, 0, 0.1)),
                  shapes.make_shape("prolate", P, reduced_volume=0.85, rotation=(0, 40, 0), center=(1.3, 0, -0.1))])
    st = Stepper(c, P, VesicleParams([0.1, 0.3], [1.0, 4.0], [0.0, 0.0]), Physics(flow="shear", flow_args={"rate": 1.0}))
    S = Surface(c, P)
    lp, op = st._setup(S, 0.01)
    return op, st.rhs(S, lp, op)


def _solve(op, b_arr, ctx):
    n = op.N * op.block
    A = PETSc.Mat().createPython([n, n], op, comm=PETSc.COMM_SELF)
    A.setUp()
    b, x = A.createVecRight(), A.createVecLeft()
    b.setArray(b_arr)
    ksp = PETSc.KSP().create(comm=PETSc.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("gmres")
    ksp.setTolerances(rtol=1e-10, max_it=500)
    ksp.getPC().setType("none" if ctx is None else "python")
    if ctx is not None:
        ksp.getPC().setPythonContext(ctx)
    ksp.solve(b, x)
    its, reason = ksp.getIterationNumber(), ksp.getConvergedReason()
    r = b.duplicate()
    A.mult(x, r)
    r.aypx(-1.0, b)
    return x.getArray().copy(), its, reason, r.norm() / b.norm()


def test_preconditioners_reach_the_true_residual_and_cut_iterations():
    op, b = _pair_system()
    out = {name: _solve(op, b, ctx) for name, ctx in
           [("none", None), ("bjacobi", BlockJacobi(lag=1)), ("sphere", SphereSpectral(lag=1))]}
    for name, (x, its, reason, relres) in out.items():
        print(f"[precond] {name}: {its} iterations, true relative residual {relres:.1e}")
        assert reason > 0 and relres < 1e-7
        assert np.abs(x - out["none"][0]).max() < 1e-6 * np.abs(out["none"][0]).max()
    assert out["bjacobi"][1] < out["sphere"][1] < out["none"][1]


def test_sphere_blocks_are_invertible():
    """A sphere's block alone is singular (constant tension exerts no force); ours is fixed."""
    op, _ = _pair_system()
    for B in SphereSpectral(lag=1).blocks(op):
        assert np.linalg.cond(B) < 1e4


def test_false_convergence_is_caught_by_the_true_residual():
    """A preconditioner that maps everything to 0 except one component makes GMRES 'converge'
    on the preconditioned residual; Stepper.solve checks the true one and raises."""
    class Broken:
        def setUp(self, pc):
            pass

        def apply(self, pc, x, y):
            y.set(0.0)
            y.setValue(0, x.getArray(readonly=True)[0])

    c = shapes.make_shape("oblate", P, reduced_volume=0.9)[None]
    st = Stepper(c, P, VesicleParams([0.1], [1.0], [0.0]), Physics(flow="shear", flow_args={"rate": 1.0}))
    st._pc_context = Broken()
    with pytest.raises(ConvergenceError, match="true relative residual|did not converge"):
        st.solve(0.01)
