"""A fixed closed container: a no-slip spherical-harmonic wall carrying a completed double layer (docs/explanation/walls.md).

The fluid is inside the wall surface Gamma (normal n outward, away from the fluid).  Its
velocity is the wall's double layer plus that of the vesicles,

    u(x) = D_w[q](x) + u_ves(x),       D_w the lambda = 0 kernel (2.9) over Gamma           (W.1)

with D[1] = 1 inside (docs/explanation/method.md, section 4), so that the limit on Gamma from
the fluid side is q/2 + pv D_w[q].  No slip, u = 0 on Gamma, and the rank-one completion
N[q](x) = n(x) int_Gamma n . q dA (the interior double layer's deficiency: every D_w[q] has zero
flux through Gamma, so the range of q/2 + pv D_w misses n) give the second-kind equation

    (1/2 I + pv D_w + N) q = - u_ves   on Gamma                                            (W.2)

which is uniquely solvable (the flux of the right side is zero for divergence-free u_ves; the
completion then only fixes int n . q = 0).  The wall is a degree-p_w surface of the vesicles'
kind: the density q is expanded in its spherical harmonics (Galerkin, 3 C_w unknowns), pv D_w is
the singular self operator of section 5.1, the wall's velocity at other targets is the smooth
rule on its q_w grid with the near-singular correction of section 5.2 within h_w of it
(h_w = near_factor sqrt(A_w / q_w), the vesicles' rule with the wall's area and grid).

The wall does not move: its self operator, the completion and the LU of (W.2) are built once.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import lu_factor, lu_solve

from .. import sph
from .._kernels import stokes
from ..errors import SettingsError
from ..surface import Surface
from . import near as nearmod
from .evaluator import _Oriented
from .singular import SelfOperators

WALL_ID = -2          # the source id of the wall's points (no target carries it)
# the near zone h_w at most this fraction of the container's width (twice the smallest distance
# from its centroid to its points): the line points Y0 - n s, s in [h_w, 2 h_w], stay in the fluid
NEAR_WIDTH = 0.45
# the default degree of the wall's smooth and near-singular rules, q_w = Q_FACTOR p_w: with 2 p_w
# (the vesicles' rule) h_w = sqrt(A_w / q_w) scales with the container, and a vesicle 0.3 from a wall
# of radius 3 settles 2.4 % too fast (p_w = 16); 4 p_w: 0.5 %, 6 p_w: 0.16 % (experiments/container_near_wall.py,
# docs/explanation/walls.md)
Q_FACTOR = 4


def check_degree(surface, p, q_far=None, near_factor=1.0):
    """(h_w, width) of a wall surface of degree p, or a SettingsError naming the smallest valid
    wall.p (or -ves_wall_q) when its near zone h_w = near_factor sqrt(A_w / q_w) exceeds NEAR_WIDTH
    of its width (q_w = q_far, default Q_FACTOR p)."""
    q_far = q_far or Q_FACTOR * p
    area = float(surface.area(q_far)[0])
    pts = surface.points().reshape(-1, 3)
    width = 2.0 * float(np.linalg.norm(pts - pts.mean(axis=0), axis=1).min())
    h = float(nearmod.near_distance([area], q_far, near_factor)[0])
    if h > NEAR_WIDTH * width:
        q_min = int(np.ceil(near_factor ** 2 * area / (NEAR_WIDTH * width) ** 2))
        raise SettingsError(f"wall.p = {p}, -ves_wall_q {q_far}: too low for this container (its near zone "
                            f"h_w = {h:.3g} would exceed {NEAR_WIDTH:g} of its width {width:.3g}, the line points "
                            f"of the near-singular rule would leave the fluid); use -ves_wall_q >= {q_min} "
                            f"(or wall.p >= {-(-q_min // Q_FACTOR)} with the default q_w = {Q_FACTOR} p_w)")
    return h, width


class Wall:
    """The container Gamma of degree p (position coefficients (3, C)), its operators (W.2)."""

    def __init__(self, coeffs, p, q_self=None, q_far=None, near_factor=1.0):
        """q_self: the singular quadrature's degree (2 p); q_far: that of the smooth and near-singular
        rules (Q_FACTOR p, -ves_wall_q)."""
        coeffs = np.asarray(coeffs, dtype=float).reshape(3, sph.n_coeffs(p))
        self.p, self.C = p, sph.n_coeffs(p)
        self.surface = Surface(coeffs[None], p)
        self.q_self = q_self or 2 * p
        self.q_far = q_far or Q_FACTOR * p
        self.Tp, self.Tq = sph.transform(p), sph.transform(p, self.q_far)
        self.points = np.ascontiguousarray(self.surface.points().reshape(-1, 3))     # p-grid: the collocation targets
        gq = self.surface.geometry(self.q_far)
        self.src = np.ascontiguousarray(gq.X.reshape(-1, 3))
        self.src_w = gq.dA.reshape(-1)
        self.src_n = gq.normal.reshape(-1, 3)
        self.src_nw = np.ascontiguousarray(self.src_n * self.src_w[:, None])
        self.src_id = np.full(len(self.src), WALL_ID, dtype=np.int64)
        self.src_off = np.array([0, len(self.src)], dtype=np.int64)
        self.src_planar = stokes.planar(self.src, self.src_off)
        self.nw_planar = stokes.planar(self.src_nw, self.src_off)
        self.area = float(self.src_w.sum())
        self.h, self.width = check_degree(self.surface, p, self.q_far, near_factor)
        self.D = SelfOperators(coeffs[None], p, self.q_self, want_single=False, want_double=True).double[0]
        self.completion = self._completion()
        self.matrix = 0.5 * np.eye(3 * self.C) + self.D + self.completion
        self.lu = lu_factor(self.matrix, check_finite=False)

    @property
    def n_unknowns(self):
        return 3 * self.C

    def _completion(self):
        """N (3C, 3C): coefficients of n(x) int n . q dA (W.2), the integral on the q_w grid."""
        B = sph.basis_on_grid(self.p, self.q_far)[""]                       # (C, Mq)
        flux = (B[None] * (self.src_n.T * self.src_w)[:, None, :]).sum(axis=-1)   # (3, C): int n_k Y_c dA
        nc = self.Tq.analysis(self.src_n.T)                                   # (3, C): n in coefficients
        return np.outer(nc.ravel(), flux.ravel())

    def flux(self, q):
        """int n . q dA of a density (3C,)."""
        B = sph.basis_on_grid(self.p, self.q_far)[""]
        return float(np.einsum("kc,cm,km,m->", np.reshape(q, (3, self.C)), B, self.src_n.T, self.src_w))

    def apply(self, q):
        """(1/2 I + pv D_w + N) q, coefficients (3C,) (W.2)."""
        return self.matrix @ np.ravel(q)

    def solve(self, rhs):
        """q of (W.2) for the coefficients rhs (3C,) (the LU kept from the set-up)."""
        return lu_solve(self.lu, np.ravel(rhs), check_finite=False)

    def to_coeffs(self, values):
        """Galerkin coefficients (3C,) of values (Mp, 3) at the wall's p-grid points."""
        return self.Tp.analysis(np.asarray(values).T).ravel()

    def targets(self, targets):
        """The wall's double layer at fixed targets (T, 3) inside it: WallTargets."""
        return WallTargets(self, targets)

    def signed_gaps(self, targets):
        """Signed distances (T,) of targets to the wall (negative inside, in the fluid) for the
        targets within h_w of it, with their indices: (index (P,), distance (P,))."""
        wt = WallTargets(self, targets, zone_only=True)
        return wt.index, wt.distance

    def contains(self, targets):
        """Whether each target (T, 3) lies inside the wall: D_w[1] = 1 inside, 0 outside
        (the smooth rule; targets within h_w are decided by their projection)."""
        targets = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        one = np.ones_like(self.src)
        vals = np.zeros((len(targets), 3))
        stokes.stresslet_sum(self.src, self.src_nw, one, targets, vals)
        inside = vals[:, 0] > 0.5
        idx, d = self.signed_gaps(targets)
        inside[idx] = d < 0
        return inside


class WallCoupling:
    """The wall and the vesicles of one geometry (vesflow.operator.StepOperator): the vesicles'
    layers at the wall's p-grid points (LayerPotentials.target_set) and D_w at the vesicles'
    p-grid points (WallTargets)."""

    def __init__(self, wall, lp):
        self.wall = wall
        self.at_wall = lp.target_set(wall.points)
        self.at_vesicle_points = wall.targets(lp.trg)
        self.N, self.Tp = lp.N, lp.Tp

    def on_vesicles(self, q):
        """Coefficients (N, 3, C) of D_w[q] on the vesicles' surfaces."""
        vals = self.at_vesicle_points.apply(q).reshape(self.N, -1, 3)
        return self.Tp.analysis(np.moveaxis(vals, -1, -2))

    def rhs(self, values):
        """The wall rows' right side of (W.2), -u_ves, from the known part of the vesicles'
        velocity at the wall points (T, 3)."""
        return -self.wall.to_coeffs(values)


class WallTargets:
    """D_w[q] at fixed targets (T, 3): the smooth rule over the wall's q_w grid, replaced within
    h_w of the wall by the near-singular value (docs/explanation/method.md, section 5.2: the line
    extrapolation through the target's projection Y0, the on-surface value there the one-sided
    limit pv D_w[q] -/+ q/2 of the target's side)."""

    def __init__(self, wall, targets, zone_only=False):
        self.wall = wall
        self.trg = np.ascontiguousarray(np.asarray(targets, dtype=float).reshape(-1, 3))
        T = len(self.trg)
        tid = np.full(T, -1, dtype=np.int64)
        pairs, tpos = nearmod.near_pairs_images(self.trg, tid, wall.src, wall.src_id, wall.src_off, wall.h)
        t = pairs[:, 0]
        self.index, self.distance = np.zeros(0, dtype=np.int64), np.zeros(0)
        self.normal = np.zeros((0, 3))      # the wall's outward normal at each zone target's projection
        self.near = None
        if not len(t):
            return
        nearest = np.empty(len(t), dtype=np.int64)
        for k0 in range(0, len(t), 128):                  # closest q-grid point: the projection's start
            sl = slice(k0, k0 + 128)
            d = wall.src[None, :, :] - tpos[sl][:, None, :]
            nearest[sl] = np.einsum("bmk,bmk->bm", d, d).argmin(axis=1)
        it, jp = np.divmod(nearest, wall.Tq.nlon)
        proj = nearmod.Projection(wall.surface.coeffs, wall.p, tpos, np.zeros(len(t), dtype=np.int64),
                                  wall.Tq.theta[it], wall.Tq.phi[jp])
        zone = np.abs(proj.signed_distance) < wall.h
        self.index, self.distance, self.normal = t[zone], proj.signed_distance[zone], proj.normal[zone]
        if zone_only or not zone.any():
            return
        for name in ("theta", "phi", "point", "normal", "signed_distance", "converged"):
            setattr(proj, name, getattr(proj, name)[zone])
        side = np.where(proj.signed_distance >= 0, 1.0, -1.0)
        oriented = _Oriented(proj, side)
        line, _ = nearmod.line_points(oriented, wall.h)
        P = len(self.index)
        self.near = dict(
            side=side, weights=nearmod.interpolation_weights(oriented, wall.h),
            blocks=np.ascontiguousarray(np.concatenate([self.trg[self.index][:, None],
                                                        line.reshape(P, nearmod.L_POINTS, 3)], axis=1)),
            basis=sph.evaluate(np.eye(wall.C), wall.p, proj.theta, proj.phi).T)

    def apply(self, q):
        """D_w[q] at the targets (T, 3) for density coefficients q (3C,)."""
        w = self.wall
        qc = np.reshape(q, (3, w.C))
        g = np.ascontiguousarray(w.Tq.synth(qc).T)                   # (Mq, 3) on the q_w grid
        out = np.zeros((len(self.trg), 3))
        stokes.stresslet_sum(w.src, w.src_nw, g, self.trg, out)
        nr = self.near
        if nr is None:
            return out
        pv = (w.D @ qc.ravel()).reshape(3, w.C)
        u0 = nr["basis"] @ pv.T - 0.5 * nr["side"][:, None] * (nr["basis"] @ qc.T)   # one-sided limit at Y0
        blk = np.zeros(nr["blocks"].shape)
        stokes.stresslet_sum_blocks(w.src_planar, w.nw_planar, stokes.planar(g, w.src_off), w.src_off,
                                    nr["blocks"], np.zeros(len(self.index), dtype=np.int64), blk)
        wt = nr["weights"]
        corr = wt[:, :1] * u0 + np.einsum("pl,plk->pk", wt[:, 1:], blk[:, 1:]) - blk[:, 0]
        np.add.at(out, self.index, corr)
        return out

