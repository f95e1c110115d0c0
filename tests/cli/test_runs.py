"""Everything in runs/ keeps working: each scene runs end to end in its small variant
(`-options_file runs/small.opts`), the options files are valid, the SLURM template runs and
continues a run."""
import glob
import os
import shlex
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.harness import ROOT  # noqa: E402
RUNS = ROOT / "runs"
VESFLOW = [sys.executable, "-m", "vesflow"]
ENV = dict(os.environ, OMP_NUM_THREADS="1")
SMALL_T = 0.15           # the horizon of runs/small.opts


BIG = 32                 # scenes with more vesicles: slow (runs/taylor_green_64.toml: minutes at p = 4)


def _scenes():
    from vesflow.scene import load_scene
    out = []
    for path in sorted(glob.glob(str(RUNS / "*.toml"))):
        big = load_scene(path).n_vesicles > BIG
        out.append(pytest.param(path, id=Path(path).stem, marks=[pytest.mark.slow] if big else []))
    return out


@pytest.mark.parametrize("scene", _scenes())
def test_small_variant_runs_end_to_end(scene, tmp_path):
    from vesflow.io import read_checkpoint, read_output
    from vesflow.scene import load_scene
    out = tmp_path / "small.h5"
    r = subprocess.run(VESFLOW + ["run", scene, "-o", str(out), "-options_file", str(RUNS / "small.opts")],
                       capture_output=True, text=True, timeout=1800, env=ENV, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    res = read_output(out)
    sc = load_scene(scene)
    assert res.p == 4 and res.n_vesicles == sc.n_vesicles and res.attrs["scene"] == sc.text
    t = res.time
    assert res.n_frames >= 3 and t[0] == 0.0 and t[-1] == pytest.approx(SMALL_T) and np.all(np.diff(t) > 0)
    for name, v in res.frames.items():
        assert np.all(np.isfinite(v)), f"non-finite values in /frames/{name}"
    assert np.all(np.isfinite(res.steps["dt"])) and res.steps["accepted"].sum() >= 2
    A, V = res.frames["area"], res.frames["volume"]
    assert np.abs(A / A[0] - 1).max() < 1e-8 and np.abs(V / V[0] - 1).max() < 1e-8
    assert read_checkpoint(out)["time"] == pytest.approx(SMALL_T)


@pytest.mark.parametrize("opts", sorted(glob.glob(str(RUNS / "*.opts"))), ids=lambda p: Path(p).name)
def test_options_files_in_runs_are_valid(opts):
    from vesflow import options
    from vesflow.cli import expand_options_files
    from vesflow.scene import default_scene
    args = expand_options_files(["-options_file", opts])
    assert args and all(not a.startswith("-options_file") for a in args)
    options.check_unknown([a for a in args if a.startswith("-ves_")])
    getter = options.argv_getter(args)
    sc = options.apply_overrides(default_scene(), getter)
    given = options.read_options(getter, sc).given
    ves = {a for a in args if a.startswith(("-ves_", "-ts_"))}
    scene_keys = {o.name for o in options.REGISTRY if o.scene_key}
    assert ves - scene_keys <= set(given)         # every vesflow option in it is read


def test_slurm_template_starts_then_continues_a_run(tmp_path):
    """runs/slurm_job.sh with a stand-in srun: the first job starts the scene, the second one
    (same OUT) continues it from its checkpoint."""
    from vesflow.io import read_checkpoint, read_output
    script = RUNS / "slurm_job.sh"
    assert subprocess.run(["bash", "-n", str(script)]).returncode == 0
    text = script.read_text()
    assert "#SBATCH --ntasks=" in text and "mpiexec -n" in text and "--restart" in text and "-options_file" in text
    bindir = tmp_path / "bin"
    bindir.mkdir()
    srun = bindir / "srun"
    srun.write_text('#!/bin/bash\nwhile [[ "$1" == --* ]]; do shift; done\nexec "$@"\n')
    srun.chmod(srun.stat().st_mode | stat.S_IEXEC)
    out = tmp_path / "job.h5"
    env = dict(ENV, PATH=f"{bindir}:{ENV['PATH']}", SLURM_SUBMIT_DIR=str(ROOT), SLURM_JOB_ID="42",
               SLURM_CPUS_PER_TASK="1", SCENE="runs/relaxation.toml", OUT=str(out),
               EXTRA="-options_file runs/small.opts -ts_max_steps 1")
    env.pop("VIRTUAL_ENV", None)
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "continuing" not in r.stdout and read_checkpoint(out)["n_accepted"] == 1
    assert "-ksp_rtol 1e-7" in read_output(out).attrs["options"]         # runs/production.opts
    env["EXTRA"] = "-ts_max_steps 2"
    r = subprocess.run(["bash", str(script)], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "continuing" in r.stdout
    res = read_output(out)
    assert len(res.restarts) == 1 and read_checkpoint(out)["n_accepted"] == 2
    assert shlex.split(res.attrs["restart_options"][0]) == ["-ts_max_steps", "2", "-log_view"]
