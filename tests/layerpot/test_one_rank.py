"""A serial run is the one-rank case of the vesicle partition (vesflow.parallel.Partition.single):
its collectives return their argument, its halo holds the rank's own vesicles as they are, and
the layer potentials take the same code as over MPI ranks (tests/mpi/test_mpi.py for several)."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot import ewald
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.layerpot.far import FarField
from vesflow.layerpot.groups import group_by_vesicle
from vesflow.layerpot.near import NearPairs
from vesflow.parallel import Halo, Partition, make_partition, vesicle_boxes
from vesflow.surface import Surface
from vesflow.timing import NullTimers, Timers

P = 6
CENTERS = [(0.0, 0.0, 0.0), (2.45, 0.0, 0.1), (-2.45, 0.1, 0.0)]


def pair_surface():
    return Surface(np.stack([shapes.make_shape("oblate", P, center=c, reduced_volume=0.9, rotation=(0, 10 * k, 0))
                             for k, c in enumerate(CENTERS)]), P)


class _OneProcess:
    def Get_size(self):
        return 1


def test_the_one_rank_partition_and_its_collectives():
    part = Partition.single(3)
    assert (part.rank, part.size, part.n_local) == (0, 1, 3) and list(part.idx) == [0, 1, 2]
    local = np.arange(12.0).reshape(3, 2, 2)
    assert np.array_equal(part.gather(local), local)
    assert part.max(2.5) == 2.5 and part.sum(7) == 7 and part.any(False) is False and part.any(1) is True
    a = np.ones(4)
    assert part.allreduce_inplace(a) is a and np.array_equal(a, np.ones(4))
    assert part.alltoall([[5, 6]]) == [[5, 6]] and list(part.owner()) == [0, 0, 0]
    seen = []
    part.ring(np.arange(6.0), [6], lambda data, r: seen.append((r, data.copy())))
    assert len(seen) == 1 and seen[0][0] == 0 and np.array_equal(seen[0][1], np.arange(6.0))
    with pytest.raises(ValueError, match="lengths"):
        part.ring(np.arange(6.0), [5], lambda data, r: None)
    # make_partition with one process is this partition (scene order, no Morton reordering)
    one = make_partition(np.array([[3.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0]]), comm=_OneProcess())
    assert one.size == 1 and list(one.idx) == [0, 1, 2]


def test_the_one_rank_halo_returns_the_rows_as_they_are():
    S = pair_surface()
    part = Partition.single(3)
    halo = Halo(part, part.gather(vesicle_boxes(S.points(2 * P), S.points())), 0.5)
    assert list(halo.known) == [0, 1, 2] and halo.n_received == 0 and halo.n_sent == 0
    x = np.ascontiguousarray(S.points(2 * P))
    assert halo.exchange(x) is x                                     # no copy
    u, w = np.ones((3, 3, 4)), np.zeros((3, 5))
    got = halo.exchange_rows(u, w)
    assert got[0] is u and got[1] is w


def test_layer_potentials_of_a_serial_run_hold_the_one_rank_partition():
    S = pair_surface()
    timers = Timers(use_petsc=False)
    lp = LayerPotentials(S, lam=[3.0, 1.0, 0.5], settings=Settings(backend="direct"), timers=timers)
    assert lp.part.size == 1 and list(lp.known) == [0, 1, 2] and lp.halo.n_received == 0
    assert lp.local is S                                             # its cached geometry is reused
    assert lp.n_near_pairs_total == lp.n_near_pairs > 0
    C = sph.n_coeffs(P)
    rng = np.random.default_rng(2)
    f, g = rng.standard_normal((2, 3, 3, C))
    lp.apply(f, g)
    for stage in ("self_setup", "near_setup", "far_setup", "gather", "self", "far", "near"):
        assert timers.counts.get(stage, 0) >= 1, stage
    # the one-rank ring (direct far field) is the plain direct sum over the other vesicles
    fw, gq = lp._densities(f, g)
    plain = FarField(lp.src, lp.src_id, lp.trg, lp.trg_id, backend="direct").evaluate(fw, lp.src_nw, gq)
    assert lp.far.ring is lp.part
    assert np.array_equal(lp._far_evaluate(fw, gq), plain)


def test_near_pairs_of_the_set_up():
    S = pair_surface()
    lp = LayerPotentials(S, lam=0.5, settings=Settings(backend="direct", near_blend=0.5))
    near = lp.near
    assert isinstance(near, NearPairs) and len(near.pairs) == lp.n_near_pairs > 0
    assert np.array_equal(near.blocks[:, 0], near.tpos)             # each block starts at its target
    assert np.array_equal(near.rows, np.searchsorted(lp.known, near.pairs[:, 1]))
    assert np.allclose(near.weights.sum(axis=1), 1.0, atol=1e-10)   # Lagrange weights reproduce constants
    assert np.all(np.abs(near.projection.signed_distance) < lp.h[near.pairs[:, 1]] * 1.5)
    assert near.blend is not None and np.all((near.blend >= 0) & (near.blend <= 1))
    assert np.array_equal(near.side, np.where(near.projection.signed_distance >= 0, 1.0, -1.0))
    # a single free vesicle has no near field at all
    one = LayerPotentials(Surface(S.coeffs[:1], P))
    assert one.near is None and one.n_near_pairs == 0 and one.far is None
    assert one.contacts()[0].shape == (0, 2)


def test_null_timers_record_nothing():
    t = NullTimers()
    with t.stage("self"):
        pass
    t.count("solve")
    assert t.counts == {} and t.as_dict()["total"] == 0.0
    r = Timers(use_petsc=False)
    with r.stage("self"):
        pass
    assert r.counts == {"self": 1}


def test_ewald_spread_of_every_source_uses_the_plan_of_all_of_them(rng):
    src = rng.uniform(0, 3, (60, 3))
    sid = np.repeat(np.arange(6), 10)[rng.permutation(60)]
    trg = rng.uniform(0, 3, (40, 3))
    tid = np.repeat(np.arange(4), 10)
    f = rng.standard_normal((60, 3))
    plain = ewald.EwaldSum(src, sid, trg, tid, tol=1e-8, period=3.0)
    spread = ewald.EwaldSum(src, sid, trg, tid, params=plain.params, period=3.0,
                            spread=(Partition.single(6), slice(0, 60)))
    assert spread._spread[1] is None and spread._spread[2] is spread._nufft
    assert np.array_equal(spread.evaluate(f), plain.evaluate(f))


def test_sources_grouped_by_vesicle():
    src = np.arange(15.0).reshape(5, 3)
    grp = group_by_vesicle(src, np.array([4, 2, 4, 9, 2]), np.array([2, 7, 9, 4]))
    assert list(grp.perm) == [1, 4, 0, 2, 3] and list(grp.sid) == [2, 2, 4, 4, 9]
    assert list(grp.ids) == [2, 4, 9] and list(grp.off) == [0, 2, 4, 5]
    assert list(grp.trg_vi) == [0, -1, 2, 1]
    assert np.array_equal(grp.src, src[[1, 4, 0, 2, 3]]) and np.array_equal(grp.sorted(src[:, 0]), [3, 12, 0, 6, 9])
    done = group_by_vesicle(src, np.array([0, 0, 1, 1, 1]), np.array([1]))
    assert done.perm is None and done.src is src
