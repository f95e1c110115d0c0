"""Exact geometry of the analytic initial shapes (no spherical harmonics): ZYZ Euler angles,
spheroid axes of a reduced volume, the Evans-Fung biconcave cell, areas and volumes,
inside tests and dense surface samples for the overlap check."""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

SHAPES = ("sphere", "ellipsoid", "oblate", "prolate", "biconcave")
EVANS_FUNG = (0.207, 2.003, -1.123)


# ----------------------------------------------------------------------------------------
# Geometry of the analytic shapes
# ----------------------------------------------------------------------------------------
def euler_zyz(angles_deg) -> np.ndarray:
    """Rotation matrix Rz(alpha) Ry(beta) Rz(gamma) of ZYZ Euler angles in degrees (an active
    rotation about the centre: world = center + R @ body)."""
    a, b, g = np.radians(np.asarray(angles_deg, dtype=float))

    def rz(t):
        c, s = math.cos(t), math.sin(t)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    cb, sb = math.cos(b), math.sin(b)
    ry = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    return rz(a) @ ry @ rz(g)


def _euler_from_matrix(R) -> tuple[float, float, float]:
    """Inverse of euler_zyz (degrees)."""
    b = math.acos(max(-1.0, min(1.0, R[2, 2])))
    if abs(math.sin(b)) > 1e-12:
        a = math.atan2(R[1, 2], R[0, 2])
        g = math.atan2(R[2, 1], -R[2, 0])
    else:  # gimbal lock: only a + g (or a - g) matters
        a = math.atan2(R[1, 0], R[0, 0]) if R[2, 2] > 0 else math.atan2(-R[1, 0], -R[0, 0])
        g = 0.0
    return (math.degrees(a) % 360.0, math.degrees(b), math.degrees(g) % 360.0)


def _spheroid_area(c: float) -> float:
    """Area of the spheroid with semi-axes (1, 1, c)."""
    if abs(c - 1.0) < 1e-9:
        return 4.0 * math.pi * (1.0 + 2.0 * (c - 1.0) / 3.0)  # first order in c - 1
    if c < 1.0:
        e = math.sqrt(1.0 - c * c)
        return 2.0 * math.pi * (1.0 + c * c / e * math.log((1.0 + e) / c))   # atanh(e) = log((1 + e) / c)
    e = math.sqrt(1.0 - 1.0 / (c * c))
    return 2.0 * math.pi * (1.0 + c / e * math.asin(e))


def spheroid_reduced_volume(c: float) -> float:
    """Reduced volume 6 sqrt(pi) V / A^1.5 of the spheroid with semi-axes (1, 1, c)."""
    return 6.0 * math.sqrt(math.pi) * (4.0 / 3.0 * math.pi * c) / _spheroid_area(c) ** 1.5


@lru_cache(maxsize=4096)
def spheroid_axes(kind: str, reduced_volume: float) -> tuple[float, float, float]:
    """Unscaled semi-axes (1, 1, c) of the oblate (c < 1) or prolate (c > 1) spheroid with the
    given reduced volume in (0, 1]; c is along z."""
    from scipy.optimize import brentq

    v = float(reduced_volume)
    if kind not in ("oblate", "prolate"):
        raise ValueError(f"spheroid kind must be 'oblate' or 'prolate', got {kind!r}")
    if not 0.0 < v <= 1.0:
        raise ValueError(f"reduced_volume = {v!r}: must be in (0, 1]")
    if v >= 1.0 - 1e-15:
        return (1.0, 1.0, 1.0)
    f = lambda c: spheroid_reduced_volume(c) - v
    if kind == "oblate":
        c = brentq(f, 1e-12, 1.0 - 1e-12, xtol=1e-15, rtol=1e-15)
    else:
        c = brentq(f, 1.0 + 1e-12, 1e14, xtol=1e-15, rtol=1e-15)
    return (1.0, 1.0, float(c))


def _ellipsoid_area(axes) -> float:
    """Area of the ellipsoid with semi-axes (a, b, c) (Legendre's formula)."""
    from scipy.special import ellipeinc, ellipkinc

    a, b, c = sorted((float(x) for x in axes), reverse=True)
    if a - c < 1e-12 * a:
        return 4.0 * math.pi * a * a
    phi = math.acos(c / a)
    m = (a * a * (b * b - c * c)) / (b * b * (a * a - c * c))
    s = math.sin(phi)
    return 2.0 * math.pi * c * c + 2.0 * math.pi * a * b / s * (
        ellipeinc(phi, m) * s * s + ellipkinc(phi, m) * math.cos(phi) ** 2)


def _biconcave_profile(rho2, s):
    c0, c2, c4 = EVANS_FUNG
    return 0.5 * s * (c0 + c2 * rho2 + c4 * rho2 * rho2)   # times sqrt(1 - rho^2)


@lru_cache(maxsize=None)
def _gl_quarter(n=400):
    x, w = np.polynomial.legendre.leggauss(n)
    return (x + 1.0) * math.pi / 4.0, w * math.pi / 4.0


def _biconcave_area_volume(s: float) -> tuple[float, float]:
    """Area and volume of the Evans-Fung cell of unit radius with height factor s."""
    t, w = _gl_quarter()
    c0, c2, c4 = EVANS_FUNG
    r, rt = np.sin(t), np.cos(t)              # rho = sin t, the profile is smooth in t
    P = c0 + c2 * r ** 2 + c4 * r ** 4
    zt = 0.5 * s * (-np.sin(t) * P + np.cos(t) * (2 * c2 * r * rt + 4 * c4 * r ** 3 * rt))
    area = 4.0 * math.pi * float(np.sum(w * r * np.sqrt(rt ** 2 + zt ** 2)))
    volume = 2.0 * math.pi * s * (c0 / 3.0 + 2.0 * c2 / 15.0 + 8.0 * c4 / 105.0)
    return area, volume


def _reduced_volume(area, volume):
    return 6.0 * math.sqrt(math.pi) * volume / area ** 1.5


@lru_cache(maxsize=4096)
def biconcave_height_scale(reduced_volume: float) -> float:
    """Height factor s of the Evans-Fung profile (s = 1: the published cell, v ~ 0.644)
    giving the requested reduced volume (v is monotone in s on [0.3, 2], v in [0.29, 0.74])."""
    from scipy.optimize import brentq

    v = float(reduced_volume)
    f = lambda s: _reduced_volume(*_biconcave_area_volume(s)) - v
    if not f(0.3) < 0.0 < f(2.0):
        raise ValueError(f"reduced_volume = {v!r}: the biconcave shape reaches [0.29, 0.74]")
    return float(brentq(f, 0.3, 2.0, xtol=1e-14, rtol=1e-15))


@dataclass(frozen=True)
class _Unit:
    """An unscaled shape: quadric (exact) or biconcave, with its enclosing ellipsoid axes."""
    kind: str                 # "quadric" | "biconcave"
    axes: tuple               # semi-axes of the quadric, or of the biconcave's enclosing spheroid
    s: float                  # biconcave height factor (0 for quadrics)
    area: float
    volume: float
    rbound: float

    @property
    def r0(self):
        return math.sqrt(self.area / (4.0 * math.pi))

    @property
    def reduced_volume(self):
        return _reduced_volume(self.area, self.volume)

    def inside(self, x, margin=1e-9):
        """True where the points x (..., 3), in the body frame, are strictly inside."""
        if self.kind == "quadric":
            a = np.asarray(self.axes)
            return np.sum((x / a) ** 2, axis=-1) < 1.0 - margin
        rho2 = x[..., 0] ** 2 + x[..., 1] ** 2
        h = np.sqrt(np.maximum(1.0 - rho2, 0.0)) * _biconcave_profile(rho2, self.s)
        return (rho2 < 1.0 - margin) & (np.abs(x[..., 2]) < h - margin)

    def surface_points(self):
        return _surface_points(self)


@lru_cache(maxsize=4096)
def _unit_shape(shape, reduced_volume, axes) -> _Unit:
    if shape == "sphere":
        return _Unit("quadric", (1.0, 1.0, 1.0), 0.0, 4.0 * math.pi, 4.0 * math.pi / 3.0, 1.0)
    if shape == "ellipsoid":
        ax = tuple(float(a) for a in axes)
        return _Unit("quadric", ax, 0.0, _ellipsoid_area(ax), 4.0 / 3.0 * math.pi * ax[0] * ax[1] * ax[2], max(ax))
    if shape in ("oblate", "prolate"):
        ax = spheroid_axes(shape, reduced_volume)
        return _Unit("quadric", ax, 0.0, _spheroid_area(ax[2]), 4.0 / 3.0 * math.pi * ax[2], max(ax))
    if shape == "biconcave":
        s = biconcave_height_scale(reduced_volume)
        area, volume = _biconcave_area_volume(s)
        c0, c2, c4 = EVANS_FUNG
        pmax = c0 - c2 * c2 / (4.0 * c4) if 0.0 < -c2 / (2.0 * c4) < 1.0 else max(c0, c0 + c2 + c4)
        rho2 = np.linspace(0.0, 1.0, 20001)
        z = np.sqrt(1.0 - rho2) * _biconcave_profile(rho2, s)
        rbound = float(np.sqrt(np.max(rho2 + z * z))) * (1.0 + 1e-9)
        return _Unit("biconcave", (1.0, 1.0, 0.5 * s * pmax * (1.0 + 1e-9)), s, area, volume, rbound)
    raise ValueError(f"unknown shape {shape!r}")


@lru_cache(maxsize=256)
def _surface_points(unit: _Unit, nt=96, nphi=128) -> np.ndarray:
    """Dense surface samples (S, 3) of an unscaled shape (uniform in theta, phi)."""
    t = (np.arange(nt) + 0.5) * math.pi / nt
    f = np.arange(nphi) * 2.0 * math.pi / nphi
    tt, ff = np.meshgrid(t, f, indexing="ij")
    st, ct = np.sin(tt), np.cos(tt)
    if unit.kind == "quadric":
        a, b, c = unit.axes
        pts = np.stack([a * st * np.cos(ff), b * st * np.sin(ff), c * ct], axis=-1)
    else:
        z = ct * _biconcave_profile(st * st, unit.s)
        pts = np.stack([st * np.cos(ff), st * np.sin(ff), z], axis=-1)
    pts = pts.reshape(-1, 3)
    pts.setflags(write=False)
    return pts
