"""Spectral deferred correction (SDC) on the semi-implicit step (Quaife & Biros, JCP 2016; issue 18).

X' = F(X), with F(X) the velocity of configuration X (Stepper.velocity: the step system with
dt = 0, every force explicit, coupling, background flow, gravity and repulsion included).
On the nodes t_0 = t_n < t_1 < ... < t_M = t_n + dt (-ts_sdc_quadrature: the start and Radau IIA nodes, the
run default, or Gauss-Lobatto; substeps h_m):

  provisional   X_{m+1} = X_m + h_m u,  u = V_{X_m}[f_b(X_m) + h_m B_{X_m}[u]]    (the first-order step)
  sweep k -> k+1, with the residual r_m = X_0 + int_{t_0}^{t_m} F(X^k) - X^k_m (spectral quadrature)
  and the error e_m = X^{k+1}_m - X^k_m:

      e_{m+1} = a + h_m w,   a = e_m + r_{m+1} - r_m = X^{k+1}_m - X^k_{m+1} + int_{t_m}^{t_{m+1}} F(X^k)
      w = V_Y[B_Y[a + h_m w]]                                  (Stepper.solve(h_m, Y, displacement=a))

that is, the error equation e' = F(X^k + e) - F(X^k) + r' by the same semi-implicit step: the
stiff part of F(X^k + e) - F(X^k), the velocity of the linearized bending force of e (3.12)
with its tension (inextensibility), implicit, on the geometry Y = X^{k+1}_m frozen at the start of
the substep; the rest of the linearization is dropped (O(h e), which keeps the gain of one order
per sweep).  In the linear model F = J X, B = J this is implicit-Euler SDC.  Each sweep gains one
order up to the quadrature's 2M: K sweeps give order min(K + 1, 2M).  The difference of the
last two sweeps at t_M is the error estimate of the adaptive step (or error_estimate, from the
sweeps' contraction).
"""
from __future__ import annotations

import numpy as np

from .. import sph
from ..errors import ConvergenceError
from ..stepper import Solution
from ..surface import Surface


def lobatto_nodes(n):
    """The n >= 2 Gauss-Lobatto nodes on [0, 1]: the ends and the roots of P'_{n-1}."""
    if n < 2:
        raise ValueError(f"Gauss-Lobatto needs at least 2 nodes, got {n}")
    inner = np.polynomial.legendre.Legendre.basis(n - 1).deriv().roots() if n > 2 else np.empty(0)
    return np.concatenate([[0.0], np.sort(0.5 * (inner.real + 1.0)), [1.0]])


def radau_nodes(n):
    """0 and the n - 1 >= 1 right Radau (Radau IIA) nodes on (0, 1]: the roots of
    P_{n-1}(2t - 1) - P_{n-2}(2t - 1) (1/3 and 1 for n = 3).  0 is the step's start, not a
    quadrature node: the collocation on the Radau nodes is L-stable (its stability function
    vanishes at infinity), Lobatto's is not (it tends to -1)."""
    if n < 2:
        raise ValueError(f"Radau needs at least 2 nodes (the start and 1), got {n}")
    L = np.polynomial.legendre.Legendre
    r = (L.basis(n - 1) - L.basis(n - 2)).roots() if n > 2 else np.array([1.0])
    return np.concatenate([[0.0], np.sort(0.5 * (np.real(r) + 1.0))])


def integration_matrix(tau, quad=None):
    """S[m, j] = int_{tau_m}^{tau_{m+1}} l_j(t) dt, l_j the Lagrange polynomials of the
    quadrature nodes quad (default: all of tau)."""
    quad = tau if quad is None else quad
    n = len(quad)
    S = np.empty((len(tau) - 1, n))
    for j in range(n):
        y = np.zeros(n)
        y[j] = 1.0
        lj = np.polynomial.Polynomial.fit(quad, y, n - 1, domain=[0, 1], window=[0, 1]).integ()
        S[:, j] = np.diff(lj(tau))
    return S


QUADRATURES = ("lobatto", "radau")


def collocation_order(nodes, quadrature):
    """Order of the collocation solution the sweeps converge to: 2 (nodes - 1) for Gauss-Lobatto,
    2 (nodes - 1) - 1 for Radau IIA (nodes counts the step's start)."""
    return 2 * (nodes - 1) - (quadrature == "radau")


RHO_MAX = 0.9     # sweeps contracting slower than this: the step is treated as not converging


def error_estimate(differences):
    """Local error of the kept K-sweep state from d_k = max |X^k_M - X^{k-1}_M| (k = 1 .. K,
    X^0 the provisional solution).  The sweeps contract the error by rho = d_K / d_{K-1} per
    sweep (rho ~ L dt for the explicitly lagged part of the correction equation, L its Lipschitz
    constant), so X^K is off by about d_K rho / (1 - rho): an estimate of the kept state, not
    of the sweep before it, that grows without bound as the sweeps stop converging (rho -> 1,
    large steps).  d_K alone (K = 1, or d_{K-1} = 0) is the estimate of the state before the
    last sweep.  rho is clipped to RHO_MAX."""
    if len(differences) < 2 or differences[-2] <= 0:
        return float(differences[-1]) if differences else 0.0
    rho = min(differences[-1] / differences[-2], RHO_MAX)
    return float(differences[-1] * rho / (1.0 - rho))


class SDC:
    """SDC steps of a Stepper: nodes substep ends (with the start; Gauss-Lobatto or Radau IIA),
    sweeps correction sweeps."""

    def __init__(self, stepper, nodes=3, sweeps=2, quadrature="lobatto"):
        if stepper.coupling != "implicit":
            raise ValueError("-ts_type sdc needs -ves_coupling implicit (the quadrature integrates the "
                             "velocity field; lagged coupling terms are not it)")
        self.stepper = stepper
        if quadrature not in QUADRATURES:
            raise ValueError(f"quadrature = {quadrature!r}: must be one of {', '.join(QUADRATURES)}")
        self.tau = lobatto_nodes(nodes) if quadrature == "lobatto" else radau_nodes(nodes)
        self.first = 0 if quadrature == "lobatto" else 1           # first quadrature node
        self.S = integration_matrix(self.tau, self.tau[self.first:])
        self.sweeps = int(sweeps)
        # X_0's layer potentials are reused by every sweep (Stepper.lp_pinned, set per step); the
        # other nodes' solves at one geometry follow each other (the velocity, then the step)
        self.iterations = 0
        self.error = None                 # d_K of the last step: the error of K - 1 sweeps (-ves_adapt sweeps)
        self.contraction_error = None     # error_estimate of the last step (-ves_adapt contraction)
        self.differences = []             # max |X^k_M - X^{k-1}_M| of the last step, k = 1 .. K

    def _solve(self, dt, X, displacement=None):
        st = self.stepper
        sol = st.solve(dt, X, displacement)
        if not np.all(np.isfinite(sol.u)):
            raise ConvergenceError("the solve returned NaN or Inf", reason="nan", iterations=self.iterations)
        self.iterations += sol.its
        if displacement is None:
            st.last = sol                 # initial guess of the next velocity solve
        return sol

    def step(self, dt):
        """One step of dt from the stepper's state.  Returns (Solution, error estimate): the
        Solution is the velocity and tension at the end node of the last sweep but one (the
        final state's to the error estimate); the estimate is d_K = max |X^K_M - X^{K-1}_M| on
        the grid (self.error; the contraction estimate of the kept state: self.contraction_error)."""
        st = self.stepper
        p, M = st.p, len(self.tau) - 1
        h = dt * np.diff(self.tau)
        self.iterations = 0
        surf = [st.surface]
        st.lp_pinned = surf[0] if st.pin_start else None
        F = [self._solve(0.0, surf[0]) if self.first == 0 else None]
        for m in range(M):                                  # provisional: first-order steps
            u = self._solve(h[m], surf[m]).u
            surf.append(Surface(surf[m].coeffs + h[m] * u, p))
            F.append(self._solve(0.0, surf[m + 1]))
        X = [s.coeffs for s in surf]
        ends, F_end = [X[M]], F[M]
        for k in range(self.sweeps):
            last_sweep = k == self.sweeps - 1
            Fu = np.stack([f.u for f in F[self.first:]])
            Xn, Fn, sn = [X[0]], [F[0]], [surf[0]]
            for m in range(M):
                if m > 0 and not last_sweep:
                    Fn.append(self._solve(0.0, sn[m]))
                quad = dt * np.tensordot(self.S[m], Fu, axes=1)
                a = Xn[m] - X[m + 1] + quad
                w = self._solve(h[m], sn[m], displacement=a).u
                Xn.append(X[m + 1] + a + h[m] * w)
                sn.append(Surface(Xn[m + 1], p))
            if not last_sweep:
                Fn.append(self._solve(0.0, sn[M]))
            F_end, X, F, surf = F[M], Xn, Fn, sn
            ends.append(X[M])
        T = sph.transform(p)
        self.differences = [float(np.abs(T.synth(b - a)).max()) for a, b in zip(ends[:-1], ends[1:])]
        err = self.error = self.differences[-1]
        self.contraction_error = error_estimate(self.differences)
        st.coeffs = X[M].copy()
        st.time += dt
        return Solution(F_end.u, F_end.sigma, self.iterations, F_end.reason, F_end.wall), err
