"""Memory per vesicle (docs/explanation/parallel.md, "Memory"): what a stepper keeps after its
set-up, counted from the arrays it holds (memory_model.held_memory), against the model of `vesflow
check` (memory_model.memory_per_vesicle); the preconditioner's memory options; old layer potentials
freed before new ones are built; the memory-aware choice and refusal of run and check."""
import gc
import os
import subprocess
import sys
import weakref

import numpy as np
import pytest

petsc4py = pytest.importorskip("petsc4py")
petsc4py.init([])

from vesflow import costs, memory_model, options as O, scene as S, shapes  # noqa: E402
from vesflow.errors import NumericalFailure  # noqa: E402
from vesflow.operator import StepOperator, VesicleParams, block_at  # noqa: E402
from vesflow.precond import BlockJacobi, BlockParts  # noqa: E402
from vesflow.stepper import Physics, Stepper  # noqa: E402
from vesflow.surface import Surface  # noqa: E402
from tests.harness import ROOT  # noqa: E402

P = 6
C = (P + 1) ** 2 - 1


def _pair(lam=1.0):
    c = np.stack([shapes.make_shape("oblate", P, reduced_volume=0.9, center=(-1.3, 0, 0.1)),
                  shapes.make_shape("prolate", P, reduced_volume=0.85, rotation=(0, 40, 0), center=(1.3, 0, -0.1))])
    return c, VesicleParams([0.1, 0.3], [lam, lam], [0.0, 0.0])


def _stepper(lam=1.0, **pc):
    c, prm = _pair(lam)
    return Stepper(c, P, prm, Physics(flow="shear", flow_args={"rate": 1.0}), **pc)


def test_held_bytes_per_vesicle_after_the_set_up_are_the_arrays_of_the_model():
    """After one euler step with doubling (dt, then two dt / 2): one set of layer potentials (its
    self operator 3C x 3C), the compact parts (15 C^2), two LU sets ((4C)^2 + 4C pivots each),
    exactly as memory_model.memory_per_vesicle counts them; with a contrast the parts keep the velocity
    block (24 C^2) and D doubles the self operators."""
    for lam, parts_c2, n_ops in ((1.0, 15, 1), (4.0, 24, 2)):
        st = _stepper(lam)
        st.solve(0.02)
        st.step(0.01)
        held = memory_model.held_memory(st)
        N = 2
        assert held["layer_potentials"] == 1
        assert held["self"] == N * n_ops * (3 * C) ** 2 * 8
        assert held["pc_parts"] == N * parts_c2 * C ** 2 * 8
        assert held["pc_factors"] == N * 2 * ((4 * C) ** 2 * 8 + 4 * C * 4)
        model = memory_model.memory_per_vesicle(P, 2 * P, {"ts_type": "euler", "adapt": "doubling"}, double_layer=lam != 1)
        for k in ("self", "pc_parts", "pc_factors"):
            assert model[k] == held[k] / N, k


def test_compact_parts_give_the_blocks_entry_for_entry():
    for lam in (1.0, 4.0):
        st = _stepper(lam)
        lp, op = st._setup(st.surface, 0.03)
        for v in range(2):
            A0, SMb = op.self_block_parts(v)
            parts = BlockParts(A0, SMb)
            assert (parts.uu is None) == (lam == 1.0)
            for dt in (0.0, 0.03, 0.2):
                assert np.array_equal(parts.at(dt), block_at(A0, SMb, dt))
            assert parts.nbytes == (15 if lam == 1.0 else 24) * C ** 2 * 8


def test_fewer_factor_sets_and_dropped_parts():
    """-ves_pc_factors 1 keeps one LU set (a new dt replaces it); -ves_pc_parts drop keeps no
    parts, and a new dt rebuilds the blocks from the current geometry."""
    st = _stepper(pc_factors=1, pc_parts="drop")
    st.solve(0.02)
    ctx = st.default_pc_context()
    assert len(ctx.factors) == 1 and ctx.parts is None and ctx.rebuilds == 1
    assert memory_model.held_memory(st)["pc_parts"] == 0
    st.solve(0.01)                    # outside DT_MATCH: new blocks, one set kept
    assert len(ctx.factors) == 1 and ctx.factors[0][0] == 0.01 and ctx.rebuilds == 2
    st.solve(0.011)                   # within DT_MATCH: reused
    assert ctx.rebuilds == 2
    with pytest.raises(ValueError, match="pc factors = 4"):
        BlockJacobi(factors=4)


def test_old_layer_potentials_are_freed_before_the_new_ones_are_built():
    """The stepper's cache, its last solve, the Mat's operator and the preconditioner do not
    keep the layer potentials of an older surface alive (the preconditioner remembers its
    geometry by a weak reference and the coefficients)."""
    st = _stepper()
    st.step(0.01)
    first = weakref.ref(st.lp_last)
    seen = []
    from vesflow.layerpot import evaluator
    orig = evaluator.LayerPotentials.__init__

    def spy(self, *a, **k):
        gc.collect()
        seen.append(first() is None)
        orig(self, *a, **k)
    evaluator.LayerPotentials.__init__ = spy
    try:
        st.step(0.01)
    finally:
        evaluator.LayerPotentials.__init__ = orig
    assert seen == [True]
    rec = st.preconditioner_state()
    assert rec["built"] == 1 and rec["coeffs"].shape == st.coeffs.shape


def test_sdc_holds_two_sets_of_layer_potentials_and_sets_up_as_before():
    """sdc (3 Radau nodes, 2 sweeps) pins the step's start: 2 sets of layer potentials held, and
    6 set-ups per step (X_0, the 2 provisional nodes, the 3 sweep geometries), the count of a
    cache of 3."""
    from vesflow.stepping.sdc import SDC
    st = _stepper()
    sdc = SDC(st, nodes=3, sweeps=2, quadrature="radau")
    sdc.step(0.01)
    assert st.timers.counts["self_setup"] == 6
    assert memory_model.held_memory(st)["layer_potentials"] == 2
    assert memory_model.layer_potentials_held({"ts_type": "sdc"}) == 2 and memory_model.factor_sets({"ts_type": "sdc"}) == 3


def _scene(n=2):
    text = "[discretization]\np = 8\n[time]\nhorizon = 0.02\ndt = 0.01\n" + "".join(
        f"[[vesicle]]\nshape = 'oblate'\nreduced_volume = 0.8\ncenter = [{3 * k}, 0, 0]\n" for k in range(n))
    return S.parse_scene(text)


def test_memory_aware_choice_and_refusal():
    sc = _scene()
    opts = O.read_options(O.dict_getter({}), sc)
    est = costs.estimate(sc, opts)
    need = est.memory_peak
    # enough memory: nothing changes
    o, line = costs.fit_memory(sc, opts.replaced({"memory_limit": 2 * need / 2 ** 30}))
    assert line is None and o["pc_precision"] == "double"
    # a limit between the float32-PC figure and the defaults': the first choice, said in one line
    single = est.memory_peak_with(dict(est.options, pc_precision="single"))
    assert single < need
    o, line = costs.fit_memory(sc, opts.replaced({"memory_limit": (single + need) / 2 / 2 ** 30}))
    assert o["pc_precision"] == "single" and o["pc_factors"] == 3
    assert line.startswith("memory: the defaults need") and "-ves_pc_precision single" in line and "\n" not in line
    # a given option is not changed: the next choices are taken instead
    given = O.read_options(O.dict_getter({"ves_pc_precision": "double"}), sc)
    o, line = costs.fit_memory(sc, given.replaced({"memory_limit": (single + need) / 2 / 2 ** 30}))
    assert o["pc_precision"] == "double" and "-ves_pc_precision" not in line and "-ves_pc_factors 1" in line
    # nothing fits: one line naming what would
    with pytest.raises(NumericalFailure, match=r"at most \d+ vesicles fit at p = 8") as e:
        costs.fit_memory(sc, opts.replaced({"memory_limit": 0.5 * est.base_bytes / 2 ** 30}))
    assert "\n" not in str(e.value)


def _vesflow(args, tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "vesflow"] + args, capture_output=True, text=True, timeout=300,
                          cwd=tmp_path, env=env)


def test_run_and_check_with_a_small_memory_limit(tmp_path):
    scene = tmp_path / "two.toml"
    scene.write_text("[discretization]\np = 8\n[time]\nhorizon = 0.02\ndt = 0.01\n[output]\nfile = 'o.h5'\n"
                     "every = 0.02\n[[vesicle]]\nshape = 'oblate'\nreduced_volume = 0.8\n"
                     "[[vesicle]]\nshape = 'oblate'\nreduced_volume = 0.8\ncenter = [3, 0, 0]\n")
    r = _vesflow(["run", str(scene), "-ves_memory_limit", "0.01"], tmp_path)
    assert r.returncode == 3, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "-ves_memory_limit" in lines[0] and "vesicles fit at p = 8" in lines[0]
    assert not (tmp_path / "o.h5").exists()          # refused before any work
    r = _vesflow(["check", str(scene), "-ves_memory_limit", "0.01"], tmp_path)
    assert r.returncode == 0 and "refused  memory:" in r.stdout


def test_setup_cache_current_holds_one_set_and_takes_the_same_step():
    """-ves_setup_cache current (no pinned start): one set of layer potentials, 8 set-ups per sdc
    step instead of 6, the same iterates (a set-up computed again is the same)."""
    from vesflow.stepping.sdc import SDC
    out = {}
    for pin in (True, False):
        st = _stepper()
        st.pin_start = pin
        SDC(st, nodes=3, sweeps=2, quadrature="radau").step(0.01)
        out[pin] = (st.coeffs.copy(), st.timers.counts["self_setup"], memory_model.held_memory(st)["layer_potentials"])
    assert out[True][1:] == (6, 2) and out[False][1:] == (8, 1)
    assert np.array_equal(out[True][0], out[False][0])
    assert memory_model.layer_potentials_held({"ts_type": "sdc", "setup_cache": "current"}) == 1


def test_a_new_factor_set_is_built_after_the_old_one_is_freed():
    """-ves_pc_factors 1: at a new dt the old LU set is no longer referenced while the new one is
    factored (no two sets held together at the peak)."""
    from vesflow import precond
    st = _stepper(pc_factors=1)
    st.solve(0.02)
    old = weakref.ref(st.default_pc_context().factors[0][1][0][0])
    alive, orig = [], precond.lu_factor

    def spy(a, **k):
        gc.collect()
        alive.append(old() is not None)
        return orig(a, **k)
    precond.lu_factor = spy
    try:
        st.solve(0.01)
    finally:
        precond.lu_factor = orig
    assert alive == [False, False]
