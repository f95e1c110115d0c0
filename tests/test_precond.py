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


@pytest.mark.parametrize("lam", [1.0, 4.0])
def test_self_block_from_force_matrices_equals_the_operator_applied_to_unit_vectors(lam):
    """StepOperator.self_block (force maps as matrices, issue 16) is the operator's own block:
    equal to applying membrane_force, the self layer potentials and the divergence to every
    unit vector (self_block_by_columns), and its parts recombine at any dt."""
    from vesflow.operator import block_at
    c = np.stack([shapes.make_shape("prolate", P, reduced_volume=0.8, rotation=(20, 40, 60)),
                  shapes.make_shape("oblate", P, reduced_volume=0.7, center=(2.5, 0, 0))])
    st = Stepper(c, P, VesicleParams([0.1, 0.3], [lam, lam], [0.0, 0.0]))
    lp, op = st._setup(Surface(c, P), 0.03)
    for v in range(2):
        ref = op.self_block_by_columns(v)
        new = op.self_block(v)
        assert np.abs(new - ref).max() < 1e-11 * np.abs(ref).max()
        A0, SMb = op.self_block_parts(v)
        op.dt = 0.2
        assert np.allclose(block_at(A0, SMb, 0.2), op.self_block_by_columns(v), rtol=0, atol=1e-11 * np.abs(ref).max())
        op.dt = 0.03


def test_block_preconditioner_is_reused_until_the_iterations_grow():
    """The parts are kept across solves (other geometry, other dt) while the iterations stay
    within REFRESH_FACTOR x the first + REFRESH_SLACK; a failed or slow solve rebuilds them."""
    from vesflow import precond
    op, b = _pair_system()
    ctx = BlockJacobi(lag=100)
    _, its0, _, _ = _solve(op, b, ctx)
    assert ctx.rebuilds == 1 and ctx.base_its is None       # _solve does not report: Stepper does
    ctx.observe(its0)
    ctx.observe(its0 + 1)
    _solve(op, b, ctx)
    assert ctx.rebuilds == 1 and len(ctx.factors) == 1
    op.dt *= 1.2                                             # within DT_MATCH: same factors
    _solve(op, b, ctx)
    assert len(ctx.factors) == 1
    op.dt *= 2.0                                             # a new dt: new factors, same parts
    _solve(op, b, ctx)
    assert ctx.rebuilds == 1 and len(ctx.factors) == 2
    ctx.observe(int(precond.REFRESH_FACTOR * its0 + precond.REFRESH_SLACK) + 1)
    _solve(op, b, ctx)
    assert ctx.rebuilds == 2 and len(ctx.factors) == 1
    ctx.observe(3, failed=True)
    _solve(op, b, ctx)
    assert ctx.rebuilds == 3


def test_preconditioner_rebuilds_are_the_same_in_every_run():
    """The reuse rule prices a rebuild by the cost model, not a clock: two runs of the same
    scene rebuild at the same solves and take the same iterates (restarts rely on it)."""
    from .harness import pair_scene, simulate
    text = pair_scene(1.3, 0.2, 6, 1.0, dt=0.05, every=0.5)
    runs = [simulate(text, ves_adapt="none") for _ in range(2)]
    its = [[r[3] for r in rec.steps] for _, rec in runs]
    assert its[0] == its[1] and len(its[0]) == 20
    assert runs[0][0].stepper._pc_context.rebuilds == runs[1][0].stepper._pc_context.rebuilds >= 1
    c0, c1 = (run.stepper.coeffs for run, _ in runs)
    assert np.array_equal(c0, c1)
