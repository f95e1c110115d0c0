"""Short-range repulsion between vesicles and contact measures (paper 3.3 and eq. 3.13; docs/explanation/method.md, sections 3 and 7).

For a p-grid point X of vesicle i near vesicle j, with X0 its projection on j (closest point,
from the near search of the layer potentials, `lp.near`):

    f_r = (R^2 / |d|^3) exp(-|d|^2 / R^2) d,    d = X - X0                          (3.13)

summed over the near vesicles j.  |f_r| = exp(-1) at |d| = R, 1.4e-5 at 3R and 5.6e-13 at 5R:
pairs with |d| >= 5R are skipped.  Two guards beyond the formula: if X is behind the surface
of j (signed distance < 0, an overlap that collision detection rejects anyway) d is flipped
to point out of j, so the force still separates the vesicles; and |d| is floored at 1e-3 R so
that the force stays finite (|f_r| <= 1e6).  Only pairs inside the near zone h_n of the layer
potentials are known: the force is complete when 5R <= h_n = sqrt(A / q_far) (unit-radius
vesicles, q_far = 2p: p <= 70 for R = 0.06, p <= 600 for R = 0.02), otherwise it is cut at h_n.
"""
from __future__ import annotations

import numpy as np

from . import sph

CUTOFF = 5.0          # pairs with |d| >= CUTOFF * R contribute < 1e-10 (relative to R^0)
FLOOR = 1e-3          # |d| is floored at FLOOR * R


def _projection(lp):
    near = lp.near                   # vesflow.layerpot.near.NearPairs, None without near pairs
    if near is None or not len(near.pairs):
        return None, None
    return near.pairs, near.projection


def repulsion_force(surface, lp, radius, q_force):
    """Traction f_r of (3.13) on the q_force grid, (N, npts_q, 3).

    Formed on the p-grid (the near targets of lp), projected to degree p and synthesized on
    the q_force grid, so that it adds to the other tractions of the step.  Zero (no work
    beyond the allocation) when radius <= 0 or lp has no near projection.
    """
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q_force)
    out = np.zeros((N, Tq.npts, 3))
    pairs, proj = _projection(lp)
    if pairs is None or radius <= 0:
        return out
    R = float(radius)
    # the target's image nearest the other vesicle (periodic; the target itself in free space)
    d = lp.near.tpos - proj.point
    dist = np.linalg.norm(d, axis=1)
    hit = dist < CUTOFF * R
    if not hit.any():
        return out
    d, dist = d[hit], dist[hit]
    behind = proj.signed_distance[hit] < 0
    d[behind] *= -1.0
    tiny = dist < FLOOR * R
    if tiny.any():       # direction from the normal of j when X is (almost) on it
        d[tiny] = proj.normal[hit][tiny] * FLOOR * R
        dist[tiny] = FLOOR * R
    mag = R * R / dist ** 3 * np.exp(-(dist / R) ** 2)
    Tp = sph.transform(p)
    fp = np.zeros((N * Tp.npts, 3))
    np.add.at(fp, pairs[hit, 0], mag[:, None] * d)
    coeffs = Tp.analysis(np.moveaxis(fp.reshape(N, Tp.npts, 3), -1, -2))
    return np.moveaxis(Tq.synth(coeffs), -2, -1)


def wall_repulsion_force(surface, near_wall, radius, q_force):
    """Traction f_r of (3.13) from a container's wall on the q_force grid, (N, npts_q, 3): for the
    p-grid points within the wall's near zone (near_wall: vesflow.layerpot.wall.WallTargets of the
    vesicles' p-grid points; index, signed distance, outward normal of each), d = X - X0 turned
    into the fluid (a point beyond the wall is pushed back), |d| floored as for two vesicles."""
    p, N = surface.p, surface.n_vesicles
    Tq = sph.transform(p, q_force)
    out = np.zeros((N, Tq.npts, 3))
    dist = np.abs(near_wall.distance)
    hit = dist < CUTOFF * radius
    if radius <= 0 or not hit.any():
        return out
    R = float(radius)
    dist = np.maximum(dist[hit], FLOOR * R)
    d = -near_wall.normal[hit] * dist[:, None]                 # into the fluid (the normal points out of it)
    mag = R * R / dist ** 3 * np.exp(-(dist / R) ** 2)
    Tp = sph.transform(p)
    fp = np.zeros((N * Tp.npts, 3))
    np.add.at(fp, near_wall.index[hit], mag[:, None] * d)
    coeffs = Tp.analysis(np.moveaxis(fp.reshape(N, Tp.npts, 3), -1, -2))
    return np.moveaxis(Tq.synth(coeffs), -2, -1)


def min_gap(lp):
    """Smallest signed distance over the near pairs of lp (negative: overlap; inf if none)."""
    pairs, proj = _projection(lp)
    return float(proj.signed_distance.min()) if pairs is not None else np.inf


def contacts(lp):
    """Number of near pairs with n(X0) . (X - X0) <= 0: points on or behind another surface (3.3)."""
    pairs, proj = _projection(lp)
    return int(np.count_nonzero(proj.signed_distance <= 0)) if pairs is not None else 0
