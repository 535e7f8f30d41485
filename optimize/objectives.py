"""Composable planning objectives and constraints: functions of the outcome values,
differentiable.

An objective maps the outcomes (dict name -> JAX scalar, see eyefem.eye.variables.OUTCOMES)
to a non-negative JAX scalar; they are summed. A constraint maps them to a value that
is >= 0 when the limit holds. The planner differentiates each with respect to the
outcomes (jax.grad) and chains with the adjoint gradient of that weighted sum of the
outcomes with respect to the design (SurgerySimulator.weighted_gradient). Scales make
every term about 1 when the miss is about one tolerance: 0.05 mm of indentation, 1 mmHg,
0.1 mm of axial length, 10% of a suture force limit. The soft limits (iop_window, ...)
are penalties, for objectives that want them; the planner treats limits as constraints.
A case on the surgery's timeline (volume_regulation = true) adds its timeline outcomes
(eyefem.eye.timeline.outcome_names): limits on the peak IOP on the table and the minutes
above the central retinal artery's closing pressure, targets at a follow-up time.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class Objective:
    """A named objective term: ``fn(outcomes) -> scalar`` and the outcomes it reads."""

    name: str
    fn: Callable
    uses: tuple[str, ...]

    def __call__(self, o):
        return self.fn(o)


def target_indentation(target_mm: float, tol_mm: float = 0.05) -> Objective:
    """((indentation - target) / tol)^2: reach the indentation under the break."""
    if not target_mm > 0:
        raise ValueError(f"target indentation {target_mm} mm; must be > 0")
    return Objective(f"indentation={target_mm:g}mm",
                     lambda o: ((o["indentation_mm"] - target_mm) / tol_mm) ** 2,
                     ("indentation_mm",))


def iop_window(low_mmhg: float = 10.0, high_mmhg: float = 21.0, tol_mmhg: float = 1.0) -> Objective:
    """Squared hinge outside [low, high] mmHg: keep the post-operative IOP safe."""
    if not low_mmhg < high_mmhg:
        raise ValueError(f"IOP window [{low_mmhg}, {high_mmhg}] mmHg is empty")

    def fn(o):
        p = o["iop_mmhg"]
        return (jnp.maximum(p - high_mmhg, 0.0) ** 2 + jnp.maximum(low_mmhg - p, 0.0) ** 2) / tol_mmhg**2

    return Objective(f"iop in [{low_mmhg:g}, {high_mmhg:g}] mmHg", fn, ("iop_mmhg",))


def axial_length_limit(max_mm: float, tol_mm: float = 0.1) -> Objective:
    """Squared hinge on |axial length change| above max_mm (myopic shift limit)."""
    return Objective(f"|axial change| <= {max_mm:g} mm",
                     lambda o: (jnp.maximum(jnp.abs(o["axial_length_change_mm"]) - max_mm, 0.0)
                                / tol_mm) ** 2,
                     ("axial_length_change_mm",))


def suture_force_limit(max_n: float) -> Objective:
    """Squared hinge on the largest suture force above max_n (tissue cut-through)."""
    if not max_n > 0:
        raise ValueError(f"suture force limit {max_n} N; must be > 0")
    return Objective(f"suture force <= {max_n:g} N",
                     lambda o: (jnp.maximum(o["max_suture_force_N"] - max_n, 0.0) / (0.1 * max_n)) ** 2,
                     ("max_suture_force_N",))


def total(objectives) -> Callable:
    """The sum of objective terms, as a function of the outcomes dict."""
    objectives = list(objectives)
    if not objectives:
        raise ValueError("no objective: give at least a target or a limit")
    return lambda o: sum(obj(o) for obj in objectives)


@dataclasses.dataclass(frozen=True)
class Constraint:
    """A named limit ``fn(outcomes) >= 0`` (satisfied), in units of its tolerance (one unit:
    1 mmHg, 0.1 mm of axial length, 10% of a suture force limit), and the outcomes it reads."""

    name: str
    fn: Callable
    uses: tuple[str, ...]

    def __call__(self, o):
        return self.fn(o)


def iop_at_most(max_mmhg: float, tol_mmhg: float = 1.0) -> Constraint:
    """IOP <= max_mmhg (a safe post-operative pressure)."""
    return Constraint(f"iop <= {max_mmhg:g} mmHg", lambda o: (max_mmhg - o["iop_mmhg"]) / tol_mmhg,
                      ("iop_mmhg",))


def iop_at_least(min_mmhg: float, tol_mmhg: float = 1.0) -> Constraint:
    """IOP >= min_mmhg (no hypotony)."""
    return Constraint(f"iop >= {min_mmhg:g} mmHg", lambda o: (o["iop_mmhg"] - min_mmhg) / tol_mmhg,
                      ("iop_mmhg",))


def axial_change_within(max_mm: float, tol_mm: float = 0.1) -> list[Constraint]:
    """|axial length change| <= max_mm, as two smooth limits (the myopic shift limit)."""
    if not max_mm > 0:
        raise ValueError(f"axial length change limit {max_mm} mm; must be > 0")
    key = "axial_length_change_mm"
    return [Constraint(f"axial change <= {max_mm:g} mm", lambda o: (max_mm - o[key]) / tol_mm, (key,)),
            Constraint(f"axial change >= -{max_mm:g} mm", lambda o: (max_mm + o[key]) / tol_mm, (key,))]


def suture_force_at_most(max_n: float) -> Constraint:
    """Largest suture force <= max_n (tissue cut-through)."""
    if not max_n > 0:
        raise ValueError(f"suture force limit {max_n} N; must be > 0")
    return Constraint(f"suture force <= {max_n:g} N",
                      lambda o: (max_n - o["max_suture_force_N"]) / (0.1 * max_n),
                      ("max_suture_force_N",))


# --- the surgery's timeline (cases with volume_regulation = true) -----------------------

def iop_peak_at_most(max_mmhg: float, tol_mmhg: float = 1.0) -> Constraint:
    """Peak IOP on the table <= max_mmhg (the central retinal artery's perfusion during the
    tightening; eyefem.eye.timeline: the largest step's IOP)."""
    key = "peak_iop_on_table_mmhg"
    return Constraint(f"peak iop <= {max_mmhg:g} mmHg", lambda o: (max_mmhg - o[key]) / tol_mmhg,
                      (key,))


def minutes_above_at_most(max_min: float, tol_min: float = 1.0) -> Constraint:
    """Minutes above the central retinal artery's closing pressure <= max_min (the smooth
    count of eyefem.eye.timeline.smooth_minutes_above); one unit: a minute."""
    if not max_min > 0:
        raise ValueError(f"minutes above the closing pressure limit {max_min} min; must be > 0 "
                         "(the smooth count is never exactly 0)")
    key = "minutes_above_cra_closing"
    return Constraint(f"minutes above closing <= {max_min:g}",
                      lambda o: (max_min - o[key]) / tol_min, (key,))


def target_at(outcome: str, when: str, target: float, tol: float, unit: str) -> Objective:
    """((outcome at a follow-up time - target) / tol)^2 for a shape outcome of the timeline
    (eyefem.eye.timeline.shape_name: ("indentation_mm", "1w") reads indentation_1w_mm)."""
    from eyefem.eye.timeline import shape_name

    key = shape_name(outcome, when)
    label = outcome.rsplit("_", 1)[0].replace("_change", "")
    return Objective(f"{label} at {when}={target:g}{unit}",
                     lambda o: ((o[key] - target) / tol) ** 2, (key,))


def target_indentation_at(when: str, target_mm: float, tol_mm: float = 0.05) -> Objective:
    """((buckle height at a follow-up time - target) / tol)^2 (e.g. when = "1w")."""
    if not target_mm > 0:
        raise ValueError(f"target indentation {target_mm} mm; must be > 0")
    return target_at("indentation_mm", when, target_mm, tol_mm, "mm")


def target_refraction_at(when: str, target_d: float, tol_d: float = 0.25) -> Objective:
    """((refraction change at a follow-up time - target) / tol)^2, dioptres (negative:
    myopic; tol a quarter dioptre, a spectacle step)."""
    return target_at("refraction_change_D", when, target_d, tol_d, "D")
