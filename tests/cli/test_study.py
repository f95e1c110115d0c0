"""The accuracy-cost study (issue 7): its bookkeeping (fast) and the cheap variant (slow)."""
import csv

import numpy as np
import pytest

from vesflow import study
from vesflow.errors import SceneError


def test_parse_case_and_errors():
    assert study.parse_case("12,0.01,0.04") == study.Case(12, 0.01, 0.04)
    assert study.parse_case("8,1e-2") == study.Case(8, 0.01, 0.0)
    assert study.parse_case("8,1e-2,0,sdc") == study.Case(8, 0.01, 0.0, "sdc")
    assert study.Case(8, 0.01).key == "p8_tol0.01_R0" and study.Case(8, 0.01, 0, "sdc").key == "p8_tol0.01_R0_sdc"
    assert study.parse_case("12,1e-2,0,sdc-radau4x3").key == "p12_tol0.01_R0_sdc-radau4x3"
    assert study.scheme_options("sdc-radau4x3") == {"-ts_type": "sdc", "-ves_adapt": "sweeps", "-ts_sdc_quadrature":
                                                    "radau", "-ts_sdc_nodes": 4, "-ts_sdc_sweeps": 3}
    assert study.scheme_options("sdc-lobatto3") == {"-ts_type": "sdc", "-ves_adapt": "sweeps",
                                                    "-ts_sdc_quadrature": "lobatto", "-ts_sdc_nodes": 3}
    assert study.scheme_options("euler") == {"-ts_type": "euler", "-ves_adapt": "doubling"}
    for bad in ["8", "8.5,0.1", "8,-1", "8,0.1,-0.1", "a,b", "1,0.1", "8,0.1,0,rk4", "8,0.1,0,sdc-gauss3",
                "8,0.1,0,euler-radau3", "8,0.1,0,sdc-radau"]:
        with pytest.raises(SceneError, match="expected p,tol"):
            study.parse_case(bad)


def test_position_error_is_normalized_by_length():
    ref = {"final": {"centroid": [[0, 0, 0], [3, 0, 0]], "length": [2.0, 4.0]}}
    res = {"final": {"centroid": [[0.1, 0, 0], [3, 0.2, 0]]}}
    assert study.position_error(res, ref) == pytest.approx(0.05)
    assert study.position_error({"final": None}, ref) is None


def test_pareto_front():
    rows = [{"cpu": 1.0, "error": 0.1}, {"cpu": 2.0, "error": 0.2}, {"cpu": 3.0, "error": 0.01},
            {"cpu": 0.5, "error": None}]
    assert [r["cpu"] for r in study.pareto(rows)] == [1.0, 3.0]


def test_cli_study_bad_input_exits_2(capsys):
    from vesflow import cli
    assert cli.main(["study", "nonsense"]) == 2
    assert cli.main(["study", "accuracy-cost", "--case", "x"]) == 2
    assert "expected p,tol" in capsys.readouterr().err


@pytest.mark.slow
def test_quick_study(tmp_path):
    """The cheap variant: 4 cases against a p = 10 reference over 1.5 time units."""
    rows, ref = study.accuracy_cost("runs/accuracy_cost.toml", str(tmp_path), quick=True, log=lambda *a: None)
    assert ref["status"] == "ok"
    assert all(r["status"] == "ok" for r in rows)
    err = {(r["p"], r["tol"], r["R"]): r["error"] for r in rows}
    print("[study] quick errors:", err)
    # first order in time: 4x the tolerance gives a larger error, fewer solves
    assert err[(10, 2e-2, 0.0)] > err[(10, 5e-3, 0.0)]
    solves = {(r["p"], r["tol"]): r["N_Tstep"] for r in rows if r["R"] == 0}
    assert solves[(10, 2e-2)] < solves[(10, 5e-3)]
    assert all(e < 0.05 for e in err.values())
    with open(tmp_path / "accuracy_cost.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)
    assert (tmp_path / "accuracy_cost.png").stat().st_size > 10000
    assert "Pareto front" in (tmp_path / "accuracy_cost.md").read_text()
    assert np.isfinite(ref["wall"])
