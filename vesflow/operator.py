"""The linear operator of the semi-implicit step (docs/explanation/method.md, section 6; paper 3.6) as a petsc4py MatPython context.

Unknowns per vesicle i, stored contiguously as one block of 4C: velocity u_i (3C
coefficients, component-major) then tension sigma_i (C).  For every vesicle

    alpha_i u_i - sum_j [ S_ij (dt B_j[u_j] + f_sigma(X_j, sigma_j)) - D_ij u_j ]  = rhs_i
    div_gamma_i u_i                                                               = 0

with alpha_i = (1 + lambda_i)/2 and D_ij the (1 - lambda_j) double layer whose kernel gives
D[1] = 1 inside (docs/explanation/method.md, section 4).  The sign of D is that of
docs/explanation/method.md, section 6: with the opposite one a spherical vesicle would sediment at
U / lambda instead of Stokes' velocity U for every lambda (tests/stepping/test_dynamics.py pins this).  Forces are formed on the upsampled q-grid and filtered to
degree p (Galerkin).  With explicit coupling only j = i is kept on the left.
"""
from __future__ import annotations

import numpy as np

from . import forces, sph
from .setup_state import VesicleParams  # noqa: F401  (re-exported: vesflow.operator.VesicleParams)
from .surface import Surface


class StepOperator:
    """MatPython context: mult applies the left side above (geometry frozen at X^n)."""

    def __init__(self, surface, params, dt, layer_potentials, q_force=None, coupling="implicit", wall=None):
        """wall: a vesflow.layerpot.wall.WallCoupling of this geometry (a container), or None:
        its density's 3 C_w unknowns then follow the vesicles' (docs/explanation/walls.md)."""
        self.surface, self.params, self.dt = surface, params, float(dt)
        self.wall = wall
        self.lp = layer_potentials
        self.p = surface.p
        self.q_force = q_force or 2 * self.p
        self.geo = surface.geometry(self.q_force)
        self.Tf = sph.transform(self.p, self.q_force)
        self.N = surface.n_vesicles
        self.C = sph.n_coeffs(self.p)
        self.block = 4 * self.C
        self.coupling = coupling
        self.n_mult = 0
        # sphere constraints (stepper.sphere_constraints): the locking stiffness K_v of the force
        # -K_v P_{n >= 2}(u . n) n and the gauge c_v added at (divergence n = 0, tension n = 0)
        self.lock = np.zeros(self.N)
        self.gauge = np.zeros(self.N)

    # ------------------------------------------------------------------ pieces
    @property
    def n_wall(self):
        """Unknowns of the wall density (0 without a wall)."""
        return 0 if self.wall is None else self.wall.wall.n_unknowns

    @property
    def size(self):
        """Length of the system's vectors: the vesicles' blocks, then the wall's density."""
        return self.N * self.block + self.n_wall

    def split(self, x):
        """(u (N, 3, C), sigma (N, C)) of a vector (the wall's density, if any, is wall_part's)."""
        x = np.asarray(x)[:self.N * self.block].reshape(self.N, self.block)
        return x[:, :3 * self.C].reshape(self.N, 3, self.C), x[:, 3 * self.C:]

    def wall_part(self, x):
        """The wall density's coefficients (3 C_w,) of a vector."""
        return np.asarray(x)[self.N * self.block:]

    def join(self, u, s, q=None):
        """The vector of u, sigma and (with a wall) the wall density q (zeros when None)."""
        v = np.concatenate([u.reshape(self.N, 3 * self.C), s.reshape(self.N, self.C)], axis=1).ravel()
        if self.wall is None:
            return v
        return np.concatenate([v, np.zeros(self.n_wall) if q is None else np.ravel(q)])

    def grid_vec(self, c):
        """Coefficients (N, 3, C) -> upsampled grid (N, npts, 3)."""
        return np.moveaxis(self.Tf.synth(c), -2, -1)

    def coeffs_vec(self, v):
        return self.Tf.analysis(np.moveaxis(v, -1, -2))

    def membrane_force(self, u, sigma, geo=None, kappa=None, lock=None, du=None):
        """Coefficients of dt B[u] + f_sigma(sigma) (the implicit part of the traction jump), plus
        the locking force of spheres -K P_{n >= 2}(u . n) n where self.lock (or lock, for the
        vesicles of geo) is nonzero.  du: Tf.synth_all(u), if the caller has it (apply shares it
        with the divergence)."""
        geo = self.geo if geo is None else geo
        kappa = self.params.kappa if kappa is None else kappa
        lock = self.lock if lock is None else np.asarray(lock, dtype=float)
        du = self.Tf.synth_all(u) if du is None else du       # u and its derivatives, exact from the coefficients
        ug = np.moveaxis(du[""], -2, -1)
        sg, sg_t, sg_p = self.Tf.synth_first(sigma)
        f = (self.dt * forces.linearized_bending_force(geo, kappa, ug, dY=du)
             + forces.tension_force(geo, sg, d={"t": sg_t, "p": sg_p}))
        if np.any(lock):
            low = sph.index_tables(self.p)[0][:self.C] <= 1
            unc = self.Tf.analysis(np.einsum("...mk,...mk->...m", ug, geo.normal))
            unc[..., low] = 0.0
            f = f - (lock[:, None] * self.Tf.synth(unc))[..., None] * geo.normal
        return self.coeffs_vec(f)

    def divergence(self, u, geo=None, du=None):
        geo = self.geo if geo is None else geo
        du = self.Tf.synth_all(u, values=False) if du is None else du
        return self.Tf.analysis(geo.div(None, d=du))

    def apply(self, x):
        """The operator on a NumPy vector of length N * 4C.  The derivatives of u on the force
        grid are synthesized once from its coefficients (exact: u has degree p) and shared by
        the bending force and the divergence."""
        u, s = self.split(x)
        du = self.Tf.synth_all(u)
        f = self.membrane_force(u, s, du=du)
        g = -u if self.lp.want_double else None
        rw = None
        if self.wall is not None:            # (W.2) and D_w[q] on the vesicles (docs/explanation/walls.md)
            q = self.wall_part(x)
            lpv, at_wall = self.lp.apply(f, g, targets=self.wall.at_wall)
            with self.lp.timers.stage("wall"):
                lpv = lpv + self.wall.on_vesicles(q)
                rw = self.wall.wall.apply(q) + self.wall.wall.to_coeffs(at_wall)
        elif self.coupling == "implicit":
            lpv = self.lp.apply(f, g)
        else:
            lpv = self.lp.self_part(f, g)
        r1 = self.params.alpha[:, None, None] * u - lpv
        r2 = self.divergence(u, du=du)
        r2[:, 0] += self.gauge * s[:, 0]
        return self.join(r1, r2, rw)

    # ------------------------------------------------------------------ petsc4py Mat python interface
    def mult(self, mat, x, y):
        self.n_mult += 1
        y.setArray(self.apply(x.getArray(readonly=True)))

    def view(self, mat, viewer):
        viewer.printfASCII(f"vesflow StepOperator: {self.N} vesicles, p = {self.p}, dt = {self.dt:g}, "
                           f"coupling {self.coupling}, double layer {'on' if self.lp.want_double else 'off'}"
                           + (f", wall of {self.n_wall} unknowns" if self.wall is not None else "") + "\n")

    # ------------------------------------------------------------------ dense self blocks (preconditioner)
    def force_matrices(self, v, q=None):
        """The per-vesicle linear maps of the step as dense matrices, from the step's geometry.

        Returns (Mb (3C, 3C), Mt (3C, C), Div (C, 3C)): coefficients of the linearized bending
        force B[u] (3.12, with vesicle v's kappa_b, without dt), of the tension force f_sigma
        (2.6) and of div_gamma u, each formed on the q_force grid and filtered to
        degree p, i.e. the same maps as membrane_force and divergence (to rounding).  Built
        from the degree-p basis on the q_force grid (sph.basis_on_grid, cached per p and q):
        the derivatives of u and sigma are exact there, and only the Laplacian of the linearized
        mean curvature needs the degree-q transforms, batched over the 3C columns.
        """
        q = self.q_force if q is None else q
        g, Tf, C = self.surface.geometry(q), sph.transform(self.p, q), self.C
        Q = sph.basis_on_grid(self.p, q)                             # dict of (C, npts)
        n = g.normal[v]                                              # (npts, 3)
        Xt, Xp = g.Xup_t[v], g.Xup_p[v]
        # Laplace-Beltrami of each basis function (componentwise Laplace of u), (C, npts)
        Lb = (g.gtt[v] * Q["tt"] + 2.0 * g.gtp[v] * Q["tp"] + g.gpp[v] * Q["pp"]
              - g.gamma_t[v] * Q["t"] - g.gamma_p[v] * Q["p"])
        # linearized mean curvature h = n . Laplace(u) / 2 of the 3C unit densities, (3, C, npts)
        h = 0.5 * n.T[:, None, :] * Lb[None]
        lap_h = _laplace_one(g, v, h.reshape(3 * C, -1)).reshape(3, C, -1)
        mag = -self.params.kappa[v] * (lap_h + 2.0 * h * (g.H[v] ** 2 - g.K[v]))
        # force components: (3 [density comp], C, 3 [force comp], npts) -> coefficients
        fb = mag[:, :, None, :] * n.T[None, None]
        Mb = Tf.analysis(fb).reshape(3 * C, 3 * C).T                 # rows: force (comp, k)
        ft = ((2.0 * g.H[v] * Q[""])[:, None, :] * n.T[None]
              + Q["t"][:, None, :] * Xt.T[None] + Q["p"][:, None, :] * Xp.T[None])   # (C, 3, npts)
        Mt = Tf.analysis(ft).reshape(C, 3 * C).T
        dv = Q["t"][None] * Xt.T[:, None, :] + Q["p"][None] * Xp.T[:, None, :]      # (3, C, npts)
        Div = Tf.analysis(dv).reshape(3 * C, C).T
        return Mb, Mt, Div

    def self_block_parts(self, v, q=None):
        """(A0, SMb) with self_block(v) = A0 - dt [SMb 0; 0 0]: the dt-independent part and the
        single layer of the linearized bending force, so that a block for another dt costs a
        sum (the preconditioner keeps both across the solves of a step and of later steps)."""
        C = self.C
        Mb, Mt, Div = self.force_matrices(v, q)
        S = self.lp.self_ops.single[v]
        A0 = np.zeros((self.block, self.block))
        A0[:3 * C, 3 * C:] = -(S @ Mt)
        if self.lp.want_double:
            A0[:3 * C, :3 * C] = (1.0 - self.params.lam[v]) * self.lp.self_ops.double[v]
        if self.lock[v]:
            A0[:3 * C, :3 * C] -= S @ self.lock_matrix(v, q)
        A0[np.arange(3 * C), np.arange(3 * C)] += self.params.alpha[v]
        A0[3 * C:, :3 * C] = Div
        A0[3 * C, 3 * C] += self.gauge[v]
        return A0, S @ Mb

    def lock_matrix(self, v, q=None):
        """The locking force of vesicle v, -K_v P_{n >= 2}(u . n) n, as a (3C, 3C) matrix
        (formed as in membrane_force, on the q grid)."""
        q = self.q_force if q is None else q
        g, Tf, C = self.surface.geometry(q), sph.transform(self.p, q), self.C
        Q = sph.basis_on_grid(self.p, q)[""]                          # (C, npts)
        n = g.normal[v]
        un = Tf.analysis(n.T[:, None, :] * Q[None])                   # (3 [u comp], C [u k], C [u.n k'])
        un[..., sph.index_tables(self.p)[0][:C] <= 1] = 0.0
        f = -self.lock[v] * Tf.synth(un)[:, :, None, :] * n.T[None, None]   # (3, C, 3 [force comp], npts)
        return Tf.analysis(f).reshape(3 * C, 3 * C).T

    def self_block(self, v):
        """The dense 4C x 4C block of vesicle v with itself (forces, self layer potentials, divergence):

            [ alpha I - S (dt Mb) + (1 - lambda) D    - S Mt ]
            [ Div                                      0     ]
        """
        A0, SMb = self.self_block_parts(v)
        return block_at(A0, SMb, self.dt)

    def self_block_by_columns(self, v, chunk=256):
        """self_block by applying the operator pieces to unit vectors (the reference it is tested against)."""
        sub = Surface(self.surface.coeffs[v:v + 1], self.p)
        geo = sub.geometry(self.q_force)
        C, n = self.C, self.block
        ops_S = self.lp.self_ops.single[v]
        ops_D = self.lp.self_ops.double[v] if self.lp.want_double else None
        lam, alpha, kappa = self.params.lam[v], self.params.alpha[v], self.params.kappa[v:v + 1]
        A = np.empty((n, n))
        for c0 in range(0, n, chunk):
            cols = np.arange(c0, min(n, c0 + chunk))
            E = np.zeros((len(cols), n))
            E[np.arange(len(cols)), cols] = 1.0
            u = E[:, :3 * C].reshape(-1, 3, C)
            s = E[:, 3 * C:]
            f = self.membrane_force(u, s, geo, kappa, lock=self.lock[v:v + 1])
            r = (ops_S @ f.reshape(-1, 3 * C).T).T
            if ops_D is not None:
                r -= (1.0 - lam) * (ops_D @ u.reshape(-1, 3 * C).T).T
            r1 = alpha * u.reshape(-1, 3 * C) - r
            r2 = self.Tf.analysis(geo.div(self.grid_vec(u)))
            r2[:, 0] += self.gauge[v] * s[:, 0]
            A[:, cols] = np.concatenate([r1, r2], axis=1).T
        return A


def block_at(A0, SMb, dt):
    """A0 - dt [SMb 0; 0 0] (a new array)."""
    A = A0.copy()
    n = SMb.shape[0]
    A[:n, :n] -= dt * SMb
    return A


def _laplace_one(geo, v, f):
    """Laplace-Beltrami on vesicle v of the grid's Geometry for many fields f (B, npts) of that grid."""
    d = geo.derivatives(f)
    return (geo.gtt[v] * d["tt"] + 2.0 * geo.gtp[v] * d["tp"] + geo.gpp[v] * d["pp"]
            - geo.gamma_t[v] * d["t"] - geo.gamma_p[v] * d["p"])
