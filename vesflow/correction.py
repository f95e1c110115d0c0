"""Area and volume correction after a time step (paper 3.4, eq. 3.20; docs/explanation/method.md, section 7).

Each vesicle is moved along psi n with psi = 2 alpha H - beta.  With the sign convention of
`vesflow.surface` (outward n, H = -1/R on a sphere) the first variations of area and volume
under a displacement dX are

    dA = -int 2 H (n . dX) dA,        dV = int (n . dX) dA,

so for dX = psi n the 2x2 system (3.20) for (alpha, beta) reads

    [ -4 int H^2     2 int H ] [alpha]   [A0 - A]
    [  2 int H      -A       ] [beta ] = [V0 - V].

The displacement is formed on the upsampled q-grid and projected to degree p (the
coefficients can only hold its degree-p part), and the matrix is assembled with the
projected displacements P(2 H n), P(-n) in place of 2 H n, -n: this is (3.20) for the move
actually applied (identical when psi n is resolved at degree p), which keeps Newton's
quadratic convergence.  alpha, beta are scaled by R^2 and R (R = sqrt(A / 4 pi)) and the
rows by A and V so that the 2x2 systems are dimensionless.  A sphere (H constant) makes
the system singular: the pseudo-inverse (rcond 1e-6) then gives the least-squares move.
"""
from __future__ import annotations

import numpy as np

from . import sph
from .shapes import make_shape
from .surface import Geometry


def _area_volume(geo):
    """Area and volume with the quadrature of Surface.area()/volume()."""
    A = geo.dA.sum(axis=-1)
    V = geo.integrate(np.einsum("...k,...k->...", geo.X, geo.normal)) / 3.0
    return A, V


def correct_area_volume(coeffs, p, area0, volume0, tol=1e-6, max_its=5, q=None):
    """Newton iterations on (3.20) restoring area A0 and volume V0 of every vesicle.

    coeffs (N, 3, C) (or (3, C)); area0, volume0 scalars or (N,).  Iterates until both
    relative errors |A - A0| / A0, |V - V0| / V0 are below tol (per vesicle; converged
    vesicles are left alone) or max_its corrections were applied.  Area and volume are
    measured on the q-grid (q = 2p by default, as Surface.area()/volume()).

    Returns (new_coeffs, iterations, rel_errors): the corrected coefficients (same shape as
    coeffs), the number of corrections applied (int) and the final relative errors (N, 2)
    (area, volume); (2,) for a (3, C) input.
    """
    c = np.array(coeffs, dtype=float)
    single = c.ndim == 2
    if single:
        c = c[None]
    q = 2 * p if q is None else q
    N = c.shape[0]
    A0 = np.broadcast_to(np.asarray(area0, dtype=float), (N,))
    V0 = np.broadcast_to(np.asarray(volume0, dtype=float), (N,))
    T = sph.transform(p, q)
    its = 0
    act = np.arange(N)
    errs = np.zeros((N, 2))
    # a sphere (reduced volume 1) cannot trade area for volume: (3.20) is singular there and
    # Newton turns round-off into shape noise.  The only shape with its area and volume is the
    # sphere of volume V0: replace it by that sphere about its centroid, with the standard
    # parameterization (the minimizer of the reparameterization energy: degree 1 only), then
    # dilate to V0 against quadrature error
    c, sphere = restore_spheres(c, p, A0, V0, q)
    if sphere.any():
        act = np.nonzero(~sphere)[0]
    geo = Geometry(c, p, q)
    if sphere.any():
        A, V = _area_volume(geo)
        errs[:, 0], errs[:, 1] = np.abs(A - A0) / A0, np.abs(V - V0) / V0
        geo = Geometry(c[act], p, q)
    while len(act):
        A, V = _area_volume(geo)
        errs[act, 0] = np.abs(A - A0[act]) / A0[act]
        errs[act, 1] = np.abs(V - V0[act]) / V0[act]
        keep = errs[act].max(axis=1) >= tol
        if not keep.any() or its >= max_its:
            break
        sub = np.nonzero(keep)[0]
        act = act[sub]
        A, V = A[sub], V[sub]
        H, n, dA = geo.H[sub], geo.normal[sub], geo.dA[sub]
        R = np.sqrt(A / (4.0 * np.pi))
        # basis moves psi_1 n = 2 R^2 H n (alpha = a R^2) and psi_2 n = -R n (beta = b R)
        basis = np.stack([(2.0 * R[:, None] ** 2 * H)[..., None] * n, -R[:, None, None] * n], axis=1)  # (n,2,M,3)
        bc = T.analysis(np.moveaxis(basis, -1, -2))                     # (n, 2, 3, C)
        dn = np.einsum("vbkm,vmk->vbm", T.synth(bc), n)                  # n . P(basis) on the q-grid
        J = np.empty((len(act), 2, 2))
        J[:, 0, :] = -2.0 * np.einsum("vbm,vm->vb", dn, H * dA) / A[:, None]
        J[:, 1, :] = np.einsum("vbm,vm->vb", dn, dA) / V[:, None]
        rhs = np.stack([(A0[act] - A) / A, (V0[act] - V) / V], axis=1)
        # rcond 1e-6: near a sphere the two moves are almost parallel (J nearly singular); a tiny
        # singular value would turn a 1e-10 residual into an O(1) move (measured: blow-up of a sphere)
        ab = np.einsum("vij,vj->vi", np.linalg.pinv(J, rcond=1e-6), rhs)
        c[act] += np.einsum("vb,vbkc->vkc", ab, bc)
        its += 1
        geo = Geometry(c[act], p, q)
    return (c[0], its, errs[0]) if single else (c, its, errs)


def restore_spheres(coeffs, p, area0, volume0, q=None):
    """The vesicles (N, 3, C) whose target (area0, volume0) is a sphere (reduced volume above
    1 - 1e-6) replaced by the sphere of volume0 about their centroid (sphere_at_centroid, then
    a dilation against its quadrature error); returns (coeffs, mask of those vesicles)."""
    c = np.array(coeffs, dtype=float)
    q = 2 * p if q is None else q
    N = c.shape[0]
    A0 = np.broadcast_to(np.asarray(area0, dtype=float), (N,))
    V0 = np.broadcast_to(np.asarray(volume0, dtype=float), (N,))
    sphere = 6.0 * np.sqrt(np.pi) * V0 / A0 ** 1.5 > 1.0 - 1e-6
    if sphere.any():
        c[sphere] = sphere_at_centroid(c[sphere], p, q)
        V = _area_volume(Geometry(c[sphere], p, q))[1]
        c[sphere, :, 1:] *= (V0[sphere] / V)[:, None, None] ** (1.0 / 3.0)   # about the mean point
    return c, sphere


def sphere_at_centroid(coeffs, p, q=None):
    """The standard sphere (make_shape("sphere")) at the volume centroid of each surface
    (N, 3, C), with the same volume.  A locked sphere (stepper.sphere_constraints) is carried
    rigidly and its membrane tank-treads: the grid rotates with it, and reusing the
    preconditioner's factors across steps (-ves_pc_lag) then mismatches the stiff locking term
    (measured: GMRES 391 iterations and 2 failed solves, sphere in shear, p = 8); the standard
    parameterization keeps every step's block the same."""
    q = 2 * p if q is None else q
    geo = Geometry(coeffs, p, q)
    V = geo.integrate(np.einsum("...k,...k->...", geo.X, geo.normal)) / 3.0
    xc = geo.integrate(0.5 * geo.X ** 2 * geo.normal) / V[:, None]
    R = np.cbrt(3.0 * V / (4.0 * np.pi))
    return np.stack([make_shape("sphere", p, radius=R[k], center=xc[k]) for k in range(len(V))])
