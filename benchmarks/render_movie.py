#!/usr/bin/env python
"""Wall time of `vesflow render` on 300 frames of two vesicles (issue 20), and how much
of each frame the vesicles cover.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/render_movie.py [--frames 300] [--workers N ...]

The run file is synthetic (tests/harness.py, write_pair_run: two oblate vesicles, p = 8, passing in
shear over T = 12 and drifting 20 radii apart), written with the io writer.  Times the
command of the issue, `render OUT.h5 --frames DIR` (PNGs and the MP4, 960x540).  Runs with
whatever vesflow is importable (PYTHONPATH=/path/to/other/checkout times another version:
only the keywords that version knows are passed).  Coverage: the fraction of pixels that
differ from the white background, outside the label boxes when the renderer reports them.
cpu: user + system time of this process and its children (ffmpeg, worker processes), less
sensitive than the wall time to other jobs on a shared machine.
"""
import argparse
import inspect
import os
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def coverage(png, layout):
    from PIL import Image
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    drawn = np.abs(img - 255).sum(axis=-1) > 40
    if layout is not None:
        for l, t, r, b in layout.boxes.values():
            drawn[max(t, 0):b, max(l, 0):r] = False
    return drawn.mean()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--separation", type=float, default=20.0, help="final centre distance in radii")
    ap.add_argument("--workers", type=int, nargs="*", default=[None], help="worker counts to time (new renderer)")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()

    import importlib.util
    spec = importlib.util.spec_from_file_location("harness", ROOT / "tests" / "harness.py")
    runs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(runs)
    import vesflow.render as R
    known = inspect.signature(R.render).parameters
    with tempfile.TemporaryDirectory() as tmp:
        h5 = Path(tmp) / "pair.h5"
        runs.write_pair_run(h5, p=8, n_frames=args.frames, horizon=12.0, separation=args.separation)
        print(f"# vesflow from {Path(R.__file__).parent}; {args.frames} frames, 960x540, PNGs + MP4; "
              f"{len(os.sched_getaffinity(0))} cpus, load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        for workers in args.workers:
            for rep in range(args.repeat):
                kw = {}
                if "workers" in known:
                    kw["workers"] = workers
                t0, c0 = time.perf_counter(), os.times()
                res = R.render(h5, movie=Path(tmp) / "pair.mp4", frames_dir=Path(tmp) / "png", size=(960, 540), **kw)
                wall, c1 = time.perf_counter() - t0, os.times()
                cpu = sum(c1[:4]) - sum(c0[:4])          # this process and its children (ffmpeg, workers)
                cov = [coverage(f, getattr(res, "layout", None)) for f in res.frames]
                print(f"workers {getattr(res, 'workers', 1)}  camera {getattr(res, 'camera_mode', 'fit'):6s}  "
                      f"{wall:6.1f} s  ({1e3 * wall / len(res.frames):5.1f} ms/frame)  cpu {cpu:6.1f} s  vesicle coverage "
                      f"min {100 * min(cov):.2f}%  mean {100 * np.mean(cov):.2f}%  "
                      f"(load average {os.getloadavg()[0]:.2f})", flush=True)


if __name__ == "__main__":
    main()
