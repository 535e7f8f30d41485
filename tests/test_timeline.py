"""The surgery's timeline (eyefem.eye.timeline): the follow-up times, the stages on the
clock, the outcomes at named times, and coarse case 1 on the calibrated eye run through
its surgery and three months after it (slow)."""

import json
import math

import numpy as np
import pytest

from eyefem.eye.surgery import SURGERY_FIELDS
from eyefem.eye.timeline import (parse_followup, smooth_minutes_above, timed_stages,
                                 timeline_outcomes)
from eyefem.solve.solver import Stage

P = {f.name: f.default for f in SURGERY_FIELDS}


def test_followup_times_and_their_errors():
    assert parse_followup("1h, 48h, 1w, 3mo") == (
        ("1h", 60.0), ("48h", 2880.0), ("1w", 10080.0), ("3mo", 3 * 43830.0))
    assert parse_followup("30min,2d") == (("30min", 30.0), ("2d", 2880.0))
    for text, words in (("1h, 1x", "'1x' is not a time after surgery"),
                        ("2d, 1h", "the times must increase"),
                        ("0h", "'0h' is not a time"), ("30mo", "beyond two years")):
        with pytest.raises(ValueError, match=words):
            parse_followup(text)


def _stages():
    fix = (np.array([0]), np.array([0.0]))
    return [Stage("pressurise", 1, fix), Stage("tighten", 4, fix, params={"cavity": {"dv": 0.0}},
                                               before=lambda m, q, t: (m, q, t)),
            Stage("suture", 2, fix, params={"sutures": {"tightening": 0.3}})]


def test_the_stages_on_the_clock():
    stages = _stages()
    assert timed_stages(stages, P) == stages  # without volume_regulation: the seed's
    p = {**P, "volume_regulation": True, "paracentesis_volume": 100.0, "followup": "1h, 2d"}
    out = timed_stages(stages, p)
    assert [s.name for s in out] == ["pressurise", "tighten", "paracentesis", "suture",
                                     "follow-up"]
    assert [s.duration for s in out[:4]] == [None, 10.0, None, 15.0]
    assert out[2].params == {"cavity": {"paracentesis": 100.0}} and out[2].before is None
    follow = out[4]
    assert follow.params == {} and follow.before is None and follow.duration == 2880.0
    assert 60.0 in follow.times and follow.times[-1] == 2880.0 and follow.times[0] == 5.0
    assert all(np.array_equal(a, b) for a, b in zip(follow.prescribed, stages[2].prescribed))
    with pytest.raises(ValueError, match="needs a procedure of 3 stages"):
        timed_stages(stages[:2], p)


def test_minutes_above_the_closing_pressure_are_a_smooth_count():
    t = np.linspace(0.0, 10.0, 2001)
    assert smooth_minutes_above(t, np.full_like(t, 90.0), 60.0) == pytest.approx(10.0, 1e-9)
    assert smooth_minutes_above(t, np.full_like(t, 30.0), 60.0) == pytest.approx(0.0, abs=1e-9)
    # a linear rise from 40 to 80 mmHg over 10 min is above 60 for 5 min; the logistic's
    # symmetric tails cancel (to the trapezoid's error)
    assert smooth_minutes_above(t, 40.0 + 4.0 * t, 60.0) == pytest.approx(5.0, abs=1e-6)
    # differentiable: a small change of the IOP changes the count smoothly
    a = smooth_minutes_above(t, 40.0 + 4.0 * t, 60.0)
    b = smooth_minutes_above(t, 40.0 + 4.0 * t + 1e-3, 60.0)
    assert 0 < b - a < 1e-3


def _row(stage, time, iop, **kw):
    base = {"stage": stage, "cavity/time_min": time, "iop_mmhg": iop, "indentation_mm": 0.7,
            "axial_length_mm": 24.0, "volume_mm3": 4800.0, "corneal_power_D": 43.0,
            "anterior_chamber_depth_mm": 3.0, "corneal_astigmatism_D": 0.0,
            "max_suture_force_N": 0.1}
    return {**base, **kw}


def test_outcomes_at_named_times():
    p = {**P, "volume_regulation": True, "followup": "1h, 1w", "cra_closing_mmhg": 60.0}
    rows = [_row("pressurise", 0.0, 15.0),
            _row("tighten", 5.0, 50.0), _row("tighten", 10.0, 90.0),
            _row("suture", 25.0, 30.0),
            _row("follow-up", 25.0 + 30.0, 20.0), _row("follow-up", 25.0 + 60.0, 17.0),
            _row("follow-up", 25.0 + 10080.0, 16.7, axial_length_mm=24.3)]
    out = timeline_outcomes(rows, p)
    assert out["peak_iop_on_table_mmhg"] == 90.0 and out["iop_end_of_surgery_mmhg"] == 30.0
    assert out["surgery_minutes"] == 25.0
    assert out["iop_1h_mmhg"] == 17.0 and out["iop_1w_mmhg"] == 16.7
    assert out["axial_length_change_1w_mm"] == pytest.approx(0.3)
    assert "axial_length_change_1h_mm" not in out  # shapes from a week on
    # above 60 mmHg between the crossings at about 6.4 min and 18.6 min on the table
    assert 10.0 < out["minutes_above_cra_closing"] < 14.0
    assert timeline_outcomes(rows, P) == {}  # without volume_regulation


@pytest.mark.slow
def test_coarse_case1_on_the_timeline(tmp_path, capsys):
    """cases/surgery/timeline_case1.toml on the coarse eye: the on-table peak, the minutes
    above the central retinal artery's closing pressure, the IOP back at Goldmann's steady
    state by two days, the volume balance closed at every step, every step in equilibrium.
    Recorded outcomes pinned at 1e-6 (the tolerance of the surgical cases' records)."""
    from eyefem.cli.main import main

    out = tmp_path / "out"
    assert main(["-q", "run", "cases/surgery/timeline_case1.toml", "--mesh", "coarse",
                 "--no-vtu", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["unbalanced_steps"]["count"] == 0
    recorded = {"peak_iop_on_table_mmhg": 77.38567604, "iop_end_of_surgery_mmhg": 29.51686253,
                "iop_1h_mmhg": 17.31923028, "minutes_above_cra_closing": 6.718713991,
                "axial_length_change_3mo_mm": 0.10983491}
    for k, v in recorded.items():
        assert s[k] == pytest.approx(v, rel=1e-6), k
    steady = 6.3 + 2.5 / 0.24  # Goldmann: P_ev + F / C
    assert s["iop_48h_mmhg"] == pytest.approx(steady, rel=1e-6)
    import csv

    rows = list(csv.DictReader(open(out / "surgery_history.csv")))
    flows = [abs(float(r["cavity/wetted/balance_mm3"])) for r in rows
             if r["cavity/wetted/balance_mm3"] not in ("", "nan")]
    assert flows and max(flows) < 1e-9 * 200.0  # of the largest flow, ~ the 175 uL lost
    assert (out / "iop_timeline.png").stat().st_size > 10_000
    assert not math.isnan(s["refraction_change_1w_D"])


def test_the_paracentesis_after_a_wait_and_as_events():
    """A paracentesis delay puts a wait of WAIT_STEPS held steps between the tightening and
    the paracentesis; ``events`` keeps both stages at a zero volume and delay (the design
    gradients' load path has the same steps at every design)."""
    from eyefem.eye.timeline import WAIT_STEPS

    stages = _stages()
    p = {**P, "volume_regulation": True, "paracentesis_volume": 80.0,
         "paracentesis_delay_minutes": 4.0, "followup": "1h"}
    out = timed_stages(stages, p)
    assert [s.name for s in out] == ["pressurise", "tighten", "wait", "paracentesis", "suture",
                                     "follow-up"]
    wait = out[2]
    assert wait.duration == 4.0 and wait.n_steps == WAIT_STEPS and wait.params == {}
    assert wait.before is None and wait.active == stages[1].active
    none = {**p, "paracentesis_volume": 0.0, "paracentesis_delay_minutes": 0.0}
    assert [s.name for s in timed_stages(stages, none)] == ["pressurise", "tighten", "suture",
                                                           "follow-up"]
    events = timed_stages(stages, none, events=True)
    assert [s.name for s in events] == ["pressurise", "tighten", "wait", "paracentesis",
                                        "suture", "follow-up"]
    assert events[2].duration == 0.0 and events[3].params == {"cavity": {"paracentesis": 0.0}}


def test_the_timeline_outcome_names():
    from eyefem.eye.timeline import outcome_names, shape_name

    p = {**P, "volume_regulation": True, "followup": "1h, 48h, 1w"}
    names = outcome_names(p)
    assert names[:3] == ("peak_iop_on_table_mmhg", "minutes_above_cra_closing",
                         "iop_end_of_surgery_mmhg")
    assert {"iop_1h_mmhg", "iop_48h_mmhg", "iop_1w_mmhg", "indentation_1w_mm",
            "refraction_change_1w_D"} <= set(names)
    assert "indentation_48h_mm" not in names  # shapes from a week on
    assert shape_name("axial_length_change_mm", "3mo") == "axial_length_change_3mo_mm"


def test_the_table_outcomes_are_one_definition_for_numpy_and_jax():
    """timeline_outcomes (summary.json) and the design gradients read the on-table
    outcomes from one function; with JAX arrays it is differentiable (the peak's
    derivative is its step's)."""
    import jax
    import jax.numpy as jnp

    from eyefem.eye.timeline import table_outcomes

    jax.config.update("jax_enable_x64", True)
    p = {**P, "volume_regulation": True, "cra_closing_mmhg": 60.0}
    t = np.array([0.0, 5.0, 10.0, 25.0])
    iop = np.array([15.0, 50.0, 90.0, 30.0])
    a = table_outcomes(t, iop, p)
    b = table_outcomes(jnp.asarray(t), jnp.asarray(iop), p)
    for k in a:
        assert float(b[k]) == pytest.approx(float(a[k]), rel=1e-14)
    g = jax.grad(lambda x: table_outcomes(jnp.asarray(t), x, p)["peak_iop_on_table_mmhg"])(
        jnp.asarray(iop))
    np.testing.assert_array_equal(np.asarray(g), [0.0, 0.0, 1.0, 0.0])
    h = 1e-3  # mmHg: the count's roundoff (1e-15 x 10 min / h) and h^2 truncation below 1e-9
    gm = jax.grad(lambda x: table_outcomes(jnp.asarray(t), x, p)["minutes_above_cra_closing"])(
        jnp.asarray(iop))
    for i in range(4):
        e = np.eye(4)[i] * h
        fd = (table_outcomes(t, iop + e, p)["minutes_above_cra_closing"]
              - table_outcomes(t, iop - e, p)["minutes_above_cra_closing"]) / (2 * h)
        assert float(gm[i]) == pytest.approx(fd, rel=1e-6, abs=1e-9)


def _plan(tmp_path, capsys, case_text, *flags):
    from optimize.plan import main as plan_main

    case = tmp_path / "t.toml"
    case.write_text('[case]\nproblem = "surgery"\n[parameters]\nmesh = "coarse"\n' + case_text)
    rc = plan_main([str(case), *flags, "--out", str(tmp_path / "p")])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("case_text, flags, words", [
    ("", ("--iop-peak-max", "40", "--vars", "tightening"),
     "--iop-peak-max: outcomes and variables of the surgery's timeline"),
    ("", ("--target-indentation", "1.0", "--vars", "tightening,paracentesis_volume"),
     "paracentesis_volume: outcomes and variables of the surgery's timeline"),
    ("volume_regulation = true\nfollowup = \"1h, 48h\"\n",
     ("--target-refraction-1w", "-1", "--vars", "tightening"), "has no 1w; add 1w"),
    ("volume_regulation = true\n", ("--iop-peak-max", "0", "--vars", "tightening"),
     "--iop-peak-max 0 mmHg cannot be reached"),
    ("volume_regulation = true\n", ("--minutes-above-max", "nan", "--vars", "tightening"),
     "--minutes-above-max nan: need a finite number"),
    ("volume_regulation = true\n", ("--target-indentation-1w", "9", "--vars", "tightening"),
     "--target-indentation-1w 9 mm cannot be reached"),
    ("volume_regulation = true\n", ("--iop-peak-max", "40", "--vars", "paracentesis_volum"),
     "unknown design variable"),
])
def test_the_planners_timeline_options_are_checked(tmp_path, capsys, case_text, flags, words):
    """The timeline's limits, targets and variables are refused by name (exit 2) on a case
    off the timeline, without a week in its follow-up, or out of range, before any solve."""
    rc, err = _plan(tmp_path, capsys, case_text, *flags)
    assert rc == 2 and words in err, err
