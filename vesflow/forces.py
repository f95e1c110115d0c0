"""Interfacial forces (docs/explanation/method.md, section 3; paper 2.5, 2.6, 3.12).

All forces are traction jumps on the grid of a Geometry, shape (N, npts, 3).

    bending      f_b = -kappa_b [Laplace H + 2 H (H^2 - K)] n                 (2.5)
    tension      f_s = sigma Laplace X + grad sigma = 2 sigma H n + grad sigma   (2.6)
    linearized   B[Y] = -kappa_b [Laplace H[Y] + 2 H[Y] (H^2 - K)] n,  H[Y] = n . Laplace Y / 2   (3.12)
    gravity      f_g = drho (g . X) n
"""
from __future__ import annotations

import numpy as np


def _per_vesicle(value, geo):
    """Broadcast a scalar or per-vesicle array to (N, 1)."""
    return np.broadcast_to(np.asarray(value, dtype=float), (geo.H.shape[0],))[:, None]


def bending_force(geo, kappa):
    """f_b = -kappa_b [Laplace H + 2 H (H^2 - K)] n on the grid of geo."""
    lapH = geo.laplace(geo.H)
    mag = -_per_vesicle(kappa, geo) * (lapH + 2.0 * geo.H * (geo.H ** 2 - geo.K))
    return mag[..., None] * geo.normal


def tension_force(geo, sigma, d=None):
    """f_s = 2 sigma H n + grad sigma; sigma is a grid field (N, npts) of this grid (d: its
    derivatives 't', 'p' if known, e.g. synthesized from its coefficients)."""
    return (2.0 * sigma * geo.H)[..., None] * geo.normal + geo.grad(sigma, d)


def linear_mean_curvature(geo, Y, dY=None):
    """H[Y] = n . (Laplace Y) / 2 with the frozen geometry of geo; Y is (N, npts, 3) (dY: the
    derivatives of Y as Geometry.derivatives gives them for (N, 3, npts), if known)."""
    return 0.5 * np.einsum("...k,...k->...", geo.laplace_vector(Y, dY), geo.normal)


def linearized_bending_force(geo, kappa, Y, dY=None):
    """B[Y] of (3.12): linear in Y, equal to f_b when Y is the position of geo."""
    h = linear_mean_curvature(geo, Y, dY)
    mag = -_per_vesicle(kappa, geo) * (geo.laplace(h) + 2.0 * h * (geo.H ** 2 - geo.K))
    return mag[..., None] * geo.normal


def gravity_force(geo, excess_density, g):
    """f_g = drho (g . X) n; its integral is drho V g (buoyancy-corrected weight)."""
    gx = geo.X @ np.asarray(g, dtype=float)
    return (_per_vesicle(excess_density, geo) * gx)[..., None] * geo.normal
