"""The vesicle partition under `mpiexec -n 2 pytest -m mpi` (make test-mpi): every rank builds
the one-process objects too and checks that its own rows of the partitioned ones equal them."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.operator import VesicleParams
from vesflow.parallel import balanced_blocks, make_partition, morton_order, world_comm
from vesflow.stepper import Physics, Stepper
from vesflow.surface import Surface

pytestmark = pytest.mark.mpi

P = 6
# scene order is not the Morton order: the middle vesicle first; gaps ~0.1 (near pairs between ranks)
CENTERS = [(0.0, 0.0, 0.0), (2.45, 0.0, 0.1), (-2.45, 0.1, 0.0)]
LAM = [3.0, 1.0, 0.5]


def coeffs():
    return np.stack([shapes.make_shape("oblate", P, center=c, reduced_volume=0.9, rotation=(0, 10 * k, 0))
                     for k, c in enumerate(CENTERS)])


@pytest.fixture(scope="module")
def part():
    comm = world_comm()
    if comm.Get_size() != 2:
        pytest.skip("run under mpiexec -n 2")
    return make_partition(Surface(coeffs(), P).centroid(), comm=comm)


def test_morton_order_and_balanced_blocks():
    x = np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    assert list(morton_order(x)) == [1, 3, 2, 0]             # bits interleaved x, y, z from the lowest
    assert list(balanced_blocks(np.ones(3), 2)) == [0, 2, 3]
    assert list(balanced_blocks([1.0, 1.0, 1.0, 3.0], 2)) == [0, 3, 4]


def test_partition_and_gather(part):
    # Morton order of the row: left (2), middle (0), right (1); rank 0 the first two
    assert list(part.order) == [2, 0, 1] and list(part.counts) == [2, 1]
    assert list(part.idx) == ([2, 0] if part.rank == 0 else [1])
    local = np.stack([np.full((2, 3), 10.0 * v) for v in part.idx])
    full = part.gather(local)
    assert full.shape == (3, 2, 3) and np.array_equal(full[:, 0, 0], [0.0, 10.0, 20.0])
    assert part.max(part.rank) == 1.0 and part.sum(1) == 2 and part.any(part.rank == 1)


@pytest.mark.parametrize("backend", ["direct", "ewald"])
def test_layer_potentials_rows_equal_the_one_process_ones(part, backend):
    S = Surface(coeffs(), P)
    st = Settings(backend=backend, fmm_eps=1e-10)
    serial = LayerPotentials(S, lam=LAM, settings=st)
    dist = LayerPotentials(S, lam=LAM, settings=st, part=part)
    assert dist.far.backend == serial.far.backend == backend
    assert dist.n_near_pairs_total == serial.n_near_pairs > 0
    # near pairs whose source vesicle lives on the other rank
    other = np.setdiff1d(np.arange(3), part.idx)
    assert np.isin(dist.near["pairs"][:, 1], other).any()
    rng = np.random.default_rng(1)
    C = sph.n_coeffs(P)
    f, g = rng.standard_normal((3, 3, C)), rng.standard_normal((3, 3, C))
    want = serial.apply(f, g)[part.idx]
    got = dist.apply(f[part.idx], g[part.idx])
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    e1, e2 = serial.error_estimate(), dist.error_estimate()
    for k in e1:
        assert e2[k] == pytest.approx(e1[k], rel=1e-10, abs=1e-14)


def test_solve_on_two_ranks_equals_one_process(part):
    params = VesicleParams([0.1] * 3, LAM, [0.0] * 3)
    phys = Physics("shear", {"rate": 1.0})
    one = Stepper(coeffs(), P, params, phys, Settings(backend="direct"))
    two = Stepper(coeffs(), P, params, phys, Settings(backend="direct"), part=part)
    for st in (one, two):
        st.step(0.05)
        st.step(0.05)
    assert two.last.its == one.last.its
    assert np.abs(two.coeffs - one.coeffs).max() <= 1e-12
    assert np.abs(two.last.sigma - one.last.sigma).max() <= 1e-10 * np.abs(one.last.sigma).max()


def test_contacts_across_ranks_sum_to_the_one_process_count(part):
    """Vesicle 1 (rank 1) pushed into vesicle 0 (rank 0): each rank counts its own points
    behind another surface, with the other rank's surfaces gathered."""
    from vesflow import collision
    c = coeffs()
    c[1, 0, 0] -= 0.3 * np.sqrt(4 * np.pi)        # 0.3 closer in x (degree-0 coefficient)
    S = Surface(c, P)
    pairs, d = collision.signed_gaps(S, 2 * P)
    mine = collision.contacts(Surface(c, P), 2 * P, part=part)
    assert part.sum(mine) == np.count_nonzero(d <= 0) > 0
    own = np.isin(pairs[:, 0] // sph.transform(P).npts, part.idx)
    assert mine == np.count_nonzero(d[own] <= 0)
