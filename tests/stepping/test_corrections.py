"""Long-time robustness: area/volume correction (paper 3.4), reparameterization (3.5),
repulsion (3.13) and contact counting (3.3)."""
import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.correction import correct_area_volume
from vesflow.layerpot.evaluator import LayerPotentials
from vesflow.layerpot.near import Projection
from vesflow.reparam import reparameterize, spectral_energy
from vesflow.repulsion import contacts, min_gap, repulsion_force
from vesflow.surface import Surface

P = 16


def oblate(p=P, **kw):
    return shapes.make_shape("oblate", p, reduced_volume=0.85, **kw)


def smooth_perturbation(rng, p, size):
    """Random displacement coefficients (3, C) decaying like e^-n, max grid amplitude `size`."""
    ns, _, _ = sph.index_tables(p)
    C = sph.n_coeffs(p)
    d = rng.standard_normal((3, C)) * np.exp(-ns[:C])
    return d * size / np.abs(sph.transform(p).synth(d)).max()


def rel_changes(c_new, c_ref, p):
    a, b = Surface(c_new, p), Surface(c_ref, p)
    return (a.area() - b.area()) / b.area(), (a.volume() - b.volume()) / b.volume()


def hausdorff(ca, cb, p, q_fine=48):
    """Symmetric max distance between two single surfaces: fine-grid points of one projected
    on the other (brute-force nearest fine-grid point as the start of the Newton projection)."""
    Tq = sph.transform(p, q_fine)
    worst = 0.0
    for c1, c2 in ((ca, cb), (cb, ca)):
        x = Surface(c1, p).points(q_fine)[0]
        y = Surface(c2, p).points(q_fine)[0]
        j = np.einsum("ijk,ijk->ij", x[:, None] - y[None], x[:, None] - y[None]).argmin(axis=1)
        it, jp = np.divmod(j, Tq.nlon)
        pr = Projection(np.asarray(c2)[None], p, x, np.zeros(len(x), dtype=np.int64), Tq.theta[it], Tq.phi[jp])
        assert pr.converged.all()
        worst = max(worst, float(np.linalg.norm(x - pr.point, axis=1).max()))
    return worst


# ------------------------------------------------------------------ area / volume correction
def test_area_volume_correction_restores_both_to_1e10(rng):
    c0 = oblate()[None]
    S0 = Surface(c0, P)
    A0, V0 = S0.area(), S0.volume()
    cp = c0 + smooth_perturbation(rng, P, 2e-3)
    dA, dV = rel_changes(cp, c0, P)
    print(f"perturbation: dA/A = {dA[0]:.2e}, dV/V = {dV[0]:.2e}")
    assert 1e-4 < max(abs(dA[0]), abs(dV[0])) < 1e-2
    history = []
    for its_max in (1, 2, 3):
        _, _, e = correct_area_volume(cp, P, A0, V0, tol=1e-16, max_its=its_max)
        history.append(e[0].max())
    print("max rel error after 1, 2, 3 Newton steps:", ["%.1e" % e for e in history])
    cn, its, errs = correct_area_volume(cp, P, A0, V0, tol=1e-11)
    dA, dV = rel_changes(cn, c0, P)
    move = np.abs(sph.transform(P, 2 * P).synth(cn - cp)).max()
    print(f"corrected in {its} iterations: area {abs(dA[0]):.1e}, volume {abs(dV[0]):.1e} "
          f"(reported {errs[0]}), max point move {move:.2e}")
    assert its <= 5
    assert abs(dA[0]) < 1e-10 and abs(dV[0]) < 1e-10
    assert np.allclose(errs[0], [abs(dA[0]), abs(dV[0])], rtol=1e-6, atol=1e-15)
    assert 1e-5 < move < 5e-3                         # an O(1e-3) move, not a blow-up
    assert history[1] < 1e-3 * history[0]             # Newton: quadratic convergence


def test_correction_is_per_vesicle_and_leaves_converged_ones(rng):
    c0 = np.stack([oblate(), shapes.make_shape("prolate", P, reduced_volume=0.8, radius=0.7,
                                                 center=(3, 0, 0), rotation=(10, 50, 0)),
                   oblate(center=(0, 3, 0))])
    S0 = Surface(c0, P)
    A0, V0 = S0.area(), S0.volume()
    cp = c0.copy()
    cp[0] += smooth_perturbation(rng, P, 2e-3)
    cp[1] += smooth_perturbation(rng, P, 1e-3)
    cn, its, errs = correct_area_volume(cp, P, A0, V0, tol=1e-11)
    print("three vesicles: iterations", its, "rel errors", errs.max(axis=1))
    assert errs.max() < 1e-11 and its <= 5
    assert np.array_equal(cn[2], cp[2])               # already converged: untouched
    single, _, _ = correct_area_volume(cp[1], P, A0[1], V0[1], tol=1e-11)
    assert np.abs(single - cn[1]).max() < 1e-13       # batched == one at a time
    # default tolerance 1e-6, no work at all on the unperturbed shapes
    _, its0, _ = correct_area_volume(c0, P, A0, V0)
    assert its0 == 0


# ------------------------------------------------------------------ reparameterization
def badly_parameterized(amplitude, p=P):
    """The oblate with its p-grid points slid along the surface by a smooth tangential field, refit."""
    g = Surface(oblate(p)[None], p).geometry(p)
    x, y, z = np.moveaxis(g.X, -1, 0)
    V = amplitude * np.stack([np.sin(2 * x) + z, np.cos(y) * z + x, x * y], axis=-1)
    V -= np.einsum("...k,...k->...", V, g.normal)[..., None] * g.normal
    return Surface.from_points(g.X + V, p).coeffs[0]


def test_reparameterization_lowers_energy_and_keeps_shape():
    cb = badly_parameterized(0.02)
    e_good = spectral_energy(oblate(), P)
    print(f"E(oblate) = {e_good:.4f}, E(bad parameterization) = {spectral_energy(cb, P):.4f}")
    for kw in ({}, {"max_its": 200}):
        cn, its, e0, e1 = reparameterize(cb, P, **kw)
        dA, dV = rel_changes(cn, cb, P)
        dist = hausdorff(cb, cn, P)
        print(f"{kw or 'defaults'}: {its} its, E {e0:.4f} -> {e1:.4f}, dA/A = {dA[0]:.1e}, "
              f"dV/V = {dV[0]:.1e}, Hausdorff {dist:.1e}")
        assert e1 < e0 and np.isclose(e1, spectral_energy(cn, P))
        assert abs(dA[0]) < 1e-6 and abs(dV[0]) < 1e-6
        assert dist < 1e-4
    assert e0 - e1 > 0.1                              # 200 steps: a clear decrease
    # a good parameterization (the exact degree-1 spheroid) barely moves
    cg, _, g0, g1 = reparameterize(oblate(), P)
    dA, dV = rel_changes(cg, oblate(), P)
    dist = hausdorff(oblate(), cg, P)
    print(f"exact oblate: E {g0:.4f} -> {g1:.4f}, dA/A = {dA[0]:.1e}, dV/V = {dV[0]:.1e}, Hausdorff {dist:.1e}")
    assert g1 <= g0 and abs(dA[0]) < 1e-7 and abs(dV[0]) < 1e-7 and dist < 2e-5


def test_reparameterization_batched_and_stops_on_tolerance():
    cb = np.stack([badly_parameterized(0.02), oblate(center=(3, 0, 0))])
    cn, its, e0, e1 = reparameterize(cb, P, max_its=5)
    one, _, _, _ = reparameterize(cb[0], P, max_its=5)
    assert np.abs(one - cn[0]).max() < 1e-11          # the Newton projections' rounding (measured 2e-13)
    # tol above any step size: nothing moves
    same, its0, f0, f1 = reparameterize(cb, P, dtau_max=1e-3, tol=2e-3)
    assert its0 == 0 and np.array_equal(same, cb) and np.array_equal(f0, f1)


# ------------------------------------------------------------------ repulsion and contacts
def two_spheres(gap, p=12):
    c = np.stack([shapes.make_shape("sphere", p), shapes.make_shape("sphere", p, center=(2.0 + gap, 0, 0))])
    S = Surface(c, p)
    return S, LayerPotentials(S)


def test_repulsion_pushes_apart_and_decays():
    R, q = 0.05, 24
    totals = []
    for gap in (0.05, 0.1, 0.2):
        S, lp = two_spheres(gap)
        f = repulsion_force(S, lp, R, q)
        assert f.shape == (2, sph.transform(12, q).npts, 3)
        F = S.geometry(q).integrate(f)
        print(f"gap {gap}: net force on vesicle 0 {F[0]}, on 1 {F[1]}; min gap {min_gap(lp):.3f}, "
              f"contacts {contacts(lp)}")
        assert F[0, 0] < 0 and F[1, 0] > 0                    # pushes 0 to -x, away from 1
        assert np.abs(F[:, 1:]).max() < 1e-8 * abs(F[0, 0])
        assert np.isclose(F[0, 0], -F[1, 0], rtol=1e-10)
        assert np.isclose(min_gap(lp), gap, atol=1e-12) and contacts(lp) == 0
        totals.append(-F[0, 0])
    assert totals[0] > 10 * totals[1] > 100 * totals[2] > 0
    S, lp = two_spheres(1.0)
    f = repulsion_force(S, lp, R, q)
    assert not f.any() and min_gap(lp) == np.inf and contacts(lp) == 0
    # a single vesicle: no near structure at all
    one = Surface(shapes.make_shape("sphere", 12)[None], 12)
    assert not repulsion_force(one, LayerPotentials(one), R, q).any()


def test_contacts_count_interpenetration():
    S, lp = two_spheres(-0.05)
    n, g = contacts(lp), min_gap(lp)
    F = S.geometry(24).integrate(repulsion_force(S, lp, 0.05, 24))
    print(f"overlap 0.05: contacts {n}, min gap {g:.3f}, net force on 0 {F[0]}")
    assert n >= 2 and g == pytest.approx(-0.05, abs=1e-10)
    assert F[0, 0] < 0 < F[1, 0]                               # still separating


@pytest.mark.parametrize("keep", [True, False])
def test_post_step_keeps_the_centroid(keep):
    """Run._post_processed (reparameterization, then area/volume correction) on a sheared,
    asymmetric shape with area and volume off by ~1e-3: with -ves_keep_centroid (default) the
    centroid is where the step put it (to round-off) and area, volume are restored; without it
    the two moves shift the centroid (measured here: 1.4e-5)."""
    from vesflow import options as O, scene as S
    from vesflow.simulation import Run
    text = ('title = "one oblate"\n[discretization]\np = 8\n[time]\nhorizon = 1.0\ndt = 0.1\n'
            '[[vesicle]]\nshape = "oblate"\nreduced_volume = 0.85\nbending_modulus = 0.01\n')
    sc = S.parse_scene(text)
    run = Run(sc, O.read_options(O.dict_getter({"-ves_keep_centroid": keep}), sc))
    c = run.stepper.coeffs.copy()
    T = sph.transform(8)
    X = np.moveaxis(T.synth(c), -2, -1)
    shear = X.copy()
    shear[..., 0] += 0.3 * X[..., 2] + 0.05 * X[..., 2] ** 2 + 0.02 * X[..., 1] ** 3   # asymmetric
    moved = T.analysis(np.moveaxis(shear * 1.0005, -1, -2))
    before = Surface(moved, 8)
    after = Surface(run._post_processed(moved, True), 8)
    shift = np.linalg.norm(after.centroid() - before.centroid())
    assert np.abs(after.area() / run.area0 - 1).max() < 1e-9
    assert np.abs(after.volume() / run.volume0 - 1).max() < 1e-9
    print(f"keep_centroid {keep}: centroid moved by {shift:.2e}")
    if keep:
        assert shift < 1e-13
    else:
        assert shift > 1e-5


def test_reparameterization_budget_is_per_unit_time(monkeypatch):
    """A step of dt reparameterizes with up to max(-ves_reparam_max_its, -ves_reparam_rate dt)
    descent steps (default 20, and 1000 per unit time with sdc, 0 with euler): a long step gets
    the descent of the many short ones it replaces, and the mesh energy falls further."""
    from vesflow import options as O, scene as S
    import vesflow.simulation as sim
    text = ('title = "one oblate"\n[discretization]\np = 8\n[time]\nhorizon = 1.0\ndt = 0.1\n'
            '[[vesicle]]\nshape = "oblate"\nreduced_volume = 0.85\nbending_modulus = 0.01\n')
    sc = S.parse_scene(text)
    assert O.read_options(O.dict_getter({"-ts_type": "euler"})).reparam_rate == 0.0
    assert O.read_options(O.dict_getter({})).reparam_rate == 1000.0          # sdc, the default
    run = sim.Run(sc, O.read_options(O.dict_getter({"-ves_reparam_rate": 1000}), sc))
    bad = badly_parameterized(0.15, p=8)[None]
    seen = []
    import vesflow.stepping.poststep as post
    real = post.reparameterize
    monkeypatch.setattr(post, "reparameterize", lambda c, p, **kw: seen.append(kw["max_its"]) or real(c, p, **kw))
    energy = {dt: spectral_energy(run._post_processed(bad, True, dt=dt), 8)[0] for dt in (0.01, 0.3)}
    assert seen == [20, 300]
    print(f"mesh energy {spectral_energy(bad, 8)[0]:.4g} -> {energy[0.01]:.4g} (dt 0.01), {energy[0.3]:.4g} (dt 0.3)")
    assert energy[0.3] < energy[0.01] < spectral_energy(bad, 8)[0]
