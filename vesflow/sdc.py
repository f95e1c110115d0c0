"""Spectral deferred correction (SDC) on the semi-implicit step (Quaife & Biros, JCP 2016; issue 18).

X' = F(X), with F(X) the velocity of configuration X (Stepper.velocity: the step system with
dt = 0, every force explicit, coupling, background flow, gravity and repulsion included).
On Gauss-Lobatto nodes t_0 = t_n < t_1 < ... < t_M = t_n + dt (substeps h_m):

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
last two sweeps at t_M is the error estimate of the adaptive step.
"""
from __future__ import annotations

import numpy as np

from . import sph
from .errors import ConvergenceError
from .stepper import Solution
from .surface import Surface


def lobatto_nodes(n):
    """The n >= 2 Gauss-Lobatto nodes on [0, 1]: the ends and the roots of P'_{n-1}."""
    if n < 2:
        raise ValueError(f"Gauss-Lobatto needs at least 2 nodes, got {n}")
    inner = np.polynomial.legendre.Legendre.basis(n - 1).deriv().roots() if n > 2 else np.empty(0)
    return np.concatenate([[0.0], np.sort(0.5 * (inner.real + 1.0)), [1.0]])


def integration_matrix(tau):
    """S[m, j] = int_{tau_m}^{tau_{m+1}} l_j(t) dt, l_j the Lagrange polynomials of the nodes tau."""
    n = len(tau)
    S = np.empty((n - 1, n))
    for j in range(n):
        y = np.zeros(n)
        y[j] = 1.0
        lj = np.polynomial.Polynomial.fit(tau, y, n - 1, domain=[0, 1], window=[0, 1]).integ()
        S[:, j] = np.diff(lj(tau))
    return S


class SDC:
    """SDC steps of a Stepper: nodes Gauss-Lobatto nodes, sweeps correction sweeps."""

    def __init__(self, stepper, nodes=3, sweeps=2):
        if stepper.coupling != "implicit":
            raise ValueError("-ts_type sdc needs -ves_coupling implicit (the quadrature integrates the "
                             "velocity field; lagged coupling terms are not it)")
        self.stepper = stepper
        self.tau = lobatto_nodes(nodes)
        self.S = integration_matrix(self.tau)
        self.sweeps = int(sweeps)
        stepper.lp_cache_size = max(stepper.lp_cache_size, nodes)   # X_0 reused by every sweep
        self.iterations = 0
        self.error = None                 # estimate of the last step

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
        final state's to the error estimate); the estimate is max |X^K_M - X^{K-1}_M| on the grid
        (of the order of the local error of K - 1 sweeps)."""
        st = self.stepper
        p, M = st.p, len(self.tau) - 1
        h = dt * np.diff(self.tau)
        self.iterations = 0
        surf = [st.surface]
        F = [self._solve(0.0, surf[0])]
        for m in range(M):                                  # provisional: first-order steps
            u = self._solve(h[m], surf[m]).u
            surf.append(Surface(surf[m].coeffs + h[m] * u, p))
            F.append(self._solve(0.0, surf[m + 1]))
        X = [s.coeffs for s in surf]
        prev_end, F_end = X[M], F[M]
        for k in range(self.sweeps):
            last_sweep = k == self.sweeps - 1
            Fu = np.stack([f.u for f in F])
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
            prev_end, F_end, X, F, surf = X[M], F[M], Xn, Fn, sn
        err = self.error = float(np.abs(sph.transform(p).synth(X[M] - prev_end)).max())
        st.coeffs = X[M].copy()
        st.time += dt
        return Solution(F_end.u, F_end.sigma, self.iterations, F_end.reason), err
