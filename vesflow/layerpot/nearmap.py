"""The near correction of a set-up as a fixed linear map of the densities (docs/explanation/method.md, section 5.2).

A near pair (target x, vesicle v) replaces the smooth rule at x by the line extrapolation
through its projection: w_0 u_0 + sum_l w_l S_v[f](c_l) - S_v[f](x), the smooth rule S_v over
the m q-grid sources of v at the 8 line points c_l and at x.  With the geometry frozen the
smooth-rule part is a fixed linear map of v's density coefficients,

    sum_l w_l S_v[f](c_l) - S_v[f](x) = sum_c A_c f_{v,c},    A_c = sum_s R(y_s) Y_c(y_s),

R(y_s) = sum_k c_k K(x_k, y_s) w_s / mu the pair's combined kernel at source s (c = (-1, w_1..w_8),
symmetric 3 x 3: 6 numbers, stokes.near_map_rows) and Y_c the degree-p basis on the q-grid,
so that A = Q^T R (sph.Transform.synth_transpose).  Set up once per geometry (the combined
kernel, 9 m evaluations, and one transposed synthesis of 6 fields per pair), A costs 6 C
numbers per pair and layer (13.8 KB at p = 16) and a GMRES iteration 9 C multiply-adds per pair
instead of 9 m kernel evaluations (m = 2112 at q = 2p = 32).  The same values as the smooth
rule evaluated each iteration, to rounding (the sums reassociated).

Only the pairs whose source vesicle is one of this rank's (its coefficients are at hand) and
only as many as the memory budget holds get a map; the others keep the per-iteration blocks.
"""
from __future__ import annotations

import numpy as np

from .._kernels import stokes

CHUNK_PAIRS = 32         # pairs per batch: their kernel rows, 3.2 MB at q = 32 (as fast as 128 in
                         # benchmarks/near_field.py, a quarter of the temporary)


def map_bytes_per_pair(C, layers):
    """Bytes of the maps of one near pair: 6 C float64 per layer."""
    return 6 * int(C) * 8 * int(layers)


class NearMaps:
    """Maps A (P, 6, C) (single layer; A_double for the double layer, or None) of the near pairs
    ``index`` (into the set-up's NearPairs), their source vesicles as indices ``local`` of the
    densities' rows.

    near: vesflow.layerpot.near.NearPairs; index (P,) the pairs to map; local (P,) the density
    row of each one's vesicle; src_planar, src_off: the sources (stokes.planar); weight (n,):
    quadrature weight over mu of every source; nw_planar: normal times weight (planar) or None
    (single layer only); Tq: the q-grid transform (sph.Transform(p, q))."""

    def __init__(self, near, index, local, src_planar, src_off, weight, nw_planar, Tq):
        self.index = np.ascontiguousarray(index, dtype=np.int64)
        self.local = np.ascontiguousarray(local, dtype=np.int64)
        P, C, m = len(self.index), Tq.ncoef, Tq.npts
        self.single = np.empty((P, 6, C))
        self.double = None if nw_planar is None else np.empty((P, 6, C))
        rows = near.rows[self.index]
        # c_0 = -1: the smooth rule at the target (the far field's share) removed; c_l = w_l
        coef = np.concatenate([-np.ones((P, 1)), near.weights[self.index, 1:]], axis=1)
        R = np.empty((min(P, CHUNK_PAIRS), 6, m))
        for k0 in range(0, P, CHUNK_PAIRS):
            sl = slice(k0, min(P, k0 + CHUNK_PAIRS))
            n = sl.stop - sl.start
            blocks = np.ascontiguousarray(near.blocks[self.index[sl]])
            cf = np.ascontiguousarray(coef[sl])
            rv = np.ascontiguousarray(rows[sl])
            for out, w, dl in ((self.single, weight, False), (self.double, nw_planar, True)):
                if out is None:
                    continue
                stokes.near_map_rows(src_planar, w, src_off, blocks, cf, rv, R[:n], dl)
                out[sl] = Tq.synth_transpose(R[:n])

    @property
    def nbytes(self):
        return self.single.nbytes + (0 if self.double is None else self.double.nbytes)

    def apply(self, f, g=None):
        """(P, 3): sum_l w_l S[f](c_l) - S[f](x) (+ the same for D[g]) of the mapped pairs, from
        the density coefficients f (N, 3, C) (and g (N, 3, C), already times 1 - lambda)."""
        out = np.zeros((len(self.index), 3))
        stokes.near_map_apply(self.single, self.local, np.ascontiguousarray(f, dtype=np.float64), out)
        if g is not None and self.double is not None:
            stokes.near_map_apply(self.double, self.local, np.ascontiguousarray(g, dtype=np.float64), out)
        return out
