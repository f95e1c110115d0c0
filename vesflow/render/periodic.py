"""Vesicles of a triply periodic run drawn in the periodic cube [0, L)^3.

wrap:   each vesicle is moved by a multiple of L so that its centre (mean of its
        points) lies in the cube; parts that cross a face stick out of it.
images: as wrap, plus the image of every vesicle that crosses a face, moved by
        -+L across that face (and across edges and corners when it crosses
        several faces), so a vesicle crossing a face shows on both sides.
"""
from __future__ import annotations

import itertools

import numpy as np

PERIODIC_MODES = ("images", "wrap")


def wrap_and_image(points, period, mode="images", values=None, normals=None):
    """points (N, P, 3) -> (N', P, 3) drawn in [0, L)^3, with the matching rows of values
    (N, P) and normals (N, P, 3) (None passes through).  Returns (points, values, normals)."""
    if mode not in PERIODIC_MODES:
        raise ValueError(f"render: periodic = {mode!r}: must be one of {', '.join(PERIODIC_MODES)}")
    L = float(period)
    pts = np.asarray(points, dtype=float)
    shift = -L * np.floor(pts.mean(axis=1) / L)                     # (N, 3)
    pts = pts + shift[:, None, :]
    rows, shifts = list(range(len(pts))), [np.zeros(3)] * len(pts)
    if mode == "images":
        lo, hi = pts.min(axis=1), pts.max(axis=1)
        for v in range(len(pts)):
            # per axis: 0 (inside), +L (crosses 0: image moved up), -L (crosses L: moved down)
            options = []
            for k in range(3):
                opts = [0.0]
                if lo[v, k] < 0:
                    opts.append(L)
                if hi[v, k] > L:
                    opts.append(-L)
                options.append(opts)
            for s in itertools.product(*options):
                if any(s):
                    rows.append(v)
                    shifts.append(np.array(s))
    rows = np.array(rows)
    out = pts[rows] + np.array(shifts)[:, None, :]
    pick = lambda a: None if a is None else np.asarray(a)[rows]
    return out, pick(values), pick(normals)


def box_corners(period):
    """The 8 corners (8, 3) of the cube [0, L]^3."""
    L = float(period)
    return np.array(list(itertools.product((0.0, L), repeat=3)))
