"""Surfaces of many vesicles from spherical-harmonic coefficients (docs/explanation/method.md, sections 1-2).

`Surface(coeffs, p)` holds the position coefficients (N, 3, C) of N vesicles of degree p.
`Surface.geometry(q)` evaluates the differential geometry on the q-grid (q >= p; q > p
upsamples, which is where nonlinear products are formed without aliasing):

    E, F, G      first fundamental form  X_t.X_t, X_t.X_p, X_p.X_p
    W            sqrt(E G - F^2);  n = X_t x X_p / W  (outward)
    L, M, N      second fundamental form X_tt.n, X_tp.n, X_pp.n
    H            (E N - 2 F M + G L) / (2 W^2)   (sphere of radius R: H = -1/R)
    K            (L N - M^2) / W^2               (sphere: K = 1/R^2)
    dA           quadrature weight times W / sin(theta)

Surface operators (gradient, divergence, Laplace-Beltrami) act pointwise on values and
derivatives: Laplace f = g^ij (f_ij - (X_ij . X^k) f_k), so Laplace X = 2 H n exactly.
"""
from __future__ import annotations

import numpy as np

from . import sph


class Geometry:
    """Differential geometry of N surfaces on one grid (see module docstring)."""

    def __init__(self, coeffs, p, q):
        self.p, self.q = p, q
        # derivatives of the position are exact: evaluate the degree-p series on the q-grid
        self.T = sph.transform(p, q)
        d = self.T.synth_all(coeffs)                       # each (N, 3, npts)
        mv = lambda a: np.moveaxis(a, -2, -1)              # -> (N, npts, 3)
        self.X, self.Xt, self.Xp = mv(d[""]), mv(d["t"]), mv(d["p"])
        self.Xtt, self.Xtp, self.Xpp = mv(d["tt"]), mv(d["tp"]), mv(d["pp"])
        dot = lambda a, b: np.einsum("...k,...k->...", a, b)
        self.E, self.F, self.G = dot(self.Xt, self.Xt), dot(self.Xt, self.Xp), dot(self.Xp, self.Xp)
        self.W = np.sqrt(self.E * self.G - self.F ** 2)
        self.normal = np.cross(self.Xt, self.Xp) / self.W[..., None]
        self.L, self.M, self.N = (dot(self.Xtt, self.normal), dot(self.Xtp, self.normal),
                                  dot(self.Xpp, self.normal))
        W2 = self.W ** 2
        self.H = (self.E * self.N - 2.0 * self.F * self.M + self.G * self.L) / (2.0 * W2)
        self.K = (self.L * self.N - self.M ** 2) / W2
        self.sin_theta = np.repeat(self.T.sin_theta, self.T.nlon)
        self.area_element = self.W / self.sin_theta          # W / sin(theta): smooth
        self.dA = self.area_element * self.T.weights
        # inverse metric and dual basis X^t, X^p (for gradients and Laplace-Beltrami)
        self.gtt, self.gtp, self.gpp = self.G / W2, -self.F / W2, self.E / W2
        self.Xup_t = self.gtt[..., None] * self.Xt + self.gtp[..., None] * self.Xp
        self.Xup_p = self.gtp[..., None] * self.Xt + self.gpp[..., None] * self.Xp
        # Christoffel contractions g^ij X_ij . X^k, k = t, p
        Xij = self.gtt[..., None] * self.Xtt + 2.0 * self.gtp[..., None] * self.Xtp + self.gpp[..., None] * self.Xpp
        self.gamma_t = dot(Xij, self.Xup_t)
        self.gamma_p = dot(Xij, self.Xup_p)
        self._scalar_T = sph.transform(q, q)

    @property
    def npts(self):
        return self.T.npts

    # ------------------------------------------------------------ integrals
    def integrate(self, f):
        """Surface integral of a grid field (N, npts) or (N, npts, k) -> (N,) or (N, k)."""
        f = np.asarray(f)
        if f.ndim == self.dA.ndim:
            return np.einsum("...i,...i->...", f, self.dA)
        return np.einsum("...ik,...i->...k", f, self.dA)

    # ------------------------------------------------------------ derivatives of grid fields
    def derivatives(self, f):
        """Values and first/second theta/phi derivatives of grid fields (..., npts) of this grid.

        The field is expanded to degree q on the q-grid (the grid's own resolution).
        """
        c = self._scalar_T.analysis(f)
        return self._scalar_T.synth_all(c)

    def grad(self, f, d=None):
        """Surface gradient of scalar fields (N, npts) -> (N, npts, 3)."""
        d = self.derivatives(f) if d is None else d
        return d["t"][..., None] * self.Xup_t + d["p"][..., None] * self.Xup_p

    def div(self, V, d=None):
        """Surface divergence of vector fields (N, npts, 3) -> (N, npts) (d: the derivatives
        't', 'p' of V as (N, 3, npts), if known; V is then not used)."""
        if d is None:
            c = self._scalar_T.analysis(np.moveaxis(np.asarray(V), -1, -2))   # (N, 3, K)
            d = {"t": self._scalar_T.synth(c, "t"), "p": self._scalar_T.synth(c, "p")}
        Vt, Vp = np.moveaxis(d["t"], -2, -1), np.moveaxis(d["p"], -2, -1)
        return np.einsum("...k,...k->...", Vt, self.Xup_t) + np.einsum("...k,...k->...", Vp, self.Xup_p)

    def laplace(self, f, d=None):
        """Laplace-Beltrami of scalar fields (..., npts) defined on this grid."""
        d = self.derivatives(f) if d is None else d
        return (self.gtt * d["tt"] + 2.0 * self.gtp * d["tp"] + self.gpp * d["pp"]
                - self.gamma_t * d["t"] - self.gamma_p * d["p"])

    def laplace_vector(self, V, d=None):
        """Componentwise Laplace-Beltrami of vector fields (N, npts, 3) (d: derivatives of V as
        derivatives() gives them for (N, 3, npts), if known; V is then not used)."""
        if d is None:
            d = self.derivatives(np.moveaxis(np.asarray(V), -1, -2))          # of (N, 3, npts)
        Lt = lambda a: a[:, None, :] if a.ndim == 2 else a
        out = (Lt(self.gtt) * d["tt"] + 2.0 * Lt(self.gtp) * d["tp"] + Lt(self.gpp) * d["pp"]
               - Lt(self.gamma_t) * d["t"] - Lt(self.gamma_p) * d["p"])
        return np.moveaxis(out, -2, -1)


class Surface:
    """N vesicle surfaces of degree p: position coefficients (N, 3, C)."""

    def __init__(self, coeffs, p):
        coeffs = np.asarray(coeffs, dtype=float)
        if coeffs.ndim == 2:
            coeffs = coeffs[None]
        if coeffs.shape[1:] != (3, sph.n_coeffs(p)):
            raise ValueError(f"position coefficients must have shape (N, 3, {sph.n_coeffs(p)}) for p = {p}, "
                             f"got {coeffs.shape}")
        self.p = p
        self.coeffs = coeffs
        self._geo = {}

    @property
    def n_vesicles(self):
        return self.coeffs.shape[0]

    @classmethod
    def from_points(cls, points, p):
        """Fit from positions on the p-grid, (N, M, 3)."""
        T = sph.transform(p)
        return cls(T.analysis(np.moveaxis(points, -1, -2)), p)

    def geometry(self, q=None):
        """Geometry on the q-grid (cached per q); q defaults to p."""
        q = self.p if q is None else q
        if q not in self._geo:
            self._geo[q] = Geometry(self.coeffs, self.p, q)
        return self._geo[q]

    def release_geometry(self):
        """Forget the cached geometries (computed again, identically, if asked for)."""
        self._geo = {}

    def points(self, q=None):
        """Positions on the q-grid (N, npts, 3)."""
        return self.geometry(q).X

    def pole_points(self):
        """Positions at the north and south poles (N, 2, 3), for pictures."""
        return np.moveaxis(sph.evaluate(self.coeffs, self.p, [0.0, np.pi], [0.0, 0.0]), -1, -2)

    # ------------------------------------------------------------ global quantities
    def area(self, q=None):
        g = self.geometry(q or 2 * self.p)
        return g.dA.sum(axis=-1)

    def volume(self, q=None):
        """(1/3) integral of X . n dA."""
        g = self.geometry(q or 2 * self.p)
        return g.integrate(np.einsum("...k,...k->...", g.X, g.normal)) / 3.0

    def centroid(self, q=None):
        """Centroid of the enclosed volume: (1/V) integral (x_k^2 / 2) n_k dA."""
        g = self.geometry(q or 2 * self.p)
        m = g.integrate(0.5 * g.X ** 2 * g.normal)
        return m / self.volume(q)[:, None]

    def reduced_volume(self, q=None):
        """v = 6 sqrt(pi) V / A^(3/2)."""
        return 6.0 * np.sqrt(np.pi) * self.volume(q) / self.area(q) ** 1.5

    def effective_radius(self, q=None):
        return np.sqrt(self.area(q) / (4.0 * np.pi))

    def bending_energy(self, kappa=1.0, q=None):
        """kappa_b * integral(H^2 dA) (a sphere: 4 pi kappa_b)."""
        g = self.geometry(q or 2 * self.p)
        return np.asarray(kappa) * g.integrate(g.H ** 2)

    def bending_energy_density(self, kappa=1.0, q=None):
        """kappa_b H^2 (N, npts) at the q-grid points (default the p-grid): bending_energy
        is its integral."""
        g = self.geometry(q or self.p)
        return np.reshape(np.asarray(kappa, dtype=float), (-1, 1)) * g.H ** 2

    def translated(self, shift):
        """A copy moved by shift (N, 3) or (3,)."""
        c = self.coeffs.copy()
        c[:, :, 0] += np.sqrt(4.0 * np.pi) * np.broadcast_to(shift, (self.n_vesicles, 3))
        return Surface(c, self.p)

    def bounding_spheres(self):
        """Centres (N, 3) and radii (N,) enclosing the p-grid points and poles."""
        X = np.concatenate([self.points(), self.pole_points()], axis=1)
        c = X.mean(axis=1)
        r = np.linalg.norm(X - c[:, None], axis=-1).max(axis=1)
        return c, r


def to_coeffs(values, p, q=None):
    """Grid fields (N, npts, k) or (N, npts) on the q-grid -> degree-p coefficients (N, k, C) / (N, C)."""
    T = sph.transform(p, p if q is None else q)
    values = np.asarray(values)
    if values.ndim == 3:
        return T.analysis(np.moveaxis(values, -1, -2))
    return T.analysis(values)


def to_grid(coeffs, p, q=None):
    """Degree-p coefficients (N, k, C) or (N, C) -> values on the q-grid (N, npts, k) / (N, npts)."""
    T = sph.transform(p, p if q is None else q)
    v = T.synth(coeffs)
    if np.asarray(coeffs).ndim == 3:
        return np.moveaxis(v, -2, -1)
    return v
