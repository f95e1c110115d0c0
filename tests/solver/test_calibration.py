"""The machine calibration (vesflow.calibration) moves `vesflow check`'s predicted times and
nothing else: the far-field backend, the Ewald cutoff, the own-vesicle mode and the
preconditioner's rebuild price (vesflow.costs.decisions), and a run's trajectory, are the same
with a wildly different calibration file (docs/explanation/calibration.md)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from vesflow import calibration, costs, options, scene as scenemod
from vesflow.errors import SettingsError
from vesflow.layerpot import ewald, far

# two vesicles in a periodic box (the Ewald far field, own-vesicle mode "auto") and a free pair
PERIODIC = """title = "calibration, periodic pair"
[domain]
period = 5.0
[gravity]
g = [0.0, 0.0, -1.0]
[discretization]
p = 6
[time]
horizon = 0.2
dt = 0.05
[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [1.2, 1.5, 2.5]
excess_density = 1.0
[[vesicle]]
shape = "sphere"
center = [3.8, 2.0, 2.2]
rotation = [10.0, 30.0, 0.0]
"""
LATTICE = """title = "calibration, periodic lattice"
[domain]
period = 6.0
[discretization]
p = 6
[[lattice]]
count = [2, 2, 2]
orientation = "random"
seed = 5
vesicle = { shape = "oblate", reduced_volume = 0.85, radius = 1.0 }
"""
FREE = """title = "calibration, free pair"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 8
[time]
horizon = 0.1
dt = 0.05
[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [-1.3, 0.0, 0.3]
[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [1.3, 0.0, -0.3]
viscosity_contrast = 3.0
"""


def wild():
    """A calibration far from the defaults, each constant by its own factor (10^-3 .. 10^3)."""
    d = calibration.DEFAULTS
    return dataclasses.replace(
        d, self_gemv_bytes_per_s=d.self_gemv_bytes_per_s / 100, forces_s=(d.forces_s[0] * 50, d.forces_s[1] * 20),
        self_setup_s=(d.self_setup_s[0] * 30, 2.0), pc_setup_s=(d.pc_setup_s[0] / 100, 6.0),
        near_s_per_eval=d.near_s_per_eval * 30, direct_s_per_pair=d.direct_s_per_pair * 1000,
        fmm_s_per_point=tuple((e, t / 1000) for e, t in d.fmm_s_per_point),
        ewald={"pair": 3.7e-6, "target": 2.3e-9, "own_pair": 1.5e-7, "nufft_point": 8.8e-12, "fft_point": 6.3e-12,
               "fft_growth": 0.1, "mode": 4.0e-11})


@pytest.fixture
def wild_file(tmp_path, monkeypatch):
    path = Path(calibration.write(wild(), tmp_path / "calibration.json", machine="made up"))
    monkeypatch.setenv(calibration.ENV, str(path))
    return path


def scene_and_opts(text, args=()):
    sc = scenemod.parse_scene(text)
    getter = options.argv_getter(list(args))
    sc = options.apply_overrides(sc, getter)
    return sc, options.read_options(getter, sc)


def test_the_file_round_trips_and_bad_files_are_one_line_errors(tmp_path, monkeypatch):
    monkeypatch.delenv(calibration.ENV, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))                         # no ~/.cache/vesflow/calibration.json
    assert calibration.load() is calibration.DEFAULTS
    path = Path(calibration.write(wild(), tmp_path / "c.json", machine="made up"))
    back = calibration.load(path)
    assert back.source == str(path) and back.constants() == wild().constants()
    monkeypatch.setenv(calibration.ENV, str(path))
    assert calibration.load().direct_s_per_pair == pytest.approx(1.4e-6)
    data = json.loads(path.read_text())
    for change, says in [(lambda c: c.update(direct_s_per_pair=-1.0), "direct_s_per_pair = -1.0"),
                         (lambda c: c.update(bogus=1.0), "unknown constant(s) bogus"),
                         (lambda c: c["ewald"].pop("pair"), "ewald must give exactly"),
                         (lambda c: c.update(forces_s=[1.0]), "forces_s = [1.0] must be a pair")]:
        bad = json.loads(json.dumps(data))
        change(bad["constants"])
        path.write_text(json.dumps(bad))
        with pytest.raises(SettingsError) as err:
            calibration.load()
        assert str(err.value).startswith(f"calibration file {path}: ") and says in str(err.value), err.value
    path.write_text("{not json")
    with pytest.raises(SettingsError, match="cannot read it"):
        calibration.load()
    monkeypatch.setenv(calibration.ENV, str(tmp_path / "missing.json"))
    with pytest.raises(SettingsError, match="does not exist"):
        calibration.load()


def test_the_calibration_moves_the_predicted_times(wild_file, capsys):
    """`vesflow check`'s times by the file's constants: the parts that are one constant times a
    count move by exactly the constant's factor."""
    sc, opts = scene_and_opts(FREE)
    base = costs.estimate(sc, opts, calibration=calibration.DEFAULTS)
    moved = costs.estimate(sc, opts)                                 # the file of $VESFLOW_CALIBRATION
    assert moved.calibration == str(wild_file) and base.calibration == "defaults"
    assert base.far_backend == moved.far_backend == "direct"
    assert moved.t_far == pytest.approx(1000 * base.t_far, rel=1e-12)
    assert moved.t_self == pytest.approx(100 * base.t_self, rel=1e-12)
    assert moved.t_pc == pytest.approx(base.t_pc / 100 * (8 / 16) ** 2, rel=1e-12)   # exponent 4 -> 6 at p = 8
    assert moved.t_step > 10 * base.t_step
    assert moved.memory == base.memory and moved.decisions == base.decisions
    ps, po = scene_and_opts(PERIODIC, ["-ves_far_tol", "1e-6"])
    eb = costs.estimate(ps, po, calibration=calibration.DEFAULTS)
    ew = costs.estimate(ps, po)
    assert eb.far_backend == ew.far_backend == "ewald" and not 0.1 < ew.t_far / eb.t_far < 10
    assert eb.decisions == ew.decisions
    ls, lo = scene_and_opts(LATTICE, ["-ves_far_tol", "1e-6"])
    lb, lw = costs.estimate(ls, lo, calibration=calibration.DEFAULTS), costs.estimate(ls, lo)
    assert lb.decisions == lw.decisions and lb.ewald_best[0] == lb.decisions["ewald"]["rc"]   # defaults: the rule's weights
    assert lw.ewald_best[0] < 0.9 * lw.decisions["ewald"]["rc"] and lw.ewald_best[1] < lw.t_far   # this calibration's best
    assert "would be rc = " in str(lw) and "also the fastest" in str(lb)
    from vesflow import cli
    assert cli.main(["check", str(write_scene(wild_file.parent, FREE))]) == 0
    out = capsys.readouterr().out
    assert f"calibration: {wild_file}" in out and f"per time step ~ {moved.t_step:.4g} s" in out


def write_scene(d, text):
    path = d / "scene.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, args", [(FREE, ()), (FREE, ("-ves_far", "fmm")), (PERIODIC, ("-ves_far_tol", "1e-6")),
                                        (LATTICE, ("-ves_far_tol", "1e-6")),
                                        (LATTICE, ("-ves_far_tol", "1e-4", "-ves_q_near", "8"))])
def test_the_decisions_do_not_read_the_calibration(text, args, wild_file, monkeypatch):
    """The rules' choices are the same with the wild file as with none; the same rules fed the
    wild constants would choose otherwise (so the comparison can fail)."""
    sc, opts = scene_and_opts(text, args)
    with_file = costs.decisions(sc, opts)
    monkeypatch.delenv(calibration.ENV)
    monkeypatch.setenv("HOME", str(wild_file.parent))
    assert calibration.load() is calibration.DEFAULTS
    assert costs.decisions(sc, opts) == with_file
    w = wild()
    if with_file["ewald"] and text == LATTICE:
        monkeypatch.setattr(ewald, "COST", w.ewald)                    # the cutoff rule fed the wild weights
        assert costs.decisions(sc, opts)["ewald"]["rc"] != with_file["ewald"]["rc"]
    else:
        monkeypatch.setattr(costs, "REBUILD_WEIGHTS", {"forces_s": w.forces_s, "bytes_per_s": w.self_gemv_bytes_per_s,
                                                       "pc_setup_s": w.pc_setup_s, "near_s_per_eval": w.near_s_per_eval})
        assert costs.decisions(sc, opts)["pc_rebuild_iterations"] < with_file["pc_rebuild_iterations"] / 10


def run_once(text, args, tmp_path, name):
    """`vesflow run` of the scene (in this process): the file's last checkpoint and attributes."""
    from vesflow import cli
    from vesflow.io import read_attributes, read_checkpoint
    out = tmp_path / f"{name}.h5"
    assert cli.main(["run", str(write_scene(tmp_path, text)), "-o", str(out), *args]) == 0
    return read_checkpoint(str(out)), read_attributes(str(out))


def test_a_run_takes_the_same_steps_with_any_calibration(tmp_path, monkeypatch):
    """The periodic pair (Ewald far field, own-vesicle mode auto, the block preconditioner's
    reuse rule) run with no calibration file and with the wild one: the same decisions recorded,
    bit for bit the same final state; and the recorded decisions are the run's own (the first
    FarField and the preconditioner's first rebuild price)."""
    pytest.importorskip("petsc4py")
    from vesflow import precond
    seen = {"far": [], "its": []}
    init, price = far.FarField.__init__, precond.pc_rebuild_iterations

    def spy_init(self, *a, **k):
        init(self, *a, **k)
        seen["far"].append((self.backend, None if self.ewald is None else self.ewald.params.rc, self.smooth_own))

    def spy_price(*a, **k):
        seen["its"].append(price(*a, **k))
        return seen["its"][-1]
    monkeypatch.setattr(far.FarField, "__init__", spy_init)
    monkeypatch.setattr(precond, "pc_rebuild_iterations", spy_price)
    args = ["-ves_far_tol", "1e-6", "-ves_adapt", "none", "-ts_max_steps", "3"]
    monkeypatch.delenv(calibration.ENV, raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))
    ck0, at0 = run_once(PERIODIC, args, tmp_path, "defaults")
    first_far, first_its = seen["far"][0], seen["its"][0]
    path = calibration.write(wild(), tmp_path / "wild.json")
    monkeypatch.setenv(calibration.ENV, str(path))
    ck1, at1 = run_once(PERIODIC, args, tmp_path, "wild")
    d0, d1 = json.loads(at0["decisions"]), json.loads(at1["decisions"])
    assert d0 == d1 and at0["decision_rules"] == at1["decision_rules"]
    assert float(ck0["time"]) == float(ck1["time"]) > 0
    assert np.array_equal(np.asarray(ck0["coeffs"]), np.asarray(ck1["coeffs"]))
    assert (d0["far_backend"], d0["ewald"]["rc"], d0["ewald_own"] == "smooth") == first_far
    assert d0["pc_rebuild_iterations"] == pytest.approx(first_its, rel=1e-12)
    assert json.loads(at0["decision_rules"])["ewald_cutoff"]["weights"] == ewald.COST
