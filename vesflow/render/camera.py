"""Cameras of a movie: fit (one camera for the whole run), follow (one per frame,
smoothed in time), fixed (given position and focal point).

Framing is exact for a perspective camera looking along -back (view basis from an
azimuth about z and an elevation): a point with coordinates (a, b, c) along
(right, up, back) seen from the camera at u right + v up + D back lands at
x = (a - u) / ((D - c) T_x) in normalized device coordinates, T_x = tan(view
angle / 2) W / H (and y likewise with b, v, T_y = tan(view angle / 2)).  Every point
lies inside the window [x0, x1] x [y0, y1] iff
    D >= (max(a + x1 T_x c) - min(a + x0 T_x c)) / ((x1 - x0) T_x)    (and likewise in y)
and u lies in [max(a + x1 T_x c) - x1 T_x D, min(a + x0 T_x c) - x0 T_x D].  The
smallest such D frames the points tightly; within the interval, the pan that leaves equal
gaps on both sides of the picture centres it.  Only the convex hulls of the points in the
(a, c) and (b, c) planes matter (the extremes of these ratios lie on them).

follow: the per-frame distances D_k are replaced by a Gaussian-smoothed running
maximum (the camera pulls back before the vesicles need it), then by
max(smoothed, D_k); the pans (u, v) are Gaussian-smoothed and clipped to each
frame's admissible interval, so every frame keeps every point inside the window.
"""
from __future__ import annotations

import numpy as np

CAMERAS = ("auto", "follow", "fit", "fixed")
VIEW_ANGLE = 30.0            # vertical view angle (degrees)


def view_basis(azimuth, elevation):
    """(back, right, up): back points from the focal point to the camera, seen from the
    azimuth (degrees about z, from -y towards +x) and elevation (degrees), z up."""
    az, el = np.radians(azimuth), np.radians(elevation)
    back = np.array([np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), np.sin(el)])
    return _basis_from_back(back)


def _basis_from_back(back):
    back = np.asarray(back, dtype=float) / np.linalg.norm(back)
    up0 = np.array([0.0, 0.0, 1.0]) if abs(back[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    right = np.cross(-back, up0)
    right /= np.linalg.norm(right)
    return back, right, np.cross(right, -back)


def _tangents(size):
    t = np.tan(np.radians(VIEW_ANGLE) / 2)
    return t * size[0] / size[1], t


def _hull(xy):
    """The vertices of the convex hull of 2D points (K, 2) (all points if degenerate):
    every linear function, and every ratio (a - u) / (D - c) framing needs, takes its
    extremes there."""
    if len(xy) > 16:
        from scipy.spatial import ConvexHull, QhullError
        try:
            return xy[ConvexHull(xy).vertices]
        except QhullError:          # collinear points: keep them all (exact, only slower)
            pass
    return xy


class Extent:
    """What framing needs of one point set seen from one view into one window
    (module docstring): the convex hulls of the points in the (a, c) and (b, c) planes.
    merge() unites several (a camera for all of them)."""

    def __init__(self, points, basis, size, window, _hulls=None):
        self.basis, self.size, self.window = basis, size, window
        (x0, x1, y0, y1), (tx, ty) = window, _tangents(size)
        self.kx, self.ky = (x0 * tx, x1 * tx), (y0 * ty, y1 * ty)
        if _hulls is None:
            back, right, up = basis
            P = np.asarray(points, dtype=float).reshape(-1, 3)
            a, b, c = P @ right, P @ up, P @ back
            _hulls = (_hull(np.stack([a, c], 1)), _hull(np.stack([b, c], 1)))
        self.ac, self.bc = _hulls
        a, c = self.ac.T
        b, cb = self.bc.T
        self.hi_x, self.lo_x = np.max(a + self.kx[1] * c), np.min(a + self.kx[0] * c)
        self.hi_y, self.lo_y = np.max(b + self.ky[1] * cb), np.min(b + self.ky[0] * cb)
        spread = max(np.ptp(a), np.ptp(b), np.ptp(c), 1e-9)
        self.near = np.max(c) + 0.05 * spread                   # every point in front of the camera

    @property
    def distance(self):
        """The smallest camera distance D that holds every point in the window."""
        return max((self.hi_x - self.lo_x) / (self.kx[1] - self.kx[0]),
                   (self.hi_y - self.lo_y) / (self.ky[1] - self.ky[0]), self.near)

    def pan_range(self, D):
        """Admissible (u_lo, u_hi), (v_lo, v_hi) at distance D >= self.distance."""
        return ((self.hi_x - self.kx[1] * D, self.lo_x - self.kx[0] * D),
                (self.hi_y - self.ky[1] * D, self.lo_y - self.ky[0] * D))

    def centred_pan(self, D):
        """(u, v) at distance D that centres the picture of the points in the window: the
        same gap (normalized device coordinates) on both sides, by bisection (the sum of
        the largest and smallest projected coordinate falls as the pan grows)."""
        out = []
        for pts, k, (lo, hi) in ((self.ac, self.kx, self.pan_range(D)[0]), (self.bc, self.ky, self.pan_range(D)[1])):
            a, c = pts.T
            s = 1.0 / (D - c)
            target = k[0] + k[1]                                  # (x0 + x1) T
            for _ in range(60):
                mid = 0.5 * (lo + hi)
                proj = (a - mid) * s
                if proj.max() + proj.min() > target:
                    lo = mid
                else:
                    hi = mid
            out.append(0.5 * (lo + hi))
        return tuple(out)

    @staticmethod
    def merge(extents):
        e0 = extents[0]
        hulls = tuple(_hull(np.concatenate([getattr(e, name) for e in extents])) for name in ("ac", "bc"))
        return Extent(None, e0.basis, e0.size, e0.window, _hulls=hulls)


def _camera(basis, u, v, D):
    back, right, up = basis
    pos = u * right + v * up + D * back
    return (tuple(map(float, pos)), tuple(map(float, pos - D * back)), tuple(map(float, up)))


def fit_cameras(extents):
    """One camera holding the points of every extent (the same for every frame)."""
    ext = Extent.merge(extents)
    D = ext.distance
    return [_camera(ext.basis, *ext.centred_pan(D), D)] * len(extents)


def follow_cameras(extents, smooth=5.0):
    """One camera per extent (frame), each holding its frame's points, smoothed over
    about `smooth` frames (standard deviation of the Gaussian; 0: no smoothing)."""
    from scipy.ndimage import gaussian_filter1d, maximum_filter1d

    D_tight = np.array([e.distance for e in extents])
    D = D_tight.copy()
    if smooth > 0 and len(D) > 1:
        reach = int(np.ceil(smooth))
        D = gaussian_filter1d(maximum_filter1d(D, size=2 * reach + 1, mode="nearest"), smooth, mode="nearest")
        D = np.maximum(D, D_tight)
    ranges = [e.pan_range(d) for e, d in zip(extents, D)]
    lo = np.array([[r[0][0], r[1][0]] for r in ranges])
    hi = np.array([[r[0][1], r[1][1]] for r in ranges])
    pan = np.array([e.centred_pan(d) for e, d in zip(extents, D)])
    if smooth > 0 and len(D) > 1:
        pan = np.clip(gaussian_filter1d(pan, smooth, axis=0, mode="nearest"), lo, hi)
    return [_camera(e.basis, u, v, d) for e, (u, v), d in zip(extents, pan, D)]


def fit_camera(points, size, view=(45.0, 20.0), window=(-0.9, 0.9, -0.9, 0.9)):
    """(position, focal point, view up) of the closest camera looking from `view`
    (azimuth, elevation) whose picture holds every point (K, 3) inside `window`
    (x0, x1, y0, y1 in normalized device coordinates, -1..1), centred in it."""
    return fit_cameras([Extent(points, view_basis(*view), size, window)])[0]


def fixed_camera(position, focal_point):
    """(position, focal point, view up) for a given position and focal point, z up
    (y up when looking along z)."""
    pos, foc = np.asarray(position, dtype=float), np.asarray(focal_point, dtype=float)
    if pos.shape != (3,) or foc.shape != (3,) or not np.all(np.isfinite(np.r_[pos, foc])):
        raise ValueError(f"render: camera position and focal point must be 3 finite numbers each, "
                         f"got {position} and {focal_point}")
    if np.linalg.norm(pos - foc) == 0:
        raise ValueError(f"render: camera position {tuple(pos)} equals the focal point: they must differ")
    _, _, up = _basis_from_back(pos - foc)
    return (tuple(map(float, pos)), tuple(map(float, foc)), tuple(map(float, up)))


def project(points, camera, size):
    """Normalized device coordinates (K, 2) and depths (K,) of points seen by a camera
    (position, focal point, view up) with the VIEW_ANGLE of this module."""
    pos, foc, up = (np.asarray(v, dtype=float) for v in camera)
    back = (pos - foc) / np.linalg.norm(pos - foc)
    right = np.cross(-back, up)
    right /= np.linalg.norm(right)
    upv = np.cross(right, -back)
    q = np.asarray(points, dtype=float).reshape(-1, 3) - pos
    depth = -q @ back
    tx, ty = _tangents(size)
    return np.stack([(q @ right) / (depth * tx), (q @ upv) / (depth * ty)], axis=1), depth
