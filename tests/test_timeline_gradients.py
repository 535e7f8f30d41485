"""Gradients of the surgery's timeline outcomes (eyefem.eye.design.TimelineSimulator, issue
74) against central differences of whole timelines, and the planner on the timeline
(coarse eye, slow: each timeline is a full load path of about 30 steps from the closing to
a week after surgery, and its gradient one adjoint per step).

The case: cases/surgery/timeline_case1.toml on the coarse eye with a paracentesis of 30 uL
two minutes after the tightening and a follow-up to one week (1h, 48h, 1w: the three-month
step adds nothing a week does not show, the IOP being back at Goldmann's steady state).
"""

import numpy as np
import pytest

from eyefem.api import load_case

pytestmark = pytest.mark.slow

CASE = "cases/surgery/timeline_case1.toml"
NAMES = ("peak_iop_on_table_mmhg", "minutes_above_cra_closing", "iop_48h_mmhg",
         "iop_end_of_surgery_mmhg", "indentation_1w_mm", "refraction_change_1w_D")
STEPS = {"tightening": 5e-3, "paracentesis_volume": 3e-2, "paracentesis_delay_minutes": 2e-3}
"""Central-difference steps, 1e-3 of each variable's value (5 mm, 30 uL, 2 min): the
outcomes' third derivatives leave a truncation error below 1e-6 relative there, and the
Newton tolerance (1e-10 of the force scale) a roundoff of about 1e-7 relative; the peak's
argmax (the last tightening step) does not move within the step."""


@pytest.fixture(scope="module")
def timeline():
    import jax

    from eyefem.eye.design import SurgerySimulator

    jax.config.update("jax_enable_x64", True)
    case = load_case(CASE)
    p = {**case.parameters, "mesh": "coarse", "followup": "1h, 48h, 1w",
         "paracentesis_volume": 30.0, "paracentesis_delay_minutes": 2.0}
    sim = SurgerySimulator(p, case.materials, case.solver)
    res = sim.run()
    return sim, res, sim.gradients(res, NAMES)


def test_a_timeline_case_gets_the_timeline_simulator(timeline):
    from eyefem.eye.design import TimelineSimulator

    sim, res, grads = timeline
    assert isinstance(sim, TimelineSimulator)
    assert set(NAMES) <= set(sim.outcome_names) and set(grads) == set(NAMES)
    stages = [s for s, *_ in res.steps]
    assert stages[:10] == ["tighten"] * 8 + ["wait"] * 2 and stages[10] == "paracentesis"
    # the step params the adjoint differentiates are those the load path solved with
    assert sim.params_mismatch(res) < 1e-12
    # the paracentesis lowers the IOP at once; the peak is the tightening's last step's
    iops = [i for *_, i in res.steps]
    assert iops[10] < iops[9] - 10.0
    assert res.outcomes["peak_iop_on_table_mmhg"] == pytest.approx(max(iops[:8]), rel=1e-12)


@pytest.mark.parametrize("var", list(STEPS))
def test_timeline_gradients_against_central_differences(timeline, var):
    """d outcome / d variable by the adjoint through the timeline's steps against central
    differences of two whole timelines: 1e-4 relative for the peak IOP, the smooth minutes
    above the closing pressure, the IOP at the end of surgery and the shape a week later.
    The IOP at 48 hours is back at Goldmann's steady state P_ev + F / C (time constant about
    half an hour, 48 hours later e^-100 of the surgery's trace), which no design variable
    moves: both derivatives vanish there (compared to 1e-6 mmHg per unit); the peak,
    before the paracentesis, has no derivative in its volume or time."""
    sim, res, grads = timeline
    h = STEPS[var]
    d = res.design
    up = sim.run({var: d[var] + h}).outcomes
    down = sim.run({var: d[var] - h}).outcomes
    for name in NAMES:
        fd = (up[name] - down[name]) / (2 * h)
        g = grads[name][var]
        if name == "iop_48h_mmhg" or (name == "peak_iop_on_table_mmhg"
                                     and var != "tightening"):
            assert abs(g) < 1e-6 and abs(fd) < 1e-6, (name, var, g, fd)
        else:
            assert g == pytest.approx(fd, rel=1e-4), (name, var, g, fd)


def test_the_planner_meets_the_peak_iop_limit_on_the_timeline(tmp_path):
    """python -m optimize.plan on the timeline case (coarse, follow-up to a week): a limit on
    the peak IOP on the table (60 mmHg, where the case's 5 mm tightening peaks at 77) and on
    the minutes above the central retinal artery's closing pressure, a buckle height target
    a week after surgery, the tightening and the paracentesis's volume as variables. It
    ends feasible (every limit met to half a unit)."""
    import json
    import re

    from optimize.plan import main

    text = open(CASE).read()
    case = tmp_path / "timeline.toml"
    case.write_text(re.sub(r'followup = "[^"]*"', 'followup = "1h, 48h, 1w"', text))
    out = tmp_path / "plan"
    rc = main([str(case), "--mesh", "coarse", "--iop-peak-max", "60", "--minutes-above-max",
               "2", "--target-indentation-1w", "0.6", "--vars",
               "tightening,paracentesis_volume", "--iterations", "6", "--out", str(out)])
    assert rc in (0, 1)
    s = json.loads((out / "plan_summary.json").read_text())
    assert s["violated_constraints"] == []
    assert s["outcomes"]["peak_iop_on_table_mmhg"] <= 60.5
    assert s["outcomes"]["minutes_above_cra_closing"] <= 2.5
    assert 0.0 <= s["design"]["paracentesis_volume"] <= 200.0
    assert (out / "planned_case.toml").exists() and (out / "plan_history.csv").exists()
