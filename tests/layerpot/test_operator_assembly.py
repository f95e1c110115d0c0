"""The fast assembly of the per-vesicle operators (SelfOperators, OwnSmoothOperators;
docs/explanation/far_field.md, "Periodic: where the time of a large suspension goes") against the
plain per-latitude assembly it replaced: one latitude of targets at a time, every rotation and
transform as in docs/explanation/method.md, section 5.1, the projection by the dense p-grid analysis
matrix.  Equal to rounding (1e-13 relative), both layers, p = 8, q = 16 and p = 6, q = 15."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow._kernels import ewald as ek
from vesflow._kernels import stokes
from vesflow.layerpot.own_smooth import OwnSmoothOperators
from vesflow.layerpot.singular import FULL, SelfOperators, graham_sloan_weights
from vesflow.surface import Surface


def dense_analysis(p):
    T = sph.transform(p)
    return T.analysis(np.eye(T.npts)).T                               # (C, Mp)


def to_operator(proj, C):
    """(k', ab, k) -> (3C, 3C) with blocks [a, b]."""
    return proj[:, FULL].transpose(1, 0, 2, 3).reshape(3 * C, 3 * C)


def self_reference(X, p, q):
    """S_hat = P R_t^T Q^T (Lambda W K) per target (module docstring of singular.py)."""
    Tp, Tq = sph.transform(p), sph.transform(p, q)
    C, K = sph.n_coeffs(p), sph.n_full(p)
    lam_w = graham_sloan_weights(q) / np.repeat(Tq.sin_theta, Tq.nlon)
    Xt = Tp.synth(X).T.reshape(Tp.nlat, Tp.nlon, 3)
    rows = {w: np.empty((Tp.nlat, Tp.nlon, 6, K)) for w in "SD"}
    ker = {w: np.empty((Tp.nlon, 6, Tq.npts)) for w in "SD"}
    for i, theta0 in enumerate(Tp.theta):
        Xr = np.stack([sph.rotate_to_pole(X, p, theta0, phi0) for phi0 in Tp.phi])
        x, xt, xp = Tq.synth_first(Xr)
        stokes.self_kernel_tables(np.ascontiguousarray(Xt[i]), x, xt, xp, lam_w, ker["S"], ker["D"])
        for w in "SD":
            R = Tq.synth_transpose(ker[w], full=True)                 # (J, 6, K)
            for j, phi0 in enumerate(Tp.phi):                         # R_t^T = D_z(-phi0) D_y(theta0)^T
                back = sph.apply_degree_blocks(R[j], p, sph.wigner_blocks(p, float(theta0)), transpose=True)
                rows[w][i, j] = sph.rotate_z(back, p, -phi0)
    return [to_operator((dense_analysis(p) @ rows[w].reshape(Tp.npts, 6 * K)).reshape(C, 6, K)[:, :, :C], C)
            for w in "SD"]


def own_reference(x, y, w, nw, xi, p, q):
    """-P K^F diag(w) Q_q (module docstring of own_smooth.py), one target latitude at a time."""
    Tp, Tq = sph.transform(p), sph.transform(p, q)
    C = sph.n_coeffs(p)
    x = x.reshape(Tp.nlat, Tp.nlon, 3)
    rows = {k: np.empty((Tp.nlat, Tp.nlon, 6, C)) for k in "SD"}
    ker = {k: np.empty((Tp.nlon, 6, Tq.npts)) for k in "SD"}
    for i in range(Tp.nlat):
        ek.smooth_kernel_tables(np.ascontiguousarray(x[i]), y, w, nw, xi, ker["S"], ker["D"])
        for k in "SD":
            rows[k][i] = Tq.synth_transpose(ker[k])
    return [-to_operator((dense_analysis(p) @ rows[k].reshape(Tp.npts, 6 * C)).reshape(C, 6, C), C) for k in "SD"]


def cells(p, n=2):
    return np.stack([shapes.make_shape("biconcave", p, center=(0.4 * i, -0.3, 0.2), rotation=(0.4 + i, 1.1, 0.2 * i))
                     for i in range(n)])


def rel(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("p, q", [(8, 16), (6, 15)])
def test_self_operators_equal_the_per_latitude_assembly(p, q):
    c = cells(p)
    ops = SelfOperators(c, p, q, want_single=True, want_double=True, viscosity=1.5)
    for v in range(len(c)):
        S, D = self_reference(c[v], p, q)
        assert rel(ops.single[v], S / 1.5) < 1e-13
        assert rel(ops.double[v], D) < 1e-13
    only = SelfOperators(c, p, q, want_single=False, want_double=True)
    assert only.single is None and rel(only.double[1], ops.double[1]) < 1e-15


@pytest.mark.parametrize("p, q", [(8, 16), (6, 15)])
def test_own_smooth_operators_equal_the_per_latitude_assembly(p, q):
    c = cells(p)
    S = Surface(c, p)
    geo = S.geometry(q)
    x = np.ascontiguousarray(S.points().reshape(len(c), -1, 3))
    y = np.ascontiguousarray(geo.X.reshape(len(c), -1, 3))
    w = np.ascontiguousarray(geo.dA.reshape(len(c), -1))
    nw = np.ascontiguousarray((geo.normal * geo.dA[..., None]).reshape(len(c), -1, 3))
    xi = 2.3
    ops = OwnSmoothOperators(x, y, w, nw, xi, p, q, True, True, viscosity=0.7)
    for v in range(len(c)):
        Sref, Dref = own_reference(x[v], y[v], w[v], nw[v], xi, p, q)
        assert rel(ops.single[v], Sref / 0.7) < 1e-13
        assert rel(ops.double[v], Dref) < 1e-13
    only = OwnSmoothOperators(x, y, w, nw, xi, p, q, True, False)
    assert only.double is None and rel(only.single[0], ops.single[0] * 0.7) < 1e-15
