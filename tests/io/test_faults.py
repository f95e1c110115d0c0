"""How runs end when the world interferes (issue 32, docs/howto/cluster_runs.md): SIGKILL at random
moments then --restart, SIGTERM / SIGUSR1 / SIGINT on 1 and 2 ranks, a full disk, I/O errors and
process death at every write of the file layer, a second run on a file in use.  In every case: no
traceback, no segfault, a readable file, and a restart that gives the uninterrupted run."""
import errno
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from vesflow.errors import OutputError, SceneError
from vesflow.io import OutputWriter, journal, read_checkpoint, read_output

from tests.harness import synthetic_frames

ROOT = Path(__file__).resolve().parents[2]

PY = sys.executable
VESFLOW = [PY, "-m", "vesflow"]
ENV = dict(os.environ, OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
MPIEXEC = Path(PY).parent / "mpiexec"

# two oblate vesicles in shear, p = 4: 10 steps of 0.05, a frame (and checkpoint) every 0.1
PAIR = """title = "fault test: two vesicles in shear"
[flow]
type = "shear"
rate = 1.0
[discretization]
p = 4
[time]
horizon = 0.5
dt = 0.05
[output]
file = "out/fault_test.h5"
every = 0.1
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
# a signal stops a run between frames, at a checkpoint the uninterrupted run does not write: with
# the preconditioner rebuilt for every new shape (-ves_pc_lag 1) the state at a step boundary
# determines the rest of the run whatever the preconditioner's reuse policy (with the lagged
# default the restart differs by ~3e-10: its preconditioner starts fresh where the uninterrupted
# run's was reused)
SIGNAL_OPTS = ["-ves_output_every", "0.25", "-ves_pc_lag", "1", "-ts_monitor"]
STOP_LINE = re.compile(r"^vesflow: stopped by (SIG\w+) at t = (\S+), step (\d+); checkpoint at t = (\S+); "
                       r"continue with --restart (\S+)$")


def vesflow(args, launcher=(), **kw):
    return subprocess.run(list(launcher) + VESFLOW + [str(a) for a in args], capture_output=True, text=True,
                          timeout=300, env=ENV, cwd=ROOT, **kw)


def popen(args, launcher=()):
    return subprocess.Popen(list(launcher) + VESFLOW + [str(a) for a in args], cwd=ROOT, env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def clean(stderr, returncode):
    """No traceback, no PETSc error block, no segfault."""
    assert "Traceback" not in stderr and "PETSC ERROR" not in stderr, stderr
    assert returncode not in (-signal.SIGSEGV, 128 + signal.SIGSEGV, -signal.SIGABRT), (returncode, stderr)


def one_line(stderr):
    lines = [ln for ln in stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


def wait_for_step(proc, k):
    """Read -ts_monitor lines until step k (numbered in this process) was attempted."""
    for line in proc.stdout:
        if line.startswith("step") and int(line.split()[1]) >= k:
            return
    raise AssertionError(f"the run ended before step {k}")


def same_run(out, ref):
    """The frames of out are those of the uninterrupted run ref: the same times, the same steps,
    the coefficients within 1e-12 of the largest."""
    assert np.array_equal(out.time, ref.time), (out.time, ref.time)
    np.testing.assert_array_equal(out.steps["dt"], ref.steps["dt"])
    c, c_ref = out.frames["coefficients"], ref.frames["coefficients"]
    err = np.abs(c - c_ref).max()
    assert err <= 1e-12 * np.abs(c_ref).max(), f"differs from the uninterrupted run by {err:.2e}"


def _reference(tmp_path_factory, name, opts, launcher=()):
    d = tmp_path_factory.mktemp(name)
    scene = d / "pair.toml"
    scene.write_text(PAIR)
    t0 = time.perf_counter()
    proc = popen(["run", scene, "-o", d / "ref.h5"] + opts, launcher)
    first = None
    for line in proc.stdout:
        if first is None and line.startswith("step"):
            first = time.perf_counter() - t0
    assert proc.wait() == 0, proc.stderr.read()
    total = time.perf_counter() - t0
    ref = read_output(d / "ref.h5")
    assert ref.time[-1] == pytest.approx(0.5)
    n = len(ref.steps["dt"])
    return dict(scene=scene, ref=ref, path=d / "ref.h5", startup=first, step=(total - first) / n, n_steps=n)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run, default options (-ts_monitor for the kill timing)."""
    return _reference(tmp_path_factory, "ref", ["-ts_monitor"])


@pytest.fixture(scope="module")
def signal_reference(tmp_path_factory):
    return _reference(tmp_path_factory, "ref_signal", SIGNAL_OPTS)


@pytest.fixture(scope="module")
def mpi_reference(tmp_path_factory):
    """The uninterrupted run on two ranks (they sum in another order than one: 2e-14 apart)."""
    if not MPIEXEC.exists():
        pytest.skip(f"no {MPIEXEC}")
    return _reference(tmp_path_factory, "ref_mpi", SIGNAL_OPTS, [str(MPIEXEC), "-n", "2"])


# ------------------------------------------------------------------------------------------
# SIGKILL at random moments, each followed by --restart
# ------------------------------------------------------------------------------------------
def _accepted_in(path):
    try:
        return int(read_checkpoint(path)["n_accepted"])
    except Exception:           # killed before the file had its first checkpoint
        return None


def kill_chain(reference, tmp_path, n_kills, seed):
    """Start the run, SIGKILL it at a random moment, continue it with --restart, kill that at a
    random moment, ... n_kills times; then let the last restart finish.  A moment is, with
    probability 1/4, a time in the start-up (imports, PETSc, reopening the file), else a time
    within the step after a random step of the process (the step, its frame and checkpoint)."""
    rng = random.Random(seed)
    out = tmp_path / "killed.h5"
    fresh = ["run", reference["scene"], "-o", out, "-ts_monitor"]
    args, moments = fresh, []
    for _ in range(n_kills):
        done = _accepted_in(out) if out.exists() else None
        remaining = reference["n_steps"] - (done or 0)
        proc = popen(args)
        try:
            if remaining < 3 or rng.random() < 0.25:
                delay = rng.uniform(0.0, reference["startup"])
                moments.append(("start-up", round(delay, 3)))
                time.sleep(delay)
            else:
                k, u = rng.randrange(0, remaining - 2), rng.random()
                moments.append((f"step {k}", round(u, 3)))
                wait_for_step(proc, k)
                time.sleep(u * reference["step"])
            proc.send_signal(signal.SIGKILL)
            proc.wait(60)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == -signal.SIGKILL, f"the run ended before the kill at {moments[-1]}"
        clean(proc.stderr.read(), proc.returncode)
        if out.exists() and _accepted_in(out) is not None:     # readable, with a checkpoint
            read_output(out)
            args = ["run", "--restart", out]
        else:
            args = fresh
    r = vesflow(args)
    assert r.returncode == 0, (moments, r.stderr)
    clean(r.stderr, r.returncode)
    res = read_output(out)
    same_run(res, reference["ref"])
    assert not Path(str(out) + ".journal").exists()
    return moments


def test_sigkill_at_5_random_moments_each_followed_by_restart(reference, tmp_path):
    kill_chain(reference, tmp_path, 5, seed=32)


@pytest.mark.slow
def test_sigkill_at_20_random_moments_each_followed_by_restart(reference, tmp_path):
    kill_chain(reference, tmp_path, 20, seed=2032)


# ------------------------------------------------------------------------------------------
# Signals: stop at the next step boundary, a checkpoint, one line, exit 128 + N
# ------------------------------------------------------------------------------------------
def _stop_by_signal(signal_reference, tmp_path, sig, launcher=(), target=None):
    """The signal during step 1 (0.05 -> 0.107): the run stops at t = 0.107, between the frames at
    0 and 0.25 (later if this process was slow to send it)."""
    out = tmp_path / "stopped.h5"
    proc = popen(["run", signal_reference["scene"], "-o", out] + SIGNAL_OPTS, launcher)
    try:
        wait_for_step(proc, 0)
        os.kill(target(proc) if target else proc.pid, sig)
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = proc.stderr.read()
    clean(err, proc.returncode)
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    m = STOP_LINE.match(one_line(err))
    assert m, err
    name, t, step, t_ck, cont = m.groups()
    assert name == signal.Signals(sig).name and cont == str(out) and t == t_ck
    ck = read_checkpoint(out)
    assert float(ck["time"]) == pytest.approx(float(t), rel=1e-5) and int(ck["n_accepted"]) == int(step)
    assert 1 <= int(step) < signal_reference["n_steps"]       # after the step the signal came in
    stopped = read_output(out)
    assert stopped.time[-1] <= float(ck["time"]) + 1e-12
    return out, float(ck["time"])


def test_sigterm_stops_at_a_step_boundary_and_restart_gives_the_uninterrupted_run(signal_reference, tmp_path):
    for attempt in range(3):      # a stop between frames (the work since the frame kept), unless slow
        out, t_ck = _stop_by_signal(signal_reference, tmp_path / str(attempt), signal.SIGTERM)
        if min(abs(t_ck - k * 0.25) for k in range(3)) > 1e-6:
            break
    assert min(abs(t_ck - k * 0.25) for k in range(3)) > 1e-6, t_ck
    r = vesflow(["run", "--restart", out])
    assert r.returncode == 0, r.stderr
    clean(r.stderr, r.returncode)
    res = read_output(out)
    same_run(res, signal_reference["ref"])
    np.testing.assert_array_equal(res.restarts, [t_ck])


@pytest.mark.parametrize("sig", [signal.SIGUSR1, signal.SIGINT])
def test_sigusr1_and_sigint_stop_the_same_way(signal_reference, tmp_path, sig):
    _stop_by_signal(signal_reference, tmp_path, sig)


SECOND_SIGNAL = """
import os, signal, sys, time
from vesflow.signals import StopRequest
stop = StopRequest().install()
stop.out = "out.h5"
os.kill(os.getpid(), signal.SIGINT)
time.sleep(0.1)                     # the handler has run: the stop is requested
print("first", stop.received, stop.poll(), stop.signum, flush=True)
os.kill(os.getpid(), signal.SIGINT)
time.sleep(5)
print("still running", flush=True)
"""


def test_a_second_signal_stops_at_once():
    """Ctrl-C twice: the first requests the stop, the second ends the process by SIGINT's default
    action at once (a run waiting for the end of a long step)."""
    r = subprocess.run([PY, "-c", SECOND_SIGNAL], capture_output=True, text=True, timeout=60, env=ENV, cwd=ROOT)
    assert r.returncode == -signal.SIGINT, (r.returncode, r.stdout, r.stderr)
    assert r.stdout.split() == ["first", "2", "True", "2"]
    assert one_line(r.stderr) == "vesflow: second SIGINT: stopped at once; --restart out.h5 continues from the last checkpoint"


def _rank1_pid(mpiexec_pid):
    """The pid of rank 1 among the processes mpiexec started (PMI_RANK in its environment)."""
    deadline = time.time() + 30
    while time.time() < deadline:
        for d in Path("/proc").iterdir():
            if not d.name.isdigit():
                continue
            try:
                env = (d / "environ").read_bytes().split(b"\0")
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if b"PMI_RANK=1" in env and _descends_from(int(d.name), mpiexec_pid) and "python" in stat:
                return int(d.name)
        time.sleep(0.1)
    raise AssertionError("rank 1 not found")


def _descends_from(pid, ancestor):
    while pid > 1:
        if pid == ancestor:
            return True
        try:
            pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except OSError:
            return False
    return False


@pytest.mark.slow
@pytest.mark.parametrize("to", ["mpiexec", "rank 1 only"])
def test_sigterm_on_two_ranks(mpi_reference, tmp_path, to):
    """mpiexec forwards SIGTERM to every rank; sent to one rank only, the reduction of the flag at
    the step boundary stops both at the same boundary.  The restart on two ranks gives the
    uninterrupted two-rank run."""
    launcher = [str(MPIEXEC), "-n", "2"]
    target = (lambda proc: _rank1_pid(proc.pid)) if to == "rank 1 only" else None
    out, t_ck = _stop_by_signal(mpi_reference, tmp_path, signal.SIGTERM, launcher, target)
    r = vesflow(["run", "--restart", out], launcher)
    assert r.returncode == 0, r.stderr
    clean(r.stderr, r.returncode)
    same_run(read_output(out), mpi_reference["ref"])


# ------------------------------------------------------------------------------------------
# A second run on a file in use
# ------------------------------------------------------------------------------------------
def test_a_file_in_use_is_refused_before_any_work_and_the_first_run_is_unharmed(reference, tmp_path):
    out = tmp_path / "busy.h5"
    first = popen(["run", reference["scene"], "-o", out, "-ts_monitor"])
    try:
        wait_for_step(first, 1)
        first.send_signal(signal.SIGSTOP)             # held mid-run, the file open
        before = out.read_bytes()
        for args in (["run", reference["scene"], "-o", out], ["run", "--restart", out],
                     ["run", "--restart", reference["path"], "-o", out]):
            r = vesflow(args)
            clean(r.stderr, r.returncode)
            assert r.returncode == 2 and one_line(r.stderr) == f"vesflow: error: {out} is in use by another process"
            assert r.stdout == ""                     # no run started
        assert out.read_bytes() == before
        with pytest.raises(SceneError, match="in use by another process"):
            read_output(out)
        first.send_signal(signal.SIGCONT)
        assert first.wait(120) == 0
    finally:
        if first.poll() is None:
            first.send_signal(signal.SIGCONT)
            first.kill()
    same_run(read_output(out), reference["ref"])


# ------------------------------------------------------------------------------------------
# A full disk: a 200 kB tmpfs (the run's file grows to ~330 kB)
# ------------------------------------------------------------------------------------------
@pytest.fixture
def small_disk(tmp_path):
    d = tmp_path / "small"
    d.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200k", "tmpfs", str(d)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs: {r.stderr.strip()}")
    try:
        yield d
    finally:
        subprocess.run(["umount", str(d)], capture_output=True)


@pytest.mark.parametrize("ranks", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_full_disk_is_one_line_exit_3_a_readable_file_and_a_restart_once_there_is_space(reference, small_disk,
                                                                                      ranks):
    """On two ranks the failed write of rank 0 stops both at the next step boundary (no rank left
    waiting); the restart (on one rank) gives the one-rank run: the file holds frame 0 only."""
    if ranks > 1 and not MPIEXEC.exists():
        pytest.skip(f"no {MPIEXEC}")
    out = small_disk / "run.h5"
    launcher = [str(MPIEXEC), "-n", str(ranks)] if ranks > 1 else []
    r = vesflow(["run", reference["scene"], "-o", out, "-ts_monitor"], launcher)
    clean(r.stderr, r.returncode)
    assert r.returncode == 3, r.stderr
    line = one_line(r.stderr)
    m = re.match(rf"^vesflow: OutputError: {re.escape(str(out))}: no space left on device \((writing [^)]*)\); "
                 rf"the file holds (\d+) frames? up to t = (\S+) and the checkpoint at t = (\S+): "
                 rf"vesflow run --restart {re.escape(str(out))} continues it once there is space$", line)
    assert m, line
    n, t_frame, t_ck = int(m.group(2)), float(m.group(3)), float(m.group(4))
    ref = reference["ref"]
    part = read_output(out)
    assert 1 <= part.n_frames == n < ref.n_frames and part.time[-1] == pytest.approx(t_frame)
    assert ranks == 1 or n == 1
    np.testing.assert_array_equal(part.time, ref.time[:n])
    np.testing.assert_allclose(part.frames["coefficients"], ref.frames["coefficients"][:n], rtol=0, atol=1e-12)
    assert float(read_checkpoint(out)["time"]) == pytest.approx(t_ck)
    assert not Path(str(out) + ".journal").exists()
    subprocess.run(["mount", "-o", "remount,size=4m", str(small_disk)], check=True)
    r = vesflow(["run", "--restart", out])
    assert r.returncode == 0, r.stderr
    same_run(read_output(out), ref)


# ------------------------------------------------------------------------------------------
# Every write of the file layer: ENOSPC, EIO, process death, a torn write
# ------------------------------------------------------------------------------------------
P, N = 4, 2


def _frames(n):
    return synthetic_frames(p=P, n_vesicles=N, n_frames=n, dt=0.1, seed=5)


def _write_run(path, frames, start=0, writer=None):
    """What a run writes: the file, then per frame the frame, its step, the timings, the
    checkpoint; closed at the end whatever happened (as `vesflow run` does)."""
    w = writer or OutputWriter(path, scene_text="s", options_text="-x", version="t", p=P, n_vesicles=N,
                               periodic_length=0.0)
    try:
        if writer is None:
            w.write_attrs(options_resolved="-x")
        for k in range(start, len(frames)):
            fr = frames[k]
            if k:                                 # the step from the last frame to this one
                w.write_steps([(frames[k - 1]["time"], 0.1, 1, 4 + k, 0.01, "accepted")])
            w.write_frame(**fr)
            w.write_timings({"total": float(k)})
            w.write_checkpoint({"time": fr["time"], "x": fr["coefficients"], "k": k})
    finally:
        w.close()


class Faults:
    """Replaces the file layer's writes (journal._write_all, journal._truncate) and counts them.
    At write number `at`: "enospc" fails that write; "eio" fails it and every later one; "kill"
    copies the file and its journal as they are before it (what a process killed there leaves)
    to `dead`; "torn" does half of the write first, then copies.  The writer then goes on."""

    def __init__(self, monkeypatch, mode=None, at=None, path=None, dead=None):
        self.n, self.mode, self.at, self.path, self.dead = 0, mode, at, path, dead
        write, trunc = journal._write_all, journal._truncate

        def faulty_write(fd, data, offset):
            if self._fault():
                if self.mode == "torn":
                    write(fd, bytes(data)[:max(len(data) // 2, 1)], offset)
                if self.mode in ("kill", "torn"):
                    self._copy()
                else:
                    raise OSError(self._errno(), os.strerror(self._errno()))
            write(fd, data, offset)

        def faulty_trunc(fd, size):
            if self._fault():
                if self.mode in ("kill", "torn"):
                    self._copy()
                else:
                    raise OSError(self._errno(), os.strerror(self._errno()))
            trunc(fd, size)
        monkeypatch.setattr(journal, "_write_all", faulty_write)
        monkeypatch.setattr(journal, "_truncate", faulty_trunc)

    def _errno(self):
        return errno.ENOSPC if self.mode == "enospc" else errno.EIO

    def _fault(self):
        k, self.n = self.n, self.n + 1
        if self.at is None or k < self.at:
            return False
        return k == self.at or self.mode == "eio"

    def _copy(self):
        for src, dst in ((self.path, self.dead), (journal.journal_path(self.path), journal.journal_path(self.dead))):
            if os.path.exists(src):
                shutil.copyfile(src, dst)


def _check_file(path, frames, restart=True):
    """The file reads (after the rollback of a journal left beside it) with a prefix of the frames,
    exactly as written, and a checkpoint consistent with them; a restart continues it.  Returns
    (frames in the file, the checkpoint's frame or None)."""
    res = read_output(path)
    n = res.n_frames
    for i in range(n):
        np.testing.assert_array_equal(res.frames["coefficients"][i], frames[i]["coefficients"])
        np.testing.assert_array_equal(res.frames["points"][i], frames[i]["points"])
    assert not Path(journal.journal_path(path)).exists()
    try:
        ck = read_checkpoint(path)
    except SceneError:
        return n, None
    k = int(ck["k"])
    np.testing.assert_array_equal(ck["x"], frames[k]["coefficients"])
    assert k in (n - 1, n - 2), (n, k)
    assert len(res.steps["time"]) in (k, k + 1)
    if restart:
        w = OutputWriter.reopen(path)             # the restart: continue from the checkpoint
        _write_run(path, frames, start=k + 1, writer=w)
        full = read_output(path)
        np.testing.assert_array_equal(full.time, [f["time"] for f in frames])
        np.testing.assert_array_equal(full.steps["ksp_its"], 5 + np.arange(len(frames) - 1))
    return n, k


def _marks(monkeypatch, tmp_path, frames):
    """The write numbers at which creating the file ends, each frame's writes end, the close ends."""
    marks = []
    with monkeypatch.context() as mp:
        count = Faults(mp)
        w = OutputWriter(tmp_path / "count.h5", scene_text="s", options_text="-x", version="t", p=P,
                         n_vesicles=N, periodic_length=0.0)
        marks.append(count.n)
        w.close()
        count.n = 0
        w = OutputWriter(tmp_path / "count.h5", scene_text="s", options_text="-x", version="t", p=P,
                         n_vesicles=N, periodic_length=0.0)
        w.write_attrs(options_resolved="-x")
        for k in range(len(frames)):
            _write_run(None, frames[:k + 1], start=k, writer=_NoClose(w))
            marks.append(count.n)
        w.close()
        marks.append(count.n)
    return marks


class _NoClose:
    """A writer whose close() does nothing (to write a run a frame at a time)."""

    def __init__(self, w):
        self._w = w

    def __getattr__(self, name):
        return getattr(self._w, name)

    def close(self):
        pass


def _every_site(monkeypatch, tmp_path, n_frames, modes, sites="all", restart="all", kill_stride=1):
    """Each mode at each write number of `sites` ("all", or "last frame": the writes of the last
    frame and of the close); restart "all" (every case) or "first" (the first case of each
    outcome); kill and torn at every kill_stride-th write."""
    frames = _frames(n_frames)
    marks = _marks(monkeypatch, tmp_path, frames)
    n_create, n_sites = marks[0], marks[-1]
    assert n_sites > 10 * n_frames
    todo = range(n_sites) if sites == "all" else range(marks[-3], n_sites)
    seen = set()
    for mode in modes:
        for at in todo:
            if mode in ("kill", "torn") and at % kill_stride:
                continue
            path = tmp_path / f"{mode}_{at}.h5"
            dead = tmp_path / f"{mode}_{at}_dead.h5"
            with monkeypatch.context() as mp:
                Faults(mp, mode, at, path, dead)
                if mode in ("enospc", "eio"):
                    with pytest.raises(OutputError) as e:
                        _write_run(path, frames)
                    msg = str(e.value)
                    cause = "no space left on device" if mode == "enospc" else "input/output error"
                    assert msg.startswith(f"{path}: {cause} (") and "\n" not in msg, msg
                else:
                    _write_run(path, frames)
                    path = dead
            if at < n_create:      # while the file was created: left empty, or complete without a frame
                journal.recover(path)
                assert not Path(journal.journal_path(path)).exists()
                assert path.stat().st_size == 0 or read_output(path).n_frames == 0
                continue
            try:
                outcome = _check_file(path, frames, restart=False)
                if restart == "all" or (mode, outcome) not in seen:
                    _check_file(path, frames)
            except Exception as exc:
                raise AssertionError(f"{mode} at write {at} of {n_sites}: {exc}") from exc
            seen.add((mode, outcome))
    return seen


def test_enospc_and_eio_at_every_write_of_a_frame_and_death_at_every_third(monkeypatch, tmp_path):
    """The writes of frame 1 (frame, step, timings, checkpoint) and of the close, after frame 0."""
    seen = _every_site(monkeypatch, tmp_path, 2, ("enospc", "eio", "kill"), sites="last frame",
                       restart="first", kill_stride=3)
    for mode in ("enospc", "eio", "kill"):    # every outcome: frame 1 lost, kept without, with its checkpoint
        assert {s for m, s in seen if m == mode} == {(1, 0), (2, 0), (2, 1)}, (mode, seen)


@pytest.mark.slow
def test_enospc_eio_death_and_torn_writes_at_every_write_of_four_frames(monkeypatch, tmp_path):
    seen = _every_site(monkeypatch, tmp_path, 4, ("enospc", "eio", "kill", "torn"))
    for mode in ("enospc", "eio", "kill", "torn"):
        assert {s for m, s in seen if m == mode} >= {(1, None), (1, 0)} | {(k, k - 1) for k in range(2, 5)}, seen
