"""Contacts that never stop a run (vesflow/contact.py, docs/explanation/contacts.md).

A touching candidate whose step started in contact (gap below contact.ZONE h) is separated
rigidly; one that started farther is an overshoot, rejected as before (paper 3.3).  A run with
no such step is bit-identical with the mechanism on and off.
"""
from __future__ import annotations

import copy

import numpy as np
import pytest

from vesflow import collision, contact, shapes
from vesflow.surface import Surface

from tests import harness

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


def test_keep_apart_acts_only_in_contact():
    """After a separation (watch set) an accepted state closer than TARGET h / 2 is moved to
    TARGET h; one within [TARGET h / 2, ZONE h) is kept as it is; one beyond ZONE h clears the
    watch; without the watch (no separation so far, start outside the zone) nothing is done."""
    q = 2 * P
    h = contact.grid_spacing(Surface(_pair(0.0), P))
    c = contact.Contacts(P, start=_pair(0.5), q=q)
    assert not c.watch
    close = _pair(0.1 * contact.TARGET * h)
    assert c.keep_apart(close, q) is close                           # not in contact: untouched
    c.watch = True
    out = c.keep_apart(close, q)
    assert collision.min_gap(Surface(out, P), q) == pytest.approx(contact.TARGET * h, rel=0.5) and c.count == 1
    mid = _pair(0.7 * contact.TARGET * h)
    assert c.keep_apart(mid, q) is mid and c.watch
    far = _pair(2 * contact.ZONE * h)
    assert c.keep_apart(far, q) is far and not c.watch
    assert contact.Contacts(P, start=_pair(0.5 * contact.ZONE * h), q=q).watch      # a start in contact


def _pair_run(dz, T, every, scheme, **options):
    text = harness.pair_scene(1.3, dz, P, T, every=every, dt=0.05)
    return harness.simulate(text, allow_failure=True, **{"-ts_type": scheme}, **options)


def test_a_run_whose_collisions_are_overshoots_is_bit_identical_with_and_without_it():
    """The detector case of tests/stepping/test_robustness.py (dz = 0.15, E/T = 0.15) with euler: its
    collision rejections start at gaps 2.4e-2 and 1.3e-2, above the contact zone (3.9e-3), so
    the separation never acts and the run is the same bits with -ves_contact on and off."""
    runs = {}
    for on in ("on", "off"):
        run, rec, failure = harness.simulate(harness.pair_scene(1.3, 0.15, P, 6.0, every=6.0, dt=0.05),
                                             allow_failure=True, **{"-ts_type": "euler", "-ves_adapt_tol": 0.15,
                                                                    "-ves_contact": on})
        assert failure is None
        runs[on] = (run, rec)
    (a, ra), (b, rb) = runs["on"], runs["off"]
    assert a.contacts.count == 0 and b.contacts is None
    assert harness.rejections(ra).get("collision", 0) >= 1          # the detector did act
    assert ra.steps == rb.steps
    assert np.array_equal(a.stepper.coeffs, b.stepper.coeffs)


def test_a_run_without_near_contact_never_separates():
    """Two vesicles sheared past each other at 3.5% of their radius (p = 6, sdc): no step touches,
    no separation, the same bits with -ves_contact on and off."""
    out = {}
    for on in ("on", "off"):
        run, rec = harness.simulate(harness.pair_scene(0.3, 0.64, p=P, T=0.3), **{"-ves_contact": on})
        out[on] = (run, rec)
    (a, ra), (b, rb) = out["on"], out["off"]
    assert a.opts["ts_type"] == "sdc" and a.contacts.count == 0 and b.contacts is None
    assert "collision" not in harness.rejections(ra)
    assert min(f["min_gap"] for f in ra.frames) < 0.05                # a close pass
    assert ra.steps == rb.steps and np.array_equal(a.stepper.coeffs, b.stepper.coeffs)


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["euler", "sdc"])
def test_pair_pushed_into_contact_reaches_its_horizon(scheme):
    """Oblate pair (v = 0.9) at (-1.3, 0, 0.3), (1.3, 0, -0.3) in shear, p = 6, no repulsion,
    default options, T = 6: the pair comes into contact near t = 4.5-5 (without the separation:
    exit 3 after collision rejections down to dt_min, docs/explanation/contacts.md).  With it the
    run reaches T = 6: steps that start in contact are separated, none ends the run, no frame has
    a grid point on or behind the other surface."""
    run, rec, failure = _pair_run(0.3, 6.0, 0.5, scheme)
    gaps = [f["min_gap"] for f in rec.frames]
    print(f"\n[contacts] pushed pair, {scheme}: t = {run.t:.4g}, {run.counts}, rejections {harness.rejections(rec)}, "
          f"separated {run.contacts.count}, min frame gap {min(gaps):.3g}, failure {failure}")
    assert failure is None and run.t == pytest.approx(6.0)
    assert run.contacts.count >= 1                                   # the pair was in contact
    assert min(gaps) > 0 and max(f["contacts"] for f in rec.frames) == 0
    assert collision.contacts(Surface(run.stepper.coeffs, P), run.q_near) == 0


class _Checkpoints:
    """A monitor keeping (checkpoint after the step, in contact, smallest gap / h) of every
    accepted step (vesflow.stepping.Monitor's hooks)."""

    def __init__(self):
        self.kept = []

    def attempt(self, run, row):
        pass

    def output(self, run):
        pass

    def end(self, run):
        pass

    def stepped(self, run, row):
        if row[2]:
            h = contact.grid_spacing(Surface(run.state.coeffs, P))
            g = contact.min_gap(run.state.coeffs, P, run.q_near, run.period)
            self.kept.append((copy.deepcopy(run.checkpoint()), run.contacts.watch, g / h))


def test_a_restart_in_contact_continues_as_the_uninterrupted_run(tmp_path):
    """The pushed pair (dz = 0.3, euler, E/T = 2e-2, T = 5.5: in contact from t ~ 5) checkpointed
    after every accepted step; restarts through a run file's /checkpoint from (a) a state in the
    contact zone that was never separated (the rule of a fresh start, gap < ZONE h, would set the
    in-contact flag and separate the next close state) and (b) a state in contact after a
    separation: each reaches the uninterrupted run's final coefficients to 1e-12 and its count of
    separations (bit-identical, measured).  Measured without the contact state in the checkpoint:
    (a) ends 7.8e-4 away with 10 separations instead of 8, (b) counts 4 of the 8."""
    from vesflow import options as O, scene as S
    from vesflow.io import OutputWriter, read_checkpoint
    from vesflow.simulation import Run
    text = harness.pair_scene(1.3, 0.3, P, 5.5, every=0.5, dt=0.05)
    given = {"-ts_type": "euler", "-ves_adapt_tol": 0.02}
    sc = S.parse_scene(text)
    opts = O.read_options(O.dict_getter(given), sc)
    mon = _Checkpoints()
    run = Run(sc, opts, writer=harness.Recorder(opts["q_near"]))
    run.monitors.append(mon)
    run.run()
    assert run.t == pytest.approx(5.5) and run.contacts.count >= 2
    kept = mon.kept
    # (a): in the zone, never separated, and the next accepted state closer than TARGET h / 2
    # without being separated (with the flag set, Contacts.keep_apart would have moved it)
    zone = [a for a, b in zip(kept, kept[1:]) if not a[1] and a[2] < contact.ZONE and not b[1]
            and b[2] < 0.5 * contact.TARGET]
    watched = [k for k in kept if k[1] and k[2] < contact.ZONE]            # (b): in contact
    assert zone and watched
    for ck, watch, _ in (zone[0], watched[len(watched) // 2]):
        path = tmp_path / f"restart_{int(watch)}.h5"
        with OutputWriter(path, scene_text=text, options_text="", version="test", p=P, n_vesicles=2,
                          periodic_length=None) as w:
            w.write_checkpoint(ck, force=True)
        back = read_checkpoint(path)
        again = Run(sc, opts, writer=harness.Recorder(opts["q_near"]), checkpoint=back)
        assert again.contacts.watch == watch and again.contacts.count == len(ck["contact"]["log"])
        again.run()
        assert again.t == pytest.approx(5.5)
        assert np.abs(again.stepper.coeffs - run.stepper.coeffs).max() < 1e-12
        assert again.contacts.count == run.contacts.count
