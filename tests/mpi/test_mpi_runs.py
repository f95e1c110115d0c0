"""`mpiexec -n 2 vesflow run` (issue 19): the same trajectory as one process, and restarts across
process counts.  Ordinary tests that start the runs as subprocesses (make test runs them)."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vesflow.io import read_checkpoint, read_output

from tests.harness import ROOT  # noqa: E402
MPIEXEC = Path(sys.executable).parent / "mpiexec"
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")

# three vesicles in a row, scene order not the Morton order (rank 0: vesicles 2 and 0, rank 1:
# vesicle 1); gaps ~0.1, inside the near zone: near pairs cross the rank boundary; viscosity
# contrasts 3 and 0.5 (double layer); repulsion
SCENE = """title = "three vesicles in a row, two ranks"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 6
[time]
horizon = 0.1
dt = 0.05
[output]
file = "out/mpi_row.h5"
every = 0.05
[repulsion]
radius = 0.1
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
center = [0.0, 0.0, 0.0]
viscosity_contrast = 3.0
[[vesicle]]
shape = "prolate"
reduced_volume = 0.9
center = [2.1, 0.0, 0.1]
[[vesicle]]
shape = "oblate"
reduced_volume = 0.9
center = [-2.45, 0.1, 0.0]
viscosity_contrast = 0.5
"""
OPTS = ["-ves_far", "direct"]


def vesflow(args, ranks=1):
    cmd = [sys.executable, "-m", "vesflow"] + [str(a) for a in args]
    if ranks > 1:
        cmd = [str(MPIEXEC), "-n", str(ranks)] + cmd
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=ENV, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    return r


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted one-process run."""
    d = tmp_path_factory.mktemp("mpi")
    scene = d / "row.toml"
    scene.write_text(SCENE)
    vesflow(["run", scene, "-o", d / "one.h5"] + OPTS)
    ref = read_output(d / "one.h5")
    assert ref.time[-1] == pytest.approx(0.1) and ref.n_frames == 3
    return scene, ref


def assert_same_trajectory(out, ref, tol=1e-10):
    assert np.array_equal(out.time, ref.time)
    np.testing.assert_allclose(out.steps["dt"], ref.steps["dt"], rtol=1e-8)       # the same steps (dt: a ratio of differences, ~1e-11)
    assert np.array_equal(out.steps["ksp_its"], ref.steps["ksp_its"])
    c, c_ref = out.frames["coefficients"], ref.frames["coefficients"]
    err = np.abs(c - c_ref).max()
    assert err <= tol, f"trajectories differ by {err:.2e}"
    return err


def test_two_ranks_give_the_one_process_trajectory(reference, tmp_path):
    scene, ref = reference
    r = vesflow(["run", scene, "-o", tmp_path / "two.h5"] + OPTS, ranks=2)
    assert r.stdout.count("vesflow: done") == 1          # progress lines from rank 0 only
    out = read_output(tmp_path / "two.h5")
    assert_same_trajectory(out, ref)
    # the pair across the ranks did interact: the row is not three independent vesicles
    assert ref.steps["ksp_its"].max() > 0 and out.n_vesicles == 3


@pytest.mark.parametrize("first,second", [(2, 1), (1, 2)])
def test_restart_on_another_number_of_ranks(reference, tmp_path, first, second):
    """Stop at t = 0.05 (a frame, where the uninterrupted run checkpoints too), continue with the
    other number of processes to 0.1: the uninterrupted run's final state."""
    scene, ref = reference
    out = tmp_path / "cont.h5"
    vesflow(["run", scene, "-o", out, "-ts_max_time", "0.05"] + OPTS, ranks=first)
    assert float(read_checkpoint(out)["time"]) == pytest.approx(0.05)
    vesflow(["run", "--restart", out, "-ts_max_time", "0.1"], ranks=second)
    res = read_output(out)
    assert list(res.restarts) == pytest.approx([0.05])
    assert_same_trajectory(res, ref)


def test_single_precision_options_same_on_one_and_two_ranks(reference, tmp_path):
    """-ves_self_precision / -ves_pc_precision single on 2 ranks give the 1-rank trajectory to
    float32 rounding, not to 1e-10: the last-bit differences of the ranks' sums (1e-16) round
    to a different float32 now and then, and the step-doubling error (a difference of two
    solutions) magnifies them in dt.  Measured: dt 3e-6 relative, coefficients 5.0e-9; from
    double's run 2.2e-8 (not nothing: the options act)."""
    scene, ref = reference
    single = OPTS + ["-ves_self_precision", "single", "-ves_pc_precision", "single"]
    vesflow(["run", scene, "-o", tmp_path / "one.h5"] + single)
    vesflow(["run", scene, "-o", tmp_path / "two.h5"] + single, ranks=2)
    one, two = read_output(tmp_path / "one.h5"), read_output(tmp_path / "two.h5")
    assert np.array_equal(two.time, one.time) and len(two.steps["dt"]) == len(one.steps["dt"])
    np.testing.assert_allclose(two.steps["dt"], one.steps["dt"], rtol=1e-4)
    d2 = np.abs(two.frames["coefficients"] - one.frames["coefficients"]).max()
    d = np.abs(one.frames["coefficients"] - ref.frames["coefficients"]).max()
    assert d2 < 1e-7, d2
    assert 0 < d < 1e-6, d
