"""Off-screen rendering (PNG + MP4) from the run file and from the .pvd: cameras,
label layout, smooth surfaces from the coefficients, periodic boxes, workers; and the
time-series plot.  Needs pyvista, imageio-ffmpeg and an off-screen OpenGL (EGL/Mesa)."""
import importlib.util
import os
from pathlib import Path

import numpy as np
import pytest

pv = pytest.importorskip("pyvista")
imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
from PIL import Image  # noqa: E402  (a pyvista dependency)

from tests.harness import write_pair_run, write_synthetic  # noqa: E402
from vesflow import sph  # noqa: E402
from vesflow.render import fit_camera, main, render  # noqa: E402
from vesflow.render.camera import Extent, follow_cameras, project, view_basis  # noqa: E402
from vesflow.render.labels import make_layout, wrap_title, text_extent  # noqa: E402
from vesflow.render.periodic import wrap_and_image  # noqa: E402
from vesflow.io import iter_frames  # noqa: E402
from vesflow.render.surfaces import RunFrames, auto_resolution, surface_on_grid  # noqa: E402
from vesflow.shapes import make_shape  # noqa: E402

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
from tests.harness import ROOT  # noqa: E402
SMALL = (480, 270)


def _load(png):
    return np.asarray(Image.open(png).convert("RGB")).astype(int)


def _drawn(img, background=(255, 255, 255), threshold=40):
    """Mask of pixels that differ clearly from the background."""
    return np.abs(img - np.array(background)).sum(axis=-1) > threshold


def _vesicle_pixels(img, layout):
    """Drawn pixels outside every label box."""
    d = _drawn(img)
    for l, t, r, b in layout.boxes.values():
        d[t:b, l:r] = False
    return d


def _movie_frames(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    n = sum(1 for _ in gen)
    return meta, n


@pytest.fixture(scope="module")
def pair_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("render") / "pair.h5"
    write_pair_run(path, p=8, n_frames=24, separation=10.0)
    return path


# ---------------------------------------------------------------------- the movie
def test_render_h5_png_and_mp4(pair_file, tmp_path):
    res = render(pair_file, movie=tmp_path / "x.mp4", frames_dir=tmp_path / "png", color="tension",
                 size=SMALL, fps=5, frames=slice(0, 24, 8))
    assert [Path(f).name for f in res.frames] == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]
    imgs = [_load(f) for f in res.frames]
    assert imgs[0].shape == (270, 480, 3)
    for img in imgs:
        # coloured (tension colormap), not only gray shading; nothing on the outer margin
        rgb = img[_vesicle_pixels(img, res.layout)]
        assert np.ptp(rgb, axis=1).max() > 80
        m = res.layout.margin
        assert not _drawn(img)[:m // 2].any() and not _drawn(img)[:, -(m // 2):].any()
    for a, b in zip(imgs, imgs[1:]):
        assert np.abs(a - b).sum(axis=-1).astype(bool).mean() > 0.01
    # one colour range for all frames, from the data: x z over the tilted oblate, plus 0.1 sin t
    lo, hi = res.clim
    assert -1.0 < lo < -0.2 and 0.2 < hi < 1.0
    meta, n = _movie_frames(tmp_path / "x.mp4")
    assert n == 3 and tuple(meta["size"]) == SMALL


def test_follow_fills_frames_and_labels_do_not_overlap(pair_file, tmp_path):
    """Acceptance: vesicles separating by 10 radii cover >= 10 % of every frame in
    follow mode (the default here); the title and time label boxes do not intersect."""
    res = render(pair_file, movie=False, frames_dir=tmp_path / "follow", size=SMALL)
    assert res.camera_mode == "follow"
    cov = [_vesicle_pixels(_load(f), res.layout).mean() for f in res.frames]
    assert min(cov) >= 0.10, cov
    assert not res.layout.overlapping(), res.layout.boxes
    ti, tl = res.layout.boxes["title"], res.layout.boxes["time"]
    assert ti[2] <= tl[0]
    # the boxes are where the text is: the top band's drawn pixels lie in them
    img = _load(res.frames[-1])
    band = _drawn(img)[: max(ti[3], tl[3]) + 1]
    inside = np.zeros_like(band)
    for l, t, r, b in (ti, tl):
        inside[t:b + 1, l:r + 1] = True
    assert band[inside].any() and not band[~inside].any()
    assert len(set(res.cameras)) == len(res.cameras)        # one camera per frame


def test_follow_versus_fit_on_a_long_drift(tmp_path):
    """Vesicles drifting 30 radii apart: the whole-run camera (fit) shows them tiny at
    t = 0 (the issue's complaint); follow keeps them large in every frame."""
    path = tmp_path / "drift.h5"
    write_pair_run(path, p=6, n_frames=3, separation=30.0)
    cov = {}
    for mode in ("fit", "follow"):
        res = render(path, movie=False, frames_dir=tmp_path / mode, size=SMALL, camera=mode, smooth=0, color="none")
        cov[mode] = [_vesicle_pixels(_load(f), res.layout).mean() for f in res.frames]
    assert cov["fit"][0] < 0.03 and cov["follow"][0] > 5 * cov["fit"][0], cov
    assert min(cov["follow"]) >= max(0.9 * c for c in cov["fit"]), cov


def test_long_title_wrapped_inside_the_frame(tmp_path):
    path = tmp_path / "long.h5"
    title = ("two oblate vesicles of reduced volume 0.85 in simple shear of rate 1, passing each other "
             "and drifting apart until they are ten radii away from each other, then leaving the picture")
    write_pair_run(path, p=6, n_frames=2, title=title)
    res = render(path, movie=False, frames_dir=tmp_path / "png", size=SMALL, color="speed")
    lay = res.layout
    assert len(lay.title_lines) == 2 and lay.title_lines[-1].endswith("...")
    assert lay.boxes["title"][2] < lay.boxes["time"][0] and not lay.overlapping()
    assert all(0 <= b[0] and b[2] <= SMALL[0] and 0 <= b[1] and b[3] <= SMALL[1] for b in lay.boxes.values())
    # wrapping keeps words whole and the text (up to the "...")
    words = " ".join(lay.title_lines)[:-3].split()
    assert title.startswith(" ".join(words))
    assert wrap_title("a " * 3 + "b", 10 ** 4, 12) == ["a a a b"]
    assert all(text_extent(s, 12)[2] <= 60 for s in wrap_title("abcdefghijklmnopqrstuvwxyz" * 3, 60, 12, max_lines=9))


# ---------------------------------------------------------------------- surfaces
def _max_adjacent_normal_angle(points, faces):
    """Largest angle (degrees) between the normals of triangles that share an edge."""
    a, b, c = (points[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    tri = np.tile(np.arange(len(faces)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, tri = key[order], tri[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    assert same.sum() * 2 == len(key)          # closed surface: each edge in two triangles
    cosang = np.einsum("ij,ij->i", n[tri[1:][same]], n[tri[:-1][same]])
    return np.degrees(np.arccos(np.clip(cosang.min(), -1, 1)))


@pytest.mark.parametrize("shape", ["oblate", "biconcave"])
def test_p6_default_resolution_has_no_facets(tmp_path, shape):
    """Acceptance: a p = 6 run drawn at the default resolution: adjacent triangles
    differ by less than 10 degrees (drawn on the p-grid itself they do not)."""
    path = tmp_path / "p6.h5"
    write_pair_run(path, p=6, n_frames=2, shape=shape)
    angles = {}
    for q in (None, 6):
        src = RunFrames(path, resolution=q)
        fm = next(src.read([1], "tension"))
        angles[q] = _max_adjacent_normal_angle(fm.points.reshape(-1, 3), fm.all_faces())
    assert angles[None] < 10.0 < angles[6], angles
    # a large suspension keeps within the point budget, and says so when that leaves facets
    c = next(iter_frames(path, fields=["coefficients"], frames=[1]))["coefficients"]
    assert auto_resolution(c, 6, 2) == RunFrames(path).q
    with pytest.warns(UserWarning, match="2000 vesicles at resolution 24: adjacent triangles differ by up to"):
        assert auto_resolution(c, 6, 2000) == 24


def test_normals_are_analytic_at_grid_and_poles():
    """Rotated ellipsoid: the normals (poles included) equal the gradient of its
    implicit equation, and the points lie on it."""
    p, q = 6, 20
    axes = np.array([1.5, 1.0, 0.6])
    R = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))[0]
    c = make_shape("ellipsoid", p, axes=tuple(axes))          # scaled to radius 1: axes times a factor
    c = R @ c
    pts, nrm = surface_on_grid(c[None], p, q)
    local = pts[0] @ R                                       # back to the ellipsoid's axes
    s = np.sqrt(np.sum((local / axes) ** 2, axis=1))        # constant on the surface
    assert np.ptp(s) < 1e-12 * s.mean()
    grad = (local / axes ** 2) @ R.T
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    np.testing.assert_allclose(nrm[0], grad, atol=1e-12)
    assert pts.shape == (1, (q + 1) * 2 * q + 2, 3)
    assert np.allclose(pts[0, -2:], np.moveaxis(sph.evaluate(c, p, [0, np.pi], [0, 0]), -1, -2))


# ---------------------------------------------------------------------- cameras
def test_fit_camera_holds_points_tightly():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-10, 10, (400, 3)) * [2, 1, 0.5]
    size, window = (960, 540), (-0.8, 0.95, -0.7, 0.6)
    cam = fit_camera(pts, size, view=(40, 25), window=window)
    xy, depth = project(pts, cam, size)
    assert depth.min() > 0
    assert np.all(xy[:, 0] >= window[0] - 1e-9) and np.all(xy[:, 0] <= window[1] + 1e-9)
    assert np.all(xy[:, 1] >= window[2] - 1e-9) and np.all(xy[:, 1] <= window[3] + 1e-9)
    # tight: both edges of one axis are touched (the camera is as close as it can be)
    gaps = np.array([[xy[:, 0].min() - window[0], window[1] - xy[:, 0].max()],
                     [xy[:, 1].min() - window[2], window[3] - xy[:, 1].max()]])
    k = int(np.argmin(gaps.max(axis=1)))
    assert np.abs(gaps[k]).max() < 1e-9 and gaps[1 - k].min() > 0.01, gaps
    assert abs(gaps[1 - k, 0] - gaps[1 - k, 1]) < 1e-9, gaps        # centred along the other axis


def test_follow_cameras_hold_every_frame_and_are_smooth():
    """Two points drifting apart with noise: every frame holds its points; smoothing
    cuts the frame-to-frame jitter of the camera distance."""
    rng = np.random.default_rng(0)
    nf, size, window = 120, (480, 270), (-0.9, 0.9, -0.8, 0.7)
    frames = []
    for k in range(nf):
        s = 1 + 0.1 * k + 0.3 * rng.standard_normal()
        frames.append(np.array([[-s, 0, 0], [s, 0, 0.2 * s]]) + rng.normal(0, 0.2, (2, 3)))
    basis = view_basis(30, 20)
    ext = [Extent(P, basis, size, window) for P in frames]
    jitter = {}
    for smooth in (0.0, 6.0):
        cams = follow_cameras(ext, smooth)
        for P, c in zip(frames, cams):
            xy, _ = project(P, c, size)
            assert np.all(xy[:, 0] >= window[0] - 1e-9) and np.all(xy[:, 0] <= window[1] + 1e-9)
            assert np.all(xy[:, 1] >= window[2] - 1e-9) and np.all(xy[:, 1] <= window[3] + 1e-9)
        D = np.array([np.linalg.norm(np.subtract(c[0], c[1])) for c in cams])
        jitter[smooth] = np.abs(np.diff(D, 2)).mean()
    assert jitter[6.0] < 0.2 * jitter[0.0], jitter


def test_fixed_camera_and_bad_input(pair_file, tmp_path):
    cam = ((0.0, -30.0, 5.0), (0.0, 0.0, 0.0))
    res = render(pair_file, movie=False, frames_dir=tmp_path / "png", size=SMALL, camera="fixed",
                 position=cam[0], focal_point=cam[1], frames=[0, 5])
    assert res.camera_mode == "fixed" and all(c[:2] == cam for c in res.cameras)
    with pytest.raises(ValueError, match="camera = 'fixed' needs"):
        render(pair_file, movie=False, camera="fixed", position=(1, 2, 3))
    with pytest.raises(ValueError, match="camera = 'fixed' only"):
        render(pair_file, movie=False, position=(1, 2, 3), focal_point=(0, 0, 0))
    with pytest.raises(ValueError, match="resolution = 5: must be an integer >= p = 8"):
        render(pair_file, movie=False, resolution=5)
    assert main([str(pair_file), "--no-movie", "--resolution", "4"]) == 2
    assert main([str(pair_file), "--no-movie", "--camera", "fixed", "--position", "0", "-30", "5"]) == 2


# ---------------------------------------------------------------------- periodic
def test_wrap_and_image():
    u = np.array([[0.0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    pts = np.stack([u + [5.5 + 6, 3, 3], u + [3, 3, 3], u + [5.5, 5.5, 5.5]])   # crossing x = L; inside; a corner
    vals = np.arange(3)[:, None] * np.ones(7)
    out, v, _ = wrap_and_image(pts, 6.0, "images", vals)
    cen = out.mean(axis=1)
    assert len(out) == 1 + 1 + 1 + 1 + 7
    assert np.allclose(cen[:3], [[5.5, 3, 3], [3, 3, 3], [5.5, 5.5, 5.5]])
    assert np.allclose(cen[3], [-0.5, 3, 3]) and np.all(v[3] == 0)
    corner = cen[4:]
    assert np.all(v[4:] == 2) and len({tuple(c) for c in np.round(corner, 9)}) == 7
    assert np.allclose(np.sort(np.unique(corner)), [-0.5, 5.5])
    out, _, _ = wrap_and_image(pts, 6.0, "wrap")
    assert len(out) == 3 and np.allclose(out.mean(axis=1)[0], [5.5, 3, 3])


def test_periodic_run_draws_box_and_images(tmp_path):
    path = tmp_path / "periodic.h5"
    L = 8.0
    centres = np.array([[[L - 0.3 + 0.2 * k, 4.0, 4.0], [3.0, 4.0, 4.0]] for k in range(3)])
    write_pair_run(path, p=6, n_frames=3, centres=centres, period=L, shape="sphere")
    res = render(path, movie=False, frames_dir=tmp_path / "png", size=SMALL, color="none", view=(0, 0))
    assert res.camera_mode == "fit"
    img = _load(res.frames[0])
    # seen along y: the box is a square whose edges are gray; the crossing vesicle shows
    # at its left and right faces, the inner one in the middle
    gray = (np.abs(img - 128).max(axis=-1) < 60) & _drawn(img)
    cols = np.nonzero(gray.sum(axis=0) > 0.4 * gray.sum(axis=0).max())[0]
    left, right = cols.min(), cols.max()
    ves = _vesicle_pixels(img, res.layout) & ~gray
    mid_row = ves[:, left:right + 1].sum(axis=1).argmax()
    row = ves[mid_row, left - 5:right + 6]
    runs = np.flatnonzero(np.diff(row.astype(int)) == 1)
    assert len(runs) >= 3, runs     # left image, inner vesicle, right part
    assert main([str(path), "--no-movie", "--periodic", "none"]) == 2


# ---------------------------------------------------------------------- .pvd, colours, workers
def test_render_pvd_speed(pair_file, tmp_path):
    from vesflow.vtk_export import export_vtk

    pvd = export_vtk(pair_file, tmp_path / "vtk", frames=[0, 12])
    res_pvd = render(pvd, movie=False, frames_dir=tmp_path / "pvd", color="speed", size=SMALL)
    res_h5 = render(pair_file, movie=False, frames_dir=tmp_path / "h5", color="speed", size=SMALL, frames=[0, 12])
    assert res_pvd.movie is None and len(res_pvd.frames) == 2
    np.testing.assert_allclose(res_pvd.clim, res_h5.clim, rtol=0.05)
    a, b = _load(res_pvd.frames[1]), _load(res_h5.frames[1])
    assert abs(_vesicle_pixels(a, res_pvd.layout).mean() - _vesicle_pixels(b, res_h5.layout).mean()) < 0.02
    res = render(pvd, movie=False, frames_dir=tmp_path / "none", color="none", size=SMALL, frames=[0])
    assert len(res.frames) == 1 and _vesicle_pixels(_load(res.frames[0]), res.layout).mean() > 0.1
    with pytest.raises(ValueError, match="color"):
        render(pair_file, movie=False, color="pressure")
    with pytest.raises(ValueError, match="resolution = 16: applies to run files"):
        render(pvd, movie=False, resolution=16)


def test_render_speed_needs_velocity(tmp_path):
    path = tmp_path / "novel.h5"
    write_pair_run(path, p=6, n_frames=1, velocity=False)
    with pytest.raises(ValueError, match="needs point data 'speed'"):
        render(path, movie=False, frames_dir=tmp_path / "png", color="speed")
    assert main([str(path), "--color", "speed", "--no-movie"]) == 2


@pytest.mark.slow            # ~8 s: spawning two worker processes that import pyvista
def test_workers_draw_the_same_frames(pair_file, tmp_path):
    one = render(pair_file, movie=False, frames_dir=tmp_path / "w1", size=(320, 180), frames=range(0, 24, 6),
                 workers=1)
    two = render(pair_file, movie=False, frames_dir=tmp_path / "w2", size=(320, 180), frames=range(0, 24, 6),
                 workers=2)
    assert two.workers == 2 and len(two.frames) == 4
    for a, b in zip(one.frames, two.frames):
        assert np.abs(_load(a) - _load(b)).max() <= 2


def test_layout_boxes_are_disjoint_at_every_size():
    for size in ((320, 180), (480, 270), (960, 540), (1920, 1080), (600, 600)):
        lay = make_layout(size, "a title " * 12, ["t = 0.00", "t = 120.00"], bar=("tension (force/length)", -0.5, 2.5))
        assert not lay.overlapping(), (size, lay.boxes)
        W, H = size
        assert all(0 <= b[0] < b[2] <= W and 0 <= b[1] < b[3] <= H for b in lay.boxes.values()), (size, lay.boxes)
        px = lay.window_pixels()
        for name, box in lay.boxes.items():
            assert not (box[0] < px[2] and px[0] < box[2] and box[1] < px[3] and px[1] < box[3]), (size, name)
    with pytest.raises(ValueError, match="size 160x90 is too small for the labels"):
        make_layout((160, 90), None, ["t = 0"], bar=("tension (force/length)", -0.5, 2.5))


def test_plot_timeseries(tmp_path):
    path = tmp_path / "run.h5"
    write_synthetic(path, p=8, n_vesicles=3, n_frames=3)
    spec = importlib.util.spec_from_file_location("plot_timeseries", ROOT / "postprocess" / "plot_timeseries.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    png = mod.plot_timeseries(path, tmp_path / "ts.png")
    img = _load(png)
    assert img.shape[0] > 500 and _drawn(img).mean() > 0.02
