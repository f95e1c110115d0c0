"""Short-range repulsion between vesicles (paper eq. 3.13) and collision queries on the near pairs.

For a p-grid point X of vesicle i and its projection X0 on vesicle j (the near-singular
projection of the layer potentials), d = X - X0 and

    f_r = (R^2 / |d|^3) exp(-|d|^2 / R^2) d,

summed over the other vesicles; only pairs with |d| < 5R contribute (the rest is < 1e-10 R^-1).
Zero cost when the scene has no repulsion: the stepper never calls this module then.
"""
from __future__ import annotations

import numpy as np

from . import sph


def repulsion_force(surface, lp, radius, q_force):
    """Traction f_r on the q_force grid, (N, npts_q, 3)."""
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q_force)
    out = np.zeros((N, Tq.npts, 3))
    info = getattr(lp, "near", None)
    if info is None or "projection" not in info:
        return out
    M = sph.transform(p).npts
    X = surface.points().reshape(-1, 3)
    proj = info["projection"]
    d = X[info["pairs"][:, 0]] - proj.point
    r = np.linalg.norm(d, axis=1)
    R = float(radius)
    use = (r < 5.0 * R) & (r > 0)
    f = np.zeros((N * M, 3))
    mag = R * R / r[use] ** 3 * np.exp(-(r[use] / R) ** 2)
    np.add.at(f, info["pairs"][use, 0], mag[:, None] * d[use])
    coeffs = sph.transform(p).analysis(np.moveaxis(f.reshape(N, M, 3), -1, -2))
    return np.moveaxis(Tq.synth(coeffs), -2, -1)


def min_gap(lp):
    """Smallest signed distance over the near pairs (inf without near pairs)."""
    info = getattr(lp, "near", None)
    if info is None or "projection" not in info or not len(info["pairs"]):
        return np.inf
    return float(info["projection"].signed_distance.min())


def contacts(lp):
    """Near pairs whose point lies on or behind the other surface (paper 3.3)."""
    info = getattr(lp, "near", None)
    if info is None or "projection" not in info:
        return 0
    return int(np.count_nonzero(info["projection"].signed_distance <= 0))
