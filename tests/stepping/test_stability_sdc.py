"""The stability suite's hard cases (tests/stepping/test_stability.py) with -ts_type sdc (issue 18).

Same scenes and the same invariants (no intersection, area/volume drift, mesh quality, GMRES
converged on every accepted step, no vesicle lost); the time integrator is SDC (3 Gauss-Lobatto
nodes, 2 sweeps, its own error estimate).  Fast cases run in `make test`, the long ones (`slow`)
in `make test-all`; docs/explanation/dynamics.md lists which were run and what they gave.
"""
from __future__ import annotations

import numpy as np
import pytest

from vesflow import options as O, scene as S
from vesflow.errors import ConvergenceError
from vesflow.simulation import Run
from vesflow.stepper import Stepper

from tests import harness
from tests.harness import (BICONCAVE, CROWD, LAMBDA10, ONE, SHEAR, AngleRecorder as Recorder, _long_axis_angle,
                           invariants, simulate_angles as simulate)

pytestmark = pytest.mark.stability
SDC = {"-ts_type": "sdc"}


def test_close_pair_in_shear_sdc():
    run, rec = simulate(harness.pair_scene(0.3, 0.64, p=8, T=0.3), **SDC)
    inv = invariants("sdc: close pair (start gap 3.5% of the radius) in shear", run, rec)
    assert inv["min_gap"] < 0.05


@pytest.mark.slow
def test_near_contact_in_shear_sdc():
    """The pair sheared to a gap below 1% of the radius, repulsion R = 0.01 (euler: 0.0061 at t = 5.22)."""
    text = harness.pair_scene(1.25, 0.1, p=8, T=5.25, kb=1.0, extra="[repulsion]\nradius = 0.01")
    run, rec = simulate(text, **SDC)
    inv = invariants("sdc: near contact in shear", run, rec)
    assert inv["min_gap"] < 0.01


def test_crowding_27_vesicles_at_35_percent_sdc():
    run, rec = simulate(CROWD.format(p=6, T=0.04, every=0.02, R=0.1), **{"-ves_adapt": "none"}, **SDC)
    invariants("sdc: crowding, 27 vesicles at 35%, p = 6", run, rec)


@pytest.mark.slow
def test_crowding_27_vesicles_long_sdc():
    run, rec = simulate(CROWD.format(p=8, T=0.5, every=0.1, R=0.08), **SDC)
    invariants("sdc: crowding, 27 vesicles at 35%, p = 8, T = 0.5", run, rec)


def test_biconcave_065_in_shear_sdc():
    run, rec = simulate(BICONCAVE.format(flow=SHEAR, p=12, T=0.3, every=0.1), **SDC)
    invariants("sdc: biconcave v = 0.65 in shear, p = 12", run, rec)


def _taylor_green_run(p, T):
    sc = S.parse_scene(BICONCAVE.format(flow="", p=p, T=T, every=0.1).replace(
        'center = [0.0, 0.0, 0.0]', 'center = [0.3, 0.2, 1.0]'))
    opts = O.read_options(O.dict_getter(SDC), sc)
    rec = Recorder(opts["q_near"])
    run = Run(sc, opts, writer=rec)
    run.stepper.physics.flow = "taylor_green"
    run.stepper.physics.flow_args = {"amplitude": 1.0, "period": 2 * np.pi * 2.0}
    run.run()
    return run, rec


def test_biconcave_065_in_taylor_green_sdc():
    run, rec = _taylor_green_run(12, 0.3)
    invariants("sdc: biconcave v = 0.65 in Taylor-Green, p = 12", run, rec)
    assert np.linalg.norm(run.stepper.surface.centroid()[0] - [0.3, 0.2, 1.0]) > 1e-3


@pytest.mark.slow
def test_biconcave_065_long_sdc():
    run, rec = simulate(BICONCAVE.format(flow=SHEAR, p=12, T=4.0, every=0.25), **SDC)
    invariants("sdc: biconcave v = 0.65 in shear, p = 12, T = 4", run, rec)
    run, rec = _taylor_green_run(12, 4.0)
    invariants("sdc: biconcave v = 0.65 in Taylor-Green, p = 12, T = 4", run, rec)


def test_viscosity_contrast_10_in_shear_sdc():
    run, rec = simulate(LAMBDA10.format(p=8, T=0.5, every=0.1), **SDC)
    invariants("sdc: lambda = 10 in shear, p = 8", run, rec)


@pytest.mark.slow
def test_viscosity_contrast_10_tumbles_sdc():
    run, rec = simulate(LAMBDA10.format(p=8, T=8.0, every=0.25), **SDC)
    invariants("sdc: lambda = 10 in shear, p = 8, T = 8", run, rec)
    angles = np.array([f["angle"] for f in rec.frames])
    print("[stability] sdc: long-axis angle in the shear plane:", np.round(angles, 2).tolist())
    assert np.all(np.diff(angles) < 0) and angles[-1] < -0.1
    assert _long_axis_angle(run.stepper.coeffs, 8) == pytest.approx(angles[-1])


@pytest.mark.slow
def test_ten_thousand_steps_in_shear_sdc():
    """10^4 fixed sdc steps (110000 solves) of one vesicle in shear, p = 6."""
    text = ONE.replace("horizon = 0.5", "horizon = 10.0").replace("dt = 0.05", "dt = 0.001") \
              .replace("every = 0.1", "every = 0.5")
    run, rec = simulate(text, **{"-ves_adapt": "none"}, **SDC)
    inv = invariants("sdc: 10^4 steps of one vesicle in shear, p = 6", run, rec)
    assert inv["accepted"] == 10000


def _fail_solve_on(monkeypatch, calls, kind):
    """Make Stepper.solve (every solve of an sdc step goes through it) fail on the given call
    numbers (a set, or ("from", k)): a GMRES failure, or NaN in the returned velocity."""
    real = Stepper.solve
    count = {"n": 0}

    def solve(self, dt, surface=None, displacement=None):
        count["n"] += 1
        n = count["n"]
        bad = n >= calls[1] if isinstance(calls, tuple) else n in calls
        if bad and kind == "ksp":
            raise ConvergenceError("injected GMRES failure", reason=-3, iterations=7)
        sol = real(self, dt, surface, displacement)
        if bad and kind == "nan":
            sol.u = sol.u.copy()
            sol.u[0, 0, 3] = np.nan
        return sol

    monkeypatch.setattr(Stepper, "solve", solve)
    return count


@pytest.mark.parametrize("kind, reason", [("ksp", "ksp"), ("nan", "nonfinite")])
def test_injected_failure_is_rejected_and_recovered_sdc(monkeypatch, kind, reason):
    """A failed solve in the middle of the second step (solve 17 of 11 per step) rejects that
    step only."""
    _fail_solve_on(monkeypatch, {17}, kind)
    run, rec = simulate(ONE, **SDC)
    inv = invariants(f"sdc: injected {kind} failure on the 17th solve", run, rec)
    assert inv["rejected"] == {reason: 1}


@pytest.mark.parametrize("kind", ["ksp", "nan"])
def test_unrecoverable_failure_saves_last_good_state_and_exits_3_sdc(monkeypatch, tmp_path, kind):
    from vesflow import cli
    from vesflow.io import read_checkpoint
    scene = tmp_path / "one.toml"
    scene.write_text(ONE)
    out = tmp_path / "one.h5"
    _fail_solve_on(monkeypatch, ("from", 30), kind)        # 11 solves per step: steps 1-2 succeed
    status = cli.main(["run", str(scene), "-o", str(out), "-ves_max_rejects", "4", "-ts_type", "sdc"])
    assert status == 3
    ck = read_checkpoint(str(out))
    print(f"\n[stability] sdc: unrecoverable {kind}: exit {status}, checkpoint at t = {float(ck['time']):.4g}")
    assert float(ck["time"]) > 0 and np.all(np.isfinite(np.asarray(ck["coeffs"])))
    monkeypatch.undo()
    assert cli.main(["run", "--restart", str(out), "-ts_type", "sdc"]) == 0
    assert float(read_checkpoint(str(out))["time"]) == pytest.approx(0.5)
