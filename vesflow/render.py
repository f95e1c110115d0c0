"""Off-screen rendering of a run (HDF5 run file or .pvd collection) to PNG frames and MP4.

    render("out/run.h5", movie="out/run.mp4", frames_dir="out/run_frames", color="tension")

One fixed camera frames the whole suspension over all frames (bounding spheres
of every vesicle in every frame, slightly elevated oblique view, z up), one
colour range holds for all frames (robust: the 0.5 and 99.5 percentiles of each
frame, widest over frames), a time label, smooth shading.  MP4 goes through
imageio-ffmpeg's bundled ffmpeg (H.264, yuv420p); PNGs through Pillow.

Headless: with no DISPLAY, VTK uses EGL (Mesa); set
VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow (done here when DISPLAY is unset)
to avoid the X-server warning.  pyvista is imported lazily.
"""
from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

COLORS = ("tension", "speed", "none")
_CMAPS = {"tension": "coolwarm", "speed": "viridis"}
_TITLES = {"tension": "tension", "speed": "speed"}
_SOLID = "#e0785a"


@dataclass
class RenderResult:
    movie: Path | None
    frames: list = field(default_factory=list)      # PNG paths
    times: list = field(default_factory=list)
    clim: tuple | None = None
    camera: tuple | None = None                     # (position, focal point, view up)


# ---------------------------------------------------------------------- sources
class _Source:
    """Frames of a run file or a .pvd as (time, pyvista.PolyData)."""

    def __init__(self, path, frames=None):
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"render: {self.path}: no such file")
        suffix = self.path.suffix.lower()
        self.title = None
        if suffix in (".h5", ".hdf5"):
            from .io import read_output
            out = read_output(self.path, frames=frames, fields=[])
            self.kind = "h5"
            self.times = [float(t) for t in out.time]
            self._index = out.frame_index
            self.title = _scene_title(out.attrs.get("scene", ""))
        elif suffix == ".pvd":
            import pyvista as pv
            self.kind = "pvd"
            self._reader = pv.get_reader(str(self.path))
            times = list(self._reader.time_values)
            idx = np.arange(len(times))
            if frames is not None:
                idx = idx[frames] if isinstance(frames, slice) else np.asarray(frames)
            self._index = idx
            self.times = [float(times[i]) for i in idx]
        else:
            raise ValueError(f"render: {self.path}: expected a run file (.h5) or a .pvd collection")
        if not self.times:
            raise ValueError(f"render: {self.path} has no frames")

    def meshes(self):
        if self.kind == "h5":
            from .vtk_export import h5_frame_meshes
            yield from h5_frame_meshes(self.path, frames=self._index)
        else:
            for t in self.times:
                self._reader.set_active_time_value(t)
                data = self._reader.read()
                yield t, _as_polydata(data)


def _as_polydata(data):
    import pyvista as pv
    if isinstance(data, pv.MultiBlock):
        blocks = [b for b in data if b is not None]
        data = blocks[0] if len(blocks) == 1 else data.combine()
    if not isinstance(data, pv.PolyData):
        data = data.extract_surface()
    return data


def _scene_title(scene_text):
    try:
        import tomllib
        t = tomllib.loads(scene_text or "").get("title")
        return str(t) if t else None
    except Exception:
        return None


def _color_values(mesh, color):
    if color == "none":
        return None
    if color in mesh.point_data:
        return np.asarray(mesh.point_data[color])
    if color == "speed" and "velocity" in mesh.point_data:
        return np.linalg.norm(np.asarray(mesh.point_data["velocity"]), axis=1)
    have = sorted(k for k in mesh.point_data.keys() if k != "vesicle_id")
    raise ValueError(f"render: color={color!r} needs point data {color!r}"
                     + (" (or velocity)" if color == "speed" else "")
                     + f"; this run has {have or 'none'}. Use --color none or one of {have}")


# ---------------------------------------------------------------------- camera
def _view_basis(azimuth, elevation):
    az, el = np.radians(azimuth), np.radians(elevation)
    back = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])  # focal -> camera
    up0 = np.array([0.0, 0.0, 1.0])
    fwd = -back
    right = np.cross(fwd, up0)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return back, right, up


def fit_camera(centers, radii, size, *, azimuth=30.0, elevation=20.0, view_angle=30.0, fill=(0.72, 0.85),
               shift=0.0):
    """Camera (position, focal point, view up) that shows every sphere (centers (K, 3),
    radii (K,)) inside `fill` fractions of the picture, seen from the given azimuth
    (about z, from -y towards +x) and elevation (degrees); the picture is then moved
    left by `shift` times its width (room for a scalar bar on the right)."""
    centers = np.asarray(centers, dtype=float).reshape(-1, 3)
    radii = np.asarray(radii, dtype=float).reshape(-1)
    lo = (centers - radii[:, None]).min(axis=0)
    hi = (centers + radii[:, None]).max(axis=0)
    focal = 0.5 * (lo + hi)
    back, right, up = _view_basis(azimuth, elevation)
    tan_v = np.tan(np.radians(view_angle) / 2)
    half = {"x": np.arctan(fill[0] * tan_v * size[0] / size[1]), "y": np.arctan(fill[1] * tan_v)}
    q = centers - focal
    depth = q @ back
    dist = 0.0
    for axis, a in (("x", q @ right), ("y", q @ up)):
        h = half[axis]
        # the frustum plane through the camera at half-angle h keeps the sphere inside
        dist = max(dist, np.max(depth + (radii + np.abs(a) * np.cos(h)) / np.sin(h)))
    dist = max(dist, 1e-6 + np.max(depth + radii))
    focal = focal + right * (shift * 2 * dist * tan_v * size[0] / size[1])
    return tuple(float(x) for x in focal + dist * back), tuple(float(x) for x in focal), tuple(float(x) for x in up)


# ---------------------------------------------------------------------- render
def _even(n):
    return int(n) + (int(n) % 2)


def render(source, movie=None, frames_dir=None, color="tension", size=(960, 540), fps=None, *,
           clim=None, cmap=None, frames=None, view=(30.0, 20.0), background="white",
           quality=7, progress=False):
    """Render a run file (.h5) or a .pvd collection off-screen.

    movie: MP4 path; None -> next to the source with suffix .mp4; False or "" -> no movie.
    frames_dir: write frame_000000.png ... there if given.  color: tension | speed | none.
    size: (width, height) in pixels (made even).  fps: None -> about a 10 s movie, 5..30 fps.
    clim: fixed (lo, hi) colour range, default from all frames.  frames: a slice or indices.
    view: (azimuth, elevation) in degrees.  Returns a RenderResult."""
    if color not in COLORS:
        raise ValueError(f"render: color must be one of {COLORS}, got {color!r}")
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    src = _Source(source, frames)
    size = (_even(size[0]), _even(size[1]))
    if movie is None:
        movie = src.path.with_suffix(".mp4")
    movie = Path(movie) if movie else None
    nf = len(src.times)
    if fps is None:
        fps = int(np.clip(round(nf / 10), 5, 30))

    # pass 1: bounding spheres of every vesicle in every frame, colour range
    centers, radii, lows, highs = [], [], [], []
    for _, mesh in src.meshes():
        pts = np.asarray(mesh.points)
        if "vesicle_id" in mesh.point_data:
            vid = np.asarray(mesh.point_data["vesicle_id"]).astype(np.int64)
        else:
            vid = np.zeros(len(pts), dtype=np.int64)
        cnt = np.bincount(vid)
        c = np.stack([np.bincount(vid, pts[:, k]) for k in range(3)], 1) / np.maximum(cnt, 1)[:, None]
        r = np.zeros(len(cnt))
        np.maximum.at(r, vid, np.linalg.norm(pts - c[vid], axis=1))
        keep = cnt > 0
        centers.append(c[keep])
        radii.append(r[keep])
        vals = _color_values(mesh, color)
        if vals is not None:
            vals = vals[np.isfinite(vals)]
            if vals.size:
                lo, hi = np.percentile(vals, [0.5, 99.5])
                lows.append(lo)
                highs.append(hi)
    bar = color != "none"
    camera = fit_camera(np.concatenate(centers), np.concatenate(radii), size, azimuth=view[0],
                        elevation=view[1], fill=(0.72 if bar else 0.85, 0.85), shift=0.06 if bar else 0.0)
    if color != "none":
        if clim is None:
            lo, hi = (min(lows), max(highs)) if lows else (0.0, 1.0)
            if not hi > lo:
                d = max(abs(lo) * 0.1, 1e-6)
                lo, hi = lo - d, hi + d
            clim = (float(lo), float(hi))
        clim = tuple(map(float, clim))

    # pass 2: draw
    text_color = "black" if background == "white" else "white"
    pl = pv.Plotter(off_screen=True, window_size=list(size))
    pl.set_background(background)
    if src.title:
        pl.add_text(src.title, position="upper_edge", font_size=11, color=text_color, name="title")
    writer = None
    result = RenderResult(movie=movie, clim=clim if color != "none" else None, camera=camera)
    if frames_dir is not None:
        frames_dir = Path(frames_dir)
        frames_dir.mkdir(parents=True, exist_ok=True)
    try:
        if movie is not None:
            import imageio_ffmpeg
            movie.parent.mkdir(parents=True, exist_ok=True)
            writer = imageio_ffmpeg.write_frames(str(movie), size, fps=fps, quality=quality,
                                                 macro_block_size=2, ffmpeg_log_level="error")
            writer.send(None)
        shown = None
        for k, (t, mesh) in enumerate(src.meshes()):
            vals = _color_values(mesh, color)
            if shown is not None and (shown.n_points, shown.n_cells) == (mesh.n_points, mesh.n_cells):
                shown.points[:] = np.asarray(mesh.points)   # same topology: update in place
                if vals is not None:
                    shown.point_data["color"][:] = vals
                shown.Modified()
            else:
                shown = pv.PolyData(np.asarray(mesh.points).copy(), faces=mesh.faces.copy())
                kw = dict(smooth_shading=True, ambient=0.15, diffuse=0.85, specular=0.3, specular_power=20,
                          name="vesicles")
                if vals is None:
                    pl.add_mesh(shown, color=_SOLID, **kw)
                else:
                    shown.point_data["color"] = np.asarray(vals, dtype=float).copy()
                    pl.add_mesh(shown, scalars="color", cmap=cmap or _CMAPS[color], clim=clim,
                                scalar_bar_args=dict(title=_TITLES[color], vertical=True, position_x=0.88,
                                                     position_y=0.2, height=0.6, width=0.05, fmt="%.3g",
                                                     color=text_color, title_font_size=14,
                                                     label_font_size=12),
                                **kw)
                pl.camera.position, pl.camera.focal_point, pl.camera.up = camera
                pl.camera.view_angle = 30.0
            pl.add_text(f"t = {t:.4g}", position=(14, size[1] - 34), font_size=12, color=text_color, name="time")
            pl.renderer.ResetCameraClippingRange()
            pl.render()
            img = pl.screenshot(return_img=True)
            if frames_dir is not None:
                from PIL import Image
                png = frames_dir / f"frame_{k:06d}.png"
                Image.fromarray(img).save(png)
                result.frames.append(png)
            if writer is not None:
                writer.send(np.ascontiguousarray(img[:, :, :3]).tobytes())
            result.times.append(t)
            if progress:
                print(f"\rrender: frame {k + 1}/{nf}  t = {t:.4g}", end="", file=sys.stderr, flush=True)
        if progress:
            print(file=sys.stderr)
    finally:
        if writer is not None:
            writer.close()
        pl.close()
    return result


# ---------------------------------------------------------------------- command line
def build_parser(prog="vesflow render"):
    ap = argparse.ArgumentParser(prog=prog, description="Render a run (OUT.h5 or OUT.pvd) off-screen to MP4 and PNGs.")
    ap.add_argument("source", help="run file (.h5) or VTK collection (.pvd)")
    ap.add_argument("-o", "--output", default=None, help="movie path (default: SOURCE with .mp4)")
    ap.add_argument("--frames", default=None, metavar="DIR", help="also write one PNG per frame into DIR")
    ap.add_argument("--color", default="tension", choices=COLORS)
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT in pixels (default 960x540)")
    ap.add_argument("--fps", type=int, default=None, help="frames per second (default: about a 10 s movie)")
    ap.add_argument("--clim", type=float, nargs=2, default=None, metavar=("LO", "HI"), help="fixed colour range")
    ap.add_argument("--view", type=float, nargs=2, default=(30.0, 20.0), metavar=("AZIMUTH", "ELEVATION"),
                    help="camera direction in degrees (default 30 20)")
    ap.add_argument("--no-movie", action="store_true", help="PNG frames only")
    return ap


def main(argv=None, prog="vesflow render"):
    """Command line of `vesflow render`; returns the exit status (0 ok, 2 bad input)."""
    args = build_parser(prog).parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"{prog}: --size must look like 960x540, got {args.size!r}", file=sys.stderr)
        return 2
    try:
        res = render(args.source, movie=False if args.no_movie else args.output, frames_dir=args.frames,
                     color=args.color, size=(w, h), fps=args.fps, clim=args.clim, view=tuple(args.view),
                     progress=sys.stderr.isatty())
    except (FileNotFoundError, ValueError, KeyError) as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    if res.movie:
        print(f"movie: {res.movie} ({len(res.times)} frames)")
    if res.frames:
        print(f"frames: {Path(res.frames[0]).parent}/frame_*.png")
    return 0


__all__ = ["render", "fit_camera", "RenderResult", "main", "build_parser", "COLORS"]
