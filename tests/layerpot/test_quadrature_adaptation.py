"""The double-layer identity drives the quadrature degrees during a run (paper 3.2.4, -ves_quad_tol)."""
import numpy as np
import pytest

petsc4py = pytest.importorskip("petsc4py")
petsc4py.init([])

from vesflow import options as O, scene as S  # noqa: E402
from vesflow.simulation import Run, _step_q  # noqa: E402

PAIR = """
title = "pair"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 8
[time]
horizon = {T}
dt = 0.05
[output]
every = 0.5
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
center = [-1.25, 0.0, 0.4]
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
center = [1.25, 0.0, -0.4]
"""


class _Steps:
    """The writer interface of Run, keeping the step rows only."""

    def __init__(self):
        self.rows = []

    def write_steps(self, rows):
        self.rows.extend(rows)

    def __getattr__(self, name):             # frames, timings, checkpoints: ignored
        return lambda *a, **k: None


def _run(T, **opts):
    """Pinned to -ts_type euler: q moves by at most one per accepted step, and the degrees the
    tests below reach were measured over euler's steps."""
    sc = S.parse_scene(PAIR.format(T=T))
    w = _Steps()
    run = Run(sc, O.read_options(O.dict_getter({"-ts_type": "euler", **opts}), sc), writer=w)
    run.run()
    q = np.array([(r[6], r[7]) for r in w.rows if r[2] == 1])
    assert len(q) == run.counts["accepted"] > 3
    return run, q


def test_q_columns_in_the_output_file(tmp_path):
    from vesflow import cli
    from vesflow.io import read_output
    scene = tmp_path / "pair.toml"
    scene.write_text(PAIR.format(T=0.2))
    out = tmp_path / "pair.h5"
    assert cli.main(["run", str(scene), "-o", str(out), "-ves_quad_tol", "1e-3", "-ts_type", "euler"]) in (0, None)
    st = read_output(str(out)).steps
    print("[quad] file q_self", st["q_self"].tolist(), "q_near", st["q_near"].tolist())
    assert st["q_self"][0] == 16 and st["q_self"][-1] < 16 and np.all(st["q_near"] > 0)


def test_step_rule():
    assert _step_q(16, 2e-4, 1e-4, 9, 32) == 17          # above the tolerance: up
    assert _step_q(16, 5e-5, 1e-4, 9, 32) == 16          # inside the dead band: kept
    assert _step_q(16, 5e-6, 1e-4, 9, 32) == 15          # below a tenth: down
    assert _step_q(32, 1.0, 1e-4, 9, 32) == 32 and _step_q(9, 0.0, 1e-4, 9, 32) == 9    # bounds
    assert _step_q(16, np.nan, 1e-4, 9, 32) == 17


def test_fixed_q_by_default():
    run, q = _run(0.4)
    assert np.all(q == 16) and not hasattr(run, "quad_errors")


def test_tight_tolerance_raises_q_until_the_identity_holds():
    """From q = p + 1 = 9 with tol 1e-6: both degrees rise (measured 9 -> 15 self, 9 -> 17 near,
    identity errors 5e-7 / 4e-7 / 5e-9 at t = 1)."""
    run, q = _run(0.6, **{"-ves_quad_tol": 1e-6, "-ves_q_self": 9, "-ves_q_near": 9})
    print("[quad] q_self, q_near per accepted step:", q.tolist(), "errors", run.quad_errors)
    assert q[0].tolist() == [9, 9] and np.all(np.diff(q, axis=0) >= -1)
    assert q[-1, 0] >= 13 and q[-1, 1] >= 14
    assert max(run.quad_errors.values()) < 1e-5


def test_loose_tolerance_lowers_q_and_keeps_the_identity():
    """From the default q = 2p = 16 with tol 1e-3: the degrees fall (measured to 9 / 9)."""
    run, q = _run(0.6, **{"-ves_quad_tol": 1e-3})
    print("[quad] q_self, q_near per accepted step:", q.tolist(), "errors", run.quad_errors)
    assert q[0].tolist() == [16, 16] and q[-1, 0] <= 12 and q[-1, 1] <= 12
    assert max(run.quad_errors.values()) < 1e-3
    assert run.checkpoint()["q_self"] == run.q_self and run.checkpoint()["q_near"] == run.q_near
