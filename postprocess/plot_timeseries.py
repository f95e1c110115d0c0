#!/usr/bin/env python
"""Time series of a run: dt, GMRES iterations per step, relative area and volume
error, bending energy against time, read from the run file (HDF5); writes a PNG.

    python postprocess/plot_timeseries.py out/run.h5 [-o out/run_timeseries.png]

Rejected steps are red crosses; restarts are dashed vertical lines.  The relative
errors are |A(t) - A(0)| / A(0) per vesicle (max over vesicles, and each vesicle
when there are at most 8).
"""
import argparse
import sys
from pathlib import Path

import numpy as np

from vesflow.io import read_output

MAX_LINES = 8


def _positive(y):
    y = np.asarray(y, dtype=float)
    return np.where(y > 0, y, np.nan)


def _log_or_linear(ax, y):
    if np.any(np.asarray(y) > 0):
        ax.set_yscale("log")


def plot_timeseries(h5path, png=None, dpi=110):
    """Write the figure to png (default: next to the run file, *_timeseries.png); returns its path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h5path = Path(h5path)
    png = Path(png) if png else h5path.with_name(h5path.stem + "_timeseries.png")
    out = read_output(h5path, fields=["area", "volume", "bending_energy"])
    st = out.steps
    t = out.time
    fig, axes = plt.subplots(5, 1, figsize=(8, 11), sharex=True, constrained_layout=True)
    title = out.attrs.get("scene", "")
    try:
        import tomllib
        title = tomllib.loads(title).get("title", "") if title else ""
    except Exception:
        title = ""
    fig.suptitle(f"{h5path.name}{': ' + title if title else ''}  (N = {out.n_vesicles}, p = {out.p})")

    ax = axes[0]
    if len(st.get("time", [])):
        acc = st["accepted"].astype(bool)
        ax.plot(st["time"][acc], st["dt"][acc], ".-", ms=3, lw=0.8, label="accepted")
        if np.any(~acc):
            ax.plot(st["time"][~acc], st["dt"][~acc], "x", color="tab:red", ms=5,
                    label=f"rejected ({int(np.sum(~acc))})")
        ax.set_yscale("log")
        ax.legend(loc="best", fontsize=8)
        ax2 = axes[1]
        ax2.plot(st["time"][acc], st["ksp_its"][acc], ".", ms=3)
        if np.any(~acc):
            ax2.plot(st["time"][~acc], st["ksp_its"][~acc], "x", color="tab:red", ms=5)
    else:
        for a in axes[:2]:
            a.text(0.5, 0.5, "no steps recorded", ha="center", va="center", transform=a.transAxes)
    axes[0].set_ylabel("dt")
    axes[1].set_ylabel("GMRES iterations\nper step")

    for ax, name, label in ((axes[2], "area", "relative area error"),
                            (axes[3], "volume", "relative volume error")):
        v = out.frames[name]
        if len(t):
            err = np.abs(v - v[:1]) / np.abs(v[:1])
            if out.n_vesicles <= MAX_LINES and out.n_vesicles > 1:
                for j in range(out.n_vesicles):
                    ax.plot(t, _positive(err[:, j]), lw=0.7, alpha=0.6, label=f"vesicle {j}")
            ax.plot(t, _positive(err.max(axis=1)), "k-", lw=1.4, label="max over vesicles")
            _log_or_linear(ax, err)
            ax.legend(loc="best", fontsize=7, ncol=3)
        ax.set_ylabel(label)

    ax = axes[4]
    e = out.frames["bending_energy"]
    if len(t):
        if 1 < out.n_vesicles <= MAX_LINES:
            for j in range(out.n_vesicles):
                ax.plot(t, e[:, j], lw=0.7, alpha=0.6, label=f"vesicle {j}")
        ax.plot(t, e.sum(axis=1) / out.n_vesicles, "k-", lw=1.4, label="mean over vesicles")
        ax.legend(loc="best", fontsize=7, ncol=3)
    ax.set_ylabel("bending energy")
    ax.set_xlabel("time")
    for tr in out.restarts:
        for a in axes:
            a.axvline(tr, color="gray", ls="--", lw=0.8)
    for a in axes:
        a.grid(True, alpha=0.3)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=dpi)
    plt.close(fig)
    return png


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="run file (.h5)")
    ap.add_argument("-o", "--output", default=None, help="PNG path (default: RUN_timeseries.png)")
    args = ap.parse_args(argv)
    if not Path(args.run).exists():
        print(f"plot_timeseries: {args.run}: no such file", file=sys.stderr)
        return 2
    print(plot_timeseries(args.run, args.output))
    return 0


if __name__ == "__main__":
    sys.exit(main())
