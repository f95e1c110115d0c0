"""Off-screen movies of a run: `vesflow render OUT.h5` (docs/reference/output.md, "Rendering").

    render("out/run.h5", movie="out/run.mp4", frames_dir="out/run_frames", color="tension")

surfaces.py  the surfaces drawn: run-file frames evaluated from their coefficients on a finer grid
camera.py    fit, follow and fixed cameras (exact perspective framing of the drawn points)
labels.py    title, time label, colour bar and axes triad laid out without overlaps
periodic.py  vesicles of a periodic run drawn in its cube (wrapped, with images)
movie.py     the two passes, worker processes, PNG and MP4 output
cli.py       the command line
"""
from .camera import CAMERAS, fit_camera
from .cli import build_parser, main
from .movie import COLORS, RenderResult, render

__all__ = ["render", "fit_camera", "RenderResult", "main", "build_parser", "COLORS", "CAMERAS"]
