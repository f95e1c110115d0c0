"""Off-screen rendering (PNG + MP4) from the run file and from the .pvd, and the
time-series plot.  Needs pyvista, imageio-ffmpeg and an off-screen OpenGL (EGL/Mesa)."""
import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
from PIL import Image  # noqa: E402  (a pyvista dependency)

from tests.test_io import write_synthetic  # noqa: E402
from vesflow.render import fit_camera, main, render  # noqa: E402

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
ROOT = Path(__file__).resolve().parents[1]


def _load(png):
    return np.asarray(Image.open(png).convert("RGB")).astype(int)


def _drawn(img, background=(255, 255, 255), threshold=40):
    """Mask of pixels that differ clearly from the background."""
    return np.abs(img - np.array(background)).sum(axis=-1) > threshold


def _movie_frames(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    n = sum(1 for _ in gen)
    return meta, n


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("render") / "run.h5"
    write_synthetic(path, p=8, n_vesicles=3, n_frames=3)
    return path


def test_render_h5_png_and_mp4(run_file, tmp_path):
    res = render(run_file, movie=tmp_path / "x.mp4", frames_dir=tmp_path / "png", color="tension",
                 size=(480, 270), fps=5)
    assert [Path(f).name for f in res.frames] == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]
    imgs = [_load(f) for f in res.frames]
    assert imgs[0].shape == (270, 480, 3)
    for img in imgs:
        drawn = _drawn(img)
        # three unit spheres plus labels and colour bar: a good part of the picture,
        # not everything (they are framed with margins)
        assert 0.04 < drawn.mean() < 0.6, drawn.mean()
        # nothing but background along the left, top-right and bottom borders of the frame
        assert not drawn[-3:, :].any() and not drawn[:, :3].any()
        # coloured (tension colormap), not only gray shading
        rgb = img[drawn]
        assert np.ptp(rgb, axis=1).max() > 80
    # the vesicles move: consecutive frames differ, and the drawn region moves right
    for a, b in zip(imgs, imgs[1:]):
        assert np.abs(a - b).sum(axis=-1).astype(bool).mean() > 0.01
    cols = [np.nonzero(_drawn(img[:, : int(0.85 * img.shape[1])]).any(axis=0))[0] for img in imgs]
    assert cols[2].max() > cols[0].max()
    # one colour range for all frames, from the data
    lo, hi = res.clim
    assert lo < 0 < hi and hi <= 3.2
    meta, n = _movie_frames(tmp_path / "x.mp4")
    assert n == 3 and tuple(meta["size"]) == (480, 270)


def test_render_pvd_speed_and_camera(run_file, tmp_path):
    from vesflow.vtk_export import export_vtk

    pvd = export_vtk(run_file, tmp_path / "vtk")
    res_pvd = render(pvd, movie=False, frames_dir=tmp_path / "pvd", color="speed", size=(320, 180))
    res_h5 = render(run_file, movie=False, frames_dir=tmp_path / "h5", color="speed", size=(320, 180))
    assert res_pvd.movie is None and len(res_pvd.frames) == 3
    np.testing.assert_allclose(res_pvd.clim, res_h5.clim, rtol=1e-12)
    np.testing.assert_allclose(res_pvd.camera[0], res_h5.camera[0], rtol=1e-12)
    # same data, same camera: the same picture from either source (below the title,
    # which only the run file has: the scene title)
    a, b = _load(res_pvd.frames[1]), _load(res_h5.frames[1])
    assert np.abs(a - b)[36:].max() <= 2 and np.abs(a - b)[:36].max() > 0
    # no colour: solid vesicles still drawn; unknown field: clear error
    res = render(pvd, movie=False, frames_dir=tmp_path / "none", color="none", size=(320, 180), frames=[0])
    assert len(res.frames) == 1 and _drawn(_load(res.frames[0])).mean() > 0.04
    with pytest.raises(ValueError, match="color"):
        render(run_file, movie=False, color="pressure")


def test_render_speed_needs_velocity(tmp_path):
    path = tmp_path / "novel.h5"
    write_synthetic(path, n_frames=1, velocity=False)
    with pytest.raises(ValueError, match="needs point data 'speed'"):
        render(path, movie=False, frames_dir=tmp_path / "png", color="speed")
    assert main([str(path), "--color", "speed", "--no-movie"]) == 2


def test_fit_camera_contains_spheres():
    """Every sphere projects inside the picture."""
    rng = np.random.default_rng(1)
    centers = rng.uniform(-10, 10, (50, 3)) * [2, 1, 0.5]
    radii = rng.uniform(0.5, 1.5, 50)
    size = (960, 540)
    pos, focal, up = (np.array(v) for v in fit_camera(centers, radii, size, fill=(0.9, 0.9)))
    back = (pos - focal) / np.linalg.norm(pos - focal)
    right = np.cross(-back, up)
    tan_v = np.tan(np.radians(15))
    for c, r in zip(centers, radii):
        for d in np.vstack([np.eye(3), -np.eye(3)]):
            q = c + r * d - pos
            depth = -q @ back
            assert depth > 0
            assert abs(q @ up) / depth <= tan_v * 1.0001
            assert abs(q @ right) / depth <= tan_v * size[0] / size[1] * 1.0001


def test_plot_timeseries(run_file, tmp_path):
    spec = importlib.util.spec_from_file_location("plot_timeseries", ROOT / "postprocess" / "plot_timeseries.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    png = mod.plot_timeseries(run_file, tmp_path / "ts.png")
    img = _load(png)
    assert img.shape[0] > 500 and _drawn(img).mean() > 0.02
