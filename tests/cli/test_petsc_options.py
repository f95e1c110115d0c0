"""PETSc's own options (issue #21): a bad one is one line and exit status 2 before the output
file is opened or a checkpoint touched; an unexpected error during a run is one line, exit
status 3 and the last accepted state saved; options nobody read are reported at the end."""
import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.harness import ROOT  # noqa: E402
VESFLOW = [sys.executable, "-m", "vesflow"]
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
SMALL = ["-ves_p", "4", "-ves_adapt", "none", "-ts_dt", "0.05"]       # the built-in scene, seconds


def vesflow(args):
    return subprocess.run(VESFLOW + [str(a) for a in args], capture_output=True, text=True, timeout=120,
                          env=ENV, cwd=ROOT)


def digest(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def one_line_error(r):
    lines = [line for line in r.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished short run (two steps to t = 0.1): the file a bad option must not touch."""
    path = tmp_path_factory.mktemp("finished") / "A.h5"
    r = vesflow(["run", "-o", path, "-ts_max_time", "0.1"] + SMALL)
    assert r.returncode == 0, r.stderr
    return path


# (options, what the line names, PETSc's reason in it); the first five are the table
BAD = [
    (["-ksp_rtol", "abc"], "-ksp_rtol abc", "Input string abc has no numeric value"),
    (["-ksp_type", "foo"], "-ksp_type foo", "Unable to find requested KSP type foo"),
    (["-pc_type", "nonsense"], "-pc_type nonsense", "Unable to find requested PC type nonsense"),
    (["-ksp_max_it", "-5"], "-ksp_max_it -5", "Maximum number of iterations -5 must be non-negative"),
    (["-ksp_gmres_restart", "x"], "-ksp_gmres_restart x", "Input string x has no integer value"),
    (["-ksp_gmres_restart", "-3"], "-ksp_gmres_restart -3", "Restart must be positive"),
    (["-ksp_max_it", "1.5"], "-ksp_max_it 1.5", "no integer value"),
    (["-ksp_rtol", "2"], "-ksp_rtol 2", "less than 1.0"),
    (["-ksp_type", "gmrs"], "-ksp_type gmrs", "did you mean gmres?"),
    (["-ksp_norm_type", "foo"], "-ksp_norm_type foo", "Available options"),
    (["-ksp_initial_guess_nonzero", "maybe"], "-ksp_initial_guess_nonzero maybe", "Unknown logical value"),
    (["-ksp_type", "cg", "-ksp_pc_side", "right"], "-ksp_type cg, -ksp_pc_side right",
     "does not support preconditioner side RIGHT"),
    (["-pc_type", "python"], "-pc_type python", "needs -pc_python_type"),
    (["-pc_type", "python", "-pc_python_type", "nosuch.Module"], "-pc_python_type nosuch.Module",
     "No module named 'nosuch'"),
    (["-pc_type", "python", "-pc_python_type", "vesflow.timing.Timers"], "-pc_python_type vesflow.timing.Timers",
     "not a preconditioner"),
    (["-pc_type", "lu"], "-pc_type lu", "matrix-free"),           # valid type, needs matrix entries
    (["-pc_type", "jacobi"], "-pc_type jacobi", "matrix-free"),   # ... found at its first apply
    ("options file", "bad.opts:3: -ksp_rtol abc", "Input string abc has no numeric value"),
]


@pytest.mark.parametrize("bad,names,reason", BAD, ids=[" ".join(b) if isinstance(b, list) else b
                                                       for b, _, _ in BAD])
def test_a_bad_petsc_option_is_one_line_exit_2_and_touches_no_file(tmp_path, finished, bad, names, reason):
    if bad == "options file":
        (tmp_path / "bad.opts").write_text("# solver\n-ksp_monitor\n-ksp_rtol abc   # typo\n")
        bad = ["-options_file", tmp_path / "bad.opts"]
    bad = bad + ["-ksp_converged_reason"]          # never read: PETSc's exit report must stay quiet
    new = tmp_path / "new.h5"
    r = vesflow(["run", "-o", new, "-ts_max_steps", "1"] + SMALL + bad)
    assert r.returncode == 2 and r.stdout == "", (r.stdout, r.stderr)
    line = one_line_error(r)
    assert names in line and reason in line, line
    assert not new.exists()
    # an existing file (its checkpoint included): continued in place, or overwritten by a new run
    existing = tmp_path / "A.h5"
    shutil.copyfile(finished, existing)
    before = digest(existing)
    for args in (["--restart", existing, "-o", existing, "-ts_max_time", "0.2"], ["-o", existing] + SMALL):
        r = vesflow(["run"] + args + bad)
        assert r.returncode == 2 and names in one_line_error(r), r.stderr
        assert digest(existing) == before


def test_check_reports_a_bad_petsc_option_too():
    r = vesflow(["check", "runs/relaxation.toml", "-ksp_type", "foo"])
    assert r.returncode == 2 and "-ksp_type foo: Unable to find requested KSP type foo" in one_line_error(r)


def test_good_petsc_options_run_and_unread_ones_are_reported_at_the_end(tmp_path):
    """-options_left (PETSc's convention, also PETSc's default): the misspelled options, and
    only those, are listed when the run ends; options vesflow itself read are not."""
    out = tmp_path / "o.h5"
    r = vesflow(["run", "-o", out, "-ts_max_steps", "1"] + SMALL +
                ["-ksp_rtoll", "1e-6", "-ts_max_tim", "2", "-ksp_rtol", "1e-7", "-ksp_gmres_restart", "40",
                 "-pc_type", "python", "-pc_python_type", "vesflow.precond.SphereSpectral",
                 "-ves_traceback", "-ts_monitor", "-options_left"])
    assert r.returncode == 0, r.stderr
    left = [line for line in r.stdout.splitlines() if line.startswith("Option left")]
    assert len(left) == 2 and "-ksp_rtoll value: 1e-6" in left[0] and "-ts_max_tim value: 2" in left[1], r.stdout
    assert "There are 2 unused database options" in r.stdout
    r = vesflow(["run", "-o", out, "-ts_max_steps", "1"] + SMALL + ["-ksp_rtol", "1e-7", "-options_left"])
    assert r.returncode == 0 and "There are no unused options" in r.stdout and "Option left" not in r.stdout


# ------------------------------------------------------------------------------------------
# An unexpected error during a run: one line (step, time, why), exit 3, last good state saved
# ------------------------------------------------------------------------------------------
def _cli(monkeypatch, args):
    from vesflow import cli
    monkeypatch.chdir(ROOT)
    return cli.main([str(a) for a in args])


# pinned to -ts_type euler: the failing call counts below are euler's with step doubling (3 solves a step)
RUN = ["run", "-ves_p", "4", "-ves_output_every", "1.0", "-ts_max_time", "1.0", "-ts_type", "euler"]


def _failing_solve(monkeypatch, at_call, exc):
    from vesflow import stepper
    orig, calls = stepper.Stepper.solve, []

    def solve(self, dt, surface=None):
        calls.append(dt)
        if len(calls) == at_call:
            raise exc()
        return orig(self, dt, surface)
    monkeypatch.setattr(stepper.Stepper, "solve", solve)
    return calls


def _petsc_error():
    from petsc4py import PETSc
    try:
        PETSc.KSP().create(comm=PETSc.COMM_SELF).setType("no_such_type")
    except PETSc.Error as e:
        return e


@pytest.mark.parametrize("exc,reason", [(_petsc_error, "Unable to find requested KSP type no_such_type"),
                                        (lambda: ValueError("boom"), "ValueError: boom")])
def test_an_error_inside_a_step_is_one_line_exit_3_and_the_last_accepted_state_is_saved(
        monkeypatch, tmp_path, capsys, exc, reason):
    """The error hits the second half step of step 3 (step doubling: 3 solves a step), when the
    stepper holds a half-advanced state: the checkpoint must be the state after step 2, the
    same bits as a run stopped by -ts_max_steps 2."""
    pytest.importorskip("petsc4py").init([])
    from vesflow.io import read_checkpoint, read_output
    ref = tmp_path / "ref.h5"
    assert _cli(monkeypatch, RUN + ["-o", ref, "-ts_max_steps", "2"]) == 0
    capsys.readouterr()
    out = tmp_path / "fail.h5"
    calls = _failing_solve(monkeypatch, 9, exc)
    rc = _cli(monkeypatch, RUN + ["-o", out])
    err = capsys.readouterr().err
    assert rc == 3 and len(calls) == 9
    line = one_line_error(type("R", (), {"stderr": err}))
    res = read_output(out)
    assert list(res.steps["accepted"]) == [1, 1]                  # no rejection: call 9 is in step 3
    t2 = float(np.sum(res.steps["dt"]))
    assert f"step 3 (t = {t2:.6g}, dt = " in line and reason in line and "--restart" in line, line
    ck, ck_ref = read_checkpoint(out), read_checkpoint(ref)
    assert ck["n_accepted"] == 2 and ck["time"] == ck_ref["time"] == pytest.approx(t2)
    np.testing.assert_array_equal(ck["coeffs"], ck_ref["coeffs"])
    np.testing.assert_array_equal(ck["sigma"], ck_ref["sigma"])


def test_ves_traceback_shows_the_trace_then_the_line(monkeypatch, tmp_path, capsys):
    pytest.importorskip("petsc4py").init([])
    _failing_solve(monkeypatch, 1, lambda: ValueError("boom"))
    rc = _cli(monkeypatch, RUN + ["-o", tmp_path / "x.h5", "-ves_traceback"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 3 and err[0].startswith("Traceback") and "ValueError: boom" in err[-2]
    assert err[-1].startswith("vesflow: RunError: step 1 (t = 0, dt = ") and "ValueError: boom" in err[-1]
