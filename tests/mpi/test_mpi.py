"""The vesicle partition under `mpiexec -n 2 pytest -m mpi` (make test-mpi): every rank builds
the one-process objects too and checks that its own rows of the partitioned ones equal them."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot import evaluator
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.operator import VesicleParams
from vesflow import parallel
from vesflow.parallel import balanced_blocks, box_gaps, make_partition, morton_order, world_comm
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


@pytest.mark.parametrize("backend, own", [("direct", "smooth"), ("ewald", "smooth"), ("ewald", "subtract")])
def test_layer_potentials_rows_equal_the_one_process_ones(part, backend, own):
    S = Surface(coeffs(), P)
    st = Settings(backend=backend, fmm_eps=1e-10, ewald_own=own)
    serial = LayerPotentials(S, lam=LAM, settings=st)
    dist = LayerPotentials(S, lam=LAM, settings=st, part=part)
    assert dist.far.backend == serial.far.backend == backend
    assert dist.far.smooth_own == serial.far.smooth_own == (backend == "ewald" and own == "smooth")
    assert dist.n_near_pairs_total == serial.n_near_pairs > 0
    if backend == "direct":
        # only the near-zone surface is exchanged: the middle vesicle (0, rank 0) and the right
        # one (1, rank 1) are 0.1 apart; the left one (2) is 2.5 from the right one (h_n = 1.02)
        assert list(dist.known) == ([0, 1, 2] if part.rank == 0 else [0, 1])
        assert dist.halo.n_received == 1 and dist.halo.n_sent == 1
    # near pairs whose source vesicle lives on the other rank
    other = np.setdiff1d(np.arange(3), part.idx)
    assert np.isin(dist.near.pairs[:, 1], other).any()
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
    stats = {}
    mine = collision.contacts(Surface(c, P), 2 * P, part=part, stats=stats)
    assert part.sum(mine) == np.count_nonzero(d <= 0) > 0
    assert stats["received"] == 1          # rank 0 needs vesicle 1 only, rank 1 vesicle 0 only
    own = np.isin(pairs[:, 0] // sph.transform(P).npts, part.idx)
    assert mine == np.count_nonzero(d[own] <= 0)


def test_box_gaps_minimum_image():
    a = np.array([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]])
    b = np.array([[[8.5, 0.5, 0.0], [9.5, 1.5, 1.0]],       # x gap 7.5, overlaps in y and z
                  [[2.0, 3.0, 0.0], [3.0, 4.0, 1.0]]])      # gaps 1 (x) and 2 (y)
    assert np.allclose(box_gaps(a, b), [[7.5, np.sqrt(5.0)]])
    # period 10: the first box's image at -1.5 .. -0.5 is 0.5 from a
    assert np.allclose(box_gaps(a, b, 10.0), [[0.5, np.sqrt(5.0)]])
    assert np.allclose(box_gaps(b, a, 10.0), [[0.5], [np.sqrt(5.0)]])


def test_ring_passes_every_block(part):
    """Rank r's block is r + 1 repeated (counts[r] x 4 numbers); every rank sees every block once,
    its own first, then the left neighbour's."""
    lengths = part.counts * 4
    seen = []
    part.ring(np.full(lengths[part.rank], part.rank + 1.0), lengths,
              lambda data, r: seen.append((r, data.size, float(data.sum()))))
    want = [(r, lengths[r], float(lengths[r] * (r + 1))) for r in ((part.rank - k) % 2 for k in range(2))]
    assert seen == want


def far_apart():
    """Four vesicles 5 apart in a row: box gaps 2.6, beyond the near zone (h_n = 1.02 at p = 6)."""
    return np.stack([shapes.make_shape("oblate", P, center=(5.0 * k, 0.1 * k, 0.0), reduced_volume=0.9,
                                       rotation=(0, 10 * k, 0)) for k in range(4)])


def test_far_apart_vesicles_exchange_no_surface_and_the_ring_sums_all(part):
    c = far_apart()
    part4 = make_partition(Surface(c, P).centroid(), comm=part.comm)
    S = Surface(c, P)
    lam = [3.0, 1.0, 0.5, 2.0]
    st = Settings(backend="direct")
    serial = LayerPotentials(S, lam=lam, settings=st)
    dist = LayerPotentials(S, lam=lam, settings=st, part=part4)
    assert serial.n_near_pairs == 0 and dist.n_near_pairs_total == 0
    assert dist.halo.n_received == 0 and dist.halo.n_sent == 0 and list(dist.known) == sorted(part4.idx)
    assert len(dist.src) == 2 * dist.Tq.npts                     # sources of its own two vesicles only
    rng = np.random.default_rng(2)
    C = sph.n_coeffs(P)
    f, g = rng.standard_normal((4, 3, C)), rng.standard_normal((4, 3, C))
    want = serial.apply(f, g)[part4.idx]
    got = dist.apply(f[part4.idx], g[part4.idx])
    far_only = want - serial.self_part(f, g)[part4.idx]
    assert np.abs(far_only).max() > 1e-3 * np.abs(want).max()   # the other rank's far field counts
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    e1, e2 = serial.error_estimate(), dist.error_estimate()
    assert e2["far"] == pytest.approx(e1["far"], rel=1e-10) and e1["far"] > 0
    from vesflow import collision
    stats = {}
    assert collision.contacts(S, 2 * P, part=part4, stats=stats) == 0 and stats["received"] == 0


def test_a_missing_near_zone_surface_changes_the_rows(part, monkeypatch):
    """The check above fails if the halo leaves out the other rank's near vesicle: with a zero
    halo distance the near corrections across the rank boundary are lost."""
    class NoHalo(parallel.Halo):
        def __init__(self, part, boxes, distance, period=None):
            super().__init__(part, boxes, 0.0, period)

    S = Surface(coeffs(), P)
    st = Settings(backend="direct")
    serial = LayerPotentials(S, lam=LAM, settings=st)
    monkeypatch.setattr(evaluator, "Halo", NoHalo)
    dist = LayerPotentials(S, lam=LAM, settings=st, part=part)
    assert dist.halo.n_received == 0 and dist.n_near_pairs_total < serial.n_near_pairs
    rng = np.random.default_rng(1)
    C = sph.n_coeffs(P)
    f, g = rng.standard_normal((3, 3, C)), rng.standard_normal((3, 3, C))
    want = serial.apply(f, g)[part.idx]
    got = dist.apply(f[part.idx], g[part.idx])
    assert np.abs(got - want).max() > 1e-4 * np.abs(want).max()


def test_periodic_neighbours_across_the_face_are_exchanged(part):
    """Box of side 6: vesicle 0 at x = 1.25, vesicle 1 at x = 4.85, 3.6 apart directly (box gap
    1.23 > h_n = 1.02) but 2.4 through the face x = 0 (box gap 0.03): the minimum image makes
    each rank receive the other's surface, for the collision check (distance h_n) and the layer
    potentials (Ewald, real-space cutoff), whose rows equal the one-process rows."""
    c = np.stack([shapes.make_shape("oblate", P, center=(x, 3.0, 3.0), reduced_volume=0.9) for x in (1.25, 4.85)])
    S = Surface(c, P)
    part2 = make_partition(S.centroid(), comm=part.comm)
    assert part2.n_local == 1
    from vesflow import collision
    stats = {}
    collision.contacts(S, 2 * P, 6.0, part=part2, stats=stats)
    assert stats["received"] == 1
    st = Settings(backend="ewald", fmm_eps=1e-10, period=6.0, ewald_own="smooth")
    serial = LayerPotentials(S, lam=[1.0, 0.5], settings=st)
    dist = LayerPotentials(S, lam=[1.0, 0.5], settings=st, part=part2)
    assert dist.far.smooth_own and serial.far.smooth_own
    assert dist.halo.n_received == 1 and dist.n_near_pairs_total == serial.n_near_pairs > 0
    rng = np.random.default_rng(3)
    C = sph.n_coeffs(P)
    f, g = rng.standard_normal((2, 3, C)), rng.standard_normal((2, 3, C))
    want = serial.apply(f, g)[part2.idx]
    got = dist.apply(f[part2.idx], g[part2.idx])
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_ewald_holds_the_sources_within_its_real_space_cutoff(part):
    """125 vesicles 3 apart at p = 4, Ewald at 1e-4 (real-space cutoff 5.6, less than half the
    lattice's extent of 12.0 + 2.4; the 4 x 4 x 4 lattice of 64 takes pure real space since the
    vectorized real-space kernel of issue 17): each rank holds its vesicles and the other
    rank's within the cutoff only, and its rows equal the one-process rows (the real-space sum
    stops at the cutoff; the Fourier part is spread from each rank's own sources)."""
    p, n = 4, 125
    c = np.stack([shapes.make_shape("oblate", p, center=(3.0 * i, 3.0 * j, 3.0 * k), reduced_volume=0.9)
                  for i in range(5) for j in range(5) for k in range(5)])
    S = Surface(c, p)
    partn = make_partition(S.centroid(), comm=part.comm)
    lam = np.where(np.arange(n) % 3 == 0, 0.5, 1.0)
    st = Settings(backend="ewald", fmm_eps=1e-4)
    serial = LayerPotentials(S, lam=lam, settings=st)
    dist = LayerPotentials(S, lam=lam, settings=st, part=partn)
    rc = dist.far.ewald.params.rc
    assert rc == serial.far.ewald.params.rc and rc < 0.5 * (12.0 + 2.4)
    others = n - partn.n_local
    assert 0 < dist.halo.n_received < others and part.sum(dist.halo.n_received) == part.sum(dist.halo.n_sent)
    rng = np.random.default_rng(4)
    C = sph.n_coeffs(p)
    f, g = rng.standard_normal((n, 3, C)), rng.standard_normal((n, 3, C))
    want = serial.apply(f, g)[partn.idx]
    got = dist.apply(f[partn.idx], g[partn.idx])
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()


def test_fmm_holds_every_surface(part):
    """fmm sums over gathered sources: the halo is every vesicle (an Alltoallv of all), and the
    rows equal one process's at the FMM's accuracy (its tree depends on the targets)."""
    pytest.importorskip("fmm3dpy")
    S = Surface(coeffs(), P)
    st = Settings(backend="fmm", fmm_eps=1e-10)
    serial = LayerPotentials(S, lam=LAM, settings=st)
    dist = LayerPotentials(S, lam=LAM, settings=st, part=part)
    assert dist.far.backend == "fmm" and list(dist.known) == [0, 1, 2]
    rng = np.random.default_rng(1)
    C = sph.n_coeffs(P)
    f, g = rng.standard_normal((3, 3, C)), rng.standard_normal((3, 3, C))
    want = serial.apply(f, g)[part.idx]
    got = dist.apply(f[part.idx], g[part.idx])
    assert np.abs(got - want).max() <= 1e-8 * np.abs(want).max()
