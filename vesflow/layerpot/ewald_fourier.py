"""The Fourier-space part of the spectral Ewald sum (vesflow.layerpot.ewald, whose module
docstring has the formulas): the kernel ``Psi(k)`` on the NUFFT grid (periodic, or the windowed
free-space kernel), the wave vectors, the non-uniform FFTs (finufft or ducc0.nufft) and the
symmetric source components of the stresslet."""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.special import erf

from vesflow.errors import SettingsError

NUFFT_LIBS = ("finufft", "ducc0")
# ducc0.nufft's range of oversampling factors (its default 1.19 .. 2.51 picks slower ones here)
DUCC0_SIGMA = (1.3, 1.6)
DUCC0_SIGMA_MIN_EPS = 5e-11


def kvectors(p):
    """The wave numbers per axis of the NUFFT grid of EwaldParams ``p``, ``2 pi m / P``, m = -K/2 .. K/2 - 1."""
    return [2.0 * math.pi / P * (np.arange(n) - n // 2) for P, n in zip(p.period, p.modes)]


def phi_smooth(r, xi):
    """``phi^F(r) = r erf(xi r) + exp(-xi^2 r^2) / (xi sqrt(pi))`` (``d phi^F / dr = erf(xi r)``)."""
    return r * erf(xi * r) + np.exp(-(xi * r) ** 2) / (xi * math.sqrt(math.pi))


def window_1d(x, half, sigma):
    """One axis of the free-space window W (vesflow.layerpot.ewald module docstring)."""
    s = math.sqrt(2.0) * sigma
    return 0.5 * (erf((half - x) / s) + erf((half + x) / s))


def kernel_psi(p, threads=1):
    """``Psi(k)`` for ``k_a = 2 pi m_a / P_a``, ``m_a = 0 .. K_a/2`` (Psi is even in each
    component of k), real (K_0/2 + 1, K_1/2 + 1, K_2/2 + 1)."""
    k = [2.0 * math.pi / P * np.arange(n // 2 + 1) for P, n in zip(p.period, p.modes)]
    if p.periodic:
        k2 = k[0][:, None, None] ** 2 + k[1][None, :, None] ** 2 + k[2][None, None, :] ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            q = k2 / (4.0 * p.xi ** 2)
            psi = (1.0 + q) * np.exp(-q) / (k2 * k2)
        psi[k2 == 0.0] = 0.0
        return psi
    import scipy.fft
    # the periodized K = phi^F W, sum_n K(x + n P), sampled at x_j = j P / K, j = 0 .. K/2 per
    # axis: on [0, P/2] the images n_a = 0 and -1 (at distance P_a - x_a) count, the latter
    # where its window is not 0, i.e. for x_a > ~B_a (the period is 2 B + w, _free_period);
    # the DFT of the even function on the full periodic grid is the type-1 DCT of this octant
    x = [P / n * np.arange(n // 2 + 1) for P, n in zip(p.period, p.modes)]
    phi = np.zeros(tuple(n // 2 + 1 for n in p.modes))
    terms = []                                   # per axis: (index range, coordinate, window)
    for a in range(3):
        half = p.box[a] + 0.5 * p.w
        wa = window_1d(x[a], half, p.sigma)
        wi = window_1d(p.period[a] - x[a], half, p.sigma)
        live = np.flatnonzero(wi > 0.0)
        first = int(live[0]) if live.size else x[a].size
        terms.append([(slice(0, None), x[a], wa),
                      (slice(first, None), (p.period[a] - x[a])[first:], wi[first:])])
    for (s0, x0, w0), (s1, x1, w1), (s2, x2, w2) in itertools.product(*terms):
        if x0.size == 0 or x1.size == 0 or x2.size == 0:
            continue
        r = np.sqrt(x0[:, None, None] ** 2 + x1[None, :, None] ** 2 + x2[None, None, :] ** 2)
        phi[s0, s1, s2] += phi_smooth(r, p.xi) * (w0[:, None, None] * w1[None, :, None] * w2[None, None, :])
    cell = float(np.prod([P / n for P, n in zip(p.period, p.modes)]))
    psi = scipy.fft.dctn(phi, type=1, workers=threads, overwrite_x=True)
    psi *= -cell / (8.0 * math.pi)
    return np.ascontiguousarray(psi)


class Nufft:
    """Type 1 (points -> modes, e^{-i k.x}) and type 2 (modes -> points, e^{+i k.x}) transforms
    on fixed source and target points (scaled to [0, 2 pi)), finufft or ducc0.nufft."""

    def __init__(self, lib, modes, src01, trg01, eps, threads):
        if lib not in NUFFT_LIBS:
            raise SettingsError(f"NUFFT library {lib!r} is not one of {', '.join(NUFFT_LIBS)}")
        self.lib, self.modes, self.eps, self.threads = lib, tuple(int(m) for m in modes), eps, threads
        self.src, self.trg = src01, trg01
        self._plans = {}

    def _finufft_plan(self, kind, ntr):
        key = (kind, ntr)
        if key not in self._plans:
            import finufft
            # upsampling 1.25 is 2-3x faster than finufft's default here (docs/explanation/far_field.md)
            # but its kernel width is capped at 16: 2.0 below eps 1e-9
            plan = finufft.Plan(kind, self.modes, n_trans=ntr, eps=self.eps, isign=-1 if kind == 1 else 1,
                                dtype="complex128", nthreads=self.threads, modeord=0,
                                upsampfac=1.25 if self.eps >= 1e-9 else 2.0)
            pts = self.src if kind == 1 else self.trg
            plan.setpts(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                        np.ascontiguousarray(pts[:, 2]))
            self._plans[key] = plan
        return self._plans[key]

    def _ducc_plan(self, kind):
        if kind not in self._plans:
            import ducc0
            pts = self.src if kind == 1 else self.trg
            # oversampling 1.3 .. 1.6 instead of ducc0's own choice in 1.19 .. 2.51: type 1 at
            # N = 512 (1.08e6 sources, 146^3 modes) 1.64 -> 1.36-1.39 s, N = 64 0.21 -> 0.12 s
            # (docs/explanation/far_field.md, "Speed: third session")
            # (ducc0 has kernels for them down to eps 5e-11; below, its own range)
            sigma = DUCC0_SIGMA if self.eps >= DUCC0_SIGMA_MIN_EPS else (1.19, 2.51)
            self._plans[kind] = ducc0.nufft.plan(nu2u=(kind == 1), coord=np.ascontiguousarray(pts),
                                                 grid_shape=self.modes, epsilon=max(self.eps, 3e-13),
                                                 nthreads=self.threads, periodicity=2 * math.pi,
                                                 fft_order=False, sigma_min=sigma[0], sigma_max=sigma[1])
        return self._plans[kind]

    def type1(self, c, out=None):
        """``F_k = sum_s c_s e^{-i k.y_s}``: c (m, S) complex -> (m, n1, n2, n3) (into ``out``
        if given)."""
        m = c.shape[0]
        if self.lib == "finufft":
            return self._finufft_plan(1, m).execute(np.ascontiguousarray(c), out=out)
        return self._ducc_plan(1).nu2u(points=np.ascontiguousarray(c), forward=True, out=out)

    def type2(self, U, out=None):
        """``u_t = sum_k U_k e^{+i k.x_t}``: U (m, n1, n2, n3) -> (m, T) complex (into ``out``)."""
        m = U.shape[0]
        if self.lib == "finufft":
            return self._finufft_plan(2, m).execute(np.ascontiguousarray(U), out=out)
        return self._ducc_plan(2).u2nu(grid=np.ascontiguousarray(U), forward=False, out=out)


def sym6(nw, g):
    """Components (00, 11, 22, 01, 02, 12) of sym(g nw^T), (6, S)."""
    s = np.empty((6, g.shape[0]))
    s[0] = g[:, 0] * nw[:, 0]
    s[1] = g[:, 1] * nw[:, 1]
    s[2] = g[:, 2] * nw[:, 2]
    s[3] = 0.5 * (g[:, 0] * nw[:, 1] + g[:, 1] * nw[:, 0])
    s[4] = 0.5 * (g[:, 0] * nw[:, 2] + g[:, 2] * nw[:, 0])
    s[5] = 0.5 * (g[:, 1] * nw[:, 2] + g[:, 2] * nw[:, 1])
    return s
