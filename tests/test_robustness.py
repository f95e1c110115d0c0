"""Long-time robustness (acceptance of the issue): area/volume correction, reparameterization,
collisions with and without repulsion, adaptive time stepping.

Every test prints its figures ("[robustness] ..." lines: `pytest -rP` or `-s` shows them);
docs/robustness.md has the measured tables and the commands.  Fast cases run in `make test`,
the long ones (`slow`) in `make test-all`.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vesflow import collision, options as O, scene as S, shapes, sph, study
from vesflow.errors import NumericalFailure
from vesflow.layerpot.near import Projection
from vesflow.reparam import reparameterize, spectral_energy
from vesflow.simulation import Run
from vesflow.surface import Surface



# ------------------------------------------------------------------ helpers
class Recorder(study.Recorder):
    """study.Recorder plus the mesh-quality energy E (vesflow.reparam.spectral_energy) and the
    number of grid points on or behind another surface, at every frame."""

    def write_frame(self, *, coefficients, **kw):
        super().write_frame(coefficients=coefficients, **kw)
        p = int(round(np.sqrt(coefficients.shape[-1] + 1))) - 1
        self.frames[-1]["mesh_energy"] = spectral_energy(coefficients, p).tolist()
        surf = Surface(coefficients, p)
        self.frames[-1]["contacts"] = collision.contacts(surf, self.q_gap) if surf.n_vesicles > 1 else 0


def simulate(text, **options):
    sc = S.parse_scene(text)
    opts = O.read_options(O.dict_getter(options), sc)
    rec = Recorder(opts["q_near"])
    run = Run(sc, opts, writer=rec)
    run.run()
    return run, rec


def report(name, **figures):
    print(f"\n[robustness] {name}: " + ", ".join(
        f"{k} = {v:.3g}" if isinstance(v, float) else f"{k} = {v}" for k, v in figures.items()))


def rejections(rec):
    out = {}
    for r in rec.steps:
        if not r[2]:
            out[r[5]] = out.get(r[5], 0) + 1
    return out


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
        run, rec = simulate(text, **{"-ves_adapt": "none", "-ves_correct": correct})
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
        run, rec = simulate(text, **{"-ves_adapt": "none", "-ves_reparam": rep})
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
    """One call of reparameterize (the run's defaults: <= 20 pseudo-steps of <= 1e-3) on a badly
    parameterized exact prolate.  Figures, all max over a 4p-grid (Hausdorff: both ways):
    trunc  = distance of the degree-p interpolant to the exact prolate (its truncation error),
    move   = largest point displacement, change = Hausdorff distance before/after,
    dA, dV = relative area and volume change.
    Measured (amplitude 0.1): trunc 2.8e-4, 7.0e-6, 1.8e-7; change 3.4e-3, 4.6e-4, 6.9e-5 for
    p = 8, 12, 16; move 0.016, 0.016, 0.008.  The change converges with p (x7 per 4 degrees) but
    it is NOT at the shape's truncation error (12x, 66x, 390x above it): it is the normal leak
    of the tangential field truncated to degree p, 21%, 3%, 0.8% of the displacement."""
    q = 4 * p
    exact, cb = distorted_prolate(p, 0.1)
    trunc = dist_to(cb, p, exact, p, q)
    cn, its, e0, e1 = reparameterize(cb, p)
    move = float(np.abs(sph.transform(p, q).synth(cn - cb)).max())
    change = hausdorff(cn, cb, p, q)
    Sb, Sn = Surface(cb[None], p), Surface(cn[None], p)
    dA = float(abs(Sn.area(q) / Sb.area(q) - 1)[0])
    dV = float(abs(Sn.volume(q) / Sb.volume(q) - 1)[0])
    report(f"reparameterization of a distorted prolate, p = {p}", its=its, E_before=e0, E_after=e1,
           trunc=trunc, move=move, change=change, change_over_move=change / move,
           change_over_trunc=change / trunc, dA=dA, dV=dV)
    REPARAM_SHAPE_CHANGE[p] = change
    assert e1 < e0
    assert change < {8: 0.25, 12: 0.05, 16: 0.015}[p] * move      # measured 0.21, 0.028, 0.008
    assert change < {8: 5e-3, 12: 7e-4, 16: 1e-4}[p]              # measured 3.4e-3, 4.6e-4, 6.9e-5
    assert dV < {8: 1e-4, 12: 1e-5, 16: 1e-6}[p]
    if p == 16 and 8 in REPARAM_SHAPE_CHANGE:                      # the change converges with p
        assert REPARAM_SHAPE_CHANGE[16] < REPARAM_SHAPE_CHANGE[8] / 20
