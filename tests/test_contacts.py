"""Contacts that never stop a run (vesflow/contact.py, docs/explanation/contacts.md).

A touching candidate whose step started in contact (gap below contact.ZONE h) is separated
rigidly; one that started farther is an overshoot, rejected as before (paper 3.3).  A run with
no such step is bit-identical with the mechanism on and off.
"""
from __future__ import annotations

import numpy as np
import pytest

from vesflow import collision, contact, shapes
from vesflow.surface import Surface

from . import harness

P = 6


def _pair(gap, p=P, radius=(1.0, 1.0), shape="sphere"):
    """Two vesicles on the x axis whose surfaces are `gap` apart there (negative: overlap)."""
    ra, rb = radius
    kw = {"reduced_volume": 0.9} if shape == "oblate" else {}
    a = shapes.make_shape(shape, p, radius=ra, center=(-ra - gap / 2, 0.0, 0.0), **kw)
    b = shapes.make_shape(shape, p, radius=rb, center=(rb + gap / 2, 0.0, 0.0), **kw)
    return np.stack([a, b])


@pytest.mark.parametrize("radius", [(1.0, 1.0), (1.0, 0.5)])
def test_separate_moves_a_touching_pair_apart_rigidly(radius):
    """Spheres overlapping by 1e-2 on the x axis: after the separation the smallest gap is within
    [0.5, 1.5] x the target, nothing but the degree-0 coefficients (the positions) changed, the
    shifts are along x, opposite and in the ratio of the radii (the smaller sphere moves more)."""
    c = _pair(-1e-2, radius=radius)
    q = 2 * P
    S = Surface(c, P)
    target = contact.TARGET * contact.grid_spacing(S)
    assert collision.contacts(S, q) > 0
    out, moved = contact.separate(c, P, q)
    T = Surface(out, P)
    g = collision.min_gap(T, q)
    assert 0.5 * target <= g <= 1.5 * target
    assert np.array_equal(out[:, :, 1:], c[:, :, 1:])               # shapes untouched
    assert np.allclose(T.area(), S.area(), rtol=1e-14) and np.allclose(T.volume(), S.volume(), rtol=1e-14)
    shift = T.centroid() - S.centroid()
    assert np.abs(shift[:, 1:]).max() < 1e-3 * np.abs(shift[:, 0]).max()
    assert shift[0, 0] < 0 < shift[1, 0]
    ra, rb = radius
    assert shift[1, 0] / -shift[0, 0] == pytest.approx(ra / rb, rel=1e-12)   # mobility ~ 1 / R
    assert moved == pytest.approx(1e-2 + target, rel=0.2)


def test_separate_leaves_a_pair_with_a_gap_unchanged():
    c = _pair(0.1)
    out, moved = contact.separate(c, P, 2 * P)
    assert out is c or np.array_equal(out, c)
    assert moved == 0.0


def test_resolve_separates_only_steps_that_start_in_contact():
    """Start gap below ZONE h (p = 6: 3.9e-3): separated; a start gap of 5e-2 (a step that jumped
    across a gap it should have resolved): None, the step is rejected as before."""
    q = 2 * P
    cand = _pair(-5e-3)
    h = contact.grid_spacing(Surface(cand, P))
    c = contact.Contacts(P)
    assert c.resolve(cand, _pair(0.5 * contact.ZONE * h), q) is not None
    assert c.count == 1
    assert c.resolve(cand, _pair(5e-2), q) is None
    assert c.count == 1
    g0, gc, moved = c.log[0]
    assert g0 == pytest.approx(0.5 * contact.ZONE * h, rel=0.05) and gc < 0 < moved
