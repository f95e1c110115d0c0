"""Scene files and options: valid scenes give the right values, lattices and random packings
are right and reproducible, every malformed scene is one clear SceneError naming its key,
the overlap test agrees with brute force, and command-line options override scene keys."""
import copy
import dataclasses
import math

import numpy as np
import pytest

from vesflow import options as O
from vesflow import scene as S
from vesflow.scene import geometry as G, packing as PK, parser as SP
from vesflow.errors import OptionError, SceneError

from tests.harness import ROOT  # noqa: E402


# ---------------------------------------------------------------- a tiny TOML writer
def _val(v):
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == math.inf else ("-inf" if v == -math.inf else repr(v)))
    if isinstance(v, int):
        return str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_val(x)}" for k, x in v.items()) + "}"
    raise TypeError(v)


def to_toml(d):
    """Scalars and inline values first, then [tables], then [[arrays of tables]]."""
    out = []
    for k, v in d.items():
        if not isinstance(v, dict) and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v)):
            out.append(f"{k} = {_val(v)}")
    for k, v in d.items():
        if isinstance(v, dict):
            out.append(f"[{k}]")
            out += [f"{kk} = {_val(vv)}" for kk, vv in v.items()]
    for k, v in d.items():
        if isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for t in v:
                out.append(f"[[{k}]]")
                out += [f"{kk} = {_val(vv)}" for kk, vv in t.items()]
    return "\n".join(out) + "\n"


BASE = {
    "title": "base",
    "flow": {"type": "shear", "rate": 0.1},
    "fluid": {"viscosity": 1.0},
    "gravity": {"g": [0.0, 0.0, -1.0]},
    "discretization": {"p": 12},
    "time": {"horizon": 10.0, "dt": 0.1},
    "repulsion": {"radius": 0.02},
    "output": {"file": "out/base.h5", "every": 1.0},
    "vesicle": [
        {"shape": "oblate", "reduced_volume": 0.85, "radius": 1.0, "center": [-3.0, 0.0, 0.0],
         "rotation": [0.0, 0.0, 0.0], "bending_modulus": 0.01, "viscosity_contrast": 1.0, "excess_density": 0.0},
        {"shape": "ellipsoid", "axes": [1.0, 0.8, 0.6], "radius": 1.0, "center": [3.0, 0.0, 0.0],
         "rotation": [10.0, 20.0, 30.0], "bending_modulus": 0.02, "viscosity_contrast": 2.0, "excess_density": 1.0},
    ],
    "lattice": [
        {"count": [2, 2, 1], "spacing": 3.0, "origin": [10.0, 0.0, 0.0], "seed": 1, "orientation": "fixed",
         "vesicle": {"shape": "prolate", "reduced_volume": 0.9, "radius": 1.0, "bending_modulus": 0.05}},
    ],
}
PERIODIC = {
    "flow": {"type": "taylor_green", "amplitude": 0.1},
    "domain": {"period": 10.0},
    "vesicle": [{"shape": "biconcave", "reduced_volume": 0.65, "center": [2.0, 2.0, 2.0]},
                {"shape": "sphere", "center": [6.0, 6.0, 6.0]}],
}


def parse(d):
    return S.parse_scene(to_toml(d))


# ---------------------------------------------------------------- valid scenes
def test_base_scene_values():
    sc = parse(BASE)
    assert sc.title == "base"
    assert sc.flow == S.Flow("shear", rate=0.1)
    assert sc.fluid.viscosity == 1.0 and sc.gravity.g == (0.0, 0.0, -1.0)
    assert sc.p == 12 and sc.time == S.Time(10.0, 0.1) and sc.repulsion.radius == 0.02
    assert sc.output == S.Output("out/base.h5", 1.0)
    assert sc.n_vesicles == 2 + 4
    v0, v1 = sc.vesicles[:2]
    assert v0.shape == "oblate" and v0.reduced_volume == 0.85 and v0.axes is None
    assert v0.center == (-3.0, 0.0, 0.0) and v0.label == "vesicle[0]"
    assert v1.axes == (1.0, 0.8, 0.6) and v1.rotation == (10.0, 20.0, 30.0)
    assert v1.viscosity_contrast == 2.0 and v1.excess_density == 1.0 and v1.bending_modulus == 0.02
    # an ellipsoid's reduced volume is computed: Legendre's area formula vs a quadrature
    a, b, c = v1.axes
    x, w = np.polynomial.legendre.leggauss(120)
    th, ph = np.arccos(x), np.arange(240) * np.pi / 120
    T, P = np.meshgrid(th, ph, indexing="ij")
    Xt = np.stack([a * np.cos(T) * np.cos(P), b * np.cos(T) * np.sin(P), -c * np.sin(T)])
    Xp = np.stack([-a * np.sin(T) * np.sin(P), b * np.sin(T) * np.cos(P), 0 * T])
    area = np.sum(np.linalg.norm(np.cross(Xt, Xp, axis=0), axis=0) / np.sin(T) * w[:, None]) * np.pi / 120
    v_expected = 6 * math.sqrt(math.pi) * (4 / 3 * math.pi * a * b * c) / area ** 1.5
    assert v1.reduced_volume == pytest.approx(v_expected, rel=1e-10)
    assert v1.area == pytest.approx(4 * math.pi) and v1.volume == pytest.approx(v_expected * 4 / 3 * math.pi)
    eff = sc.effects()
    assert eff.as_dict() == dict(background_flow=True, gravity=True, double_layer=True, repulsion=True,
                                 periodic=False, interactions=True, wall=False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.time.dt = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        sc.vesicles[0].radius = 2.0


def test_defaults_of_a_minimal_scene():
    sc = S.parse_scene("[[vesicle]]\n")
    v = sc.vesicles[0]
    assert (v.shape, v.radius, v.center, v.rotation) == ("sphere", 1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    assert (v.bending_modulus, v.viscosity_contrast, v.excess_density, v.reduced_volume) == (0.01, 1.0, 0.0, 1.0)
    assert sc.flow is None and sc.domain is None and sc.gravity is None and sc.repulsion is None
    assert sc.fluid.viscosity == 1.0 and sc.p == 16
    assert sc.time == S.Time(10.0, 0.1) and sc.output == S.Output("out/scene.h5", 0.1)
    assert not any(sc.effects().as_dict().values())
    assert sc.effects().on() == [] and sc.periodic_length == 0.0 and sc.volume_fraction is None
    assert S.parse_scene("[time]\nhorizon = 0.5\n[[vesicle]]").time.dt == pytest.approx(0.05)
    assert S.parse_scene("[repulsion]\n[[vesicle]]").repulsion.radius == 0.02
    assert S.parse_scene("[[vesicle]]\nshape = 'biconcave'").vesicles[0].reduced_volume == 0.65


def test_periodic_scene_and_effects():
    sc = parse(PERIODIC)
    assert sc.flow == S.Flow("taylor_green", amplitude=0.1) and sc.periodic_length == 10.0
    assert sc.volume_fraction == pytest.approx(sum(v.volume for v in sc.vesicles) / 1000.0)
    e = sc.effects()
    assert e.periodic and e.background_flow and e.interactions and not e.gravity and not e.double_layer
    one = S.parse_scene("[domain]\nperiod = 5.0\n[[vesicle]]\n")
    assert one.effects().interactions                     # its periodic images
    assert not S.parse_scene("[[vesicle]]\n[[vesicle]]\ncenter=[3,0,0]\n[gravity]\ng=[0,0,-1]").effects().gravity
    assert not S.parse_scene("[flow]\ntype='shear'\nrate=0\n[[vesicle]]").effects().background_flow
    assert not S.parse_scene("[gravity]\ng=[0,0,0]\n[[vesicle]]\nexcess_density=1").effects().gravity
    assert S.parse_scene("[gravity]\ng=[0,0,-1]\n[[vesicle]]\nexcess_density=-1").effects().gravity


def test_default_scene():
    sc = S.default_scene()
    assert sc.n_vesicles == 2 and sc.flow.type == "shear" and sc.p == 8
    a, b = sc.vesicles
    assert a.shape == b.shape == "oblate" and a.reduced_volume == 0.85
    assert a.center[0] < 0 < b.center[0] and a.center[2] > 0 > b.center[2]   # they pass each other
    assert sc.time.horizon <= 10 and sc.output.file == "out/default.h5"
    eff = sc.effects()
    assert eff.background_flow and eff.interactions and not eff.periodic
    text = sc.summary()
    assert "2 (oblate x2)" in text and "near/far field" in text and "background flow" in text
    assert str(sc) == text
    assert S.DEFAULT_SCENE_TEXT in sc.text


def test_load_scene_from_file(tmp_path):
    f = tmp_path / "pair.toml"
    f.write_text("[[vesicle]]\n[[vesicle]]\ncenter = [3.0, 0.0, 0.0]\n")
    sc = S.load_scene(f)
    assert sc.output.file == "out/pair.h5" and sc.title == "pair" and sc.source == str(f)
    f.write_text("[[vesicle]]\nradius = -1\n")
    with pytest.raises(SceneError) as exc:
        S.load_scene(f)
    assert str(exc.value) == f"{f}: vesicle[0].radius = -1: must be > 0" and exc.value.key == "vesicle[0].radius"
    with pytest.raises(SceneError, match="not found"):
        S.load_scene(tmp_path / "missing.toml")


# ---------------------------------------------------------------- shapes
@pytest.mark.parametrize("kind", ["oblate", "prolate"])
@pytest.mark.parametrize("v", [0.3, 0.65, 0.85, 0.95, 0.999])
def test_spheroid_axes(kind, v):
    a, b, c = S.spheroid_axes(kind, v)
    assert a == b == 1.0 and (c < 1.0 if kind == "oblate" else c > 1.0)
    # the reduced volume from the closed-form area, recomputed independently by quadrature
    x, w = np.polynomial.legendre.leggauss(200)
    area = 2 * math.pi * np.sum(w * np.sqrt(c * c * (1 - x * x) + x * x) * 1.0) if False else None
    t = np.arccos(x)  # spheroid of revolution: A = 2 pi int sin t sqrt(cos^2 t + c^2 sin^2 t) dt
    area = 2 * math.pi * np.sum(w * np.sqrt(np.cos(t) ** 2 + c * c * np.sin(t) ** 2))
    assert 6 * math.sqrt(math.pi) * (4 / 3 * math.pi * c) / area ** 1.5 == pytest.approx(v, rel=1e-12)


def test_spheroid_axes_edges():
    assert S.spheroid_axes("oblate", 1.0) == (1.0, 1.0, 1.0)
    with pytest.raises(ValueError):
        S.spheroid_axes("oblate", 1.2)
    with pytest.raises(ValueError):
        S.spheroid_axes("disc", 0.8)


def test_biconcave_profile():
    # the published Evans-Fung cell (s = 1) has reduced volume ~0.644
    area, vol = G._biconcave_area_volume(1.0)
    assert G._reduced_volume(area, vol) == pytest.approx(0.644, abs=1e-3)
    for v in (0.6, 0.65, 0.7):
        s = S.biconcave_height_scale(v)
        assert G._reduced_volume(*G._biconcave_area_volume(s)) == pytest.approx(v, rel=1e-12)
    # the sampled surface lies on the profile and inside the enclosing spheroid
    u = G._unit_shape("biconcave", 0.65, None)
    pts = u.surface_points()
    a, b, c = u.axes
    assert np.all(np.sum((pts / [a, b, c]) ** 2, axis=1) <= 1 + 1e-9)
    assert not u.inside(pts * 1.001).any() and u.inside(pts * 0.98).mean() > 0.9
    # scaled to its effective radius: the vesicle's area is 4 pi R0^2
    ves = S.parse_scene("[[vesicle]]\nshape = 'biconcave'\nradius = 2.0").vesicles[0]
    assert ves.scale == pytest.approx(2.0 / math.sqrt(area_of(0.65) / (4 * math.pi)))


def area_of(v):
    return G._biconcave_area_volume(S.biconcave_height_scale(v))[0]


def test_euler_zyz():
    R = S.euler_zyz((30.0, 40.0, 50.0))
    assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(S.euler_zyz((90.0, 0.0, 0.0)) @ [1, 0, 0], [0, 1, 0])        # about z
    assert np.allclose(S.euler_zyz((0.0, 90.0, 0.0)) @ [0, 0, 1], [1, 0, 0])        # about y
    for ang in [(10, 20, 30), (350, 170, 5), (0, 0, 45), (0, 180, 0)]:
        assert np.allclose(S.euler_zyz(G._euler_from_matrix(S.euler_zyz(ang))), S.euler_zyz(ang), atol=1e-12)


# ---------------------------------------------------------------- lattices
def test_regular_lattice_positions_and_order():
    sc = S.parse_scene("[[vesicle]]\ncenter = [-5, 0, 0]\n[[lattice]]\ncount = [3, 2, 2]\n"
                       "spacing = [2.5, 3.0, 4.0]\norigin = [1.0, 2.0, 3.0]\n"
                       "vesicle = { shape = 'oblate', reduced_volume = 0.9, bending_modulus = 0.05 }\n")
    assert sc.n_vesicles == 1 + 12
    lat = sc.lattices[0]
    assert (lat.kind, lat.first, lat.n, lat.count) == ("regular", 1, 12, (3, 2, 2))
    c = np.array([v.center for v in sc.vesicles[1:]])
    i, j, k = np.meshgrid(range(3), range(2), range(2), indexing="ij")
    expected = np.stack([1 + 2.5 * i, 2 + 3.0 * j, 3 + 4.0 * k], -1).transpose(2, 1, 0, 3).reshape(-1, 3)
    assert np.array_equal(c, expected)                      # x fastest, then y, then z
    assert all(v.shape == "oblate" and v.bending_modulus == 0.05 for v in sc.vesicles[1:])
    assert sc.vesicles[5].label == "lattice[0] #4 at (1, 1, 0)"


def test_regular_lattice_fills_the_periodic_domain():
    sc = S.parse_scene("[domain]\nperiod = 12.0\n[[lattice]]\ncount = [4, 4, 4]\n")
    c = np.array([v.center for v in sc.vesicles])
    assert sc.n_vesicles == 64 and c.min() == 1.5 and c.max() == 10.5
    assert sc.lattices[0].spacing == (3.0, 3.0, 3.0)


def test_lattice_orientation_and_spreads_are_seeded():
    text = ("[[lattice]]\ncount = [3, 3, 3]\nspacing = 4.0\norientation = 'random'\nseed = {seed}\n"
            "radius_spread = 0.2\nbending_modulus_spread = 0.5\nexcess_density_spread = 0.1\n"
            "reduced_volume_spread = 0.05\n"
            "vesicle = {{ shape = 'oblate', reduced_volume = 0.8, excess_density = 2.0 }}\n")
    a, b, c = (S.parse_scene(text.format(seed=s)) for s in (7, 7, 8))
    assert a.vesicles == b.vesicles and a.vesicles != c.vesicles
    r = np.array([v.radius for v in a.vesicles])
    kb = np.array([v.bending_modulus for v in a.vesicles])
    rv = np.array([v.reduced_volume for v in a.vesicles])
    assert np.all((r >= 0.8) & (r <= 1.2)) and r.std() > 0.05
    assert np.all((kb >= 0.005) & (kb <= 0.015)) and np.all((rv >= 0.76) & (rv <= 0.84))
    assert all(1.8 <= v.excess_density <= 2.2 for v in a.vesicles)
    rots = np.array([v.rotation for v in a.vesicles])
    assert len({tuple(x) for x in rots}) == 27 and np.all((rots[:, 1] >= 0) & (rots[:, 1] <= 180))


def test_uniform_random_orientations():
    # uniform on SO(3): the rotated symmetry axis has a uniform z-component
    sc = S.parse_scene("[[lattice]]\ncount = [10, 10, 10]\nspacing = 3.0\norientation = 'random'\n"
                       "vesicle = { shape = 'prolate', reduced_volume = 0.9 }")
    z = np.array([v.rotation_matrix()[:, 2] for v in sc.vesicles])
    assert abs(z[:, 2].mean()) < 0.06 and abs(np.mean(z[:, 2] ** 2) - 1 / 3) < 0.03


@pytest.mark.parametrize("shape, phi", [("sphere", 0.5), ("oblate", 0.45), ("prolate", 0.4), ("biconcave", 0.35)])
def test_random_packing_periodic(shape, phi):
    ves = "{ shape = 'sphere' }" if shape == "sphere" else (
        "{ shape = 'biconcave' }" if shape == "biconcave" else f"{{ shape = '{shape}', reduced_volume = 0.85 }}")
    text = f"[domain]\nperiod = 7.0\n[[lattice]]\nvolume_fraction = {phi}\nseed = 4\nvesicle = {ves}\n"
    sc = S.parse_scene(text)
    lat = sc.lattices[0]
    one = sc.vesicles[0].volume
    assert lat.kind == "random" and lat.periodic and lat.n == sc.n_vesicles > 20
    assert abs(lat.achieved_volume_fraction - phi) <= 0.5 * one / 7.0 ** 3 + 1e-12
    assert sc.volume_fraction == pytest.approx(lat.achieved_volume_fraction)
    assert S.find_overlaps(sc.vesicles, 7.0) == []
    c = np.array([v.center for v in sc.vesicles])
    assert c.min() >= 0.0 and c.max() < 7.0
    if shape == "sphere":      # brute force: minimum-image distances >= 2 R
        d = c[:, None] - c[None]
        d -= 7.0 * np.round(d / 7.0)
        r = np.linalg.norm(d, axis=-1) + 10 * np.eye(len(c))
        assert r.min() >= 2.0
    assert S.parse_scene(text).vesicles == sc.vesicles                  # reproducible
    other = S.parse_scene(text.replace("seed = 4", "seed = 5")).vesicles
    assert [v.center for v in other] != [v.center for v in sc.vesicles]


def test_periodic_packing_keeps_minimum_image_gaps_across_the_faces():
    """64-ish biconcave cells (v = 0.65) at 30 % in a periodic cube, gap 0.08: the achieved fraction
    (volumes of the simulated SH shapes) is the requested one to half a cell, and the surfaces,
    sampled on a fine grid and compared over all 27 images by brute force, keep at least the
    gap the packing guarantees: each enclosing spheroid inflated by 1 + gap contains the spheroid
    grown by gap * (its smallest semi-axis), so two cells are >= gap (a_i + a_j) apart.  Many
    close pairs meet across a face."""
    import itertools
    from scipy.spatial import cKDTree
    from vesflow import sph
    from vesflow.simulation import initial_coefficients
    from vesflow.surface import Surface
    L, phi, gap = 8.17, 0.30, 0.08
    sc = S.parse_scene(f"[domain]\nperiod = {L}\n[discretization]\np = 16\n[[lattice]]\nvolume_fraction = {phi}\n"
                       f"gap = {gap}\nseed = 7\nvesicle = {{ shape = 'biconcave', reduced_volume = 0.65 }}\n")
    n = sc.n_vesicles
    c = initial_coefficients(sc)
    vol = Surface(c, 16).volume()
    assert n == 60 and abs(vol.sum() / L ** 3 - phi) <= 0.5 * vol.mean() / L ** 3
    assert sc.lattices[0].achieved_volume_fraction == pytest.approx(vol.sum() / L ** 3, rel=1e-9)
    cen = np.array([v.center for v in sc.vesicles])
    assert cen.min() >= 0.0 and cen.max() < L
    a_min = np.array([min(v._unit.axes) * v.scale for v in sc.vesicles])          # enclosing spheroid
    rb = np.array([v.bounding_radius for v in sc.vesicles])
    P = np.moveaxis(sph.transform(16, 48).synth(c), -2, -1)                         # ~0.08 apart
    trees = [cKDTree(x) for x in P]
    shifts = L * np.array(list(itertools.product((-1, 0, 1), repeat=3)))
    worst, across = np.inf, 0
    for i in range(n):
        for j in range(i + 1, n):
            for s in shifts:
                if np.linalg.norm(cen[j] + s - cen[i]) < rb[i] + rb[j] + 0.3:
                    d = trees[j].query(P[i] - s)[0].min()
                    worst = min(worst, d / (gap * (a_min[i] + a_min[j])))
                    across += int(np.any(s) and d < 0.3)
    assert worst >= 1.0, f"surfaces closer than the guaranteed gap: {worst:.3f} of it"
    assert across >= 10


def test_random_packing_in_a_box_and_by_count():
    sc = S.parse_scene("[[lattice]]\ncount = 40\nvolume_fraction = 0.4\nseed = 2\nradius_spread = 0.2\n"
                       "vesicle = { shape = 'oblate', reduced_volume = 0.8 }\n")
    lat = sc.lattices[0]
    assert sc.n_vesicles == 40 and lat.achieved_volume_fraction == pytest.approx(0.4, rel=1e-12)
    assert S.find_overlaps(sc.vesicles) == []
    side = lat.box[0]
    assert np.allclose(lat.origin, -side / 2)
    ext = np.array([[math.sqrt(np.sum((v.rotation_matrix()[k] * np.array(v.unit_axes()) * v.scale) ** 2))
                     for k in range(3)] for v in sc.vesicles])
    c = np.array([v.center for v in sc.vesicles])
    assert np.all(c - ext >= -side / 2 - 1e-9) and np.all(c + ext <= side / 2 + 1e-9)   # inside the walls
    sc = S.parse_scene("[[lattice]]\nbox = [8.0, 8.0, 6.0]\norigin = [0, 0, 0]\nvolume_fraction = 0.3\n"
                       "vesicle = { shape = 'prolate', reduced_volume = 0.9 }\n")
    lat = sc.lattices[0]
    assert lat.n == round(0.3 * 384 / sc.vesicles[0].volume)
    assert abs(lat.achieved_volume_fraction - 0.3) <= 0.5 * sc.vesicles[0].volume / 384
    assert S.find_overlaps(sc.vesicles) == []


def test_random_packing_fixed_orientation_keeps_rotation():
    sc = S.parse_scene("[[lattice]]\ncount = 30\nvolume_fraction = 0.3\norientation = 'fixed'\n"
                       "vesicle = { shape = 'oblate', reduced_volume = 0.8, rotation = [0, 30, 0] }")
    assert {v.rotation for v in sc.vesicles} == {(0.0, 30.0, 0.0)}
    assert S.find_overlaps(sc.vesicles) == []


def test_unreachable_packing_is_an_error():
    with pytest.raises(SceneError) as exc:
        S.parse_scene("[[lattice]]\ncount = 8\nvolume_fraction = 0.5\nseed = 1\n")   # walls, 8 spheres
    msg = str(exc.value)
    assert msg.startswith("lattice[0].volume_fraction = 0.5: random packing") and "\n" not in msg
    # periodic: biconcave cells at 46 % need their enclosing spheroids (+ 2 % gap) to fill 0.71
    with pytest.raises(SceneError) as exc:
        S.parse_scene("[domain]\nperiod = 8.17\n[[lattice]]\nvolume_fraction = 0.46\nseed = 7\n"
                      "vesicle = { shape = 'biconcave', reduced_volume = 0.65 }\n")
    msg = str(exc.value)
    assert msg.startswith("lattice[0].volume_fraction = 0.46: random packing of 92 vesicles did not converge")
    assert "would fill 0.714 of the periodic cell" in msg and "\n" not in msg


# ---------------------------------------------------------------- overlap test
def _brute_overlap(va, vb, n=400):
    """Dense sampling both ways, finer than the scene's own."""
    def pts(v):
        t = (np.arange(n) + 0.5) * np.pi / n
        f = np.arange(2 * n) * np.pi / n
        T, F = np.meshgrid(t, f, indexing="ij")
        a, b, c = v.unit_axes()
        x = np.stack([a * np.sin(T) * np.cos(F), b * np.sin(T) * np.sin(F), c * np.cos(T)], -1).reshape(-1, 3)
        return np.asarray(v.center) + v.scale * x @ v.rotation_matrix().T

    def inside(v, x):
        xb = (x - np.asarray(v.center)) @ v.rotation_matrix() / v.scale
        return np.sum((xb / np.array(v.unit_axes())) ** 2, axis=1) < 1.0

    return inside(vb, pts(va)).any() or inside(va, pts(vb)).any()


def test_perram_wertheim_agrees_with_sampling():
    rng = np.random.default_rng(3)
    checked = 0
    for _ in range(60):
        axes = [list(rng.uniform(0.4, 1.6, 3)) for _ in range(2)]
        rots = [list(rng.uniform(0, 360, 3)) for _ in range(2)]
        d = rng.normal(size=3)
        d *= rng.uniform(1.0, 3.5) / np.linalg.norm(d)
        ves = [S.Vesicle(shape="ellipsoid", axes=tuple(axes[k]), rotation=tuple(rots[k]),
                         center=tuple(d * k), reduced_volume=0.9) for k in range(2)]
        found = S.find_overlaps(ves)
        c, rot, scale, units, enc, rb = PK._arrays(ves)
        M = PK._ellipsoid_matrices(rot, enc)
        mu = PK._pw(np.array([d]), M[:1], M[1:])[0][0]
        if abs(mu - 1) < 0.01:          # too close to contact for sampling to decide
            continue
        assert bool(found) == _brute_overlap(*ves) == (mu < 1)
        checked += 1
    assert checked > 40


def test_pw_derivatives_match_finite_differences():
    RA, RB = S.euler_zyz((10, 50, 80)), S.euler_zyz((70, 20, 140))
    MA = RA @ np.diag([1.0, 0.5, 0.3]) ** 2 @ RA.T
    MB = RB @ np.diag([0.8, 0.7, 0.2]) ** 2 @ RB.T
    r = np.array([0.7, 0.4, -0.3])
    mu, lam, y = PK._pw(r[None], MA[None], MB[None])
    g_r = lam[0] * (1 - lam[0]) * y[0] / mu[0]
    g_wa = -lam[0] * (1 - lam[0]) ** 2 * np.cross(MA @ y[0], y[0]) / mu[0]
    h = 1e-6
    for k in range(3):
        e = np.eye(3)[k] * h
        fd = (PK._pw((r + e)[None], MA[None], MB[None])[0][0] - PK._pw((r - e)[None], MA[None], MB[None])[0][0]) / (2 * h)
        assert fd == pytest.approx(g_r[k], rel=1e-5, abs=1e-8)
        Rp, Rm = PK._rotvec_matrices(e[None])[0], PK._rotvec_matrices(-e[None])[0]
        fa = (PK._pw(r[None], (Rp @ MA @ Rp.T)[None], MB[None])[0][0]
              - PK._pw(r[None], (Rm @ MA @ Rm.T)[None], MB[None])[0][0]) / (2 * h)
        assert fa == pytest.approx(g_wa[k], rel=1e-5, abs=1e-8)


def test_overlap_thresholds():
    def pair(d, shape="sphere", extra=""):
        return f"[[vesicle]]\nshape = '{shape}'\n{extra}[[vesicle]]\nshape = '{shape}'\n{extra}center = {d}\n"

    S.parse_scene(pair("[2.001, 0, 0]"))
    for bad in ("[2.0, 0, 0]", "[1.999, 0, 0]", "[0, 0, 0]"):
        with pytest.raises(SceneError, match=r"^vesicle\[0\] and vesicle\[1\] overlap"):
            S.parse_scene(pair(bad))
    # stacked red cells: their thickness is 2 * scale * max profile height
    u = G._unit_shape("biconcave", 0.65, None)
    k = 1.0 / u.r0
    thick = 2 * k * np.abs(u.surface_points()[:, 2]).max()
    S.parse_scene(pair(f"[0, 0, {thick * 1.01}]", "biconcave"))
    with pytest.raises(SceneError, match="surface points of one lie inside the other"):
        S.parse_scene(pair(f"[0, 0, {thick * 0.97}]", "biconcave"))
    # a sphere in a red cell's dimple is not an overlap when it clears the surface
    dimple = k * 0.5 * u.s * 0.207
    extra = "radius = 0.2\n"
    text = f"[[vesicle]]\nshape = 'biconcave'\n[[vesicle]]\n{extra}center = [0, 0, {dimple + 0.21}]\n"
    S.parse_scene(text)
    with pytest.raises(SceneError):
        S.parse_scene(text.replace(f"{dimple + 0.21}", f"{dimple + 0.15}"))


def test_overlap_across_the_periodic_boundary_and_self_image():
    with pytest.raises(SceneError, match=r"across the periodic boundary"):
        S.parse_scene("[domain]\nperiod = 10.0\n[[vesicle]]\ncenter = [0.5, 5, 5]\n[[vesicle]]\ncenter = [9.0, 5, 5]\n")
    S.parse_scene("[domain]\nperiod = 10.0\n[[vesicle]]\ncenter = [0.5, 5, 5]\n[[vesicle]]\ncenter = [8.4, 5, 5]\n")
    with pytest.raises(SceneError, match=r"vesicle\[0\]: overlaps its own periodic image"):
        S.parse_scene("[domain]\nperiod = 1.9\n[[vesicle]]\n")
    S.parse_scene("[domain]\nperiod = 2.1\n[[vesicle]]\n")
    with pytest.raises(SceneError, match=r"^vesicle\[0\] and vesicle\[1\] overlap"):   # small cell: all images
        S.parse_scene("[domain]\nperiod = 3.0\n[[vesicle]]\n[[vesicle]]\ncenter = [2.5, 0, 0]\n")


def test_overlap_check_is_fast_for_a_thousand():
    import time
    t = time.perf_counter()
    sc = S.parse_scene("[[lattice]]\ncount = [10, 10, 10]\nspacing = [2.45, 2.45, 0.85]\n"
                       "vesicle = { shape = 'biconcave' }\n")
    assert sc.n_vesicles == 1000 and time.perf_counter() - t < 10.0


# ---------------------------------------------------------------- malformed scenes
WRONG_TYPES = {"string": "abc", "boolean": True, "array": [1.0], "table": {"a": 1}}


def _number_key(section, key, path, ranges, base=BASE):
    """Cases for a number key: every wrong type, then each out-of-range value."""
    out = []
    for tname, bad in WRONG_TYPES.items():
        out.append((f"{path} {tname}", _set(base, section, key, bad), path))
    for bad in ranges:
        out.append((f"{path} = {bad}", _set(base, section, key, bad), path))
    return out


def _set(base, section, key, value):
    d = copy.deepcopy(base)
    node = d
    for s in section:
        node = node[s]
    if value is _DEL:
        del node[key]
    else:
        node[key] = value
    return d


_DEL = object()


def _misspell(k):
    return k[:-1] + k[-1] * 2 if len(k) > 3 else k + "x"


def _malformed_cases():
    cases = []
    nan, inf = float("nan"), float("inf")
    # scalar sections
    for section, key, ranges in [
        (("flow",), "rate", [nan, inf]),
        (("fluid",), "viscosity", [0.0, -1.0, nan]),
        (("time",), "horizon", [0.0, -5.0, inf]),
        (("time",), "dt", [0.0, -0.1, 20.0]),
        (("repulsion",), "radius", [0.0, -0.02]),
        (("output",), "every", [0.0, -1.0]),
    ]:
        cases += _number_key(section, key, f"{section[0]}.{key}", ranges)
    cases += _number_key(("domain",), "period", "domain.period", [0.0, -10.0, nan], base=PERIODIC)
    cases += _number_key(("flow",), "amplitude", "flow.amplitude", [nan, -inf], base=PERIODIC)
    pois = _set(_set(BASE, ("flow",), "type", "poiseuille"), ("flow",), "radius", 5.0)
    cases += _number_key(("flow",), "radius", "flow.radius", [0.0, -1.0], base=pois)
    for bad in ["abc", True, 16.0, 1, 65, -3, [16]]:
        cases.append((f"p = {bad!r}", _set(BASE, ("discretization",), "p", bad), "discretization.p"))
    for bad in [[0, 0], [0, 0, "z"], [0, 0, True], "down", 9.8, [0, 0, nan], [0, 0, 0, 1]]:
        cases.append((f"g = {bad!r}", _set(BASE, ("gravity",), "g", bad), "gravity.g"))
    for bad in ["vortex", "Shear", 1, True, ["shear"]]:
        cases.append((f"flow.type = {bad!r}", _set(BASE, ("flow",), "type", bad), "flow.type"))
    for bad in [3, True, "out/x.vtk", "", "out/x"]:
        cases.append((f"output.file = {bad!r}", _set(BASE, ("output",), "file", bad), "output.file"))
    cases.append(("title = 3", _set(BASE, (), "title", 3), "title"))
    # unknown and misspelt keys in every table
    for section in ["flow", "fluid", "gravity", "discretization", "time", "repulsion", "output"]:
        for key in list(BASE[section]):
            d = copy.deepcopy(BASE)
            d[section][_misspell(key)] = d[section].pop(key)
            cases.append((f"misspelt {section}.{key}", d, f"{section}.{_misspell(key)}"))
        cases.append((f"unknown {section}.colour", _set(BASE, (section,), "colour", 1), f"{section}.colour"))
    for key in ["flw", "vesicles", "lattices", "domian", "gravitation", "solver"]:
        cases.append((f"unknown top {key}", _set(BASE, (), key, {"x": 1}), key))
    # missing required keys
    cases.append(("missing flow.type", _set(BASE, ("flow",), "type", _DEL), "flow.type"))
    cases.append(("missing flow.rate", _set(BASE, ("flow",), "rate", _DEL), "flow.rate"))
    cases.append(("missing gravity.g", _set(BASE, ("gravity",), "g", _DEL), "gravity.g"))
    cases.append(("missing domain.period", _set(PERIODIC, ("domain",), "period", _DEL), "domain.period"))
    cases.append(("missing amplitude", _set(PERIODIC, ("flow",), "amplitude", _DEL), "flow.amplitude"))
    cases.append(("missing poiseuille radius", _set(pois, ("flow",), "radius", _DEL), "flow.radius"))
    cases.append(("taylor_green without domain", _set(BASE, ("flow",), "type", "taylor_green"), "flow"))
    cases.append(("shear in a domain", _set(_set(PERIODIC, (), "flow", {"type": "shear", "rate": 1.0}),
                                             (), "vesicle", PERIODIC["vesicle"]), "flow.type"))
    cases.append(("rate for taylor_green", _set(PERIODIC, ("flow",), "rate", 1.0), "flow.rate"))
    cases.append(("radius for shear", _set(BASE, ("flow",), "radius", 1.0), "flow.radius"))
    cases.append(("amplitude for shear", _set(BASE, ("flow",), "amplitude", 1.0), "flow.amplitude"))
    cases.append(("no vesicles", {k: v for k, v in BASE.items() if k not in ("vesicle", "lattice")}, "vesicle"))
    cases.append(("flow not a table", _set(BASE, (), "flow", "shear"), "flow"))
    cases.append(("vesicle not array", {**BASE, "vesicle": 3}, "vesicle"))
    # vesicle keys (in vesicle[1], an ellipsoid, and vesicle[0], an oblate)
    vnum = {"radius": [0.0, -1.0, nan], "bending_modulus": [0.0, -0.01, inf],
            "viscosity_contrast": [0.0, -2.0], "excess_density": [nan, inf]}
    for key, ranges in vnum.items():
        cases += _number_key(("vesicle", 1), key, f"vesicle[1].{key}", ranges)
    for key in ["center", "rotation"]:
        for bad in [[0, 0], "origin", 1.0, [0, 0, "a"], [0, 0, True], [0, 0, nan], [[0], 0, 0]]:
            cases.append((f"vesicle {key} = {bad!r}", _set(BASE, ("vesicle", 1), key, bad), f"vesicle[1].{key}"))
    for bad in [[1, 1], [1, 1, 0], [1, -1, 1], "big", [1, 1, True], 2.0]:
        cases.append((f"axes = {bad!r}", _set(BASE, ("vesicle", 1), "axes", bad), "vesicle[1].axes"))
    for bad in [1.2, 1.0, 0.0, -0.5, "0.85", True, [0.85]]:
        cases.append((f"v = {bad!r}", _set(BASE, ("vesicle", 0), "reduced_volume", bad), "vesicle[0].reduced_volume"))
    for bad in ["oblat", "disc", "Sphere", 3, True]:
        cases.append((f"shape = {bad!r}", _set(BASE, ("vesicle", 0), "shape", bad), "vesicle[0].shape"))
    for key in list(BASE["vesicle"][1]):
        d = copy.deepcopy(BASE)
        d["vesicle"][1][_misspell(key)] = d["vesicle"][1].pop(key)
        cases.append((f"misspelt vesicle.{key}", d, f"vesicle[1].{_misspell(key)}"))
    cases.append(("missing v", _set(BASE, ("vesicle", 0), "reduced_volume", _DEL), "vesicle[0].reduced_volume"))
    cases.append(("missing axes", _set(BASE, ("vesicle", 1), "axes", _DEL), "vesicle[1].axes"))
    cases.append(("axes on oblate", _set(BASE, ("vesicle", 0), "axes", [1, 1, 1]), "vesicle[0].axes"))
    cases.append(("v on ellipsoid", _set(BASE, ("vesicle", 1), "reduced_volume", 0.9), "vesicle[1].reduced_volume"))
    bic = _set(_set(BASE, ("vesicle", 0), "shape", "biconcave"), ("vesicle", 0), "reduced_volume", 0.65)
    for bad in [0.5, 0.75, 0.85]:
        cases.append((f"biconcave v = {bad}", _set(bic, ("vesicle", 0), "reduced_volume", bad),
                      "vesicle[0].reduced_volume"))
    # lattice keys
    L = ("lattice", 0)
    for bad in [[2, 2], [2, 2, 0], [2, 2, -1], [2, 2, 1.5], "2x2", [2, 2, True], 4]:
        cases.append((f"count = {bad!r}", _set(BASE, L, "count", bad), "lattice[0].count"))
    for bad in [0.0, -3.0, [3, 3], [3, 3, 0], "3", True]:
        cases.append((f"spacing = {bad!r}", _set(BASE, L, "spacing", bad), "lattice[0].spacing"))
    for bad in [[0, 0], "here", [0, 0, "a"]]:
        cases.append((f"origin = {bad!r}", _set(BASE, L, "origin", bad), "lattice[0].origin"))
    for bad in [-1, 1.5, "one", True]:
        cases.append((f"seed = {bad!r}", _set(BASE, L, "seed", bad), "lattice[0].seed"))
    for bad in ["randm", "any", 1]:
        cases.append((f"orientation = {bad!r}", _set(BASE, L, "orientation", bad), "lattice[0].orientation"))
    for key in ["radius_spread", "bending_modulus_spread", "viscosity_contrast_spread", "excess_density_spread"]:
        for bad in [-0.1, 1.0, 2.0, "big", True]:
            cases.append((f"{key} = {bad!r}", _set(BASE, L, key, bad), f"lattice[0].{key}"))
    for bad in [0.2, -0.01]:
        cases.append((f"v spread {bad}", _set(BASE, L, "reduced_volume_spread", bad), "lattice[0].reduced_volume_spread"))
    for key in list(BASE["lattice"][0]):
        d = copy.deepcopy(BASE)
        d["lattice"][0][_misspell(key)] = d["lattice"][0].pop(key)
        cases.append((f"misspelt lattice.{key}", d, f"lattice[0].{_misspell(key)}" if key != "count"
                      else "lattice[0]"))
    cases.append(("missing spacing", _set(BASE, L, "spacing", _DEL), "lattice[0].spacing"))
    cases.append(("template center", _set(BASE, L + ("vesicle",), "center", [0, 0, 0]), "lattice[0].vesicle.center"))
    cases.append(("template v", _set(BASE, L + ("vesicle",), "reduced_volume", 1.5), "lattice[0].vesicle.reduced_volume"))
    cases.append(("template shape", _set(BASE, L + ("vesicle",), "shape", "cube"), "lattice[0].vesicle.shape"))
    cases.append(("template radiuss", _set(BASE, L + ("vesicle",), "radiuss", 1.0), "lattice[0].vesicle.radiuss"))
    cases.append(("template not a table", _set(BASE, L, "vesicle", "oblate"), "lattice[0].vesicle"))
    cases.append(("random rotation", _set(_set(BASE, L, "orientation", "random"), L + ("vesicle",), "rotation",
                                          [0, 10, 0]), "lattice[0].vesicle.rotation"))
    cases.append(("box in regular", _set(BASE, L, "box", [5, 5, 5]), "lattice[0].box"))
    cases.append(("gap in regular", _set(BASE, L, "gap", 0.1), "lattice[0].gap"))
    rnd = {"vesicle": [], "lattice": [{"volume_fraction": 0.2, "count": 10}]}
    for bad in [0.0, 0.6, -0.1, 1.0, "dense", True]:
        cases.append((f"phi = {bad!r}", _set(rnd, L, "volume_fraction", bad), "lattice[0].volume_fraction"))
    for bad in [[2, 2, 2], 0, -3, 2.5, "ten"]:
        cases.append((f"random count = {bad!r}", _set(rnd, L, "count", bad), "lattice[0].count"))
    for bad in [-0.1, 0.9, "wide"]:
        cases.append((f"gap = {bad!r}", _set(rnd, L, "gap", bad), "lattice[0].gap"))
    cases.append(("spacing in random", _set(rnd, L, "spacing", 2.0), "lattice[0].spacing"))
    cases.append(("box and count", _set(rnd, L, "box", [5.0, 5.0, 5.0]), "lattice[0].count"))
    for bad in [[5, 5], [5, 5, 0], "big"]:
        cases.append((f"box = {bad!r}", _set(_set(rnd, L, "count", _DEL), L, "box", bad), "lattice[0].box"))
    cases.append(("no box nor count", _set(rnd, L, "count", _DEL), "lattice[0]"))
    per = {"domain": {"period": 10.0}, "lattice": [{"volume_fraction": 0.2, "count": 10}]}
    cases.append(("count in periodic packing", per, "lattice[0].count"))
    cases.append(("origin in periodic packing", _set(_set(per, L, "count", _DEL), L, "origin", [0, 0, 0]),
                  "lattice[0].origin"))
    # overlapping pairs
    for k, (shape_a, shape_b, dx) in enumerate([
            ("sphere", "sphere", 1.0), ("sphere", "sphere", 1.9999), ("oblate", "oblate", 2.0),
            ("prolate", "sphere", 1.6), ("ellipsoid", "ellipsoid", 1.2), ("biconcave", "biconcave", 2.0),
            ("biconcave", "sphere", 1.5), ("sphere", "biconcave", 1.6), ("oblate", "biconcave", 2.0)]):
        def ves(shape, cx):
            v = {"shape": shape, "center": [cx, 0.0, 0.0]}
            if shape in ("oblate", "prolate"):
                v["reduced_volume"] = 0.8
            if shape == "ellipsoid":
                v["axes"] = [1.5, 1.0, 0.5]
            return v
        d = {"vesicle": [ves("sphere", -20.0), ves(shape_a, 0.0), ves(shape_b, dx)]}
        cases.append((f"overlap {shape_a}-{shape_b} at {dx}", d, "vesicle[1] and vesicle[2] overlap"))
    d = copy.deepcopy(BASE)
    d["lattice"][0]["origin"] = [3.0, 0.5, 0.0]
    cases.append(("lattice overlaps a vesicle", d, "vesicle[1] and vesicle[2] (lattice[0] #0 at (0, 0, 0)) overlap"))
    d = copy.deepcopy(BASE)
    d["lattice"][0]["spacing"] = 1.5
    cases.append(("lattice too tight", d, "vesicle[2] (lattice[0] #0 at (0, 0, 0)) and vesicle[3]"))
    return cases


SYNTAX = [
    ("missing bracket", "[flow\ntype = 'shear'\n", 1),
    ("missing closing bracket of array", "[[vesicle]]\ncenter = [1, 2, 3\n", None),
    ("missing double bracket", "[[vesicle]\n", 1),
    ("unclosed string", "title = \"abc\n[[vesicle]]\n", 1),
    ("missing value", "[[vesicle]]\nradius =\n", 2),
    ("missing equals", "[[vesicle]]\nradius 1.0\n", 2),
    ("duplicate key", "[[vesicle]]\nradius = 1.0\nradius = 2.0\n", 3),
    ("duplicate table", "[flow]\ntype='shear'\n[flow]\nrate=1\n", 3),
    ("bare word value", "[[vesicle]]\nshape = oblate\n", 2),
    ("comma decimal", "[[vesicle]]\nradius = 1,5\n", 2),
    ("table redefined as array", "[vesicle]\n[[vesicle]]\n", 2),
    ("trailing garbage", "[[vesicle]]\nradius = 1.0 2.0\n", 2),
]


@pytest.mark.parametrize("name, data, path", _malformed_cases(), ids=lambda x: x if isinstance(x, str) else "")
def test_malformed_scene(name, data, path):
    with pytest.raises(SceneError) as exc:
        S.parse_scene(to_toml(data))
    msg = str(exc.value)
    assert "\n" not in msg and path in msg, msg
    assert not isinstance(exc.value, OptionError)


@pytest.mark.parametrize("name, text, line", SYNTAX, ids=[s[0] for s in SYNTAX])
def test_toml_syntax_errors(name, text, line, tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(SceneError) as exc:
        S.load_scene(f)
    msg = str(exc.value)
    where = f"{f}: end of file: " if line is None else f"{f}: line {line}, column "
    assert "\n" not in msg and msg.startswith(where) and "TOML syntax error" in msg


def test_enough_malformed_cases_and_messages_name_the_range():
    assert len(_malformed_cases()) + len(SYNTAX) >= 200
    msgs = {}
    for name, data, path in _malformed_cases():
        with pytest.raises(SceneError) as exc:
            S.parse_scene(to_toml(data))
        msgs[name] = str(exc.value)
    assert msgs["vesicle[0].reduced_volume = 1.2" if False else "v = 1.2"] == \
        "vesicle[0].reduced_volume = 1.2: must be in (0, 1)"
    assert msgs["p = 65"] == "discretization.p = 65: must be an integer in [2, 64]"
    assert msgs["p = True"] == "discretization.p = true: expected an integer, got boolean"
    assert msgs["vesicle[1].radius boolean"] == "vesicle[1].radius = true: expected a number, got boolean"
    assert msgs["misspelt vesicle.radius"] == 'vesicle[1].radiuss: unknown key; did you mean "radius"?'
    assert msgs["shape = 'oblat'"].endswith('did you mean "oblate"?')
    assert msgs["time.dt = 20.0"] == "time.dt = 20.0: must be <= time.horizon = 10"
    assert "centres 1 apart" in msgs["overlap sphere-sphere at 1.0"] and "need about 2" in msgs["overlap sphere-sphere at 1.0"]


# ---------------------------------------------------------------- options
def test_option_overrides():
    sc = parse(BASE)
    new = O.apply_overrides(sc, O.dict_getter({"-ves_p": 8, "-ts_max_time": "20", "ts_dt": 0.5,
                                               "-ves_repulsion_radius": "0.05", "-ves_output_every": 2}))
    assert new.p == 8 and new.time == S.Time(20.0, 0.5) and new.repulsion.radius == 0.05
    assert new.output.every == 2.0 and new.vesicles == sc.vesicles and new.flow == sc.flow
    assert sc.p == 12                                                    # the original is unchanged
    assert O.apply_overrides(sc, O.dict_getter({})) is sc
    off = O.apply_overrides(sc, O.dict_getter({"-ves_repulsion_radius": 0}))
    assert off.repulsion is None and not off.effects().repulsion
    on = O.apply_overrides(S.parse_scene("[[vesicle]]"), O.argv_getter(["-ves_repulsion_radius", "0.03"]))
    assert on.repulsion.radius == 0.03 and on.effects().repulsion
    # derived defaults follow a new horizon unless they were given
    plain = S.parse_scene("[[vesicle]]")
    h = O.apply_overrides(plain, O.dict_getter({"-ves_horizon": 0.5}))
    assert h.time == S.Time(0.5, 0.05) and h.output.every == pytest.approx(0.005)
    h = O.apply_overrides(sc, O.dict_getter({"-ves_horizon": 50}))
    assert h.time == S.Time(50.0, 0.1) and h.output.every == 1.0


@pytest.mark.parametrize("opts, name", [
    ({"-ves_p": 100}, "-ves_p"), ({"-ves_p": "abc"}, "-ves_p"), ({"-ves_p": "8.5"}, "-ves_p"),
    ({"-ves_p": True}, "-ves_p"), ({"-ts_dt": "-1"}, "-ts_dt"), ({"-ts_dt": 50}, "-ts_dt"),
    ({"-ts_max_time": 0.01}, "-ts_max_time"), ({"-ts_max_time": "nan"}, "-ts_max_time"),
    ({"-ves_horizon": 1, "-ts_max_time": 2}, "-ves_horizon"), ({"-ves_repulsion_radius": -1}, "-ves_repulsion_radius"),
    ({"-ves_output_every": 0}, "-ves_output_every"), ({"-ves_output_every": "often"}, "-ves_output_every"),
])
def test_bad_override_values(opts, name):
    with pytest.raises(OptionError) as exc:
        O.apply_overrides(parse(BASE), O.dict_getter(opts))
    msg = str(exc.value)
    assert msg.startswith(name + " = ") and "\n" not in msg and exc.value.key == name
    assert isinstance(exc.value, SceneError)                 # exit status 2 as well


def test_read_options_defaults_and_values():
    sc = parse(BASE)
    o = O.read_options(O.dict_getter({}), sc)
    assert (o.q_self, o.q_near, o.q_far, o.q_max) == (24, 24, 24, 48) and o.checkpoint_every == 1.0
    assert o.quad_tol == 0.0
    assert O.read_options(O.dict_getter({"-ves_q_far": 30}), sc).q_near == 30     # one grid for both
    assert o.far == "auto" and o.ts_type == "sdc" and o.adapt == "sweeps" and o.adapt_beta == 0.75 and o.reparam is True
    assert o.reparam_dtau_max == 1e-3 and o["-ves_correct"] == "area_volume" and o["coupling"] == "implicit"
    assert o.given == frozenset()
    g = O.argv_getter(["-ves_q_self", "30", "-ves_far", "direct", "-ves_reparam", "off", "-ts_monitor",
                       "-ves_adapt", "invariants", "-ves_adapt_tol", "1e-3", "-ksp_rtol", "1e-8"])
    o = O.read_options(g, sc)
    assert o.q_self == 30 and o.far == "direct" and o.reparam is False and o.ts_monitor is True
    assert o.adapt == "invariants" and o.adapt_tol == 1e-3
    assert o.given == {"-ves_q_self", "-ves_far", "-ves_reparam", "-ts_monitor", "-ves_adapt", "-ves_adapt_tol"}
    assert "-ves_far" in o.as_argv() and o.as_argv()[o.as_argv().index("-ves_far") + 1] == "direct"
    with pytest.raises(AttributeError):
        o.q_self = 3


@pytest.mark.parametrize("opts, name", [
    ({"-ves_q_self": 8}, "-ves_q_self"), ({"-ves_q_far": "x"}, "-ves_q_far"), ({"-ves_far": "fmn"}, "-ves_far"),
    ({"-ves_q_near": 24, "-ves_q_far": 30}, "-ves_q_far"), ({"-ves_quad_tol": -1}, "-ves_quad_tol"),
    ({"-ves_quad_tol": 1e-4, "-ves_q_self": 60}, "-ves_q_self"), ({"-ves_q_max": 4}, "-ves_q_max"),
    ({"-ves_adapt": "yes"}, "-ves_adapt"), ({"-ves_adapt_tol": 0}, "-ves_adapt_tol"),
    ({"-ves_adapt_beta": 1.5}, "-ves_adapt_beta"), ({"-ves_reparam": "maybe"}, "-ves_reparam"),
    ({"-ves_dt_min": 1, "-ves_dt_max": 0.5}, "-ves_dt_min"), ({"-ves_reparam_tol": 0.1}, "-ves_reparam_tol"),
    ({"-ves_correct": "area"}, "-ves_correct"), ({"-ves_coupling": 3}, "-ves_coupling"),
    ({"-ves_max_rejects": 0}, "-ves_max_rejects"), ({"-ts_max_steps": -1}, "-ts_max_steps"),
    ({"-ves_near_factor": "inf"}, "-ves_near_factor"), ({"-ves_checkpoint_every": -1}, "-ves_checkpoint_every"),
    ({"-ves_reparam_attenuation": "n3"}, "-ves_reparam_attenuation"),
])
def test_bad_option_values(opts, name):
    with pytest.raises(OptionError) as exc:
        O.read_options(O.dict_getter(opts), parse(BASE))
    msg = str(exc.value)
    assert msg.startswith(name + " = ") and "\n" not in msg


def test_far_suggestion_and_unknown_options():
    with pytest.raises(OptionError, match="did you mean fmm"):
        O.read_options(O.dict_getter({"-ves_far": "fmn"}))
    with pytest.raises(OptionError, match="-ves_qself: unknown vesflow option; did you mean -ves_q_self"):
        O.check_unknown(["-ksp_rtol", "-ves_qself"])
    O.check_unknown(["-ksp_rtol", "ves_p", "-ts_dt"])
    with pytest.raises(OptionError, match="needs a value"):
        O.argv_getter(["-ves_p"])("-ves_p", int, None)


def test_petsc_style_getter():
    class FakeOptions:               # the part of petsc4py's PETSc.Options that petsc_getter uses
        def __init__(self, d):
            self.d = d

        def hasName(self, k):
            return k in self.d

        def getString(self, k, default=None):
            return self.d.get(k, default)

    g = O.petsc_getter(FakeOptions({"ves_p": "10", "ves_reparam": None, "ts_max_time": "3"}))
    sc = O.apply_overrides(parse(BASE), g)
    assert sc.p == 10 and sc.time.horizon == 3.0
    assert O.read_options(g, sc).reparam is True


def test_help_text_lists_every_option_with_its_default():
    text = O.help_text()
    for o in O.REGISTRY:
        line = next(l for l in text.splitlines() if l.strip().startswith(o.name + " "))
        assert f"default: {o.shown_default}" in line
        assert o.name.startswith(("-ves_", "-ts_"))
    assert len({o.key for o in O.REGISTRY}) == len(O.REGISTRY)


def test_docs_list_every_key_and_option():
    options = (ROOT / "docs" / "reference" / "options.md").read_text()
    for o in O.REGISTRY:
        assert f"`{o.name}`" in options, o.name
    doc = (ROOT / "docs" / "reference" / "scene.md").read_text()
    keys = set(SP._TOP) | set(SP._VESICLE_KEYS) | set(SP._LATTICE_KEYS) | {"period", "rate", "amplitude", "viscosity",
                                                                        "horizon", "dt", "every", "file", "p"}
    for k in keys:
        assert f"`{k}`" in doc or f"`[{k}]`" in doc or f"`[[{k}]]`" in doc, k
