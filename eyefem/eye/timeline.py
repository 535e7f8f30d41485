"""The surgery's timeline: the regulated cavity's constants, stage durations, the
follow-up after surgery and the outcomes at named times (issue 74).

With ``volume_regulation = true`` the closed cavity exchanges liquid as a living eye does
(eyefem.fem.regulation: aqueous production and outflow by Goldmann's law, a choroidal
blood compartment, the surgeon's paracentesis), the tightening and the suturing last
their minutes, and the run goes on after surgery to the follow-up times: the IOP a
surgeon sees on the table, an hour and two days later, and the eye's shape a week and
three months on. Without it the procedure is the seed's (a closed cavity, no time) and
nothing here applies.

Times: minutes from the cavity's closing (the start of the tightening); the follow-up
times are counted from the end of surgery. The shape outcomes at a week and at three
months are those of the tissues at the IOP of that time: elastic, or relaxed as far as
their Prony series has by then with a time-dependent wall (``tissue_relaxation``,
eyefem.eye.relaxation; ``preop_minutes`` lets the pre-operative IOP act on it before the
surgery). Growth and remodelling are not modelled (docs/validation.md).

The outcomes are defined once (:func:`table_outcomes`, :func:`followup_steps`,
:func:`shape_name`), for summary.json (:func:`timeline_outcomes`, from the rows) and for
the design gradients (eyefem.eye.simulators.TimelineSimulator, JAX functions of the steps'
carried IOPs, clocks and optics; the paracentesis's volume and delay are design
variables there).
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.eye.outcomes import changes
from eyefem.fem.regulation import (AQUEOUS, CHOROID_ESTIMATE, UL_MIN_MMHG, Regulation,
                                   step_times)
from eyefem.fem.units import MMHG
from eyefem.io.casefile import Field

_UNITS = {"min": 1.0, "h": 60.0, "d": 1440.0, "w": 10080.0, "mo": 43830.0}
"""Minutes of each follow-up unit (a month: 30.44 days)."""


def _default(name: str, fallback: float) -> float:
    """A published constant of eyefem.fem.regulation in clinical units."""
    values = {"facility": float(np.asarray(AQUEOUS.facility)) / UL_MIN_MMHG,
              "p_ev": float(np.asarray(AQUEOUS.p_ev)) / MMHG,
              "production": float(np.asarray(AQUEOUS.production)),
              "blood_max": float(CHOROID_ESTIMATE.get("blood_max", fallback)),
              "blood_scale": float(CHOROID_ESTIMATE.get("blood_scale", fallback * MMHG)) / MMHG}
    return values.get(name, fallback)


def parse_followup(text: str) -> tuple[tuple[str, float], ...]:
    """('1h', 60.0), ... of a follow-up list such as "1h, 48h, 1w, 3mo": a number and a
    unit (min, h, d, w, mo) each, increasing. ValueError naming the item and the fix."""
    out = []
    for item in (s.strip() for s in text.split(",")):
        m = re.fullmatch(r"(\d+(?:\.\d+)?)\s*(min|mo|h|d|w)", item)
        if not m or float(m.group(1)) <= 0:
            raise ValueError(f"followup: '{item}' is not a time after surgery; give a number "
                             "and a unit (min, h, d, w, mo), e.g. followup = \"1h, 48h, 1w, "
                             "3mo\"")
        out.append((item.replace(" ", ""), float(m.group(1)) * _UNITS[m.group(2)]))
    times = [t for _, t in out]
    if times != sorted(times) or len(set(times)) != len(times):
        raise ValueError(f"followup = \"{text}\": the times must increase; give them in order")
    if times[-1] > 2 * 365.25 * 1440:
        raise ValueError(f"followup = \"{text}\": {out[-1][0]} is beyond two years; the "
                         "model's tissue does not remodel, give at most 24mo")
    return tuple(out)


def _followup_ok(v) -> bool:
    try:
        parse_followup(v)
    except ValueError:
        return False
    return True


PREOP_MAX_MIN = 2 * 365.25 * 1440
"""The longest pre-operative time, minutes (two years)."""

TIMELINE_FIELDS = [
    Field("volume_regulation", bool, False,
          "true: the closed cavity exchanges liquid over the surgery's timeline as a living "
          "eye does (aqueous production and outflow by Goldmann's law, a choroidal blood "
          "compartment, paracentesis), the tightening and suturing take their minutes and "
          "the run continues after surgery to the follow-up times ("
          "docs/surgery_timeline.md); false: the seed's closed cavity, no time"),
    Field("outflow_facility", float, _default("facility", 0.24),
          "aqueous outflow facility C, uL/min/mmHg (Kazemi et al. 2017: 0.24 +- 0.08)",
          lambda v: 0 <= v <= 2, "0 to 2 uL/min/mmHg"),
    Field("episcleral_venous_pressure", float, _default("p_ev", 6.3),
          "episcleral venous pressure, mmHg (Sit et al. 2011: 6.3 +- 2.8)",
          lambda v: 0 <= v <= 30, "0 to 30 mmHg"),
    Field("aqueous_production", float, _default("production", 2.5),
          "aqueous production net of uveoscleral outflow, uL/min (Toris 2014: 2.5)",
          lambda v: 0 <= v <= 10, "0 to 10 uL/min"),
    Field("choroid_blood_max", float, _default("blood_max", 60.0),
          "choroidal blood the pressure can expel at most (and take up below the closing "
          "pressure), uL; an estimate (eyefem.fem.regulation.CHOROID_ESTIMATE); 0: none",
          lambda v: 0 <= v <= 300, "0 to 300 uL"),
    Field("choroid_blood_scale", float, _default("blood_scale", 25.0),
          "pressure scale over which the choroid's blood is expelled, mmHg",
          lambda v: 1 <= v <= 200, "1 to 200 mmHg"),
    Field("paracentesis_volume", float, 0.0,
          "aqueous removed by an anterior chamber paracentesis after the tightening "
          "(paracentesis_delay_minutes later), at one instant, uL (a 30-gauge needle takes "
          "50-200 uL); 0: none. A design variable (python -m optimize.plan --vars "
          "paracentesis_volume)",
          lambda v: 0 <= v <= 300, "0 to 300 uL (the anterior chamber holds about 250)"),
    Field("paracentesis_delay_minutes", float, 0.0,
          "when the paracentesis is done: minutes after the end of the tightening, min (the "
          "surgeon watches the central retinal artery meanwhile; the suturing follows the "
          "paracentesis, so the surgery lasts this much longer); 0: right after the "
          "tightening. A design variable: the wait's steps stretch with it, so the outcomes "
          "are smooth in it (eyefem.eye.timeline.timed_stages)",
          lambda v: 0 <= v <= 60, "0 to 60 min"),
    Field("preop_minutes", float, 0.0,
          "how long the pre-operative IOP has acted on the eye before the surgery, min: the "
          "pressurising stage lasts this long, so a time-dependent wall (tissue_relaxation) "
          "starts the surgery relaxed under it (e.g. 525960: a year); 0: pressurised at "
          "once (the wall's instantaneous response). No effect on elastic tissues",
          lambda v: 0 <= v <= PREOP_MAX_MIN, f"0 to {PREOP_MAX_MIN:.0f} min (two years)"),
    Field("tighten_minutes", float, 10.0, "duration of the tightening (or placing) stage, min",
          lambda v: 0 < v <= 240, "above 0, at most 240 min"),
    Field("suture_minutes", float, 15.0, "duration of the suturing stage, min",
          lambda v: 0 < v <= 240, "above 0, at most 240 min"),
    Field("followup", str, "1h, 48h, 1w, 3mo",
          "times after surgery the run continues to, a number and a unit each (min, h, d, "
          "w, mo); the outcomes are reported at each", _followup_ok,
          "e.g. \"1h, 48h, 1w, 3mo\""),
    Field("cra_closing_mmhg", float, 60.0,
          "IOP at which the central retinal artery closes (about the ophthalmic artery's "
          "diastolic pressure), mmHg: the minutes above it are an outcome",
          lambda v: 20 <= v <= 150, "20 to 150 mmHg"),
]
"""The timeline's case parameters (appended to the surgery schema)."""

SMOOTH_MMHG = 1.0
"""Width of the logistic step that counts the minutes above the closing pressure, mmHg:
the count is differentiable in the design (a hard threshold is not)."""

FIRST_STEP_MIN = 5.0
"""The first follow-up step, minutes; each next one twice as long (step_times)."""


def regulation(p: dict) -> Regulation | None:
    """The cavity's Regulation of the case parameters, or None without volume_regulation."""
    if not p.get("volume_regulation", False):
        return None
    return Regulation.clinical(p["outflow_facility"], p["episcleral_venous_pressure"],
                               p["aqueous_production"], p["choroid_blood_max"],
                               p["choroid_blood_scale"])


WAIT_STEPS = 2
"""Steps of the wait between the tightening and a paracentesis (backward Euler over the
paracentesis_delay_minutes)."""


def timed_stages(stages: list, p: dict, *, events: bool = False) -> list:
    """The procedure's stages on the timeline: the pressurising stage lasts
    ``preop_minutes`` (none when 0), the tightening (the stage that closes the cavity) and
    the suturing take their minutes; a paracentesis (if any) removes its volume
    at one instant after the tightening, ``paracentesis_delay_minutes`` after it (a
    "wait" stage of WAIT_STEPS steps in between, held, the regulation going on); a
    follow-up stage holds everything as it ends the surgery and runs to the follow-up
    times. ``stages``: the buckle body's, unchanged without volume_regulation.

    The paracentesis's time moves the wait's step ends with it (WAIT_STEPS equal steps of
    delay / WAIT_STEPS minutes) and the later steps by the same minutes; no step end is
    crossed, so every outcome is a smooth function of the delay and its adjoint derivative
    (through each step's duration, eyefem.eye.design) is exact at every delay >= 0, the
    one-sided derivative at 0. The paracentesis cannot move into the tightening: that would
    cut its ramp at a time between two steps. ``events``: the wait and the paracentesis
    stages even where the volume and the delay are 0 (trivial steps; the design
    gradients need them at every design)."""
    if not p.get("volume_regulation", False):
        return list(stages)
    if len(stages) < 3:
        raise ValueError(f"volume_regulation needs a procedure of 3 stages (pressurise, "
                         f"tighten or place, suture); this one has {len(stages)}")
    first, tighten, *rest = stages
    preop = float(p.get("preop_minutes", 0.0))
    if preop > 0:
        first = dataclasses.replace(first, duration=preop)
    out = [first, dataclasses.replace(tighten, duration=p["tighten_minutes"])]
    delay = float(p.get("paracentesis_delay_minutes", 0.0))
    if events or (p["paracentesis_volume"] > 0 and delay > 0):
        out.append(dataclasses.replace(tighten, name="wait", n_steps=WAIT_STEPS, before=None,
                                       duration=delay, times=None, params={}))
    if events or p["paracentesis_volume"] > 0:
        out.append(dataclasses.replace(
            tighten, name="paracentesis", n_steps=1, before=None, duration=None, times=None,
            params={"cavity": {"paracentesis": float(p["paracentesis_volume"])}}))
    *middle, suture = rest
    out += middle + [dataclasses.replace(suture, duration=p["suture_minutes"])]
    times = step_times([t for _, t in parse_followup(p["followup"])], FIRST_STEP_MIN)
    out.append(dataclasses.replace(suture, name="follow-up", n_steps=len(times), before=None,
                                   params={}, duration=times[-1], times=times))
    return out


def _time(row: dict) -> float:
    """The clock of a history row, minutes (the cavity's time_min; NaN before it runs)."""
    for k, v in row.items():
        if k.startswith("cavity/") and k.endswith("time_min"):
            return float(v)
    return np.nan


def smooth_minutes_above(t, iop, threshold: float, width: float = SMOOTH_MMHG):
    """Minutes the IOP spends above ``threshold`` (mmHg): the trapezoidal integral over
    the steps' times t (minutes) of the logistic 1 / (1 + exp(-(IOP - threshold) / width)),
    a differentiable count. numpy in, float out; JAX in (the design gradients), JAX out."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (t, iop)) else np
    t, iop = xp.asarray(t, float), xp.asarray(iop, float)
    if len(t) < 2:
        return 0.0
    s = 0.5 * (1.0 + xp.tanh((iop - threshold) / (2.0 * width)))
    out = xp.sum(0.5 * (s[1:] + s[:-1]) * xp.diff(t))
    return float(out) if xp is np else out


def table_outcomes(t, iop, p: dict) -> dict:
    """The on-table outcomes of the clock t (k,) (minutes from the closing, 0 first) and
    the IOP (k,) (mmHg, the pre-operative IOP first) of the steps from the closing to the
    end of surgery: the peak (the largest step's, the first of steps that tie: its
    derivative is that step's, so where a zero-length wait repeats the tightening's last
    IOP the derivative is the one-sided one of a later paracentesis, zero), the smooth
    minutes above the closing pressure and the IOP at the end of surgery. numpy or JAX (the
    one definition of :func:`timeline_outcomes` and the design gradients)."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (t, iop)) else np
    iop = xp.asarray(iop, float)
    return {"peak_iop_on_table_mmhg": iop[xp.argmax(iop)],
            "minutes_above_cra_closing": smooth_minutes_above(t, iop, p["cra_closing_mmhg"]),
            "iop_end_of_surgery_mmhg": iop[-1]}


SHAPE_OUTCOMES = ("axial_length_change_mm", "refraction_change_D",
                  "anterior_chamber_depth_change_mm", "indentation_mm")
"""The shape outcomes reported at the follow-up times of a week and more."""


def shape_name(outcome: str, when: str) -> str:
    """The name of a shape outcome at a follow-up time: ("axial_length_change_mm", "1w")
    -> "axial_length_change_1w_mm"."""
    stem, unit = outcome.rsplit("_", 1)
    return f"{stem}_{when}_{unit}"


def followup_steps(minutes_after_end, p: dict) -> dict:
    """Follow-up name -> the index of the step (of ``minutes_after_end``, minutes from the
    end of surgery of each follow-up step) that ends at that time; names no step reaches
    are left out."""
    t = np.asarray(minutes_after_end, float)
    out = {}
    for name, minutes in parse_followup(p["followup"]):
        hit = np.nonzero(np.abs(t - minutes) <= 1e-6 * max(minutes, 1.0))[0]
        if len(hit):
            out[name] = int(hit[-1])
    return out


def outcome_names(p: dict) -> tuple:
    """The timeline outcomes the design gradients report, in order: the on-table three,
    the IOP at each follow-up time, the shape outcomes at those of a week or more."""
    names = ["peak_iop_on_table_mmhg", "minutes_above_cra_closing", "iop_end_of_surgery_mmhg"]
    follow = parse_followup(p["followup"])
    names += [f"iop_{name}_mmhg" for name, _ in follow]
    names += [shape_name(k, name) for name, minutes in follow if minutes >= _UNITS["w"]
              for k in SHAPE_OUTCOMES]
    return tuple(names)


def shape_at_week(minutes: float) -> bool:
    """Whether the shape outcomes are reported at a follow-up time (a week or more)."""
    return minutes >= _UNITS["w"]


def timeline_outcomes(rows: list[dict], p: dict) -> dict:
    """summary.json's timeline outcomes of a run's history rows: the peak IOP on the table,
    the minutes above the central retinal artery's closing pressure (smooth), the IOP at
    the end of surgery and at each follow-up time, and the shape outcomes at the follow-up
    times of a week or more (:func:`table_outcomes`, :func:`followup_steps`: the
    definitions the design gradients differentiate). Empty without volume_regulation."""
    if not p.get("volume_regulation", False):
        return {}
    table = [r for r in rows if r["stage"] != "follow-up" and np.isfinite(_time(r))]
    after = [r for r in rows if r["stage"] == "follow-up"]
    out = {}
    if table:
        t = [0.0] + [_time(r) for r in table]  # from the closing, at the pre-operative IOP
        iop = [p["iop_mmhg"]] + [r["iop_mmhg"] for r in table]
        out.update({k: float(v) for k, v in table_outcomes(t, iop, p).items()})
        out["surgery_minutes"] = float(_time(table[-1]))
    end = _time(table[-1]) if table else 0.0
    first = rows[0]["stage"] if rows else None
    pre = [r for r in rows if r["stage"] == first][-1:] if rows else []
    hits = followup_steps([_time(r) - end for r in after], p)
    for name, minutes in parse_followup(p["followup"]):
        if name not in hits:
            continue
        r = after[hits[name]]
        out[f"iop_{name}_mmhg"] = float(r["iop_mmhg"])
        if shape_at_week(minutes) and pre:
            shape = {"indentation_mm": r["indentation_mm"],
                     **{k: float(v) for k, v in changes(r, pre[0]).items()}}
            out.update({shape_name(k, name): float(shape[k])
                        for k in SHAPE_OUTCOMES if k in shape})
    return out


def iop_curve(rows: list[dict]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(minutes from the closing (k,), IOP mmHg (k,), stage names (k,)) of the rows on the
    timeline."""
    keep = [r for r in rows if np.isfinite(_time(r))]
    return (np.array([_time(r) for r in keep]), np.array([r["iop_mmhg"] for r in keep]),
            [r["stage"] for r in keep])


def plot_timeline(path, rows: list[dict], p: dict, out: dict):
    """IOP against time (PNG): the surgery on a linear axis in minutes, the follow-up on a
    logarithmic one, the central retinal artery's closing pressure and Goldmann's steady
    state marked."""
    from eyefem.io.output import atomic_path

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t, iop, stage = iop_curve(rows)
    if len(t) == 0:
        return None
    surgery = np.array([s != "follow-up" for s in stage])
    end = t[surgery][-1] if surgery.any() else 0.0
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4), sharey=True,
                               gridspec_kw={"width_ratios": [1, 1.4]})
    a.plot(np.r_[0.0, t[surgery]], np.r_[p["iop_mmhg"], iop[surgery]], "o-", ms=3)
    a.set_xlabel("minutes from the closing of the eye")
    a.set_ylabel("IOP, mmHg")
    a.set_title("on the table")
    if (~surgery).any():
        b.semilogx((t[~surgery] - end) / 60.0, iop[~surgery], "o-", ms=3)
        for name, minutes in parse_followup(p["followup"]):
            b.axvline(minutes / 60.0, color="0.8", lw=0.8)
            b.text(minutes / 60.0, b.get_ylim()[1], name, ha="center", va="bottom", fontsize=8)
    b.set_xlabel("hours after surgery")
    b.set_title("after surgery", pad=14)
    steady = p["episcleral_venous_pressure"] + p["aqueous_production"] / max(
        p["outflow_facility"], 1e-12)
    for ax in (a, b):
        ax.axhline(p["cra_closing_mmhg"], color="tab:red", lw=0.8, ls="--",
                   label="central retinal artery closes")
        if p["outflow_facility"] > 0:
            ax.axhline(steady, color="tab:green", lw=0.8, ls=":",
                       label="Goldmann steady state")
        ax.grid(alpha=0.3)
    a.legend(fontsize=8, loc="best")
    if "peak_iop_on_table_mmhg" in out:
        fig.suptitle(f"peak {out['peak_iop_on_table_mmhg']:.0f} mmHg on the table, "
                     f"{out['minutes_above_cra_closing']:.1f} min above "
                     f"{p['cra_closing_mmhg']:.0f} mmHg", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path
