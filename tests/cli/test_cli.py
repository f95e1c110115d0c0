"""The command line: exit statuses, one-line errors, the scenes in runs/ stay valid."""
import glob
import os
import subprocess
import sys

import pytest

from tests.harness import ROOT

VESFLOW = [sys.executable, "-m", "vesflow"]


def run(args, **kw):
    return subprocess.run(VESFLOW + args, capture_output=True, text=True, timeout=600, **kw)


@pytest.mark.parametrize("scene", sorted(glob.glob(os.path.join(ROOT, "runs", "*.toml"))))
def test_every_scene_in_runs_checks(scene):
    r = run(["check", scene])
    assert r.returncode == 0, r.stderr
    assert "effects" in r.stdout.lower() or "on" in r.stdout


@pytest.mark.parametrize("text,key", [
    ("[discretization]\np = 1\n[[vesicle]]\n", "discretization.p"),
    ("[flow]\ntype = 'swirl'\n[[vesicle]]\n", "flow.type"),
    ("[[vesicle]]\nshape = 'oblate'\nreduced_volume = 1.5\n", "reduced_volume"),
    ("[[vesicle]]\nradiuss = 1.0\n", "radiuss"),
    ("[[vesicle]]\ncenter = [0,0,0]\n[[vesicle]]\ncenter = [0.5,0,0]\n", "overlap"),
])
def test_bad_scene_is_one_line_and_exit_2(tmp_path, text, key):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    for cmd in (["check", str(f)], ["run", str(f), "-o", str(tmp_path / "x.h5")]):
        r = run(cmd)
        assert r.returncode == 2, r.stderr
        lines = [l for l in r.stderr.strip().splitlines() if l]
        assert len(lines) == 1 and "Traceback" not in r.stderr
        assert key in lines[0]


def test_bad_option_is_one_line_and_exit_2(tmp_path):
    r = run(["run", "-o", str(tmp_path / "x.h5"), "-ves_qself", "12"])
    assert r.returncode == 2 and "did you mean -ves_q_self" in r.stderr


def test_help_lists_options_with_defaults():
    r = run(["run", "-help"])
    assert r.returncode == 0
    for name in ("-ves_p", "-ves_adapt_tol", "-ves_pc_lag", "-ts_max_time"):
        assert name in r.stdout


def test_short_run_writes_frames_and_renders(tmp_path):
    out = tmp_path / "run.h5"
    r = run(["run", "-o", str(out), "-ts_max_time", "0.2", "-ves_adapt", "none", "-ts_dt", "0.1"])
    assert r.returncode == 0, r.stderr
    from vesflow.io import read_output
    res = read_output(str(out))
    assert res.frames["points"].shape[1:] == (2, 2 * 8 * 9, 3)
    assert res.time[-1] == pytest.approx(0.2)
    assert len(res.steps["dt"]) == 2
