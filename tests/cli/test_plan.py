"""vesflow plan (vesflow.planner): the search on synthetic models, the one-line refusals, the fit
from the study's cached cases, the [accuracy] scene key and `vesflow run` of a scene with it."""
import copy
import json

import h5py
import pytest

from vesflow import cli, planner, scene as scenemod
from vesflow.errors import SceneError

ONE = """
title = "one sphere"
[time]
horizon = 0.05
dt = 0.01
[output]
every = 0.05
[[vesicle]]
shape = "ellipsoid"
axes = [1.0, 1.0, 1.3]
bending_modulus = 0.1
"""


def synthetic(spatial_A=0.0, euler=(1e-3, 1.0), sdc=(1e-4, 1.5), solves_euler=(50.0, 1.0), solves_sdc=(40.0, 0.2)):
    """A FIT-like dict with the given constants (horizon 1, free cost constants)."""
    fit = copy.deepcopy(planner.FIT)
    fit.update(source="synthetic", horizon=1.0)
    fit["spatial"] = {"A": spatial_A, "r": 0.7}
    fit["time"] = {"euler": {"A": euler[0], "a": euler[1]}, "sdc": {"A": sdc[0], "a": sdc[1]}}
    fit["solves"] = {"euler": {"s": solves_euler[0], "b": solves_euler[1]},
                     "sdc": {"s": solves_sdc[0], "b": solves_sdc[1]}}
    fit["cost"] = {"euler": {"k": 1.0, "c": 0.0}, "sdc": {"k": 1.0, "c": 0.0}}
    return planner.Model(fit)


@pytest.fixture(scope="module")
def one():
    return scenemod.parse_scene(ONE.replace("horizon = 0.05", "horizon = 1.0"))


def test_planner_picks_the_cheaper_of_two_settings_that_reach_E(one):
    # p and E/T fixed: two candidates, euler (error 1e-3 * 1) and sdc (1e-4): both reach 2e-3
    for solves_sdc, want in ((500.0, "euler"), (100.0, "sdc")):
        pl = planner.Planner(one, synthetic(solves_euler=(300.0, 1.0), solves_sdc=(solves_sdc, 0.2)),
                             fixed={"p": 8, "tol": 1e-2})
        best, runner = pl.plan(error=2e-3)
        e, s = (pl.predict(planner.replace(best.setting, scheme=k)) for k in ("euler", "sdc"))
        assert e.error <= 2e-3 and s.error <= 2e-3
        assert best.setting.scheme == want and runner.setting.scheme != want
        assert best.seconds == min(e.seconds, s.seconds) < max(e.seconds, s.seconds) == runner.seconds
    # E = 5e-4: only sdc reaches it, even when euler is cheaper
    pl = planner.Planner(one, synthetic(solves_euler=(300.0, 1.0), solves_sdc=(500.0, 0.2)), fixed={"p": 8, "tol": 1e-2})
    assert pl.plan(error=5e-4)[0].setting.scheme == "sdc"


def test_solves_are_at_least_those_of_the_fewest_steps(one):
    # the step grows at most 2x: dt0 = 0.01 over T = 1 takes 0.01, 0.02, ..., 0.64 (landing): 7 steps
    assert planner.fewest_steps(1.0, 0.01) == 7 and planner.fewest_steps(0.03, 0.01) == 2
    pl = planner.Planner(one, synthetic(solves_euler=(1.0, 1.0), solves_sdc=(1.0, 0.2)))
    for scheme, per_step in (("euler", 3), ("sdc", 10)):
        pr = pl.predict(planner.Setting(scheme, 8, 1e-2, 16, 16))
        assert pr.solves == per_step * 7


def test_planner_search_is_the_minimum_over_its_grid(one):
    pl = planner.Planner(one, synthetic(spatial_A=0.05))
    best, runner = pl.plan(error=1e-3)
    cands = pl.candidates(1e-3)
    reach = [c for c in cands if c.error <= 1e-3]
    assert best.seconds == min(c.seconds for c in reach)
    assert best.error <= 1e-3 and (runner.setting.scheme, runner.setting.p) != (best.setting.scheme, best.setting.p)
    # a larger spatial error pushes p up
    hi = planner.Planner(one, synthetic(spatial_A=5.0)).plan(error=1e-3)[0]
    assert hi.setting.p > best.setting.p


def test_unreachable_error_is_one_line_naming_the_best_reachable(one):
    pl = planner.Planner(one, synthetic(spatial_A=0.05), fixed={"p": 6})
    floor = min(c.error for c in pl.candidates())
    with pytest.raises(SceneError) as ei:
        pl.plan(error=floor / 10)
    msg = str(ei.value)
    assert "\n" not in msg and "cannot be reached" in msg
    assert f"best reachable is {floor:.2g}" in msg and "spatial error" in msg and "p = 6" in msg
    # time-limited: no spatial error, the time error at the smallest E/T names the scheme
    pl = planner.Planner(one, synthetic(spatial_A=0.0))
    with pytest.raises(SceneError, match=r"cannot be reached: .* limited by the time error of sdc"):
        pl.plan(error=1e-9)


def test_budget_gives_the_smallest_error_within_it_or_refuses(one):
    pl = planner.Planner(one, synthetic(spatial_A=0.05))
    cands = pl.candidates()
    budget = sorted(c.seconds for c in cands)[len(cands) // 2]
    best, _ = pl.plan(budget=budget)
    assert best.seconds <= budget
    assert best.error == min(c.error for c in cands if c.seconds <= budget)
    with pytest.raises(SceneError, match=r"budget .* cannot be met: the cheapest is"):
        pl.plan(budget=min(c.seconds for c in cands) / 2)


def test_fit_from_the_study_reproduces_the_stored_constants():
    from vesflow import plan_fit
    fit = plan_fit.fit_from_study()
    for part in ("spatial", "time", "solves", "cost"):
        got, want = fit[part], planner.FIT[part]
        flat = lambda d: {k: v for k, v in d.items()} if "A" in d or "s" in d or "k" in d else \
            {f"{a}.{b}": x for a, sub in d.items() for b, x in sub.items()}
        assert flat(got) == pytest.approx(flat(want), rel=1e-6), part
    # what it says about the study: sdc's time error falls faster than euler's, and the
    # spatial error at p = 8 is about the measured 3e-3 against the p = 16 reference
    assert fit["time"]["sdc"]["a"] > 1.2 > fit["time"]["euler"]["a"] > 0.8
    m = planner.Model(fit)
    assert 2e-3 < m.e_space(8, 7.0) < 4e-3 and m.e_space(16, 7.0) == 0.0


def test_scene_accuracy_key_is_parsed_and_validated():
    sc = scenemod.parse_scene(ONE + "[accuracy]\nerror = 1e-3\n")
    assert sc.accuracy.error == 1e-3 and "accuracy error 0.001" in sc.summary()
    assert scenemod.parse_scene(ONE).accuracy is None
    for bad, what in (("error = 0", "accuracy.error = 0: must be in (0, 1)"),
                      ("error = 1.5", "accuracy.error = 1.5: must be in (0, 1)"),
                      ("error = \"small\"", "accuracy.error = \"small\": expected a number"),
                      ("budget = 10", "accuracy.budget"), ("", "accuracy.error: missing")):
        with pytest.raises(SceneError) as ei:
            scenemod.parse_scene(ONE + f"[accuracy]\n{bad}\n")
        assert what in str(ei.value) and "\n" not in str(ei.value)


def test_cli_plan_prints_choice_runner_up_and_command(tmp_path, capsys):
    path = tmp_path / "one.toml"
    path.write_text(ONE)
    assert cli.main(["plan", str(path), "--error", "1e-2"]) == 0
    out = capsys.readouterr().out
    for word in ("chosen ", "runner-up ", "command  vesflow run", "-ts_type", "s CPU"):
        assert word in out
    assert cli.main(["plan", str(path), "--error", "2"]) == 2
    assert "--error 2: must be a number in (0, 1)" in capsys.readouterr().err
    assert cli.main(["plan", str(path), "--error", "1e-12"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cannot be reached: the best reachable is" in err


def test_run_with_accuracy_plans_says_it_in_one_line_and_stores_the_plan(tmp_path, capsys):
    path = tmp_path / "acc.toml"
    path.write_text(ONE + "[accuracy]\nerror = 1e-2\n")
    out = tmp_path / "acc.h5"
    assert cli.main(["run", str(path), "-o", str(out), "-ves_p", "6"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "plan for [accuracy]" in ln]
    assert len(lines) == 1 and "p = 6" in lines[0] and "predicted error" in lines[0]
    with h5py.File(out, "r") as f:
        plan = json.loads(f.attrs["plan"])
        resolved, given = (f.attrs[k].decode() if isinstance(f.attrs[k], bytes) else f.attrs[k]
                           for k in ("options_resolved", "options"))
    assert plan["error_target"] == 1e-2 and plan["chosen"]["p"] == 6 and plan["predicted_error"] <= 1e-2
    assert f"-ts_type {plan['chosen']['scheme']}" in resolved
    assert f"-ves_adapt_tol {plan['chosen']['tol']:g}" in resolved
    assert given.startswith(plan["options"]) and given.endswith("-ves_p 6")     # the plan's, then ours


def test_pilot_factors_are_measured_over_predicted(one, monkeypatch):
    from vesflow import plan_fit
    L, off = 2.0, {"sdc_lo": 3e-4, "sdc_lo_fine": 0.0, "euler_lo": 2e-3, "sdc_hi": 1e-4}
    runs = {}

    def fake(scene, s, horizon):
        key = {("sdc", 8, 2e-2): "sdc_lo", ("sdc", 8, 5e-3): "sdc_lo_fine", ("euler", 8, 2e-2): "euler_lo",
               ("sdc", 12, 2e-2): "sdc_hi"}[(s.scheme, s.p, s.tol)]
        runs[key] = horizon
        solves = {"sdc_lo": 60, "sdc_lo_fine": 80, "euler_lo": 30, "sdc_hi": 60}[key]
        return {"final": {"centroid": [[off[key] * L, 0.0, 0.0]], "length": [L]}, "solves": solves,
                "cpu": 0.05 * solves * (s.p / 8) ** 2, "status": "ok"}

    monkeypatch.setattr(plan_fit, "run_setting", fake)
    pl = planner.Planner(one)
    m = plan_fit.calibrate(one, pl, 0.25, log=lambda *a: None)
    t_p, m0 = 0.25 * one.time.horizon, pl.model
    assert set(runs) == set(off) and all(h == t_p for h in runs.values())
    a = m0.fit["time"]["sdc"]["a"]
    assert m.f_time["sdc"] == pytest.approx(3e-4 / (1 - 4.0 ** -a) / m0.e_time("sdc", 2e-2, t_p))
    assert m.f_time["euler"] == pytest.approx(2e-3 / m0.e_time("euler", 2e-2, t_p))
    assert m.f_space == pytest.approx(2e-4 / (m0.e_space(8, t_p) - m0.e_space(12, t_p)))
    assert m.f_solves["euler"] == pytest.approx(30 / m0.solves("euler", 2e-2, t_p))
    # the calibrated model predicts what the pilots measured (at the pilot's horizon)
    sub = planner.Planner(planner.optmod.apply_overrides(one, planner.optmod.dict_getter({"-ts_max_time": t_p})), m)
    e = sub.predict(planner.Setting("euler", 8, 2e-2, 16, 16))
    assert e.e_time == pytest.approx(2e-3) and e.solves == pytest.approx(30)
    assert e.seconds == pytest.approx(0.05 * 30)
    assert "4 pilot runs" in m.pilot


def test_floor_tol_is_where_the_fewest_steps_stop_being_taken():
    """Steps of dt 0.1, 0.2, 0.4 (doubling, the last landing) with err / dt = 1e-3, 2e-3, 5e-3:
    every step but the last must propose 2 dt, beta (E/T dt / err)^(1/k) >= 2, so E/T >=
    (err / dt) (2 / beta)^k; the last only needs err / dt <= E/T.  A run that took more steps
    than the fewest has no such E/T."""
    from vesflow import plan_fit
    rows = [(0.0, 0.1, 1, 5, 1e-4, "accepted"), (0.1, 0.2, 1, 5, 4e-4, "accepted"), (0.3, 0.4, 1, 5, 2e-3, "accepted")]
    assert plan_fit.floor_tol(rows, 3, 0.9, 2) == pytest.approx(2e-3 * (2 / 0.9) ** 2)
    assert plan_fit.floor_tol(rows[:2] + [(0.3, 0.4, 1, 5, 9e-3, "accepted")], 3, 0.9, 1) == pytest.approx(9e-3 / 0.4)
    assert plan_fit.floor_tol(rows, 2, 0.9, 2) is None
    assert plan_fit.floor_tol(rows[:2] + [(0.3, 0.4, 0, 5, 2e-3, "error_estimate")], 3, 0.9, 2) is None


def test_solves_from_a_measured_floor(one):
    """With floor_tol known (a pilot over the whole horizon took the fewest steps): the fewest
    steps' solves from floor_tol up, whatever the fitted rate, and n_min (E/T / floor_tol)^-b below."""
    m = synthetic(solves_euler=(1e4, 1.0), solves_sdc=(1e4, 0.5))
    m.floor_tol = {"euler": 1e-2, "sdc": None}
    n_min = 3 * planner.fewest_steps(1.0, 0.01)
    assert m.solves("euler", 2e-2, 1.0, 0.01) == n_min == m.solves("euler", 1e-2, 1.0, 0.01)
    assert m.solves("euler", 2.5e-3, 1.0, 0.01) == pytest.approx(4 * n_min)
    assert m.solves("sdc", 1e-2, 1.0, 0.01) == pytest.approx(1e4)          # unknown: the fitted rate


def test_pilots_split_the_cost_per_solve_between_t_solve_and_the_vesicles(one, monkeypatch):
    """Pilots whose CPU per solve is exactly 2 k t_solve(p) + 0.5 c N (k, c the study's): the
    calibration finds alpha = 2, beta = 0.5 (the pilots at p = 8 and 12 separate the two parts),
    the per-scheme factors 1, and a pilot that took the fewest steps gives floor_tol."""
    from vesflow import plan_fit
    pl = planner.Planner(one)

    def fake(scene, s, horizon):
        c = planner.FIT["cost"][s.scheme]
        per = 2.0 * c["k"] * pl._solve_cost(s)[0] + 0.5 * c["c"] * one.n_vesicles
        return {"final": {"centroid": [[1e-4 * s.p, 0.0, 0.0]], "length": [2.0]}, "solves": 40, "cpu": 40 * per,
                "status": "ok", "floor_tol": 1e-3 if s.scheme == "euler" else None}

    monkeypatch.setattr(plan_fit, "run_setting", fake)
    m = plan_fit.calibrate(one, pl, 1.0, log=lambda *a: None)
    assert m.split == pytest.approx((2.0, 0.5), rel=1e-6)
    assert m.f_cost["euler"] == pytest.approx(1.0, rel=1e-6) and m.f_cost["sdc"] == pytest.approx(1.0, rel=1e-6)
    assert m.floor_tol == {"euler": 1e-3, "sdc": None}
    assert "alpha 2 / beta 0.5" in m.pilot
