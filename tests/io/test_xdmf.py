"""The XDMF description beside a run file (vesflow.io.xdmf): read back by VTK's XDMF reader
(pyvista.XdmfReader, the reader of ParaView's "Xdmf Reader"), every frame's points and
per-point fields equal the HDF5 datasets exactly, as frames are appended, replaced, gain a
field and are cut by a restart; the mesh is closed and oriented outwards; the bending energy
density integrates to the bending energy."""
import subprocess
import sys

import h5py
import numpy as np
import pytest

from vesflow import sph
from vesflow.io import OutputWriter
from vesflow.io.xdmf import grid_triangles, mesh_arrays, ring_triangles
from vesflow.shapes import make_shape
from vesflow.surface import Surface

pv = pytest.importorskip("pyvista")


@pytest.fixture(autouse=True)
def _no_hdf5_lock(monkeypatch):
    """The writer holds its file open: VTK's HDF5 reads it beside (as ParaView during a run)."""
    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", "FALSE")


def read_xdmf(path):
    """[(time, points, point_data, triangles)] of every frame of an XDMF file, read by VTK."""
    r = pv.XdmfReader(str(path))
    out = []
    for t in r.time_values:
        r.set_active_time_value(t)
        m = r.read()
        if isinstance(m, pv.MultiBlock):
            assert len(m) == 1
            m = m[0]
        out.append((t, np.asarray(m.points), {k: np.asarray(m.point_data[k]) for k in m.point_data.keys()},
                    np.asarray(m.cells_dict[pv.CellType.TRIANGLE])))
    return out


def assert_xdmf_matches(h5path, fields):
    frames = read_xdmf(h5path.with_suffix(".xmf"))
    with h5py.File(h5path, "r", locking=False) as f:     # the writer holds its lock while the run goes on
        F = f["frames/time"].shape[0]
        assert len(frames) == F
        tri = f["mesh/triangles"][...]
        vid = f["mesh/vesicle_id"][...]
        for k, (t, pts, pd, cells) in enumerate(frames):
            assert t == f["frames/time"][k]
            assert np.array_equal(pts, f["frames/points"][k].reshape(-1, 3))
            assert np.array_equal(cells, tri)
            assert sorted(pd) == sorted(fields + ["vesicle_id"])
            assert np.array_equal(pd["vesicle_id"], vid)
            for name in fields:
                h = f[f"frames/{name}"][k]
                want = h.reshape(-1, 3) if name == "velocity" else h.reshape(-1)
                assert np.array_equal(pd[name], want, equal_nan=True), (k, name)
    return frames


def frame(rng, t, N, p, velocity=True):
    M, C = 2 * p * (p + 1), (p + 1) ** 2 - 1
    c = np.stack([make_shape("ellipsoid", p, axes=(1.0, 0.8, 1.3), center=(3.0 * v + t, 0.0, 0.0)) for v in range(N)])
    kw = dict(time=t, points=np.moveaxis(sph.transform(p).synth(c), -2, -1), coefficients=c,
              tension=rng.standard_normal((N, M)), area=np.ones(N), volume=np.ones(N), centroid=np.zeros((N, 3)),
              bending_energy=np.ones(N), bending_energy_density=rng.standard_normal((N, M)))
    if velocity:
        kw["velocity"] = rng.standard_normal((N, M, 3))
    return kw


def test_xdmf_follows_the_frames_appended_replaced_and_cut_by_a_restart(tmp_path):
    rng = np.random.default_rng(3)
    N, p = 3, 5
    path = tmp_path / "run.h5"
    w = OutputWriter(path, scene_text="", options_text="", version="test", p=p, n_vesicles=N, periodic_length=0.0)
    w.write_frame(**frame(rng, 0.0, N, p, velocity=False))
    w.write_frame(**frame(rng, 0.25, N, p, velocity=False))
    assert_xdmf_matches(path, ["tension", "bending_energy_density"])
    size = path.with_suffix(".xmf").stat().st_size
    w.write_frame(**frame(rng, 0.5, N, p))               # velocity from now on: earlier frames NaN
    w.write_checkpoint({"time": 0.5})
    w.write_frame(**frame(rng, 0.75, N, p))
    w.write_frame(**frame(rng, 0.75, N, p))              # replaces the frame at 0.75
    frames = assert_xdmf_matches(path, ["tension", "velocity", "bending_energy_density"])
    assert len(frames) == 4 and np.all(np.isnan(frames[0][2]["velocity"]))
    assert path.with_suffix(".xmf").stat().st_size > size
    w.write_frame(**frame(rng, 1.0, N, p))              # appended in place
    assert_xdmf_matches(path, ["tension", "velocity", "bending_energy_density"])
    w.close()
    w = OutputWriter.reopen(path)                        # back to the checkpoint at 0.5
    assert [t for t, *_ in read_xdmf(path.with_suffix(".xmf"))] == [0.0, 0.25, 0.5]
    w.write_frame(**frame(rng, 0.6, N, p))
    w.close()
    frames = assert_xdmf_matches(path, ["tension", "velocity", "bending_energy_density"])
    assert [t for t, *_ in frames] == [0.0, 0.25, 0.5, 0.6]


@pytest.mark.parametrize("p", [3, 8])
def test_mesh_is_closed_and_oriented_outwards(p):
    M = 2 * p * (p + 1)
    tri = grid_triangles(p)
    assert len(tri) == 2 * (2 * p) * p + 2 * (2 * p - 2)
    assert len(ring_triangles(p)) == 2 * (2 * p) * p
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)                                   # closed: every edge in two triangles
    directed = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)     # consistently oriented
    x = np.moveaxis(sph.transform(p).synth(make_shape("sphere", p)[None]), -2, -1)[0]
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    assert np.all(np.einsum("ij,ij->i", normal, (a + b + c) / 3) > 0)   # outwards
    # the enclosed volume of the triangulated sphere: below 4 pi / 3, within 10 % at p = 8 (the flat polar caps)
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    assert 0 < vol < 4 * np.pi / 3 and (p < 8 or vol > 0.9 * 4 * np.pi / 3)
    triangles, vid = mesh_arrays(3, p)
    assert triangles.shape == (3 * len(tri), 3) and np.array_equal(triangles[len(tri):2 * len(tri)], tri + M)
    assert np.array_equal(vid, np.repeat([0, 1, 2], M))


def test_bending_energy_density():
    p = 12
    R, kappa = 1.7, np.array([0.3, 2.0])
    c = np.stack([make_shape("sphere", p, radius=R), make_shape("ellipsoid", p, axes=(1.0, 1.0, 1.8))])
    S = Surface(c, p)
    e = S.bending_energy_density(kappa)
    assert e.shape == (2, 2 * p * (p + 1))
    assert np.allclose(e[0], kappa[0] / R ** 2, rtol=1e-12)          # H = -1/R on a sphere
    integral = S.geometry(p).integrate(e)
    assert abs(integral[0] / (4 * np.pi * kappa[0]) - 1) < 1e-12
    assert abs(integral[1] / S.bending_energy(kappa)[1] - 1) < 1e-4   # p-grid against 2p-grid quadrature


def test_run_writes_the_xdmf_and_export_rewrites_it(tmp_path):
    out = tmp_path / "run.h5"
    cmd = [sys.executable, "-m", "vesflow", "run", "-o", str(out), "-ves_p", "4", "-ts_max_time", "0.1",
           "-ves_output_every", "0.05"]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=tmp_path)
    xmf = out.with_suffix(".xmf")
    written = xmf.read_text()
    frames = assert_xdmf_matches(out, ["tension", "velocity", "bending_energy_density"])
    assert len(frames) == 3
    with h5py.File(out, "r") as f:                     # the run's density: kappa_b H^2 of its surfaces
        p = int(f.attrs["p"])
        c = f["frames/coefficients"][-1]
        e = f["frames/bending_energy_density"][-1]
        E = f["frames/bending_energy"][-1]
    S = Surface(c, p)
    kappa = E / S.bending_energy(1.0)                  # bending_energy = kappa_b integral(H^2 dA)
    assert np.allclose(e, S.bending_energy_density(1.0) * kappa[:, None], rtol=1e-12, atol=0)
    xmf.unlink()
    r = subprocess.run([sys.executable, "-m", "vesflow", "export", str(out), "--vtk", str(tmp_path / "vtk")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert xmf.read_text() == written
    assert (tmp_path / "vtk" / "run.pvd").is_file() and len(list((tmp_path / "vtk").glob("run_*.vtp"))) == 3
    r = subprocess.run([sys.executable, "-m", "vesflow", "export", str(tmp_path / "none.h5")],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "none.h5: no such file" in r.stderr


def test_export_adds_the_mesh_to_a_file_of_an_earlier_layout(tmp_path):
    rng = np.random.default_rng(5)
    path = tmp_path / "old.h5"
    with OutputWriter(path, scene_text="", options_text="", version="test", p=4, n_vesicles=2,
                      periodic_length=0.0) as w:
        w.write_frame(**frame(rng, 0.0, 2, 4))
    with h5py.File(path, "r+") as f:
        del f["mesh"]
    path.with_suffix(".xmf").unlink()
    from vesflow.io.xdmf import write_xdmf
    assert write_xdmf(path) == path.with_suffix(".xmf")
    assert_xdmf_matches(path, ["tension", "velocity", "bending_energy_density"])
