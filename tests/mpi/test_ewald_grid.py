"""The distributed Ewald grid (vesflow/layerpot/ewald_grid.py) over the ranks, under
`mpiexec -n 2 pytest -m mpi tests/mpi/test_ewald_grid.py` (any rank count >= 2: every rank
checks its rows against the one-process sum it computes itself)."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.layerpot import ewald
from vesflow.layerpot.evaluator import LayerPotentials, Settings
from vesflow.parallel import make_partition, world_comm
from vesflow.surface import Surface

pytestmark = pytest.mark.mpi


@pytest.fixture(scope="module")
def comm():
    c = world_comm()
    if c.Get_size() < 2:
        pytest.skip("run under mpiexec -n 2 (or more)")
    return c


def clusters(period):
    """16 clusters ("vesicles") of 50 sources and 30 targets, radius 0.4, in a box of side 5
    (periodic: some across a face); the same on every rank (seeded)."""
    rng = np.random.default_rng(7)
    c = rng.uniform(0, 5.0, (16, 3)) + (0.0 if period else 20.0)
    src = (c[:, None] + 0.4 * rng.uniform(-1, 1, (16, 50, 3))).reshape(-1, 3)
    trg = (c[:, None] + 0.4 * rng.uniform(-1, 1, (16, 30, 3))).reshape(-1, 3)
    dens = [rng.standard_normal(src.shape) for _ in range(3)]
    return c, src, trg, dens


@pytest.mark.parametrize("period", [5.0, None])
def test_rows_of_the_split_grid_equal_the_one_process_rows(comm, period):
    """Each rank spreads its own clusters (Morton partition) into its box, the slabs are
    exchanged: its targets' Fourier part (single, double, both layers) equals the
    one-process distributed one to 1e-12 and the replicated (NUFFT) one to the tolerance;
    every rank's grid is a slab, the ranks send bytes."""
    c, src, trg, (f, nw, g) = clusters(period)
    part = make_partition(c, comm=comm)
    sid, tid = np.repeat(np.arange(16), 50), np.repeat(np.arange(16), 30)
    mine_s = np.flatnonzero(np.isin(sid, part.idx))
    mine_t = np.flatnonzero(np.isin(tid, part.idx))
    p = ewald.choose_params(1e-8, np.concatenate([src, trg]), period, len(src), len(trg), 1, 9)
    one = ewald.EwaldSum(src, sid, trg, tid, period=period, params=p, threads=1, grid="distributed")
    rep = ewald.EwaldSum(src, sid, trg, tid, period=period, params=p, threads=1)
    # this rank: all sources known (the real space), its own spread, its own targets
    dist = ewald.EwaldSum(src, sid, trg[mine_t], tid[mine_t], period=period, params=p, threads=1,
                          spread=(part, mine_s), grid="distributed")
    d = dist._dist
    assert d.c.size == comm.Get_size() and d.z1 - d.z0 < d.n[2]
    for dens in [dict(f_w=f), dict(nw=nw, g=g), dict(f_w=f, nw=nw, g=g)]:
        want = one.fourier(**dens)[mine_t]
        got = dist.fourier(**dens)
        scale = np.abs(want).max()
        assert np.abs(got - want).max() <= 1e-12 * scale
        assert np.abs(got - rep.fourier(**dens)[mine_t]).max() <= 1e-8 * scale
    assert comm.allreduce(d.bytes_sent) > 0


def test_layer_potentials_with_the_distributed_grid(comm):
    """The layer potentials of a periodic box (Ewald, -ves_ewald_grid distributed): a rank's
    rows equal the one-process rows to 1e-12."""
    P = 4
    cen = [(1.5 + 3.0 * i, 1.6 + 3.0 * j, 1.4 + 3.0 * k) for i in range(2) for j in range(2) for k in range(2)]
    co = np.stack([shapes.make_shape("oblate", P, center=x, reduced_volume=0.9, rotation=(0, 10 * n, 0))
                   for n, x in enumerate(cen)])
    S = Surface(co, P)
    part = make_partition(S.centroid(), comm=comm)
    lam = [1.0, 0.5] * 4
    st = Settings(backend="ewald", fmm_eps=1e-8, period=6.0, ewald_own="subtract", ewald_grid="distributed")
    serial = LayerPotentials(S, lam=lam, settings=st)
    dist = LayerPotentials(S, lam=lam, settings=st, part=part)
    assert dist.far.ewald._dist is not None and dist.far.ewald._dist.c.size == comm.Get_size()
    rng = np.random.default_rng(5)
    C = sph.n_coeffs(P)
    fc, gc = rng.standard_normal((8, 3, C)), rng.standard_normal((8, 3, C))
    want = serial.apply(fc, gc)[part.idx]
    got = dist.apply(fc[part.idx], gc[part.idx])
    assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
