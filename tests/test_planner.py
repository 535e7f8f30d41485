"""The planner reaches an indentation target on the coarse case 1 (slow: a few minutes)."""

import json
from pathlib import Path

import pytest

from optimize import objectives as obj
from optimize.plan import main as plan_main

ROOT = Path(__file__).resolve().parents[1]


def test_objectives_are_zero_inside_and_grow_outside():
    o = {"indentation_mm": 0.8, "iop_mmhg": 18.0, "axial_length_change_mm": 0.2,
         "max_suture_force_N": 0.5}
    assert float(obj.target_indentation(0.8)(o)) == 0.0
    assert float(obj.iop_window(10, 21)(o)) == 0.0
    assert float(obj.iop_window(10, 16)(o)) == pytest.approx(4.0)  # (18 - 16)^2 / 1^2
    assert float(obj.axial_length_limit(0.1)(o)) == pytest.approx(1.0)
    assert float(obj.suture_force_limit(0.4)(o)) == pytest.approx(6.25)  # (0.1 / 0.04)^2
    assert float(obj.iop_at_most(21)(o)) == pytest.approx(3.0)  # met by 3 mmHg
    assert float(obj.iop_at_least(20)(o)) == pytest.approx(-2.0)  # missed by 2 mmHg
    assert [float(c(o)) for c in obj.axial_change_within(0.1)] == pytest.approx([-1.0, 3.0])
    assert float(obj.suture_force_at_most(0.4)(o)) == pytest.approx(-2.5)
    with pytest.raises(ValueError, match="empty"):
        obj.iop_window(21, 10)
    with pytest.raises(ValueError, match="no objective"):
        obj.total([])


def test_planner_refuses_material_constants_and_unknown_variables():
    from optimize.plan import plan

    terms = [obj.target_indentation(1.0)]
    with pytest.raises(ValueError, match="'c10_sclera' is a material constant"):
        plan(None, terms, ["c10_sclera"])
    with pytest.raises(ValueError, match="unknown design variable 'width'"):
        plan(None, terms, ["width"])


@pytest.mark.slow
def test_planner_reaches_the_target_indentation(tmp_path):
    rc = plan_main([str(ROOT / "cases/surgery/case1.toml"), "--mesh", "coarse",
                    "--target-indentation", "0.8", "--iop-max", "25", "--vars",
                    "tightening,suture_width", "--iterations", "15",
                    "--tol", "0.25", "--out", str(tmp_path)])
    summary = json.loads((tmp_path / "plan_summary.json").read_text())
    assert rc == 0 and summary["converged"]
    # objective < 0.25 means |indentation - 0.8| < 0.05 * sqrt(0.25) = 0.025 mm, and the IOP
    # limit is met to half a tolerance unit (0.5 mmHg)
    assert summary["outcomes"]["indentation_mm"] == pytest.approx(0.8, abs=0.026)
    assert summary["outcomes"]["iop_mmhg"] < 25.5
    assert summary["violated_constraints"] == [] and summary["simulations"] <= 15
    for f in ("plan_history.csv", "plan.png", "planned_case.toml"):
        assert (tmp_path / f).exists()


@pytest.mark.slow
def test_planner_on_the_calibrated_eye_plans_the_drainage(tmp_path):
    """The README's planning example: case 1's buckle on the physiological eye, with the
    drained volume a design variable, reaches the indentation target inside the IOP
    window (coarse: 2 simulations, about 5 minutes on 2 cores)."""
    rc = plan_main([str(ROOT / "cases/planning/case1_physiological.toml"), "--mesh", "coarse",
                    "--target-indentation", "0.8", "--iop-min", "10", "--iop-max", "21",
                    "--vars", "tightening,drain_volume", "--iterations", "8",
                    "--out", str(tmp_path)])
    summary = json.loads((tmp_path / "plan_summary.json").read_text())
    assert rc == 0 and summary["converged"] and summary["violated_constraints"] == []
    out = summary["outcomes"]
    # the default --tol 0.01: |indentation - 0.8| < 0.05 * 0.1 = 0.005 mm; the IOP window
    # met to half a tolerance unit
    assert out["indentation_mm"] == pytest.approx(0.8, abs=0.0051)
    assert 9.5 < out["iop_mmhg"] < 21.5
    assert summary["design"]["drain_volume"] > 100.0  # undrained it ends above 600 mmHg
