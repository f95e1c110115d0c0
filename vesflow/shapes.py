"""Initial vesicle shapes as spherical-harmonic coefficients (docs/explanation/method.md, section 1).

Every shape is parameterized over the unit sphere so that its coordinates are low-degree
polynomials in sin/cos of theta and phi (exactly representable for p >= 5), then scaled
to an effective radius R0 = sqrt(A / 4 pi), rotated (ZYZ Euler angles, degrees) about
its centre and moved to its centre.

- sphere, ellipsoid (semi-axes a, b, c along x, y, z): X = (a sin t cos p, b sin t sin p, c cos t)
- oblate / prolate: spheroids (a, a, c), c/a solved for the requested reduced volume
- biconcave (Evans and Fung 1972): X = (sin t cos p, sin t sin p, s/2 cos t (c0 + c2 sin^2 t + c4 sin^4 t)),
  c0 = 0.207, c2 = 2.003, c4 = -1.123; the height factor s (1 for the published cell,
  reduced volume ~0.644) is solved for a requested reduced volume.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.optimize import brentq

from . import sph
from .scene.geometry import EVANS_FUNG, SHAPES, euler_zyz, spheroid_axes  # noqa: F401 (euler_zyz re-exported)
from .surface import Surface

FIT_P = 8   # every shape is exact at degree <= 5; fits are done at this degree and resampled


def _grid_fit(fn, p=FIT_P):
    """Coefficients (3, C) of X(theta, phi) given by fn(theta, phi) -> (3, npts) on the p-grid."""
    T = sph.transform(p)
    tt, pp = np.meshgrid(T.theta, T.phi, indexing="ij")
    return T.analysis(fn(tt.ravel(), pp.ravel()))


def ellipsoid_coeffs(axes, p):
    a, b, c = axes
    fit = _grid_fit(lambda t, f: np.array([a * np.sin(t) * np.cos(f), b * np.sin(t) * np.sin(f), c * np.cos(t)]))
    return sph.resample(fit, FIT_P, p)


def biconcave_coeffs(height_scale, p):
    c0, c2, c4 = EVANS_FUNG
    def X(t, f):
        s2 = np.sin(t) ** 2
        z = 0.5 * height_scale * np.cos(t) * (c0 + c2 * s2 + c4 * s2 * s2)
        return np.array([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), z])
    return sph.resample(_grid_fit(X), FIT_P, p)


def _reduced_volume_of(coeffs, p):
    return float(Surface(coeffs[None], p).reduced_volume(q=4 * p)[0])


@lru_cache(maxsize=64)
def biconcave_height_scale(reduced_volume):
    """Height factor s of the Evans-Fung profile giving the requested reduced volume *of the
    degree-16 expansion* (so that generated shapes have it to 1e-8); scene.geometry's version
    solves the exact profile, for the overlap checks of the scene."""
    v = float(reduced_volume)
    f = lambda s: _reduced_volume_of(biconcave_coeffs(s, 16), 16) - v
    lo, hi = 0.4, 1.6
    if f(lo) * f(hi) > 0:
        raise ValueError(f"reduced_volume = {v}: the biconcave shape reaches only "
                         f"[{f(lo) + v:.3f}, {f(hi) + v:.3f}]")
    return brentq(f, lo, hi, xtol=1e-14)


def unit_shape_coeffs(shape, p, reduced_volume=None, axes=None):
    """Coefficients (3, C) of the unscaled shape centred at the origin."""
    if shape == "sphere":
        return ellipsoid_coeffs((1.0, 1.0, 1.0), p)
    if shape == "ellipsoid":
        if axes is None or len(axes) != 3 or min(axes) <= 0:
            raise ValueError(f"ellipsoid axes = {axes}: need three positive semi-axes")
        return ellipsoid_coeffs(tuple(float(a) for a in axes), p)
    if shape in ("oblate", "prolate"):
        return ellipsoid_coeffs(spheroid_axes(shape, 0.85 if reduced_volume is None else reduced_volume), p)
    if shape == "biconcave":
        s = 1.0 if reduced_volume is None else biconcave_height_scale(round(float(reduced_volume), 14))
        return biconcave_coeffs(s, p)
    raise ValueError(f"shape = {shape!r}: must be one of {', '.join(SHAPES)}")


def make_shape(shape, p, *, radius=1.0, center=(0.0, 0.0, 0.0), rotation=(0.0, 0.0, 0.0),
               reduced_volume=None, axes=None):
    """Position coefficients (3, C) of a shape scaled to effective radius `radius`, rotated, placed."""
    c = unit_shape_coeffs(shape, p, reduced_volume, axes)
    r0 = float(Surface(c[None], p).effective_radius(q=max(2 * p, 16))[0])
    c = (radius / r0) * (euler_zyz(rotation) @ c)
    c[:, 0] += np.sqrt(4.0 * np.pi) * np.asarray(center, dtype=float)
    return c
