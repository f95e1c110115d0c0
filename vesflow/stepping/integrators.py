"""Integrators: step(state, dt) -> (candidate State, error estimate, GMRES iterations).

A candidate is the raw result of the step (before the post-step); a failed solve raises
ConvergenceError.  Euler and SDC advance the Stepper; Doubling and Invariants wrap another
integrator and replace its error estimate (paper 3.7).  `order` is k of the step update
dt (beta tol dt / err)^(1/k) (Adaptor.next_dt).
"""
from __future__ import annotations

import numpy as np

from .. import sph
from ..correction import correct_area_volume, restore_spheres
from ..surface import Surface
from .sdc import SDC, collocation_order

NEAR_SPHERE = 2e-3  # reduced volume above 1 - NEAR_SPHERE: the doubling error's normal part only


class Euler:
    """The first-order semi-implicit step (vesflow.stepper); no error estimate of its own."""

    order = 1

    def __init__(self, stepper):
        self.stepper = stepper

    def step(self, state, dt):
        state.load(self.stepper)
        sol = self.stepper.step(dt)
        return state.advanced(self.stepper, sol), 0.0, sol.its


class SDCIntegrator:
    """Spectral deferred correction (vesflow.stepping.sdc); estimate "sweeps" (d_K, the error
    of K - 1 sweeps), "contraction" (of the kept K-sweep state) or None (0)."""

    def __init__(self, stepper, nodes, sweeps, quadrature, estimate=None):
        self.sdc = SDC(stepper, nodes, sweeps, quadrature)
        self.stepper, self.estimate = stepper, estimate
        top = collocation_order(nodes, quadrature)
        # sweeps: d_K, the local error of K - 1 sweeps, dt^(K + 1); contraction: the estimate of
        # the kept K-sweep state (sdc.error_estimate), dt^(K + 2) for K >= 2 (one sweep: d_1)
        self.order = {"doubling": min(sweeps + 1, top), "sweeps": min(sweeps, top),
                      "contraction": min(sweeps + 1, top) if sweeps >= 2 else 1}.get(estimate, 1)

    def step(self, state, dt):
        state.load(self.stepper)
        sol, _ = self.sdc.step(dt)
        err = {"sweeps": self.sdc.error, "contraction": self.sdc.contraction_error}.get(self.estimate, 0.0)
        return state.advanced(self.stepper, sol), err, sol.its


class Doubling:
    """Step doubling: one step of dt and two of dt/2 (the candidate), e = max |X_2 - X_1| on
    the grid (doubling_error).  Between the half steps a sphere is put back to the standard
    sphere when the post-step corrects area and volume."""

    def __init__(self, base, geometry):
        self.base, self.geometry = base, geometry
        self.order = base.order
        self.stepper = base.stepper

    def step(self, state, dt):
        one, _, its0 = self.base.step(state, dt)
        half, _, its1 = self.base.step(state, 0.5 * dt)
        g = self.geometry
        if g.opts["correct"] == "area_volume":
            half.coeffs = restore_spheres(half.coeffs, g.p, g.area0, g.volume0)[0]
        two, _, its2 = self.base.step(half, 0.5 * dt)
        return two, self.doubling_error(one.coeffs, two.coeffs), its0 + its1 + its2

    def doubling_error(self, one, two):
        """max |n . (X(two steps of dt/2) - X(one step of dt))| on the grid for (near-)spheres,
        reduced volume above 1 - NEAR_SPHERE, both candidates first moved onto the area/volume
        constraint set; max |X_2 - X_1| for every other vesicle (the estimate of paper 3.7).

        A sphere of fixed area and volume cannot deform, yet the linearized inextensibility
        lets the step deform it at O(dt) (docs/explanation/dynamics.md): one step deforms by dt u, two half
        steps by less, and the raw difference is O(dt), driving dt to dt_min.  After the
        correction both candidates differ by the O(dt^2) truncation error in their normal part
        (measured, p = 12, rate 1: err / dt = 0.038 dt normal; the tangential part is 0.27 dt
        whatever dt).  Applied to all shapes, the corrected normal part let the accuracy-cost
        study's steps grow (p = 12, E = 0.07: 219 solves instead of 306) and its error stall
        near 4e-3 whatever E (E^0.37).  Each rank takes its vesicles, the largest over the ranks."""
        g, idx = self.geometry, self.geometry.part.idx
        return g.part.max(self._vesicle_error(one[idx], two[idx], _rows(g.area0, idx), _rows(g.volume0, idx)))

    def _vesicle_error(self, one, two, area0, volume0):
        g = self.geometry
        p = g.p
        T = sph.transform(p)
        raw = np.linalg.norm(np.moveaxis(T.synth(two - one), -2, -1), axis=-1).max(axis=1)
        near_sphere = Surface(one, p).reduced_volume() > 1.0 - NEAR_SPHERE
        if not near_sphere.any():
            return float(raw.max())
        o = g.opts
        if o["correct"] == "area_volume":
            with g.timers.stage("other"):
                one = correct_area_volume(one, p, area0, volume0, tol=o["correct_tol"], max_its=o["correct_max_its"])[0]
                two = correct_area_volume(two, p, area0, volume0, tol=o["correct_tol"], max_its=o["correct_max_its"])[0]
        d = np.moveaxis(T.synth(two - one), -2, -1)                  # (N, M, 3) on the p-grid
        normal = Surface(one, p).geometry(p).normal
        locked = np.abs(np.einsum("vmk,vmk->vm", d, normal)).max(axis=1)
        return float(np.where(near_sphere, locked, raw).max())


class Invariants:
    """The base step with e = the largest relative change of a vesicle's area or volume."""

    def __init__(self, base, geometry):
        self.base, self.geometry = base, geometry
        self.order, self.stepper = base.order, base.stepper

    def step(self, state, dt):
        cand, _, its = self.base.step(state, dt)
        S, g = self.stepper.surface, self.geometry
        err = float(max(np.abs(S.area() / g.area0 - 1).max(), np.abs(S.volume() / g.volume0 - 1).max()))
        return cand, err, its


def make_integrator(opts, stepper, geometry):
    """The integrator of -ts_type (euler, sdc) with the error estimate of -ves_adapt."""
    adapt = opts["adapt"]
    if opts["ts_type"] == "sdc":
        base = SDCIntegrator(stepper, opts["ts_sdc_nodes"], opts["ts_sdc_sweeps"], opts["ts_sdc_quadrature"], adapt)
    else:
        base = Euler(stepper)
    wrapper = {"doubling": Doubling, "invariants": Invariants}.get(adapt)
    return base if wrapper is None else wrapper(base, geometry)


def _rows(a, idx):
    """a[idx] for a per-vesicle array, a itself for a scalar."""
    a = np.asarray(a)
    return a[idx] if a.ndim else a
