"""HDF5 output: exact round trip, steps and reasons, checkpoints, restart truncation,
survival of a SIGKILL, VTK export round trip (closed, outward-oriented surfaces)."""
import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from tests.harness import ROOT, synthetic_frames, write_synthetic
from vesflow.io import (STEP_REASONS, OutputWriter, iter_frames, read_checkpoint, read_output)


# ---------------------------------------------------------------- tests
def test_round_trip_exact(tmp_path):
    path = tmp_path / "run.h5"
    frames = write_synthetic(path)
    out = read_output(path)
    assert out.n_frames == 4 and out.p == 8 and out.n_vesicles == 3 and out.periodic_length == 0.0
    for name in ("time", "points", "coefficients", "tension", "area", "volume", "centroid",
                 "bending_energy", "velocity"):
        np.testing.assert_array_equal(out.frames[name], np.array([f[name] for f in frames]), err_msg=name)
    M, C = 2 * 8 * 9, 9 * 9 - 1
    assert out.frames["points"].shape == (4, 3, M, 3) and out.frames["coefficients"].shape == (4, 3, 3, C)
    assert out.attrs["scene"] == 'title = "synthetic"\n' and out.attrs["options"] == "-ves_p 8"
    assert out.attrs["vesflow_version"] == "test"
    assert out.timings["near"] == 0.25 and out.timings["total"] == 1.9375
    # steps: 3 rows per frame, reasons as codes, table in an attribute
    st = out.steps
    assert len(st["time"]) == 12
    np.testing.assert_array_equal(st["accepted"][:3], [0, 1, 1])
    np.testing.assert_array_equal(st["reason"][:3], [1, 0, 0])
    np.testing.assert_array_equal(st["ksp_its"][:3], [3, 5, 4])
    assert st["accepted"].dtype == np.int8 and st["ksp_its"].dtype == np.int32
    with h5py.File(path) as f:
        table = json.loads(f["steps/reason"].attrs["reason_table"])
        assert table["1"]["name"] == "error_estimate" and set(map(int, table)) == set(STEP_REASONS)
        assert f["frames/points"].compression == "gzip" and f["frames/points"].chunks[0] == 1
        assert f["frames/points"].maxshape[0] is None and f["steps/time"].maxshape[0] is None
    # frame selections and one-frame iteration
    sub = read_output(path, frames=[3, 1], fields=["tension"])
    np.testing.assert_array_equal(sub.frames["tension"], np.array([frames[3]["tension"], frames[1]["tension"]]))
    assert set(sub.frames) == {"time", "tension"}
    its = list(iter_frames(path, fields=["points"]))
    assert [f["index"] for f in its] == [0, 1, 2, 3]
    np.testing.assert_array_equal(its[2]["points"], frames[2]["points"])


def test_checkpoint_and_optional_velocity(tmp_path):
    path = tmp_path / "run.h5"
    frames = write_synthetic(path, velocity=False)
    out = read_output(path)
    assert "velocity" not in out.frames
    ck = read_checkpoint(path)
    assert ck["time"] == frames[-1]["time"] and ck["step"] == 3 and ck["dt"] == 0.25
    assert ck["stepper"] == {"name": "sbdf1", "history": None}
    np.testing.assert_array_equal(ck["coefficients"], frames[-1]["coefficients"])
    with h5py.File(path) as f:
        assert "checkpoint_new" not in f
    # velocity given from frame 1 on: frame 0 reads NaN; shapes are checked
    fr = synthetic_frames(n_frames=2)
    with OutputWriter(tmp_path / "v.h5", scene_text="", options_text="", version="t", p=8, n_vesicles=3,
                      periodic_length=17.0) as w:
        w.write_frame(**{k: v for k, v in fr[0].items() if k != "velocity"})
        w.write_frame(**fr[1])
        with pytest.raises(ValueError, match="tension has shape"):
            w.write_frame(**dict(fr[1], tension=np.zeros((3, 5))))
        with pytest.raises(ValueError, match="unknown reason"):
            w.write_steps([(0.0, 0.1, 0, 1, 1.0, "bogus")])
    v = read_output(tmp_path / "v.h5").frames["velocity"]
    assert np.all(np.isnan(v[0])) and np.array_equal(v[1], fr[1]["velocity"])
    assert read_output(tmp_path / "v.h5").periodic_length == 17.0


def test_restart_truncates(tmp_path):
    path = tmp_path / "run.h5"
    frames = write_synthetic(path, n_frames=6, checkpoint_every=2)  # checkpoints at t = 0, 1, 2
    assert read_output(path).n_frames == 6
    w = OutputWriter.reopen(path, options_text="-ts_max_time 5")
    state = w.checkpoint
    assert state["time"] == 2.0 and state["step"] == 4
    out = read_output(path)
    np.testing.assert_array_equal(out.time, [0.0, 0.5, 1.0, 1.5, 2.0])   # frames up to t_checkpoint
    assert np.all(out.steps["time"] < 2.0) and len(out.steps["time"]) == 12  # steps starting before it
    # continue: the writer appends after the kept rows
    w.write_frame(**dict(frames[5], time=2.5))
    w.write_steps([(2.0, 0.5, 1, 6, 0.1, "accepted")])
    w.close()
    out = read_output(path)
    np.testing.assert_array_equal(out.time, [0.0, 0.5, 1.0, 1.5, 2.0, 2.5])
    assert len(out.steps["time"]) == 13 and out.steps["ksp_its"][-1] == 6
    np.testing.assert_array_equal(out.restarts, [2.0])
    assert out.attrs["restart_options"] == ["-ts_max_time 5"]
    # a second restart is recorded too
    OutputWriter.reopen(path).close()
    np.testing.assert_array_equal(read_output(path).restarts, [2.0, 2.0])
    # no checkpoint: a clear error
    write_synthetic(tmp_path / "nock.h5", n_frames=1, checkpoint_every=0)
    from vesflow.errors import SceneError
    with pytest.raises(SceneError, match="no complete /checkpoint"):
        OutputWriter.reopen(tmp_path / "nock.h5")
    # a restart into a new file records where it came from
    with OutputWriter(tmp_path / "new.h5", scene_text="x" * 100_000, options_text="", version="t", p=8,
                      n_vesicles=3, periodic_length=0.0, restart_of=path) as w2:
        w2.write_frame(**dict(frames[5], time=2.5))
    new = read_output(tmp_path / "new.h5")
    assert new.attrs["restart_of"] == str(path) and list(new.restarts) == [2.0]
    assert len(new.attrs["scene"]) == 100_000  # scene texts above the 64 KiB attribute limit


def test_checkpoint_interrupted_swap(tmp_path):
    """A run killed between deleting /checkpoint and moving /checkpoint_new in place."""
    path = tmp_path / "run.h5"
    write_synthetic(path, n_frames=3)
    with h5py.File(path, "r+") as f:
        f.move("checkpoint", "checkpoint_new")
    assert read_checkpoint(path)["time"] == 1.0
    OutputWriter.reopen(path).close()
    with h5py.File(path) as f:
        assert "checkpoint" in f and "checkpoint_new" not in f


_KILL_CHILD = r"""
import sys, time
from tests.harness import synthetic_frames
from vesflow.io import OutputWriter
fr = synthetic_frames(n_frames=1)[0]
w = OutputWriter({path!r}, scene_text="", options_text="", version="t", p=8, n_vesicles=3, periodic_length=0)
for k in range(10**6):
    w.write_frame(**dict(fr, time=float(k)))
    w.write_steps([(float(k), 1.0, 1, 2, 0.0, "accepted")])
    if k % 3 == 0:
        w.write_checkpoint(dict(time=float(k), x=fr["coefficients"]))
    print(k, flush=True)
    if k >= 5:
        time.sleep(0.002)
"""


def test_sigkill_keeps_frames(tmp_path):
    path = tmp_path / "killed.h5"
    code = _KILL_CHILD.format(path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        written = -1
        deadline = time.time() + 30
        while written < 12 and time.time() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            written = int(line.split()[0])
        time.sleep(0.05)  # let it die in the middle of some write
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert written >= 12, "the writer subprocess did not get going"
    out = read_output(path)
    assert out.n_frames >= written + 1
    np.testing.assert_array_equal(out.time, np.arange(out.n_frames, dtype=float))
    assert len(out.steps["time"]) >= written + 1
    ck = read_checkpoint(path)
    assert ck["time"] % 3 == 0 and ck["time"] >= 12
    # and the file can be continued
    w = OutputWriter.reopen(path)
    w.close()
    assert read_output(path).time[-1] == w.checkpoint["time"] == ck["time"]


def test_vtk_round_trip(tmp_path):
    pv = pytest.importorskip("pyvista")
    from vesflow.vtk_export import export_vtk, frame_polydata

    path = tmp_path / "run.h5"
    frames = write_synthetic(path, p=8)
    pvd = export_vtk(path, tmp_path / "vtk")
    reader = pv.get_reader(str(pvd))
    np.testing.assert_array_equal(reader.time_values, [f["time"] for f in frames])
    N, M = 3, 144
    for k, fr in enumerate(frames):
        reader.set_active_time_value(fr["time"])
        mesh = reader.read()[0]
        assert mesh.n_points == N * (M + 2) and mesh.n_cells == N * 2 * M
        assert mesh.is_all_triangles and mesh.n_open_edges == 0
        pts = np.asarray(mesh.points).reshape(N, M + 2, 3)
        np.testing.assert_allclose(pts[:, :M], fr["points"], rtol=0, atol=1e-12)
        ten = np.asarray(mesh.point_data["tension"]).reshape(N, M + 2)
        np.testing.assert_allclose(ten[:, :M], fr["tension"], rtol=0, atol=1e-12)
        rings = fr["tension"].reshape(N, 9, 16)
        np.testing.assert_allclose(ten[:, M], rings[:, 0].mean(1), atol=1e-12)
        np.testing.assert_allclose(ten[:, M + 1], rings[:, -1].mean(1), atol=1e-12)
        vel = np.asarray(mesh.point_data["velocity"]).reshape(N, M + 2, 3)
        np.testing.assert_allclose(vel[:, :M], fr["velocity"], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(mesh.point_data["speed"]).reshape(N, M + 2),
                                   np.linalg.norm(vel, axis=-1), atol=1e-12)
        np.testing.assert_array_equal(np.asarray(mesh.point_data["vesicle_id"]), np.repeat(np.arange(N), M + 2))
        # outward orientation: every triangle normal points away from its vesicle's centre,
        # and the signed volume of each closed surface is close to 4 pi / 3
        tri = np.asarray(mesh.regular_faces)
        v0, v1, v2 = (np.asarray(mesh.points)[tri[:, i]] for i in range(3))
        nrm = np.cross(v1 - v0, v2 - v0)
        ves = np.asarray(mesh.cell_data["vesicle_id"])
        rel = (v0 + v1 + v2) / 3 - fr["centroid"][ves]
        assert np.all(np.einsum("ij,ij->i", nrm, rel) > 0)
        vol = np.bincount(ves, np.einsum("ij,ij->i", v0, np.cross(v1, v2)) / 6)
        assert np.all((vol > 0.9 * 4 * np.pi / 3) & (vol < 4 * np.pi / 3))  # inscribed polyhedron
        # each vesicle is one closed component
        assert mesh.connectivity().point_data["RegionId"].max() == N - 1
    # explicit poles are used as given
    fr = frames[0]
    poles = fr["centroid"][:, None, :] + np.array([[0, 0, 1.0], [0, 0, -1.0]])[None]
    mesh = frame_polydata(fr["points"], 8, {"tension": fr["tension"]}, poles=poles)
    np.testing.assert_array_equal(np.asarray(mesh.points).reshape(N, M + 2, 3)[:, M:], poles)
    assert mesh.n_open_edges == 0


def test_periodic_wrap_and_the_unwrapped_fields(tmp_path):
    """wrap_into_cell moves each vesicle by -L floor(centroid / L); the file stores the wrapped
    geometry and /frames/image, RunOutput.unwrapped adds L image back to points and coefficients."""
    from vesflow.shapes import make_shape
    from vesflow.simulation import wrap_into_cell
    from vesflow.surface import Surface
    p, L = 6, 4.0
    centres = np.array([[1.0, 2.0, 3.0], [-0.3, 4.2, 9.5], [3.99, -4.01, 0.5]])
    c = np.array([make_shape("oblate", p, center=x, reduced_volume=0.9, rotation=(10, 40, 0)) for x in centres])
    cen = Surface(c, p).centroid()
    w, k = wrap_into_cell(c, p, L)
    np.testing.assert_array_equal(k, [[0, 0, 0], [-1, 1, 2], [0, -2, 0]])
    S = Surface(w, p)
    np.testing.assert_allclose(S.centroid(), cen - L * k, atol=1e-12)
    assert np.all((S.centroid() >= 0) & (S.centroid() < L))
    np.testing.assert_allclose(S.points(), Surface(c, p).points() - L * k[:, None, :], atol=1e-12)
    assert not wrap_into_cell(w, p, L)[1].any()                           # already inside
    assert w is not c and np.array_equal(c[0], make_shape("oblate", p, center=centres[0], reduced_volume=0.9,
                                                          rotation=(10, 40, 0)))
    # the file: wrapped geometry, unwrapped centroid, image; unwrapped() restores the positions
    path = tmp_path / "periodic.h5"
    M = 2 * p * (p + 1)
    with OutputWriter(path, scene_text="", options_text="", version="t", p=p, n_vesicles=3,
                      periodic_length=L) as wr:
        for image in (None, k):
            wr.write_frame(time=0.0 if image is None else 1.0, points=S.points(), coefficients=w,
                           tension=np.zeros((3, M)), area=S.area(), volume=S.volume(),
                           centroid=cen, bending_energy=np.zeros(3), image=image)
    out = read_output(path)
    assert out.frames["image"].dtype == np.int64
    np.testing.assert_array_equal(out.frames["image"], [np.zeros((3, 3), int), k])   # before: 0
    np.testing.assert_allclose(out.unwrapped("points")[1], Surface(c, p).points(), atol=1e-12)
    np.testing.assert_allclose(out.unwrapped("coefficients")[1], c, atol=1e-12)
    np.testing.assert_array_equal(out.unwrapped("points")[0], S.points())
    with pytest.raises(ValueError, match="not a position field"):
        out.unwrapped("tension")
