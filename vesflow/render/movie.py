"""render(): a run file (.h5) or a .pvd collection to PNG frames and an MP4, off-screen.

Two passes.  The first reads every frame's surface (and colour values): the
colour range (widest 0.5-99.5 percentile range over frames), the label layout
(labels.py) and the cameras (camera.py) that keep every drawn point inside the
window left free by the labels.  The second draws the frames, in this process or
in worker processes (spawned; each draws a contiguous share of the frames and
writes their PNGs), and feeds them in order to imageio-ffmpeg's bundled ffmpeg
(H.264, yuv420p).

Headless: with no DISPLAY, VTK uses EGL (Mesa); VTK_DEFAULT_OPENGL_WINDOW=
vtkEGLRenderWindow is set here when DISPLAY is unset (the Makefile exports it).
"""
from __future__ import annotations

import os
import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import camera as cam
from .labels import Overlay, make_layout, time_formatter
from .periodic import PERIODIC_MODES, box_corners, wrap_and_image
from .surfaces import UNITS, open_frames

COLORS = ("tension", "speed", "none")
_CMAPS = {"tension": "coolwarm", "speed": "viridis"}
_SOLID = "#e0785a"
_WALL = "#7f9fbf"      # a container's wall ([wall]), drawn translucent
WALL_OPACITY = 0.18
AUTO_FOLLOW_GAIN = 1.2      # auto camera: follow when it shows some frame this much larger than fit


@dataclass
class RenderResult:
    movie: Path | None
    frames: list = field(default_factory=list)      # PNG paths
    times: list = field(default_factory=list)
    clim: tuple | None = None
    camera_mode: str = ""                           # fit | follow | fixed (auto resolved)
    cameras: list = field(default_factory=list)     # per frame (position, focal point, view up)
    layout: object = None                           # labels.Layout (label boxes, vesicle window)
    workers: int = 1
    seconds: float = 0.0

    @property
    def camera(self):
        return self.cameras[0] if self.cameras else None


@dataclass
class _Spec:
    """Everything a process needs to draw frames (picklable)."""

    source: str
    frames: object
    resolution: object
    color: str
    clim: tuple | None
    cmap: str | None
    size: tuple
    background: str
    period: float
    periodic: str
    cameras: list
    layout: object
    bar: tuple | None
    times: list
    frames_dir: str | None


def _even(n):
    return int(n) + (int(n) % 2)


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"render: {name} = {value!r}: must be one of {', '.join(map(str, choices))}")


def _drawn_points(points, period, periodic):
    if period > 0:
        points, _, _ = wrap_and_image(points, period, periodic)
        return np.concatenate([points.reshape(-1, 3), box_corners(period)])
    return points


def render(source, movie=None, frames_dir=None, color="tension", size=(960, 540), fps=None, *,
           clim=None, cmap=None, frames=None, view=(45.0, 20.0), background="white", quality=7,
           progress=False, camera="auto", position=None, focal_point=None, resolution=None,
           smooth=None, workers=None, period=None, periodic="images"):
    """Render a run file (.h5) or a .pvd collection off-screen.

    movie: MP4 path; None -> next to the source with suffix .mp4; False or "" -> no movie.
    frames_dir: write frame_000000.png ... there if given.  color: tension | speed | none.
    size: (width, height) in pixels (made even).  fps: None -> about a 10 s movie, 5..30 fps.
    clim: fixed (lo, hi) colour range, default from all frames.  frames: a slice or indices.
    camera: auto (fit for periodic runs and runs whose extent hardly changes, else
    follow) | follow | fit | fixed (needs position and focal_point).  view: (azimuth,
    elevation) in degrees of fit and follow.  smooth: follow's smoothing in frames
    (default half a second of movie).  resolution: grid degree q >= p of the surfaces
    (run files; default: the coarsest without facets, surfaces.auto_resolution).  workers: processes drawing frames
    (None: auto).  period: the periodic cube's side (default: the run file's
    periodic_length; 0: free space); periodic: images | wrap.  Returns a RenderResult."""
    t_start = _time.perf_counter()
    _check_choice("color", color, COLORS)
    _check_choice("camera", camera, cam.CAMERAS)
    _check_choice("periodic", periodic, PERIODIC_MODES)
    if camera == "fixed" and (position is None or focal_point is None):
        raise ValueError("render: camera = 'fixed' needs a camera position and a focal point")
    if camera != "fixed" and (position is not None or focal_point is not None):
        raise ValueError(f"render: a camera position and focal point apply to camera = 'fixed' only "
                         f"(camera = {camera!r})")
    if workers is not None and (int(workers) != workers or workers < 1):
        raise ValueError(f"render: workers = {workers!r}: must be an integer >= 1")
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    src = open_frames(source, frames, resolution)
    period = src.period if period is None else float(period)
    if not (np.isfinite(period) and period >= 0):
        raise ValueError(f"render: period = {period}: must be >= 0 (0: free space)")
    size = (_even(size[0]), _even(size[1]))
    if min(size) < 2:
        raise ValueError(f"render: size = {size[0]}x{size[1]}: both must be positive")
    if movie is None:
        movie = src.path.with_suffix(".mp4")
    movie = Path(movie) if movie else None
    nf = len(src.times)
    if fps is None:
        fps = int(np.clip(round(nf / 10), 5, 30))
    if int(fps) != fps or fps < 1:
        raise ValueError(f"render: fps = {fps}: must be a positive integer")
    if smooth is None:
        smooth = max(1.0, 0.5 * fps)

    # labels first: they decide the window left to the vesicles
    fmt = time_formatter(src.times)
    labels = [fmt(t) for t in src.times]
    bar_name = None if color == "none" else f"{color} ({UNITS[color]})"
    layout = make_layout(size, src.title, labels, bar=None if bar_name is None else (bar_name, 0.0, 1.0))

    # pass 1: colour range and framing
    basis = cam.view_basis(*view)
    extents, lows, highs = [], [], []
    wall = getattr(src, "wall", None)          # a container (run files with /wall): framed with the cells
    for pts, vals in src.scan(color):
        if camera != "fixed":
            drawn = _drawn_points(pts, period, periodic)
            if wall is not None:
                drawn = np.concatenate([np.reshape(drawn, (-1, 3)), wall[0]])
            extents.append(cam.Extent(drawn, basis, size, layout.window))
        if vals is not None:
            v = np.asarray(vals)[np.isfinite(vals)]
            if v.size:
                lo, hi = np.percentile(v, [0.5, 99.5])
                lows.append(lo)
                highs.append(hi)
    if color != "none":
        if clim is None:
            lo, hi = (min(lows), max(highs)) if lows else (0.0, 1.0)
            if not hi > lo:
                d = max(abs(lo) * 0.1, 1e-6)
                lo, hi = lo - d, hi + d
            clim = (float(lo), float(hi))
        clim = tuple(map(float, clim))
        if not (len(clim) == 2 and clim[1] > clim[0]):
            raise ValueError(f"render: clim = {clim}: need LO < HI")
    else:
        clim = None
    bar = None if clim is None else (bar_name, clim[0], clim[1])
    if bar is not None:
        layout = make_layout(size, src.title, labels, bar=bar)
    mode = camera
    if camera == "fixed":
        cameras = [cam.fixed_camera(position, focal_point)] * nf
    else:
        fit = cam.fit_cameras(extents)
        if camera == "auto":
            tight = min(e.distance for e in extents)
            fit_d = np.linalg.norm(np.subtract(fit[0][0], fit[0][1]))
            mode = "follow" if period == 0 and fit_d > AUTO_FOLLOW_GAIN * tight else "fit"
        cameras = fit if mode == "fit" else cam.follow_cameras(extents, smooth)

    spec = _Spec(source=str(src.path), frames=src.index if src.kind == "h5" else frames, resolution=src.q,
                 color=color, clim=clim, cmap=cmap or _CMAPS.get(color), size=size, background=background,
                 period=period, periodic=periodic, cameras=cameras, layout=layout, bar=bar, times=labels,
                 frames_dir=None if frames_dir is None else str(frames_dir))
    if frames_dir is not None:
        Path(frames_dir).mkdir(parents=True, exist_ok=True)
    n_workers = _auto_workers(nf) if workers is None else int(workers)
    n_workers = max(1, min(n_workers, nf))
    result = RenderResult(movie=movie, clim=clim, camera_mode=mode, cameras=cameras, layout=layout,
                          workers=n_workers)
    writer = None
    try:
        if movie is not None:
            import imageio_ffmpeg
            movie.parent.mkdir(parents=True, exist_ok=True)
            writer = imageio_ffmpeg.write_frames(str(movie), size, fps=fps, quality=quality,
                                                 macro_block_size=2, ffmpeg_log_level="error")
            writer.send(None)
        show = _Progress(nf, progress)
        for k, img, png in _draw_all(spec, nf, n_workers):
            if writer is not None:
                writer.send(np.ascontiguousarray(img).tobytes())
            if png is not None:
                result.frames.append(Path(png))
            result.times.append(src.times[k])
            show(k)
        show.done()
    finally:
        if writer is not None:
            writer.close()
    result.seconds = _time.perf_counter() - t_start
    return result


# ---------------------------------------------------------------------- drawing
def _auto_workers(nf):
    """Worker processes by default: the idle CPUs (count minus the 1-minute load average),
    at most 4, for renders of 60 frames or more; 1 otherwise.  Mesa's llvmpipe already
    draws on every CPU, so workers only pay off on idle CPUs (docs/reference/output.md)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:
        cpus = os.cpu_count() or 1
    idle = int(cpus - os.getloadavg()[0])
    return 1 if nf < 60 or idle < 2 else min(idle, 4)


def _chunks(nf, n_workers):
    """Contiguous shares of the frames, several per worker (keeps the movie's order cheap)."""
    n = max(1, min(nf, 4 * n_workers))
    bounds = np.linspace(0, nf, n + 1).round().astype(int)
    return [list(range(a, b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _draw_all(spec, nf, n_workers):
    """Yield (frame position, RGB image, PNG path or None) in frame order."""
    if n_workers == 1:
        painter = _Painter(spec)
        try:
            yield from painter.draw(range(nf))
        finally:
            painter.close()
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(n_workers, mp_context=ctx, initializer=_worker_init, initargs=(spec,)) as pool:
        for chunk in pool.map(_worker_draw, _chunks(nf, n_workers)):
            yield from chunk


_WORKER = None


def _worker_init(spec):
    global _WORKER
    os.environ.setdefault("LP_NUM_THREADS", "1")       # Mesa llvmpipe: one thread per worker
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    _WORKER = _Painter(spec)


def _worker_draw(positions):
    return list(_WORKER.draw(positions))


class _Painter:
    """One off-screen plotter drawing frames of a spec (in this process)."""

    def __init__(self, spec):
        import pyvista as pv
        self.spec = spec
        self.src = open_frames(spec.source, spec.frames, spec.resolution)
        self.pl = pv.Plotter(off_screen=True, window_size=list(spec.size))
        self.pl.set_background(spec.background)
        # anti-aliasing by FXAA (one screen-space pass): with Mesa's llvmpipe, 4x multisampling
        # costs twice the whole frame (docs/reference/output.md, "Speed")
        self.pl.ren_win.SetMultiSamples(0)
        self.pl.renderer.SetUseFXAA(True)
        text_color = (0, 0, 0) if spec.background == "white" else (255, 255, 255)
        self.overlay = Overlay(spec.layout, bar=spec.bar, cmap=spec.cmap, text_color=text_color)
        self.shown = None
        if spec.period > 0:
            L = spec.period
            corners = box_corners(L)
            edges = [(i, j) for i in range(8) for j in range(i + 1, 8)
                     if np.count_nonzero(corners[i] != corners[j]) == 1]
            lines = np.hstack([[2, i, j] for i, j in edges])
            self.pl.add_mesh(pv.PolyData(corners, lines=lines), color="gray", line_width=1.5, name="box")
        wall = getattr(self.src, "wall", None)
        if wall is not None:                   # the container, translucent: the cells stay visible
            mesh = pv.PolyData.from_regular_faces(wall[0].copy(), wall[2])
            mesh.point_data["Normals"] = wall[1]
            mesh.point_data.active_normals_name = "Normals"
            self.pl.add_mesh(mesh, color=_WALL, opacity=WALL_OPACITY, smooth_shading=True, name="wall",
                             show_scalar_bar=False, ambient=0.3, diffuse=0.6, specular=0.1)

    def close(self):
        self.pl.close()

    def _mesh(self, fm):
        import pyvista as pv
        pts, vals, nrm = fm.points, fm.values, fm.normals
        if self.spec.period > 0:
            pts, vals, nrm = wrap_and_image(pts, self.spec.period, self.spec.periodic, vals, nrm)
            fm = type(fm)(fm.time, pts, nrm, fm.faces, vals)
        faces = fm.all_faces()
        xyz = pts.reshape(-1, 3)
        shown = self.shown
        if shown is not None and shown.n_points == len(xyz) and shown.n_cells == len(faces):
            shown.points[:] = xyz                       # same topology: update in place
        else:
            shown = pv.PolyData.from_regular_faces(xyz.copy(), faces)
            kw = dict(ambient=0.15, diffuse=0.85, specular=0.3, specular_power=20, name="vesicles",
                      show_scalar_bar=False)
            if vals is None:
                shown.point_data["color"] = np.zeros(len(xyz))
                self.pl.add_mesh(shown, color=_SOLID, smooth_shading=nrm is None, **kw)
            else:
                shown.point_data["color"] = np.zeros(len(xyz))
                self.pl.add_mesh(shown, scalars="color", cmap=self.spec.cmap, clim=self.spec.clim,
                                 smooth_shading=nrm is None, **kw)
            if nrm is not None:
                self.pl.actors["vesicles"].prop.interpolation = "phong"
            self.shown = shown
        if vals is not None:
            shown.point_data["color"][:] = vals.reshape(-1)
        if nrm is not None:
            shown.point_data["Normals"] = nrm.reshape(-1, 3)
            shown.point_data.active_normals_name = "Normals"
        shown.Modified()

    def draw(self, positions):
        """Yield (position, RGB image, PNG path or None) for frame positions; PNGs are
        encoded in a thread (Pillow releases the GIL) while the next frame is drawn."""
        from concurrent.futures import ThreadPoolExecutor

        from PIL import Image
        spec = self.spec
        with ThreadPoolExecutor(1) as saver:
            pending = []
            for k, fm in zip(positions, self.src.read(list(positions), spec.color)):
                self._mesh(fm)
                c = spec.cameras[k]
                self.pl.camera.position, self.pl.camera.focal_point, self.pl.camera.up = c
                self.pl.camera.view_angle = cam.VIEW_ANGLE
                self.pl.renderer.ResetCameraClippingRange()
                self.pl.render()
                img = self.overlay.draw(self.pl.screenshot(return_img=True), spec.times[k], c)
                png = None
                if spec.frames_dir is not None:
                    png = str(Path(spec.frames_dir) / f"frame_{k:06d}.png")
                    pending.append(saver.submit(Image.fromarray(img).save, png, compress_level=1))
                    while len(pending) > 2:
                        pending.pop(0).result()
                yield k, img, png
            for f in pending:
                f.result()


class _Progress:
    """Progress on stderr: one updated line on a terminal; in a log, a line per 10% of
    renders of 50 frames or more."""

    def __init__(self, n, on):
        self.tty = sys.stderr.isatty()
        self.n, self.on = n, bool(on) and (self.tty or n >= 50)
        self.t0 = _time.perf_counter()
        self.next = 0.1

    def __call__(self, k):
        if not self.on:
            return
        done = (k + 1) / self.n
        el = _time.perf_counter() - self.t0
        msg = f"render: frame {k + 1}/{self.n}, {el:.0f} s, {el / done - el:.0f} s left"
        if self.tty:
            print("\r" + msg, end="", file=sys.stderr, flush=True)
        elif done >= self.next or k + 1 == self.n:
            print(msg, file=sys.stderr, flush=True)
            while self.next <= done:
                self.next += 0.1

    def done(self):
        if self.on and self.tty:
            print(file=sys.stderr)
