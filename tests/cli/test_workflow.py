"""The user's workflow end to end (issue #6): restart after SIGKILL, options files, effects that
cost nothing when off, `vesflow check`, the progress line, -help, scene overrides, exit statuses."""
import os
import pty
import random
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from tests.harness import ROOT  # noqa: E402
VESFLOW = [sys.executable, "-m", "vesflow"]
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")


def vesflow(args, **kw):
    return subprocess.run(VESFLOW + [str(a) for a in args], capture_output=True, text=True, timeout=300,
                          env=ENV, cwd=ROOT, **kw)


def one_line_error(r):
    lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


# ------------------------------------------------------------------------------------------
# Restart: SIGKILL at a random moment, continue from the file, same final state
# ------------------------------------------------------------------------------------------
PAIR = """title = "restart test: two vesicles in shear"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 6
[time]
horizon = 0.3
dt = 0.05
[output]
file = "out/restart_test.h5"
every = 0.05
[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [-1.3, 0.0, 0.3]
bending_modulus = 0.1
[[vesicle]]
shape = "oblate"
reduced_volume = 0.85
center = [1.3, 0.0, -0.3]
bending_modulus = 0.1
"""
RUN_OPTS = ["-ves_checkpoint_every", "0.05", "-ts_monitor"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run."""
    d = tmp_path_factory.mktemp("restart")
    scene = d / "pair.toml"
    scene.write_text(PAIR)
    r = vesflow(["run", scene, "-o", d / "ref.h5"] + RUN_OPTS)
    assert r.returncode == 0, r.stderr
    from vesflow.io import read_output
    ref = read_output(d / "ref.h5")
    assert ref.time[-1] == pytest.approx(0.3) and ref.n_frames >= 5
    return scene, ref


def _has_checkpoint(path):
    """Poll a file that another process is writing (no lock; it may be mid-write)."""
    try:
        with h5py.File(path, "r", locking=False) as f:
            return "checkpoint" in f or "checkpoint_new" in f
    except Exception:
        return False


def assert_same_run(out, ref):
    assert np.array_equal(out.time, ref.time), (out.time, ref.time)            # no frame lost or doubled
    np.testing.assert_array_equal(out.steps["dt"], ref.steps["dt"])            # the very same steps
    c, c_ref = out.frames["coefficients"], ref.frames["coefficients"]
    err = np.abs(c - c_ref).max()
    assert err <= 1e-12 * np.abs(c_ref).max(), f"restarted run differs from the uninterrupted one by {err:.2e}"


def test_sigkill_at_a_random_moment_then_restart_gives_the_uninterrupted_run(reference, tmp_path):
    from vesflow.io import read_checkpoint, read_output
    scene, ref = reference
    rng = random.Random(6)
    n_steps = int(ref.steps["accepted"].sum())
    kill_after = rng.randrange(0, n_steps - 1)        # kill during step kill_after + 1 ...
    step_seconds = ref.timings["total"] / len(ref.steps["dt"])   # the reference's time per attempted step
    delay = rng.uniform(0.0, 1.0) * step_seconds       # ... at a random moment of it
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(VESFLOW + ["run", str(scene), "-o", str(out)] + RUN_OPTS, cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        deadline = time.time() + 120
        while not _has_checkpoint(out) and proc.poll() is None and time.time() < deadline:
            time.sleep(0.02)
        assert _has_checkpoint(out), "no checkpoint appeared"
        for line in proc.stdout:                       # -ts_monitor: one line per attempted step
            if line.startswith("step") and int(line.split()[1]) >= kill_after:
                break
        time.sleep(delay)
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill (status {proc.returncode})"
    # the killed file is readable and has a complete checkpoint
    killed = read_output(out)
    t_ck = float(read_checkpoint(out)["time"])
    assert killed.n_frames >= 1 and t_ck < ref.time[-1]
    r = vesflow(["run", "--restart", out])
    assert r.returncode == 0, r.stderr
    assert "restart from t = " in r.stdout
    res = read_output(out)
    assert_same_run(res, ref)
    np.testing.assert_array_equal(res.restarts, [t_ck])         # the file records the restart
    assert list(res.attrs["restart_options"]) == [""]
    assert res.attrs["options"] == ref.attrs["options"]


def test_restart_from_the_first_checkpoint_into_another_file(reference, tmp_path):
    """-ts_max_steps 0: only the frame and checkpoint at t = 0; --restart ... -o continues in a copy."""
    from vesflow.io import read_output
    scene, ref = reference
    first = tmp_path / "first.h5"
    r = vesflow(["run", scene, "-o", first, "-ts_max_steps", "0"] + RUN_OPTS)
    assert r.returncode == 0, r.stderr
    r = vesflow(["run", "--restart", first, "-o", tmp_path / "cont.h5", "-ts_max_steps", "1000"])
    assert r.returncode == 0, r.stderr
    cont = read_output(tmp_path / "cont.h5")
    assert_same_run(cont, ref)
    assert cont.attrs["restart_of"] == str(first) and list(cont.restarts) == [0.0]
    assert list(cont.attrs["restart_options"]) == ["-ts_max_steps 1000"]
    untouched = read_output(first)
    assert untouched.n_frames == 1 and len(untouched.restarts) == 0
    # a longer horizon; the options of the first restart (-ts_max_steps 1000, which lifts the
    # original -ts_max_steps 0) stay in force
    r = vesflow(["run", "--restart", tmp_path / "cont.h5", "-ts_max_time", "0.4"])
    assert r.returncode == 0, r.stderr
    longer = read_output(tmp_path / "cont.h5")
    assert longer.time[-1] == pytest.approx(0.4) and np.allclose(longer.restarts, [0.0, 0.3], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(longer.time[:ref.n_frames], ref.time)


@pytest.fixture(scope="module")
def sdc_reference(tmp_path_factory):
    """The uninterrupted run with -ts_type sdc (issue 18)."""
    d = tmp_path_factory.mktemp("restart_sdc")
    scene = d / "pair.toml"
    scene.write_text(PAIR)
    r = vesflow(["run", scene, "-o", d / "ref.h5", "-ts_type", "sdc"] + RUN_OPTS)
    assert r.returncode == 0, r.stderr
    from vesflow.io import read_output
    ref = read_output(d / "ref.h5")
    assert ref.time[-1] == pytest.approx(0.3) and ref.n_frames >= 3
    return scene, ref


def test_sdc_run_killed_after_a_checkpoint_restarts_into_the_uninterrupted_run(sdc_reference, tmp_path):
    from vesflow.io import read_checkpoint, read_output
    scene, ref = sdc_reference
    out = tmp_path / "killed.h5"
    proc = subprocess.Popen(VESFLOW + ["run", str(scene), "-o", str(out), "-ts_type", "sdc"] + RUN_OPTS, cwd=ROOT,
                            env=ENV, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        for line in proc.stdout:                       # -ts_monitor: kill once a step starts after t = 0.1
            if line.startswith("step") and float(line.split()[2][2:]) > 0.1:
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill (status {proc.returncode})"
    t_ck = float(read_checkpoint(out)["time"])
    assert 0.05 <= t_ck < 0.3
    r = vesflow(["run", "--restart", out])
    assert r.returncode == 0, r.stderr
    res = read_output(out)
    assert_same_run(res, ref)
    assert list(res.restarts) == [t_ck] and "-ts_type sdc" in res.attrs["options"]


API_RUN = """import sys
import petsc4py
petsc4py.init([])
from vesflow import options as O, scene as S
from vesflow.io import OutputWriter
from vesflow.simulation import Run
sc = S.parse_scene(open(sys.argv[1]).read())
opts = O.read_options(O.dict_getter({"-ves_checkpoint_every": 0.05}), sc)
w = OutputWriter(sys.argv[2], scene_text=sc.text, options_text="", version="test", p=sc.p, n_vesicles=sc.n_vesicles,
                 periodic_length=sc.periodic_length, checkpoint_every=opts["checkpoint_every"])
with w:
    Run(sc, opts, writer=w, monitor=True, log=lambda s: print(s, flush=True)).run()
"""


def test_python_api_run_killed_mid_run_restarts_into_the_uninterrupted_run(reference, tmp_path):
    """A Run driven from Python (OutputWriter + Run), killed with SIGKILL after t = 0.1 and
    continued in this process from the file's checkpoint (OutputWriter.reopen, Run(checkpoint=)):
    the frames of the uninterrupted command-line run to 1e-12, the very same steps (the
    preconditioner is rebuilt from the record in the checkpoint, not reset at checkpoints)."""
    pytest.importorskip("petsc4py").init([])
    from vesflow import options as O, scene as S
    from vesflow.io import OutputWriter, read_checkpoint, read_output
    from vesflow.simulation import Run
    scene, ref = reference
    out = tmp_path / "api.h5"
    proc = subprocess.Popen([sys.executable, "-c", API_RUN, str(scene), str(out)], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        for line in proc.stdout:                       # kill once a step starts after t = 0.1
            if line.startswith("step") and float(line.split()[2][2:]) > 0.1:
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill (status {proc.returncode})"
    ck = read_checkpoint(out)
    assert 0.1 <= float(ck["time"]) < 0.3 and int(ck["pc"]["built"]) == 1
    sc = S.parse_scene(scene.read_text())
    opts = O.read_options(O.dict_getter({"-ves_checkpoint_every": 0.05}), sc)
    with OutputWriter.reopen(out, checkpoint_every=opts["checkpoint_every"]) as w:
        run = Run(sc, opts, writer=w, checkpoint=w.checkpoint)
        run.run()
    assert run.stepper._ksp is None                    # the run's KSP and Mat are destroyed at its end
    assert_same_run(read_output(out), ref)


def test_restart_errors_are_one_line(tmp_path):
    bad = tmp_path / "missing.h5"
    r = vesflow(["run", "--restart", bad])
    assert r.returncode == 2 and "no such file" in one_line_error(r)
    notrun = tmp_path / "other.h5"
    with h5py.File(notrun, "w") as f:
        f["x"] = 1
    r = vesflow(["run", "--restart", notrun])
    assert r.returncode == 2 and "not a vesflow run file" in one_line_error(r)
    r = vesflow(["run", "runs/relaxation.toml", "--restart", notrun])
    assert r.returncode == 2 and "not both" in one_line_error(r)


def test_writer_checkpoint_every_callbacks_and_frame_at_the_same_time(tmp_path):
    from tests.harness import synthetic_frames
    from vesflow.io import OutputWriter, read_checkpoint, read_output
    frames = synthetic_frames(n_frames=6)                       # t = 0, 0.5, ..., 2.5
    seen = []
    path = tmp_path / "w.h5"
    with OutputWriter(path, scene_text="", options_text="", version="t", p=8, n_vesicles=3,
                      periodic_length=0.0, checkpoint_every=1.0) as w:
        w.on_checkpoint.append(lambda state: seen.append(state["time"]))
        for fr in frames:
            w.write_frame(**fr)
            w.write_checkpoint({"time": fr["time"], "x": fr["coefficients"]})
        assert seen == [0.0, 1.0, 2.0] and w.last_checkpoint_time == 2.0
        assert w.write_checkpoint({"time": 2.5}, force=True) and seen[-1] == 2.5
        w.write_frame(**dict(frames[0], time=2.5))             # the same time again: replaces the frame
    res = read_output(path)
    np.testing.assert_array_equal(res.time, [0.0, 0.5, 1.0, 1.5, 2.0, 2.5])
    np.testing.assert_array_equal(res.frames["coefficients"][-1], frames[0]["coefficients"])
    assert read_checkpoint(path)["time"] == 2.5
    w = OutputWriter.reopen(path, checkpoint_every=1.0)
    assert w.last_checkpoint_time == 2.5 and not w.checkpoint_due(3.0) and w.checkpoint_due(3.5)
    w.close()


def _cli(monkeypatch, args):
    from vesflow import cli
    monkeypatch.chdir(ROOT)
    return cli.main([str(a) for a in args])


def test_numerical_failure_saves_the_last_accepted_state(monkeypatch, tmp_path, capsys):
    """Exit status 3, and the checkpoint holds the state of the last accepted step."""
    pytest.importorskip("petsc4py").init([])
    from vesflow import simulation
    from vesflow.io import read_checkpoint, read_output
    orig, calls = simulation.Run._try, []

    def failing_after_two(self, dt):
        calls.append(dt)
        if len(calls) > 2:
            return None, "ksp", 0, np.inf
        return orig(self, dt)
    monkeypatch.setattr(simulation.Run, "_try", failing_after_two)
    out = tmp_path / "fail.h5"
    rc = _cli(monkeypatch, ["run", "runs/relaxation.toml", "-o", out, "-ves_p", "4", "-ves_adapt", "none",
                            "-ves_max_rejects", "1", "-ves_output_every", "1.0"])
    err = capsys.readouterr().err
    assert rc == 3 and "rejected 1 times in a row" in err and "Traceback" not in err
    res = read_output(out)
    ck = read_checkpoint(out)
    assert list(res.time) == [0.0]                        # frames every 1.0: only t = 0
    assert ck["time"] == pytest.approx(0.1) and ck["n_accepted"] == 2   # two steps of 0.05
    assert list(res.steps["accepted"]) == [1, 1, 0]


def test_ctrl_c_is_exit_130_with_a_hint(monkeypatch, tmp_path, capsys):
    pytest.importorskip("petsc4py").init([])
    from vesflow import simulation

    def interrupted(self):
        raise KeyboardInterrupt
    monkeypatch.setattr(simulation.Run, "run", interrupted)
    rc = _cli(monkeypatch, ["run", "runs/relaxation.toml", "-o", tmp_path / "x.h5", "-ves_p", "4"])
    assert rc == 130 and "--restart" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------
# Options files
# ------------------------------------------------------------------------------------------
def test_options_files_are_honoured_and_stored(tmp_path):
    out = tmp_path / "o.h5"
    r = vesflow(["run", "runs/relaxation.toml", "-o", out, "-options_file", "runs/small.opts",
                 "-options_file", "runs/production.opts", "-ves_adapt_tol", "0.02", "-ts_max_steps", "1"])
    assert r.returncode == 0, r.stderr
    from vesflow.io import read_output
    res = read_output(out)
    assert res.p == 4                                               # -ves_p 4 from runs/small.opts
    stored, resolved = res.attrs["options"], res.attrs["options_resolved"]
    assert "-ves_p 4" in stored and "-ksp_rtol 1e-7" in stored and "-options_file" not in stored
    assert "-ves_adapt_tol 0.005" in stored                          # from runs/production.opts ...
    assert "-ves_adapt_tol 0.02" in resolved                         # ... the command line after it wins
    assert "KSP Object" not in r.stdout


@pytest.mark.parametrize("text,words", [
    ("-ves_p 4\n-ves_qself 12   # typo\n", ["bad.opts:2", "-ves_qself", "did you mean -ves_q_self"]),
    ("-ves_adapt_tol -1\n", ["-ves_adapt_tol", "must be a number > 0"]),
    ("ves_p 4\n", ["bad.opts:1", "expected an option"]),
    ("-ves_adapt bisection\n", ["-ves_adapt", "must be one of none, doubling, invariants"]),
])
def test_a_bad_option_in_an_options_file_is_exit_2_and_one_line(tmp_path, text, words):
    opts = tmp_path / "bad.opts"
    opts.write_text(text)
    r = vesflow(["run", "runs/relaxation.toml", "-o", tmp_path / "x.h5", "-options_file", opts])
    assert r.returncode == 2
    line = one_line_error(r)
    for w in words:
        assert w in line, line
    assert not (tmp_path / "x.h5").exists()
    r = vesflow(["run", "-options_file", tmp_path / "none.opts"])
    assert r.returncode == 2 and "cannot read it" in one_line_error(r)


def test_more_mpi_processes_than_vesicles_is_refused_with_one_line(tmp_path):
    """Each rank owns at least one vesicle (vesflow.parallel); one vesicle on two ranks: exit 2,
    one line (from rank 0 only), no output file.  Runs on two ranks: tests/mpi/test_mpi_runs.py."""
    mpiexec = Path(sys.executable).parent / "mpiexec"
    if not mpiexec.exists():
        pytest.skip("no mpiexec in the environment")
    r = subprocess.run([str(mpiexec), "-n", "2"] + VESFLOW + ["run", "runs/relaxation.toml", "-o", str(tmp_path / "m.h5")],
                       capture_output=True, text=True, timeout=120, env=ENV, cwd=ROOT)
    assert r.returncode == 2 and "2 MPI processes for 1 vesicles" in one_line_error(r)
    assert not (tmp_path / "m.h5").exists()


# ------------------------------------------------------------------------------------------
# Effects follow the scene and cost nothing when off: their kernels are never called
# ------------------------------------------------------------------------------------------
def scene_text(centers, lam=(), flow=True, gravity=False, drho=0.0, repulsion=False, p=4):
    s = "[discretization]\np = %d\n[time]\nhorizon = 0.1\ndt = 0.05\n" % p
    if flow:
        s += "[flow]\ntype = 'shear'\nrate = 1.0\n"
    if gravity:
        s += "[gravity]\ng = [0.0, 0.0, -1.0]\n"
    if repulsion:
        s += "[repulsion]\nradius = 0.06\n"
    for k, c in enumerate(centers):
        s += (f"[[vesicle]]\nshape = 'oblate'\nreduced_volume = 0.85\ncenter = {list(c)}\n"
              f"bending_modulus = 0.1\nexcess_density = {drho}\n"
              f"viscosity_contrast = {lam[k] if k < len(lam) else 1.0}\n")
    return s


PAIR_CLOSE = [(-1.2, 0.0, 0.2), (1.2, 0.0, -0.2)]     # near pairs exist
PAIR_FAR = [(-10.0, 0.0, 0.0), (10.0, 0.0, 0.0)]      # no near pair
SINGLE = [(0.0, 0.0, 0.0)]


class Spy:
    """Counts the calls of owner.name (monkeypatched, restored after the test)."""

    def __init__(self, monkeypatch, owner, name):
        self.calls = 0
        orig = getattr(owner, name)

        def spy(*a, **k):
            self.calls += 1
            return orig(*a, **k)
        monkeypatch.setattr(owner, name, spy)


def one_step(text):
    """A Run of one accepted step (no adaptivity) plus one velocity solve, no output."""
    pytest.importorskip("petsc4py").init([])
    from vesflow.options import dict_getter, read_options
    from vesflow.scene import parse_scene
    from vesflow.simulation import Run
    sc = parse_scene(text)
    opts = read_options(dict_getter({"-ves_adapt": "none", "-ts_max_steps": 1}), sc)
    run = Run(sc, opts)
    run.run()
    assert run.counts["accepted"] == 1
    return run


def double_layer_spies(mp):
    from vesflow._kernels import stokes
    from vesflow.layerpot import singular
    spies = [Spy(mp, stokes, "stresslet_sum_excl"), Spy(mp, stokes, "stresslet_sum_pairs")]
    orig = singular.SelfOperators._assemble
    dl = {"n": 0}

    def assemble(self, X, want_single, want_double):
        dl["n"] += bool(want_double)
        return orig(self, X, want_single, want_double)
    mp.setattr(singular.SelfOperators, "_assemble", assemble)
    return lambda: sum(s.calls for s in spies) + dl["n"]


@pytest.mark.parametrize("lam,on", [((1.0, 1.0), False), ((1.0, 3.0), True)])
def test_double_layer_kernels_only_with_a_viscosity_contrast(monkeypatch, lam, on):
    count = double_layer_spies(monkeypatch)
    one_step(scene_text(PAIR_CLOSE, lam=lam))
    assert (count() > 0) == on, count()


@pytest.mark.parametrize("repulsion", [False, True])
def test_repulsion_only_with_a_repulsion_table(monkeypatch, repulsion):
    from vesflow import repulsion as rep
    spy = Spy(monkeypatch, rep, "repulsion_force")
    one_step(scene_text(PAIR_CLOSE, repulsion=repulsion))
    assert (spy.calls > 0) == repulsion


@pytest.mark.parametrize("gravity,drho,on", [(False, 1.0, False), (True, 0.0, False), (True, 1.0, True)])
def test_gravity_force_only_with_gravity_and_a_density_difference(monkeypatch, gravity, drho, on):
    from vesflow import forces
    spy = Spy(monkeypatch, forces, "gravity_force")
    one_step(scene_text(SINGLE, flow=False, gravity=gravity, drho=drho))
    assert (spy.calls > 0) == on


def near_spies(mp):
    from vesflow import collision
    from vesflow._kernels import search, stokes
    from vesflow.layerpot import near
    return {"projection": [Spy(mp, near, "Projection"), Spy(mp, collision, "Projection")],
            "correction": [Spy(mp, near, "interpolation_weights"), Spy(mp, near, "line_points"),
                           Spy(mp, stokes, "stokeslet_sum_pairs")],
            "search": [Spy(mp, search, "near_pairs")]}


@pytest.mark.parametrize("centers,search_on,near_on", [(SINGLE, False, False), (PAIR_FAR, True, False),
                                                       (PAIR_CLOSE, True, True)])
def test_near_field_only_for_close_vesicles(monkeypatch, centers, search_on, near_on):
    spies = near_spies(monkeypatch)
    one_step(scene_text(centers))
    n = {k: sum(s.calls for s in v) for k, v in spies.items()}
    assert (n["search"] > 0) == search_on, n          # a single vesicle does not even search
    assert (n["projection"] > 0) == near_on and (n["correction"] > 0) == near_on, n


@pytest.mark.parametrize("centers,on", [(SINGLE, False), (PAIR_FAR, True)])
def test_far_field_only_with_more_than_one_vesicle(monkeypatch, centers, on):
    from vesflow._kernels import stokes
    from vesflow.layerpot import far
    spies = [Spy(monkeypatch, far.FarField, "__init__"), Spy(monkeypatch, far.FarField, "evaluate"),
             Spy(monkeypatch, stokes, "stokeslet_sum_excl")]
    one_step(scene_text(centers))
    assert all((s.calls > 0) == on for s in spies), [s.calls for s in spies]


def test_background_flow_evaluated_with_a_flow(monkeypatch):
    from vesflow import stepper
    spy = Spy(monkeypatch, stepper, "background_velocity")
    one_step(scene_text(SINGLE, flow=True))
    assert spy.calls > 0


def test_background_flow_not_evaluated_without_a_flow(monkeypatch):
    from vesflow import stepper
    spy = Spy(monkeypatch, stepper, "background_velocity")
    one_step(scene_text(SINGLE, flow=False))
    assert spy.calls == 0


def test_area_and_volume_kept_to_the_correction_tolerance():
    """The correction comes after the reparameterization (which changes A and V by ~1e-6)."""
    run = one_step(scene_text(SINGLE, p=8))
    S = run.stepper.surface
    assert np.abs(S.area() / run.area0 - 1).max() < 1e-8
    assert np.abs(S.volume() / run.volume0 - 1).max() < 1e-8


# ------------------------------------------------------------------------------------------
# vesflow check: effects and the cost estimate
# ------------------------------------------------------------------------------------------
def test_estimate_follows_the_storage_formulas():
    from vesflow.costs import estimate
    from vesflow.scene import parse_scene
    for p, lam, n in ((8, 1.0, 1), (12, 4.0, 1), (6, 1.0, 2)):
        centers = SINGLE if n == 1 else PAIR_CLOSE
        e = estimate(parse_scene(scene_text(centers, lam=(lam,) * n, p=p)))
        C = (p + 1) ** 2 - 1
        assert e.mem_self == n * (2 if lam != 1 else 1) * (3 * C) ** 2 * 8
        assert e.mem_pc == n * (4 * C) ** 2 * 8 and e.mem_pc_max == 3 * e.mem_pc
        assert e.unknowns == n * 4 * C and e.double_layer == (lam != 1)
        if n == 1:
            assert e.t_far == 0 and e.t_near == 0 and e.far_backend == "none" and e.mem_sources == 0
        else:
            assert e.t_far > 0 and e.near_pairs > 0 and e.t_near > 0
        assert 0 < e.t_iteration < 1.0 and e.memory >= e.mem_self + e.mem_pc
    small, big = (estimate(parse_scene(scene_text(PAIR_CLOSE, p=p))) for p in (6, 12))
    assert big.t_iteration > 2 * small.t_iteration and big.t_setup > 4 * small.t_setup


def test_estimate_of_a_time_step_and_the_memory_verdict():
    from vesflow.costs import ITERATIONS_PER_SOLVE, estimate
    from vesflow.scene import parse_scene
    # the euler figures (pinned to -ts_type euler): -ves_adapt doubling, dt then two dt/2
    e = estimate(parse_scene(scene_text(PAIR_CLOSE, p=6)), {"ts_type": "euler"})
    assert e.solves_per_step == 3
    assert e.t_step == pytest.approx(3 * (e.t_setup + ITERATIONS_PER_SOLVE * e.t_iteration))
    assert "per time step" in str(e) and "RAM: fits (needs" in str(e)
    one = estimate(parse_scene(scene_text(PAIR_CLOSE, p=6)), {"ts_type": "euler", "adapt": "none"})
    assert one.solves_per_step == 1 and one.t_step == pytest.approx(e.t_step / 3)
    # the default, sdc with 3 Radau nodes and 2 sweeps: 2 substeps x (1 + 2 x 2) solves
    assert estimate(parse_scene(scene_text(PAIR_CLOSE, p=6))).solves_per_step == 10
    assert estimate(parse_scene(scene_text(PAIR_CLOSE, p=6)), {"ts_sdc_quadrature": "lobatto"}).solves_per_step == 11


def test_check_prints_effects_costs_and_takes_overrides():
    r = vesflow(["check", "runs/shear_pair.toml", "-ves_p", "8"])
    assert r.returncode == 0, r.stderr
    assert "effects  on: background flow, near/far field" in r.stdout
    assert "off: gravity, double layer, repulsion, periodic" in r.stdout
    assert "unknowns p = 8:" in r.stdout and "per GMRES iteration" in r.stdout
    C = 80
    assert f"self operators {2 * (3 * C) ** 2 * 8 / 2**20:.1f} MiB" in r.stdout
    r = vesflow(["check", "runs/shear_pair.toml", "-ves_p", "100"])
    assert r.returncode == 2 and "-ves_p" in one_line_error(r)


# ------------------------------------------------------------------------------------------
# Progress line, -help, scene overrides
# ------------------------------------------------------------------------------------------
def _run_on_a_terminal(args):
    """stderr is a pseudo-terminal; returns (status, stdout, what the terminal showed)."""
    master, slave = pty.openpty()
    proc = subprocess.Popen(VESFLOW + [str(a) for a in args], cwd=ROOT, env=ENV, stdout=subprocess.PIPE,
                            stderr=slave, text=True)
    os.close(slave)
    shown = b""
    while True:
        ready, _, _ = select.select([master], [], [], 60)
        if not ready:
            break
        try:
            chunk = os.read(master, 4096)
        except OSError:        # EIO: the child closed the terminal
            break
        if not chunk:
            break
        shown += chunk
    out = proc.communicate(timeout=60)[0]
    os.close(master)
    return proc.returncode, out, shown.decode(errors="replace")


def test_progress_line_on_a_terminal_only_and_overrides_reach_the_file(tmp_path):
    from vesflow.io import read_output
    args = ["run", "-o", tmp_path / "t.h5", "-ves_p", "4", "-ts_max_time", "0.1", "-ves_output_every", "0.05"]
    rc, out, shown = _run_on_a_terminal(args)
    assert rc == 0, shown
    assert "\r t =" in shown and "dt =" in shown and "its =" in shown and "rejected" in shown
    res = read_output(tmp_path / "t.h5")
    assert res.p == 4 and res.attrs["scene"].startswith("# vesflow's built-in scene")
    np.testing.assert_allclose(res.time, [0.0, 0.05, 0.1])
    piped = lambda a: subprocess.run(VESFLOW + [str(x) for x in a], capture_output=True, timeout=300,
                                     env=ENV, cwd=ROOT)
    r = piped(args)                                      # a pipe: no progress line
    assert r.returncode == 0 and b"\r" not in r.stderr and b" t =" not in r.stderr
    r = piped(args + ["-ves_progress", "on"])
    assert r.returncode == 0 and b"\r t =" in r.stderr


def test_help_lists_every_option_with_its_default():
    from vesflow.options import REGISTRY
    r = vesflow(["run", "-help"])
    assert r.returncode == 0
    lines = r.stdout.splitlines()
    for o in REGISTRY:
        row = [line for line in lines if line.strip().startswith(o.name + " ")]
        assert row and f"default: {o.shown_default}" in row[0], o.name


@pytest.mark.parametrize("args,words", [(["runs/taylor_green.toml", "-ves_far", "direct"], "periodic domain")])
def test_unavailable_features_stop_before_any_output(monkeypatch, tmp_path, capsys, args, words):
    """Exit status 3, one line, and no output file left behind."""
    pytest.importorskip("petsc4py").init([])
    out = tmp_path / "x.h5"
    rc = _cli(monkeypatch, ["run", *args, "-o", out])
    err = capsys.readouterr().err
    assert rc == 3 and words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


# ------------------------------------------------------------------------------------------
# Periodic runs: the wrap into the cell, the unwrapped centroid, an exact restart across a face
# ------------------------------------------------------------------------------------------
FALLING = """title = "a vesicle sediments through the bottom face of a periodic box"
[domain]
period = 5.0
[gravity]
g = [0.0, 0.0, -1.0]
[discretization]
p = 4
[time]
horizon = 0.4
dt = 0.1
[output]
every = 0.1
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
center = [2.5, 2.5, 0.2]
bending_modulus = 0.1
excess_density = 10.0
"""
FALLING_OPTS = ["-ves_far_tol", "1e-5", "-ts_monitor"]


@pytest.mark.slow
def test_periodic_run_wraps_into_the_cell_and_restarts_exactly_across_a_face(tmp_path):
    """The vesicle falls through z = 0 at t ~ 0.25: from then on its stored geometry is moved
    up by L (/frames/image = -1 in z), the stored centroid stays unwrapped and continuous, and
    a run stopped after the crossing (checkpoint with image -1) and restarted ends in the very
    state of the uninterrupted run."""
    from vesflow.io import read_checkpoint, read_output
    scene = tmp_path / "falling.toml"
    scene.write_text(FALLING)
    r = vesflow(["run", scene, "-o", tmp_path / "ref.h5"] + FALLING_OPTS)
    assert r.returncode == 0, r.stderr
    ref = read_output(tmp_path / "ref.h5")
    L = 5.0
    z = ref.frames["centroid"][:, 0, 2]
    np.testing.assert_allclose(ref.time, [0.0, 0.1, 0.2, 0.3, 0.4], atol=1e-12)
    assert np.all(np.diff(z) < -0.05) and z[2] > 0 and z[3] < 0             # falls through z = 0 ...
    np.testing.assert_array_equal(ref.frames["image"][:, 0], [[0, 0, 0]] * 3 + [[0, 0, -1]] * 2)
    stored = ref.frames["points"][:, 0].mean(axis=1)                       # ... and is drawn at the top
    assert np.all((stored >= 0) & (stored < L))
    assert stored[3, 2] > L - 0.2 and stored[2, 2] < 0.2
    np.testing.assert_allclose(ref.unwrapped("points")[:, 0].mean(axis=1)[:, 2], stored[:, 2] + L * np.array([0, 0, 0, -1, -1]))
    # the unwrapped coefficients give the unwrapped centroid
    from vesflow.surface import Surface
    c_unwrapped = Surface(ref.unwrapped("coefficients")[-1], 4).centroid()
    np.testing.assert_allclose(c_unwrapped, ref.frames["centroid"][-1], atol=1e-12)
    # stopped after the crossing, restarted: the same steps and state
    out = tmp_path / "stopped.h5"
    r = vesflow(["run", scene, "-o", out, "-ts_max_steps", "3"] + FALLING_OPTS)
    assert r.returncode == 0, r.stderr
    ck = read_checkpoint(out)
    assert float(ck["time"]) == pytest.approx(0.3) and list(ck["image"][0]) == [0, 0, -1]
    r = vesflow(["run", "--restart", out, "-ts_max_steps", "1000"])
    assert r.returncode == 0, r.stderr
    res = read_output(out)
    assert_same_run(res, ref)
    np.testing.assert_array_equal(res.frames["image"], ref.frames["image"])
    np.testing.assert_array_equal(res.frames["centroid"], ref.frames["centroid"])
