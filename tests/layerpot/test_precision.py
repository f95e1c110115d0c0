"""Memory options -ves_self_precision / -ves_pc_precision single (docs/explanation/parallel.md, "Memory")."""
import numpy as np
import pytest

petsc4py = pytest.importorskip("petsc4py")
petsc4py.init([])

from vesflow import options as O, scene as S, shapes  # noqa: E402
from vesflow.costs import estimate  # noqa: E402
from vesflow.errors import OptionError  # noqa: E402
from vesflow.layerpot.evaluator import LayerPotentials, Settings  # noqa: E402
from vesflow.layerpot.singular import SelfOperators  # noqa: E402
from vesflow.operator import VesicleParams  # noqa: E402
from vesflow.stepper import Physics, Stepper  # noqa: E402
from vesflow.surface import Surface  # noqa: E402

P = 8


def _pair(lam=1.0):
    c = np.stack([shapes.make_shape("oblate", P, reduced_volume=0.85, center=(-1.6, 0, 0.3)),
                  shapes.make_shape("oblate", P, reduced_volume=0.85, center=(1.6, 0, -0.3))])
    return c, VesicleParams([0.01] * 2, [lam] * 2, [0.0] * 2)


def test_single_self_operators_are_float32_rounding_of_double_at_half_the_memory():
    c, _ = _pair()
    d = SelfOperators(c, P, want_double=True)
    s = SelfOperators(c, P, want_double=True, dtype=np.float32)
    assert s.single.dtype == np.float32 and s.double.dtype == np.float32
    assert s.nbytes * 2 == d.nbytes
    assert np.array_equal(s.single, d.single.astype(np.float32))
    f = np.random.default_rng(0).standard_normal((2, 3, s.single.shape[1] // 3))
    ud, us = SelfOperators.apply(d.single, f), SelfOperators.apply(s.single, f)
    assert us.dtype == np.float64
    rel = np.abs(us - ud).max() / np.abs(ud).max()
    assert 1e-10 < rel < 1e-6          # float32 rounding (~6e-8), not zero: the product is float32


def test_layer_potentials_single_self_part_and_error_estimate():
    c, _ = _pair()
    surf = Surface(c, P)
    lp_d = LayerPotentials(surf, lam=0.2)
    lp_s = LayerPotentials(surf, lam=0.2, settings=Settings(self_precision="single"))
    f = np.random.default_rng(1).standard_normal((2, 3, lp_d.self_ops.single.shape[1] // 3))
    ud, us = lp_d.apply(f, f), lp_s.apply(f, f)
    rel = np.abs(us - ud).max() / np.abs(ud).max()
    assert 1e-10 < rel < 1e-6
    ed, es = lp_d.error_estimate(), lp_s.error_estimate()
    assert abs(es["self"] - ed["self"]) < 1e-6 and es["near"] == ed["near"]
    with pytest.raises(ValueError, match="self_precision = 'half'"):
        Settings(self_precision="half")


# measured (p = 8 pair in shear, lambda = 5, 3 steps of 0.05, rtol 1e-8, 6-7 iterations per
# solve in all four): the centroid displacement differs from double by 2.3e-8 (self single),
# 3.1e-10 (pc single, fgmres), 7.6e-9 (both), relative; bound 1e-6
@pytest.mark.parametrize("self_prec,pc_prec", [("single", "double"), ("double", "single"), ("single", "single")])
def test_pair_in_shear_single_precision_close_to_double(self_prec, pc_prec):
    runs = {}
    for name, sp, pp in (("double", "double", "double"), ("single", self_prec, pc_prec)):
        c, prm = _pair(lam=5.0)
        st = Stepper(c, P, prm, Physics(flow="shear", flow_args={"rate": 1.0}),
                     Settings(self_precision=sp), pc_precision=pp)
        x0 = Surface(c, P).centroid()
        its = [st.step(0.05).its for _ in range(3)]
        runs[name] = (st.surface.centroid() - x0, its, st)
    dx_d, its_d, st_d = runs["double"]
    dx_s, its_s, st_s = runs["single"]
    rel = np.abs(dx_s - dx_d).max() / np.abs(dx_d).max()
    assert 0 < rel < 1e-6, rel
    assert abs(sum(its_s) - sum(its_d)) <= 3
    lp = st_s.lp_last
    want_self = np.float32 if self_prec == "single" else np.float64
    assert lp.self_ops.single.dtype == want_self and lp.self_ops.double.dtype == want_self
    pc = st_s.default_pc_context()
    want_pc = np.float32 if pc_prec == "single" else np.float64
    assert all(lu.dtype == want_pc for lu, _ in pc.lu)
    assert all(a.dtype == want_pc for parts in pc.parts for a in parts)
    assert st_s.default_ksp_type() == ("fgmres" if pc_prec == "single" else "gmres")


def test_options_are_read_checked_and_shown():
    sc = S.default_scene()
    opts = O.read_options(O.dict_getter({"ves_self_precision": "single", "ves_pc_precision": "single"}), sc)
    assert opts["self_precision"] == "single" and opts["pc_precision"] == "single"
    assert O.read_options(O.dict_getter({}), sc)["self_precision"] == "double"
    with pytest.raises(OptionError, match="-ves_self_precision = half"):
        O.read_options(O.dict_getter({"ves_self_precision": "half"}), sc)
    with pytest.raises(OptionError, match="-ves_pc_precision = float"):
        O.read_options(O.dict_getter({"ves_pc_precision": "float"}), sc)
    text = O.help_text()
    assert "-ves_self_precision" in text and "-ves_pc_precision" in text


def test_cost_model_memory_halves_with_single_precision():
    sc = S.default_scene()
    d = estimate(sc, O.read_options(O.dict_getter({}), sc), near=False)
    s = estimate(sc, O.read_options(O.dict_getter({"ves_self_precision": "single", "ves_pc_precision": "single"}),
                                    sc), near=False)
    assert s.mem_self * 2 == d.mem_self and s.mem_pc * 2 == d.mem_pc and s.mem_pc_max * 2 == d.mem_pc_max
    assert "float32" in str(s) and "float32" not in str(d)
