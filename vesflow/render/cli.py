"""`vesflow render` (and postprocess/render.py): the command line of render()."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .camera import CAMERAS
from .movie import COLORS, render
from .periodic import PERIODIC_MODES
from .surfaces import MAX_FACET_ANGLE


def build_parser(prog="vesflow render"):
    ap = argparse.ArgumentParser(prog=prog, description="Render a run (OUT.h5 or OUT.pvd) off-screen to MP4 and PNGs.")
    ap.add_argument("source", help="run file (.h5) or VTK collection (.pvd)")
    ap.add_argument("-o", "--output", default=None, help="movie path (default: SOURCE with .mp4)")
    ap.add_argument("--frames", default=None, metavar="DIR", help="also write one PNG per frame into DIR")
    ap.add_argument("--color", default="tension", choices=COLORS)
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT in pixels (default 960x540)")
    ap.add_argument("--fps", type=int, default=None, help="frames per second (default: about a 10 s movie)")
    ap.add_argument("--clim", type=float, nargs=2, default=None, metavar=("LO", "HI"), help="fixed colour range")
    ap.add_argument("--camera", default="auto", choices=CAMERAS,
                    help="follow: the vesicles fill the frame, smoothed in time; fit: one camera for the "
                         "whole run; fixed: --position and --focal-point; auto (default): fit for periodic "
                         "runs and runs whose extent hardly changes, else follow")
    ap.add_argument("--view", type=float, nargs=2, default=(45.0, 20.0), metavar=("AZIMUTH", "ELEVATION"),
                    help="direction of the follow and fit cameras in degrees (default 45 20)")
    ap.add_argument("--position", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                    help="camera position (--camera fixed)")
    ap.add_argument("--focal-point", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                    help="point the camera looks at (--camera fixed)")
    ap.add_argument("--smooth", type=float, default=None, metavar="FRAMES",
                    help="follow camera smoothing, in frames (default: half a second of movie)")
    ap.add_argument("--resolution", type=int, default=None, metavar="Q",
                    help=f"surfaces drawn on the q-grid, q >= p (run files; default: the coarsest grid whose "
                         f"adjacent triangles differ by at most {MAX_FACET_ANGLE:g} degrees)")
    ap.add_argument("--periodic", default="images", choices=PERIODIC_MODES,
                    help="periodic runs: images (vesicles crossing a face shown on both sides) or wrap")
    ap.add_argument("--workers", type=int, default=None, help="processes drawing frames (default: auto)")
    ap.add_argument("--no-movie", action="store_true", help="PNG frames only")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    return ap


def main(argv=None, prog="vesflow render"):
    """Command line of `vesflow render`; returns the exit status (0 ok, 2 bad input)."""
    try:
        args = build_parser(prog).parse_args(argv)
    except SystemExit as e:          # argparse: --help (0) or a bad option, already reported (2)
        return e.code
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        print(f"{prog}: --size must look like 960x540, got {args.size!r}", file=sys.stderr)
        return 2
    if args.smooth is not None and not args.smooth >= 0:
        print(f"{prog}: --smooth = {args.smooth}: must be >= 0 (frames)", file=sys.stderr)
        return 2
    try:
        res = render(args.source, movie=False if args.no_movie else args.output, frames_dir=args.frames,
                     color=args.color, size=(w, h), fps=args.fps, clim=args.clim, view=tuple(args.view),
                     camera=args.camera, position=args.position, focal_point=args.focal_point,
                     smooth=args.smooth, resolution=args.resolution, periodic=args.periodic,
                     workers=args.workers, progress=not args.quiet)
    except (FileNotFoundError, ValueError, KeyError) as e:
        print(f"{prog}: {e}", file=sys.stderr)
        return 2
    if res.movie:
        print(f"movie: {res.movie} ({len(res.times)} frames, camera {res.camera_mode}, {res.seconds:.1f} s)")
    if res.frames:
        print(f"frames: {Path(res.frames[0]).parent}/frame_*.png")
    return 0
