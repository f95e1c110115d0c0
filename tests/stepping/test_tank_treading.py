"""Diagnostics of runs/tank_treading.py (docs/explanation/dynamics.md): exact on known shapes and flows; one slow short run."""
import importlib.util
import os

import numpy as np
import pytest

from vesflow import shapes, sph
from vesflow.surface import Surface

from tests.harness import ROOT  # noqa: E402


def _load():
    spec = importlib.util.spec_from_file_location("tank_treading", os.path.join(ROOT, "runs", "tank_treading.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


tt = _load()


@pytest.mark.parametrize("beta", [60.0, 75.0, 100.0])
def test_inclination_angle_of_a_tilted_ellipsoid(beta):
    """An ellipsoid with its long axis (z) turned by R_y(beta) lies at 90 - beta degrees from x."""
    p = 8
    c = shapes.make_shape("ellipsoid", p, axes=(0.7, 0.8, 1.5), rotation=(0.0, beta, 0.0), center=(0.3, -0.2, 0.1))
    a, axes = tt.inclination_angle(Surface(c[None], p))
    assert np.degrees(a) == pytest.approx(90.0 - beta, abs=1e-9)
    # equivalent-ellipsoid semi-axes of an ellipsoid are its own (times the scale to unit effective radius)
    s = Surface(c[None], p).effective_radius()[0] / Surface(shapes.make_shape("ellipsoid", p, axes=(0.7, 0.8, 1.5))[None],
                                                            p).effective_radius()[0]
    assert axes / axes[0] == pytest.approx(np.array([1.5, 0.8, 0.7]) / 1.5, rel=1e-9)
    assert s == pytest.approx(1.0)


def test_rotation_measures_of_a_rigid_rotation():
    """u = omega e_y x r (clockwise in x-z) on an ellipsoid: period 2 pi / omega, weighted mean omega."""
    p, om = 10, 0.37
    c = shapes.make_shape("ellipsoid", p, axes=(1.4, 0.9, 0.8), rotation=(0.0, 50.0, 0.0), center=(0.5, 0.0, -0.2))
    S = Surface(c[None], p)
    r = S.points() - S.centroid()[:, None, :]
    u = om * np.stack([r[..., 2], 0 * r[..., 1], -r[..., 0]], axis=-1)     # = om (z, 0, -x)
    u_c = sph.transform(p).analysis(np.moveaxis(u, -1, -2))
    period, omega_w, omega_min = tt.rotation_measures(S, u_c)
    assert period == pytest.approx(2 * np.pi / om, rel=1e-3)   # linear interpolation of the section
    assert omega_w == pytest.approx(om, rel=1e-10)
    assert omega_min == pytest.approx(om, rel=1e-3)


def test_marker_projection_recovers_a_surface_point_near_a_pole():
    p = 8
    c = shapes.make_shape("prolate", p, reduced_volume=0.9, rotation=(0.0, 60.0, 0.0))
    S = Surface(c[None], p)
    m = tt.Marker(S, np.array([0.0, 0.0, 3.0]))
    target_s = np.array([0.02, 0.01, 1.0]) / np.linalg.norm([0.02, 0.01, 1.0])   # close to the parametric pole
    x = tt.Marker.position_at(S.coeffs, p, target_s)
    s, res = m.project(S.coeffs, p, x)
    assert res < 1e-10
    assert np.linalg.norm(tt.Marker.position_at(S.coeffs, p, s) - x) < 1e-10


def test_marker_periods_of_a_uniform_phase():
    t = np.linspace(0, 30, 3001)
    psi = 0.4 * t + 0.3 * np.sin(0.8 * t)          # phase with a period-2pi/0.4 modulation
    pp = tt.phase_periods(t, psi)
    assert len(pp) > 0
    assert np.allclose(pp[:, 1], 2 * np.pi / 0.4, rtol=2e-3)


@pytest.mark.slow
def test_short_tank_treading_run_tilts_toward_the_steady_angle(tmp_path):
    """p = 8, t = 3: the angle falls from 30 degrees to its plateau (about 27.5), the membrane turns clockwise."""
    petsc4py = pytest.importorskip("petsc4py")
    petsc4py.init([])
    tt.main(["--p", "8", "--horizon", "3", "--npz", str(tmp_path / "tt.npz"), "--png", str(tmp_path / "tt.png")])
    d = dict(np.load(tmp_path / "tt.npz"))
    incl = np.degrees(d["incl"])
    assert incl[0] == pytest.approx(30.0, abs=1e-6)
    assert 26.0 < incl[-1] < 29.0
    assert 0.3 < 2 * np.pi / d["period"][-1] < 0.5
    assert np.abs(np.asarray(d["marker"])[:, 1]).max() < 1e-4        # the marker stays in the shear plane
    assert (tmp_path / "tt.png").exists()
