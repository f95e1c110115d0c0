"""Contacts the discretization cannot resolve: the separation of a touching candidate.

At a given p the lubrication layer between two close surfaces is not resolved: at p = 6 a
sheared pair closes at 0.03-0.06 per unit time at every gap from 3e-2 down to 1e-5
(docs/explanation/contacts.md), so once a run resolves the approach no step avoids contact and
halving dt after each collision rejection (paper 3.3) only approaches the contact time until
dt < -ves_dt_min ends the run.  A candidate that touches is therefore treated by what it is:

- the step started at a gap g0 >= ZONE h (h = sqrt(A_max / (2 p (p + 1))), the p-grid spacing):
  the step jumped across a gap it should have resolved (an overshoot); rejected, dt halved;
- g0 < ZONE h: the surfaces are in contact at this resolution; the touching vesicles are moved
  apart rigidly until the smallest gap is TARGET h (a projection onto g >= 0, as the
  area/volume correction is onto A, V: no change of shape, area, volume or parameterization),
  each of a touching pair (i, j) by the share R_j / (R_i + R_j) of the shift along the normal
  of the closest point (Stokes mobility ~ 1 / R: the pair's mean position is kept for equal
  radii).  While the pair stays within ZONE h, an accepted state closer than TARGET h / 2 is
  separated too (Contacts.keep_apart).

Nothing changes before a step that starts in contact touches: a run without such a step is
bit-identical with and without it (tests/stepping/test_contacts.py).
"""
from __future__ import annotations

import numpy as np

from . import collision
from .surface import Surface

ZONE = 1e-2      # contact zone: start gap below ZONE h (p = 6, unit radius: 3.9e-3)
TARGET = 5e-3    # the separated state's smallest gap, TARGET h (half the zone)
ROUNDS = 8       # separation rounds (a shift can bring a third vesicle into contact)


def grid_spacing(surface):
    """h = sqrt(A_max / (2 p (p + 1))): the spacing of the p-grid of the largest vesicle."""
    p = surface.p
    return float(np.sqrt(surface.area().max() / (2.0 * p * (p + 1))))


def min_gap(coeffs, p, q, period=None):
    return collision.min_gap(Surface(coeffs, p), q, period)


def separate(coeffs, p, q, period=None, target=None):
    """coeffs with every pair of vesicles closer than target (default TARGET h) moved apart
    rigidly to a smallest gap of about target, or None if ROUNDS rounds do not clear them.
    Returns (coefficients, total shift length)."""
    surf = Surface(np.array(coeffs, dtype=float), p)
    target = TARGET * grid_spacing(surf) if target is None else float(target)
    R = surf.effective_radius()
    npts = surf.points().shape[1]
    moved = 0.0
    for _ in range(ROUNDS):
        pairs, proj = collision.near_projection(surf, q, period)
        if proj is None:
            return surf.coeffs, moved
        d = proj.signed_distance
        close = d < 0.5 * target
        if not close.any():
            return surf.coeffs, moved
        own = pairs[:, 0] // npts
        other = pairs[:, 1]
        shift = np.zeros((surf.n_vesicles, 3))
        # the closest point of each unordered pair (i, j) sets its shift
        key = np.minimum(own, other) * surf.n_vesicles + np.maximum(own, other)
        for k in np.unique(key[close]):
            sel = np.nonzero(close & (key == k))[0]
            e = sel[np.argmin(d[sel])]
            i, j = int(own[e]), int(other[e])
            s = (target - d[e]) * proj.normal[e]            # moves i out of j along j's normal
            shift[i] += R[j] / (R[i] + R[j]) * s
            shift[j] -= R[i] / (R[i] + R[j]) * s
            moved += float(target - d[e])
        surf = surf.translated(shift)
    pairs, proj = collision.near_projection(surf, q, period)
    if proj is None or proj.signed_distance.min() > 0:
        return surf.coeffs, moved
    return None, moved


class Contacts:
    """The contact step of a Run: resolve(candidate, start, q) -> separated coefficients or None
    (an overshoot, or not cleared); keep_apart(kept, q) while in contact.  Keeps the record of
    the separations."""

    def __init__(self, p, period=None, start=None, q=None):
        self.p, self.period = p, period
        self.log = []          # (start gap, candidate gap, shift) of every separated step
        # in contact: set by a separation or a start in the zone, cleared when the pair leaves it
        self.watch = start is not None and min_gap(start, p, q, period) < ZONE * grid_spacing(Surface(start, p))

    def keep_apart(self, kept, q):
        """While in contact, an accepted state closer than TARGET h / 2 is separated to TARGET h
        too: at gaps far below the grid spacing (1e-6 and less) the near-singular evaluation is
        not resolved, and sdc's error estimate then rejected step after step (the detector case
        dz = 0.22: 89 error-estimate rejections).  Leaves the zone: watch is cleared."""
        if not self.watch:
            return kept
        p = self.p
        h = grid_spacing(Surface(kept, p))
        g = min_gap(kept, p, q, self.period)
        if g >= ZONE * h:
            self.watch = False
            return kept
        if g >= 0.5 * TARGET * h:
            return kept
        out, moved = separate(kept, p, q, self.period, TARGET * h)
        if out is None:
            return kept
        self.log.append((g, g, moved))
        return out

    def resolve(self, candidate, start, q):
        """candidate separated (or None) when the step from start (coefficients) touches; q the
        collision check's grid."""
        p = self.p
        h = grid_spacing(Surface(start, p))
        g0 = min_gap(start, p, q, self.period)
        if not g0 < ZONE * h:
            return None
        out, moved = separate(candidate, p, q, self.period, TARGET * h)
        if out is not None:
            self.log.append((g0, min_gap(candidate, p, q, self.period), moved))
            self.watch = True
        return out

    @property
    def count(self):
        return len(self.log)

    def as_checkpoint(self):
        """What a restart needs to continue as the uninterrupted run: the in-contact flag (a
        restart from a state in the zone that was never separated must not start watching it)
        and the record of the separations (N, 3)."""
        return {"watch": int(self.watch), "log": np.array(self.log, dtype=float).reshape(-1, 3)}

    def restore(self, ck):
        """Continue from as_checkpoint()'s dict (a file without it keeps the start-gap rule of
        __init__)."""
        if ck is None:
            return
        self.watch = bool(int(ck["watch"]))
        self.log = [tuple(float(x) for x in row) for row in np.asarray(ck["log"], dtype=float).reshape(-1, 3)]
