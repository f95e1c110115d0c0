"""Long-time robustness (acceptance of the issue): area/volume correction, reparameterization,
collisions with and without repulsion, adaptive time stepping.

Every test prints its figures ("[robustness] ..." lines: `pytest -rP` or `-s` shows them);
docs/explanation/robustness.md has the measured tables and the commands.  Fast cases run in `make test`,
the long ones (`slow`) in `make test-all`.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vesflow import collision, shapes, sph
from vesflow.layerpot.near import Projection
from vesflow.options import REGISTRY
from vesflow.reparam import ATTENUATIONS, project_onto, reparameterize, spectral_energy
from vesflow.surface import Surface

from tests import harness
from tests.harness import robustness_pair as _pair, run_pair as _run_pair


# ------------------------------------------------------------------ helpers
Recorder, simulate, rejections = harness.Recorder, harness.simulate, harness.rejections
# The tests whose figures (drifts, mesh energies, step counts, gaps) were computed with the
# first-order step pass it explicitly; the contact tests of section 3 run with the default (sdc).
EULER = {"-ts_type": "euler"}


def report(name, **figures):
    print(f"\n[robustness] {name}: " + ", ".join(
        f"{k} = {v:.3g}" if isinstance(v, float) else f"{k} = {v}" for k, v in figures.items()))


def drift(run, rec):
    """Largest relative area and volume error over the frames (max over vesicles)."""
    area = np.array([f["area"] for f in rec.frames]) / np.asarray(run.area0)
    vol = np.array([f["volume"] for f in rec.frames]) / np.asarray(run.volume0)
    return float(np.abs(area - 1).max()), float(np.abs(vol - 1).max())


def dist_to(c_from, p_from, c_to, p_to, q):
    """max over the q-grid points of surface c_from (3, C) of the distance to surface c_to:
    nearest q-grid point of c_to (cKDTree) as the start of a Newton projection on c_to."""
    x = Surface(np.asarray(c_from)[None], p_from).points(q)[0]
    y = Surface(np.asarray(c_to)[None], p_to).points(q)[0]
    Tq = sph.transform(p_to, q)
    _, j = cKDTree(y).query(x)
    it, jp = np.divmod(j, Tq.nlon)
    pr = Projection(np.asarray(c_to)[None], p_to, x, np.zeros(len(x), dtype=np.int64), Tq.theta[it], Tq.phi[jp])
    assert pr.converged.all()
    return float(np.abs(pr.signed_distance).max())


def hausdorff(ca, cb, p, q):
    return max(dist_to(ca, p, cb, p, q), dist_to(cb, p, ca, p, q))


ONE = """
title = "one"
{flow}
[discretization]
p = {p}
[time]
horizon = {T}
dt = {dt}
[output]
every = {every}
[[vesicle]]
shape = "prolate"
reduced_volume = 0.8
center = [0.0, 0.0, {z}]
rotation = [0.0, {angle}, 0.0]
bending_modulus = 0.1
"""
SHEAR = '[flow]\ntype = "shear"\nrate = 1.0'


def one(flow, p, T, dt, every=None, z=0.0, angle=30.0):
    return ONE.format(flow=flow, p=p, T=T, dt=dt, every=every or T / 10, z=z, angle=angle)


# ------------------------------------------------------------------ 1. area and volume
def _area_volume(case, n_steps):
    """A prolate (v = 0.8, tilted 30 degrees) relaxing in a quiescent fluid or in shear, p = 6,
    n_steps fixed steps of 1e-3, with and without the area/volume correction."""
    flow = SHEAR if case == "shear" else ""
    text = one(flow, 6, n_steps * 1e-3, 1e-3)
    out = {}
    for correct in ("area_volume", "none"):
        run, rec = simulate(text, **{"-ves_adapt": "none", "-ves_correct": correct}, **EULER)
        assert run.counts == {"accepted": n_steps, "rejected": 0}
        out[correct] = max(drift(run, rec))
    with_, without = out["area_volume"], out["none"]
    report(f"area/volume, {case}, {n_steps} steps, p = 6", drift_with=with_, drift_without=without,
           ratio=without / with_)
    return with_, without


@pytest.mark.parametrize("case", ["relax", "shear"])
def test_area_volume_kept_200_steps(case):
    with_, without = _area_volume(case, 200)
    assert with_ < 1e-8                       # measured 2.5e-13 (relax and shear)
    assert without > 100 * with_              # measured 1.4e-3 (relax), 1.6e-3 (shear)
    assert without > 1e-5                     # the drift is real, not rounding


@pytest.mark.slow
@pytest.mark.parametrize("case", ["relax", "shear"])
def test_area_volume_kept_1000_steps(case):
    with_, without = _area_volume(case, 1000)
    assert with_ < 1e-8
    assert without > 100 * with_
    assert without > 1e-4


# ------------------------------------------------------------------ 2. reparameterization
def _mesh_quality(T, dt):
    """E(t) / E(0) of a prolate in shear (p = 8, fixed dt) with and without reparameterization."""
    text = one(SHEAR, 8, T, dt)
    ratios = {}
    for rep in ("on", "off"):
        run, rec = simulate(text, **{"-ves_adapt": "none", "-ves_reparam": rep}, **EULER)
        E = np.array([f["mesh_energy"][0] for f in rec.frames])
        ratios[rep] = E / E[0]
        inv = drift(run, rec)
        report(f"mesh quality, shear, p = 8, T = {T:g}, reparam {rep}",
               E_over_E0=np.round(ratios[rep], 3).tolist(), area_volume_drift=max(inv))
    return ratios["on"], ratios["off"]


def test_mesh_quality_short_shear():
    on, off = _mesh_quality(2.0, 0.01)
    assert on.max() <= 1.0 + 1e-9 and on[-1] < 0.99    # measured: 1 -> 0.978, never above the start
    assert off[-1] > 1.1 and off[-1] > 1.1 * on[-1]    # measured: 1 -> 1.138, growing at every frame
    assert np.all(np.diff(off) > 0)


@pytest.mark.slow
def test_mesh_quality_long_shear():
    on, off = _mesh_quality(10.0, 0.02)
    assert on.max() <= 1.0 + 1e-9 and on[-1] < 0.99    # measured: 0.978 - 0.981 over t in [1, 10]
    assert off.max() > 1.5                             # measured: peak 1.77 at t = 6 (tank-treading
    assert off.max() > 1.5 * on.max()                  # period: back to 1.19 at t = 10)


def distorted_prolate(p, amplitude):
    """The exact prolate (v = 0.8, a degree-1 surface) parameterized badly: X(u) = M u' with
    u' = (u + a w(u)) / |u + a w(u)| a smooth map of the unit sphere, w = (sin 2y + z, z cos y + x,
    xy).  Every point is on the exact prolate; the degree-p interpolant is returned with the
    exact surface's coefficients."""
    exact = shapes.make_shape("prolate", p, reduced_volume=0.8)
    X = Surface(exact[None], p).points()[0]
    T = sph.transform(p)
    th, ph = np.meshgrid(T.theta, T.phi, indexing="ij")
    u = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    M = np.linalg.lstsq(u, X, rcond=None)[0]
    assert np.abs(u @ M - X).max() < 1e-12
    x, y, z = u.T
    u2 = u + amplitude * np.stack([np.sin(2 * x) + z, np.cos(y) * z + x, x * y], -1)
    u2 /= np.linalg.norm(u2, axis=1, keepdims=True)
    return exact, Surface.from_points((u2 @ M)[None], p).coeffs[0]


REPARAM_SHAPE_CHANGE = {}


@pytest.mark.parametrize("p", [8, 12, 16])
def test_reparameterization_changes_shape_at_discretization_level(p):
    """One call of reparameterize (the run's defaults: <= 20 pseudo-steps of <= 1e-3, then one
    projection of the grid points onto the original surface) on a badly parameterized exact
    prolate, and the same with the projection iterated (`project_onto(max_its=10, omega=1.5)`).
    Figures, all max over a 4p-grid (Hausdorff: both ways): trunc = distance of the degree-p
    interpolant to the exact prolate (its truncation error), move = largest point displacement,
    change = Hausdorff distance before/after, dA, dV = relative area and volume change.
    Measured, p = 8 / 12 / 16: trunc 2.8e-4 / 7.0e-6 / 1.8e-7; change 1.8e-3 / 2.1e-4 / 3.8e-5
    (one projection), 2.1e-4 / 4.4e-6 / 2.4e-6 (iterated: below trunc at p = 8 and 12).  The run
    keeps one projection: iterated, it undoes part of every descent, the descent never reaches
    its stopping tolerance and moves the grid by ~7e-3 at every step whatever dt, and the
    adaptive error stops converging (docs/explanation/robustness.md section 2).  What a run must meet is
    test_reparameterization_changes_run_at_discretization_error."""
    q = 4 * p
    exact, cb = distorted_prolate(p, 0.1)
    trunc = dist_to(cb, p, exact, p, q)
    cn, its, e0, e1 = reparameterize(cb, p)
    move = float(np.abs(sph.transform(p, q).synth(cn - cb)).max())
    change = hausdorff(cn, cb, p, q)
    raw, _, _, _ = reparameterize(cb, p, project=False)
    ci = project_onto(raw[None], cb[None], p, omega=1.5, max_its=10)[0]
    change_iter = hausdorff(ci, cb, p, q)
    Sb, Sn = Surface(cb[None], p), Surface(cn[None], p)
    dA = float(abs(Sn.area(q) / Sb.area(q) - 1)[0])
    dV = float(abs(Sn.volume(q) / Sb.volume(q) - 1)[0])
    report(f"reparameterization of a distorted prolate, p = {p}", its=its, E_before=e0, E_after=e1,
           trunc=trunc, move=move, change=change, change_iterated=change_iter,
           change_over_trunc=change / trunc, dA=dA, dV=dV)
    REPARAM_SHAPE_CHANGE[p] = change
    assert e1 < e0 - 0.4                                           # measured 20.6 -> 19.8 / 19.7 / 20.1
    assert change < {8: 2.5e-3, 12: 3e-4, 16: 5e-5}[p]            # measured 1.8e-3, 2.1e-4, 3.8e-5
    assert change < 0.15 * move
    if p < 16:
        assert change_iter < trunc                                 # measured 0.76, 0.63 of trunc
    assert change_iter < change / 8                                # measured / 8.3, / 48, / 16
    assert dV < {8: 1e-4, 12: 1e-5, 16: 1e-6}[p]
    if p == 16 and 8 in REPARAM_SHAPE_CHANGE:                      # the change converges with p
        assert REPARAM_SHAPE_CHANGE[16] < REPARAM_SHAPE_CHANGE[8] / 20


def test_attenuation_schemes_as_in_the_paper_fig4():
    """-ves_reparam_attenuation, paper Fig. 4 on the distorted prolate, p = 12, 200 pseudo-steps.
    Each scheme lowers its own E; only a_n = n^2 both evens the grid and keeps the shape.
    Measured (own E before -> after; the n^2 energy after; Hausdorff change):
    n2 20.6 -> 18.0, change 2.0e-4; n 17.4 -> 15.8 but the n^2 energy rises 20.6 -> 26.0 and the
    shape changes by 1.4e-2 (the spectrum no longer decays: the surface is not resolved);
    n16 and step (H(n - 2p/3)) touch only the top degrees: the n^2 energy stays 20.6 (the
    clustering is not fixed), change 1e-6 / 4e-6."""
    p, q = 12, 48
    _, cb = distorted_prolate(p, 0.1)
    e2 = lambda c: float(spectral_energy(c[None], p)[0])
    option, = (o for o in REGISTRY if o.name == "-ves_reparam_attenuation")
    assert option.choices == ATTENUATIONS                # the option offers exactly the schemes reparam has
    out = {}
    for a in ATTENUATIONS:
        cn, its, e0, e1 = reparameterize(cb, p, attenuation=a, max_its=200)
        out[a] = (e0, e1, e2(cn), hausdorff(cn, cb, p, q))
        report(f"attenuation {a}", its=its, E_own=(float(e0), float(e1)), E_n2_after=out[a][2], change=out[a][3])
        assert e1 < e0
    assert out["n2"][2] < e2(cb) - 2 and out["n2"][3] < 5e-4
    assert out["n"][2] > e2(cb) + 2 and out["n"][3] > 5e-3
    for a in ("n16", "step"):
        assert abs(out[a][2] / e2(cb) - 1) < 1e-3 and out[a][3] < 5e-5
    # the option reaches the run: 5 shear steps at p = 8, mesh energy with n2 vs step
    E = {}
    for a in ("n2", "step"):
        run, rec = simulate(one(SHEAR, 8, 0.05, 0.01), **{"-ves_adapt": "none", "-ves_reparam_attenuation": a})
        E[a] = rec.frames[-1]["mesh_energy"][0]
    assert E["n2"] < E["step"] - 0.1                 # measured 17.52 vs 17.85 (from 17.83)


@pytest.mark.slow
def test_reparameterization_changes_run_at_discretization_error():
    """What the reparameterization does to a run, against what p does: prolate v = 0.8 in shear,
    fixed dt = 0.02, T = 2, with and without reparameterization at p = 8 and 12, reference p = 16
    without (same dt, so the time error is common).  Hausdorff distances of the final shapes
    (compared at degree 16).  Measured, p = 8 / 12: H(on, off) 6.0e-3 / 2.3e-4, the
    discretization error of the run H(off, ref) 5.2e-3 / 2.3e-4, and H(on, ref) 1.8e-3 / 9.7e-5
    (with the projection iterated at every step: 5.1e-3 / 2.3e-4 and 2.7e-3 / 5.8e-5).  The reparameterization moves the result by the
    discretization error and no more, and the reparameterized run is the closer to the reference."""
    T, dt, pref = 2.0, 0.02, 16
    final = {}
    for p, rep in ((8, "on"), (8, "off"), (12, "on"), (12, "off"), (pref, "off")):
        run, _ = simulate(one(SHEAR, p, T, dt), **{"-ves_adapt": "none", "-ves_reparam": rep}, **EULER)
        final[p, rep] = sph.resample(run.stepper.coeffs[0], p, pref)
    H = lambda a, b: hausdorff(final[a], final[b], pref, 4 * pref)
    figs = {p: (H((p, "on"), (p, "off")), H((p, "off"), (pref, "off")), H((p, "on"), (pref, "off"))) for p in (8, 12)}
    for p, (onoff, err, on_ref) in figs.items():
        report(f"reparameterization in a shear run, p = {p}", H_on_off=onoff, H_off_ref=err, H_on_ref=on_ref)
        assert onoff < 1.5 * err                    # measured 1.15, 1.02
        assert on_ref < err                         # measured 0.34, 0.43
    assert figs[12][0] < figs[8][0] / 10            # converges with p (measured / 26)


# ------------------------------------------------------------------ 3. collisions


def _detector(dz, T):
    """The pair of the tests below to T: (run, recorder, failure, collision rejections (t, dt))."""
    run, rec, failure = _run_pair(harness.pair_scene(1.3, dz, 6, T, every=T, dt=0.05),
                                  **{"-ves_adapt_tol": 0.15})
    gaps = [f["min_gap"] for f in rec.frames]
    collided = [(r[0], r[1]) for r in rec.steps if not r[2] and r[5] == "collision"]
    report(f"pair without repulsion, p = 6, dz = {dz}, E = 0.15, T = {T:g}", t_end=run.t, counts=run.counts,
           rejections=rejections(rec), collisions_t_dt=collided, min_gap=min(gaps),
           separated=run.contacts.count, failure=failure)
    assert failure is None and run.t == pytest.approx(T)
    assert len(collided) >= 1                                    # the detector acted ...
    assert max(f["contacts"] for f in rec.frames) == 0 and min(gaps) > 0   # ... and nothing intersects
    final = Surface(run.stepper.coeffs, 6)
    assert collision.contacts(final, run.q_near) == 0
    return run, collided


def test_collision_detector_rejects_overshooting_steps():
    """The case below (dz = 0.15, sdc, the default) to T = 4.5, before the pair comes into
    contact: the step of dt = 0.88 from t = 2.97 jumps across the gap and is rejected, dt is
    halved, and the run ends at T without intersection and without a separation (the contact
    step acts only from t ~ 5).  Measured: 9 accepted, 2 rejected (1 collision, 1 error
    estimate), 4.5 s CPU; the full horizon (the slow test below) takes 7-14x that with sdc."""
    run, collided = _detector(0.15, 4.5)
    assert collided[0][1] > 0.5                                   # an overshoot: a long step
    assert run.contacts.count == 0


@pytest.mark.slow
@pytest.mark.parametrize("dz", [0.15, 0.22])
def test_collision_detector_rejects_steps_and_run_ends_without_intersection(dz):
    """Acceptance (a): oblate pair, centres (-1.3, 0, dz), (1.3, 0, -dz), p = 6, no repulsion,
    default options but a loose tolerance -ves_adapt_tol 0.15: the error estimate allows steps of
    dt ~ 1.1, which near the closest approach jump across the gap.  The detector (paper 3.3)
    rejects those steps, dt is halved and the run ends at T = 6 with no grid point on or behind
    the other surface.  Measured (dz = 0.15 / 0.22): 2 / 1 collision rejections at dt = 1.13,
    min frame gap 4.0e-3 / 5.3e-3.  The window is wide: dz = 0.12 ... 0.25 all end at T = 6
    with 1-3 collision rejections (docs/explanation/robustness.md, section 3).
    Frames only at 0 and 6: since steps land on the output times (issue 15) a frame every 0.1
    caps the steps at 0.1 and the overshooting steps this test is about never happen.
    Measured with the landing steps and euler: the same rejections as before them (dz = 0.15:
    t = 2.70 and 3.26 at dt = 1.12; dz = 0.22: t = 2.73 at dt = 1.14), T = 6 reached, no contact.
    With sdc, the default: dz = 0.15 / 0.22 have 2 / 1 overshoot rejections (t = 2.97, 4.13 /
    4.41 at dt = 0.54-0.88), then the pair comes into contact and the steps that start in
    contact are separated (vesflow/contact.py; before, sdc stopped on collision rejections at
    dt ~ 1e-6, t = 5.88 / 4.98); T = 6 with 35 / 108 accepted and 18 / 49 rejected steps, 16 / 67
    separations, min frame gap 1.9e-3 / 1.9e-3.  Slow: 30 s / 64 s on the shared machine, most of
    it in contact after t ~ 5 (test_collision_detector_rejects_overshooting_steps is the default
    suite's part)."""
    run, _ = _detector(dz, 6.0)
    assert run.contacts.count >= 1                               # the pair came into contact


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")   # the NaN candidate after contact
def test_without_collision_detection_the_same_pair_intersects():
    """The control of the test above: dz = 0.15, -ves_adapt_tol 0.15, -ves_collision off.  The
    overshooting step is accepted and the vesicles interpenetrate (measured with euler: a frame
    with min gap -0.035 and 4 grid points inside the other vesicle; with sdc, the default: -8.0e-3,
    4 points), after which GMRES fails or the error estimate cannot be met (exit at t = 3.84 with
    euler, 5.90 with sdc, as in the paper: "the simulation may even break").  The contact step
    needs the detector (-ves_collision off switches both off)."""
    run, rec, failure = _run_pair(_pair(1.3, 0.15, 6, 6.0), **{"-ves_adapt_tol": 0.15, "-ves_collision": "off"})
    gaps = [f["min_gap"] for f in rec.frames]
    report("same pair, collision detection off", t_end=run.t, rejections=rejections(rec),
           min_gap=min(gaps), max_contacts=max(f["contacts"] for f in rec.frames), failure=failure)
    assert max(f["contacts"] for f in rec.frames) > 0 and min(gaps) < -1e-3


def test_close_pair_without_repulsion_ends_without_contact():
    """Oblate pair (v = 0.9), centres (-1.3, 0, 0.3), (1.3, 0, -0.3), p = 6, no repulsion,
    -ves_adapt_tol 0.05, reparameterization off.  Before the collision check moved after the
    post-step (and after the error test), this run had 26 collision rejections, 12 recovered,
    then contact at t = 5.45 and exit 3.  Measured now: it ends at T = 5.8 with min gap 0.0126,
    no contact, 4 error-estimate rejections.  (With the default options the same pair gets 13
    collision rejections, recovered, then contact at t = 5.0: docs/explanation/robustness.md.)
    Frames every 1: with the steps landing on output times every 0.1 or 0.5 (issue 15) the step
    sequence changes and this pair, at the resolution limit of p = 6, comes into contact near
    t = 5.1-5.4 (exit 3, the last good state saved); every 1 it ends at T = 5.8 without contact,
    min frame gap 0.023 (measured with the landing steps).  With sdc, the default (before the
    contact step it stopped on collision rejections at t = 5.06): T = 5.8, 44 accepted, 14
    rejected (11 error estimate, 3 GMRES), no collision rejection, min frame gap 5.5e-3."""
    run, rec, failure = _run_pair(harness.pair_scene(1.3, 0.3, 6, 5.8, every=1.0, dt=0.05),
                                  **{"-ves_reparam": "off", "-ves_adapt_tol": 0.05})
    gaps = [f["min_gap"] for f in rec.frames]
    report("pair without repulsion, p = 6, dz = 0.3", t_end=run.t, counts=run.counts,
           rejections=rejections(rec), min_gap=min(gaps),
           max_contacts=max(f["contacts"] for f in rec.frames), failure=failure)
    assert failure is None and run.t == pytest.approx(5.8)
    assert min(gaps) > 0 and max(f["contacts"] for f in rec.frames) == 0
    assert min(gaps) < 0.05                                     # a close approach (0.023 measured)


@pytest.mark.slow
def test_post_step_keeps_accepted_state_out_of_contact():
    """Default options (reparameterization on), p = 6, dz = 0.45, no repulsion.  Before the fix
    the post-step (reparameterize, then correct) ran after the collision check and near contact
    shrank the gap by ~8e-3 per step (9.6e-3 -> 7.7e-4 at t = 4.28; at t = 4.30 gap 1.7e-4 ->
    -4.7e-3, two grid points inside the other vesicle), then 10 collision rejections down to
    dt = 2e-6 and NumericalFailure.  Now the collision check sees the post-processed state, a
    step whose reparameterization alone makes contact is kept without it, and the
    reparameterized grid points are projected back onto the surface; a step whose reparameterized
    state touches is first retried with the projection iterated (Run._try).  Measured with the
    final code: the run ends at T = 6, min gap 7.7e-4, no contact, no collision rejection; 3
    steps kept out of contact by the iterated projection, 2 kept without reparameterization."""
    run, rec, failure = _run_pair(_pair(1.3, 0.45, 6, 6.0), **EULER)     # the figures above are euler's
    gaps = [f["min_gap"] for f in rec.frames]
    report("pair, default options, p = 6, dz = 0.45", t_end=run.t, rejections=rejections(rec),
           min_gap=min(gaps), max_contacts=max(f["contacts"] for f in rec.frames), failure=failure,
           reparam_iterated=run.reparam_iterated, reparam_skipped=run.reparam_skipped)
    assert failure is None and min(gaps) > 0 and max(f["contacts"] for f in rec.frames) == 0
    assert run.reparam_iterated >= 1                    # the fallback of Run._try is exercised
    assert "collision" not in rejections(rec)


# ------------------------------------------------------------------ 4. adaptive stepping
ADAPT_TOLS = (1.6e-2, 8e-3, 4e-3, 2e-3, 1e-3)


def _adapt(tols, ref_tol, reparam):
    """Prolate v = 0.8 tilted 70 degrees, centre (0, 0, 0.5), in shear, p = 6, T = 2, doubling
    with -ves_adapt_tol E; error = Hausdorff distance of the final surface to the reference's."""
    text = one(SHEAR, 6, 2.0, 0.05, every=2.0, z=0.5, angle=70.0)
    res = {}
    for tol in (ref_tol,) + tuple(tols):
        run, rec = simulate(text, **{"-ves_adapt": "doubling", "-ves_adapt_tol": tol, "-ves_reparam": reparam},
                            **EULER)         # the first-order rates are what is measured
        res[tol] = (run.counts["accepted"], run.stepper.coeffs[0].copy())
    cref = res[ref_tol][1]
    steps = np.array([res[t][0] for t in tols], dtype=float)
    err = np.array([hausdorff(res[t][1], cref, 6, 24) for t in tols])
    s_steps = np.polyfit(np.log(tols), np.log(steps), 1)[0]
    s_err = np.polyfit(np.log(tols), np.log(err), 1)[0]
    report(f"adaptive stepping, reparam {reparam}, reference E = {ref_tol:g} ({res[ref_tol][0]} steps)",
           E=list(tols), steps=steps.astype(int).tolist(), error=[float(f"{e:.3g}") for e in err],
           slope_steps=s_steps, slope_error=s_err)
    return steps, err, s_steps, s_err


def test_adaptive_rates_fast():
    """Three tolerances, reference 1e-3, reparameterization off (with it on, the error does not
    converge: see test_adaptive_rates)."""
    steps, err, s_steps, s_err = _adapt((1.6e-2, 8e-3, 4e-3), 1e-3, "off")
    assert -1.2 < s_steps < -0.8
    assert 0.7 < s_err < 1.4
    assert err.max() < 2e-2


@pytest.mark.slow
def test_adaptive_rates():
    """Measured (reparameterization off, reference E = 2.5e-4, 1011 steps): steps 16, 32, 63,
    127, 253 (slope -1.00), error 7.4e-3, 3.5e-3, 1.7e-3, 8.0e-4, 3.4e-4 (slope 1.10; the
    reference's own error, ~E_ref, pulls the smallest E down).  With reparameterization on
    (the default), after the post-step fix (collision check on the kept state, grid points
    projected back onto the surface): steps 16, 31, 61, 122, 243, error 1.4e-2, 2.6e-3, 1.3e-3,
    5.0e-4, 2.4e-4 (slope 1.41; the largest E is the outlier).  Before the fix the error stayed
    at ~5e-3 for every E (no convergence)."""
    steps, err, s_steps, s_err = _adapt(ADAPT_TOLS, 2.5e-4, "off")
    assert -1.2 < s_steps < -0.8
    assert 0.8 < s_err < 1.3
    steps_on, err_on, s_steps_on, s_err_on = _adapt(ADAPT_TOLS, 2.5e-4, "on")
    assert abs(np.log(steps_on / steps)).max() < 0.2            # the step count does not depend on it
    assert -1.2 < s_steps_on < -0.8 and 0.8 < s_err_on < 1.6     # and the error converges with E


def _repulsion_pair(p):
    """The pair of test_post_step_keeps_accepted_state_out_of_contact (dz = 0.45, which touches
    without repulsion at t = 4.30) with [repulsion] radius = 0.04, to just past the closest
    approach (t ~ 4.4)."""
    run, rec, failure = _run_pair(_pair(1.3, 0.45, p, 4.6, extra="[repulsion]\nradius = 0.04"),
                                  **EULER)                        # the figures below are euler's
    gaps = [f["min_gap"] for f in rec.frames]
    rej = rejections(rec)
    report(f"pair with repulsion R = 0.04, p = {p}, dz = 0.45", t_end=run.t, counts=run.counts,
           rejections=rej, min_gap=min(gaps), max_contacts=max(f["contacts"] for f in rec.frames),
           failure=failure)
    assert failure is None and run.t == pytest.approx(4.6)
    assert rej.get("collision", 0) == 0
    assert min(gaps) > 0 and max(f["contacts"] for f in rec.frames) == 0
    return min(gaps)


def test_repulsion_no_collision_rejections_p8():
    """Measured: 0 rejections (85 accepted steps), min gap 0.022 (0.0405 with the projection
    iterated at every step); ~60 s alone."""
    gap = _repulsion_pair(8)
    assert gap < 2 * 0.04                                        # a close approach, inside the repulsion range


@pytest.mark.slow
def test_repulsion_no_collision_rejections_p12():
    """Measured: 0 rejections (88 accepted steps), min gap 0.0601 (1.5 R: the better resolved
    pair keeps a wider gap than at p = 8), 137 s."""
    gap = _repulsion_pair(12)
    assert gap < 2 * 0.04                                        # a close approach, inside the repulsion range
