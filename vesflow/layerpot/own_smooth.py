"""The own vesicle's smooth Ewald share, removed in the per-step set-up (docs/explanation/far_field.md,
"Spectral Ewald", the own vesicle).

With ``EwaldSum(own="smooth")`` (vesflow.layerpot.ewald) the far field at a p-grid target x_t
of vesicle v holds, besides the sum over the other vesicles, the Fourier part's share of v's
own q-grid sources y_s at their given positions::

    e_v(x_t) = sum_{s in v} S^F(x_t - y_s) f(y_s) w_s / mu + D^F(x_t - y_s) g(y_s)

(``S^F = G^F / (8 pi)``, ``D^F g = T^F:(g n_s w_s) / (8 pi)``, the smooth parts of
vesflow._kernels.ewald; ``g`` already times (1 - lambda_v)).  e_v is linear in the density
coefficients and fixed during a step: the operators

    E_v = -P_p K^F_v diag(w) Q_q        (3C x 3C per vesicle and layer, the layout of SelfOperators)

map the coefficients of f (or g) to those of -e_v, so that adding E_v f to the coefficients of
the far field (LayerPotentials.apply, after the same p-grid analysis P_p) removes it to
rounding: the Fourier part evaluates the same q-grid quadrature of the same kernel, to the
Ewald tolerance.  Assembly per vesicle, one target latitude at a time: the kernel table (6
symmetric components x Mq sources, ``ewald.smooth_kernel_tables``), Q_q^T by the transposed
transform, then the fast p-grid analysis along the target axis (singular.project_rows; as
SelfOperators._assemble without rotations).
"""
from __future__ import annotations

import numpy as np

from .. import sph
from .._kernels import ewald as _ewald
from ..threads import map_vesicles
from .singular import SelfOperators, project_rows

NONE = np.empty((0, 0, 0))


class OwnSmoothOperators:
    """E_v (module docstring) of every vesicle: ``single`` (N, 3C, 3C) (divided by the
    viscosity, as SelfOperators.single), ``double`` (N, 3C, 3C) or None.

    trg (N, Mp, 3): the p-grid points (targets of the far field); src (N, Mq, 3), w (N, Mq),
    nw (N, Mq, 3): the q-grid sources, weights, normals times weights of the far field; xi:
    the Ewald splitting; dtype: storage (float32 with -ves_self_precision single)."""

    def __init__(self, trg, src, w, nw, xi, p, q, want_single=True, want_double=False, viscosity=1.0,
                 dtype=np.float64):
        self.p, self.q, self.xi = p, q, float(xi)
        N = src.shape[0]
        C = sph.n_coeffs(p)
        self.single = np.empty((N, 3 * C, 3 * C), dtype) if want_single else None
        self.double = np.empty((N, 3 * C, 3 * C), dtype) if want_double else None

        def store(v):
            S, D = self._assemble(trg[v], src[v], w[v], nw[v], want_single, want_double)
            if want_single:
                np.divide(S, viscosity, out=self.single[v])   # in place: no (3C)^2 temporary
            if want_double:
                self.double[v] = D
        map_vesicles(store, range(N), p)

    @property
    def nbytes(self):
        """Bytes held by the operators."""
        return sum(a.nbytes for a in (self.single, self.double) if a is not None)

    def _assemble(self, x, y, w, nw, want_single, want_double):
        """-P_p K^F diag(w) Q_q of one vesicle for each wanted layer, (3C, 3C)."""
        p, q = self.p, self.q
        Tp, Tq = sph.transform(p), sph.transform(p, q)
        C = sph.n_coeffs(p)
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(Tp.nlat, Tp.nlon, 3)
        y = np.ascontiguousarray(y, dtype=np.float64)
        w = np.ascontiguousarray(w, dtype=np.float64)
        nw = np.ascontiguousarray(nw, dtype=np.float64)
        kinds = [k for k, on in (("S", want_single), ("D", want_double)) if on]
        rows = {k: np.empty((Tp.nlat, Tp.nlon, 6, C)) for k in kinds}   # Q_q^T (K^F w) per target
        ker = {k: np.empty((Tp.nlon, 6, Tq.npts)) for k in kinds}
        for i in range(Tp.nlat):
            _ewald.smooth_kernel_tables(np.ascontiguousarray(x[i]), y, w, nw, self.xi,
                                        ker["S"] if want_single else NONE, ker["D"] if want_double else NONE)
            for k in kinds:
                rows[k][i] = Tq.synth_transpose(ker[k])                  # (J, 6, C)
        out = [None if k not in rows else project_rows(rows.pop(k).reshape(Tp.npts, 6, C), p, scale=-1.0)
               for k in ("S", "D")]
        return out[0], out[1]

    def apply(self, f, g=None):
        """E f (+ E_D g) as coefficients (N, 3, C); g already times (1 - lambda)."""
        u = SelfOperators.apply(self.single, f)
        if g is not None and self.double is not None:
            u += SelfOperators.apply(self.double, g)
        return u
