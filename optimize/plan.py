"""Surgical planning: optimise the design of a surgery case with adjoint gradients.

    python -m optimize.plan cases/surgery/case1.toml --mesh coarse \\
        --target-indentation 1.0 --iop-max 21 --vars tightening,suture_width

A case on the surgery's timeline (``volume_regulation = true``) is planned on its outcomes
over time (eyefem.eye.simulators.TimelineSimulator): limits on the peak IOP on the table
(--iop-peak-max) and on the minutes above the central retinal artery's closing pressure
(--minutes-above-max), targets on the buckle height or the refraction change a week after
surgery (--target-indentation-1w, --target-refraction-1w), and the paracentesis's volume
and time as variables (--vars tightening,paracentesis_volume,paracentesis_delay_minutes);
each evaluation then solves the whole timeline and one adjoint per load step.

Sequential quadratic programming (scipy's SLSQP) on the design variables scaled to
[0, 1] by their bounds: the objective (an indentation target) is minimised subject to
the limits as constraints (IOP, axial length change, suture force), with exact
gradients of both: each evaluation solves the case at the design (warm started from the
last converged states) and one block adjoint (three solves, one right-hand side per
outcome the objective or a constraint weighs: SurgerySimulator.gradients) for the
objective and every constraint together. The plan stops when the objective is
below --tol with every constraint met (to half a tolerance unit), when the projected
gradient of a feasible design vanishes, or after --iterations simulations. Writes into
--out: plan_history.csv (every simulation: design, outcomes, objective, constraint
values, gradient), plan.png, planned_case.toml (the case with the best design) and
plan_summary.json (with the active or violated constraints).

**Multi-fidelity** (``--search-mesh LEVEL``): the plan searches on a cheaper level first
(to --iterations simulations), then simulates the case's level (or --mesh) at the
search's best design; while that misses the goal, it searches the cheap level again with
its outcomes corrected to the trusted level's there (the difference and its gradient:
additive output correction) and simulates the trusted level at the new design (to
--finish-iterations trusted simulations). The first trusted simulation measures how far
the levels are apart at one design, beside the mesh study's error estimates of both
(eyefem.eye.mesh_error); the plan reports the trusted level's outcomes
(plan_summary.json: "search", "level_difference", "mesh_error").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import jax
import numpy as np

from eyefem.io.progress import Heartbeat
from optimize import objectives as obj

log = logging.getLogger("optimize.plan")

BOUNDS = {  # default bounds of the design variables
    "tightening": (0.0, 15.0),
    "buckle_shift": (-3.0, 3.0),
    "suture_width": (None, 14.0),  # lower bound: the buckle width + 1 mm
    "suture_tightening": (0.0, 1.5),
    "drain_volume": (0.0, 200.0),
    "band_tension": (0.0, 1.0),  # N; only in cases whose band is pulled (band_tension > 0)
    "buckle_meridian_deg": (None, None),  # segmental only: the case's meridian +- 20 degrees
    "paracentesis_volume": (0.0, 200.0),  # uL; timeline cases (a 30-gauge needle: 50-200)
    "paracentesis_delay_minutes": (0.0, 30.0),  # min after the tightening; timeline cases
}
TIMELINE_ONLY = ("paracentesis_volume", "paracentesis_delay_minutes")
"""Design variables of the surgery's timeline: a case with volume_regulation = true."""


FEASIBLE = 0.5
"""A constraint counts as met above -FEASIBLE (half a tolerance unit: 0.5 mmHg, ...)."""
GRADIENT_TOL = 1e-3
"""A feasible design whose projected objective gradient (per unit of the scaled
variables) is below this is stationary: the plan stops there."""


@dataclasses.dataclass
class PlanResult:
    """History rows (one per simulation), the best design (with "gradients": d outcome /
    d design of the outcomes weighed there), whether it converged, why it stopped, the
    constraints active (within FEASIBLE of their limit) or violated, and the outcomes whose
    gradients any simulation took."""

    history: list[dict]
    best: dict
    converged: bool
    message: str = ""
    active: tuple[str, ...] = ()
    violated: tuple[str, ...] = ()
    outcomes_used: tuple[str, ...] = ()
    last: object = None
    """The last simulation's result (its states only, eyefem.eye.simulators.states_only):
    ``start`` of a later plan."""


class _Stop(Exception):
    """Raised inside the optimiser's callbacks to end the plan (reached, or out of budget)."""


def bounds_for(sim, names, overrides=None) -> dict:
    """(low, high) per design variable; the suture width starts 1 mm wider than the buckle,
    a segmental buckle's meridian stays within 20 degrees of the case's."""
    out = {}
    for n in names:
        lo, hi = (overrides or {}).get(n, BOUNDS[n])
        if n == "suture_width" and lo is None:
            lo = sim.parts.buckle.width + 1.0
        if n == "buckle_meridian_deg" and lo is None:
            lo, hi = sim.meridian0 - 20.0, sim.meridian0 + 20.0
        if not lo < hi:
            raise ValueError(f"bounds of '{n}': [{lo}, {hi}] is empty")
        out[n] = (float(lo), float(hi))
    return out


def plan(sim, objective_terms, names, *, constraints=(), bounds=None, iterations=20,
         tol=1e-2, on_iteration=None, gradient_outcomes=(), start=None) -> PlanResult:
    """SLSQP on the design variables ``names`` of a SurgerySimulator.

    Args:
      sim: eyefem.eye.simulators.SurgerySimulator (its case gives the starting design).
      objective_terms: optimize.objectives.Objective terms, summed (may be empty: then
        the plan looks for a design that meets the constraints).
      names: design variables to optimise (others stay at the case's values).
      constraints: optimize.objectives.Constraint limits (>= 0 when met).
      bounds: name -> (low, high); default BOUNDS.
      iterations: the most simulations (each one forward solve and its adjoints).
      tol: the plan has reached its goal when the objective is below tol and every
        constraint is met (FEASIBLE).
      on_iteration: callback(row) after every simulation (progress, files).
      gradient_outcomes: outcomes whose gradients every simulation takes besides those
        the objective and constraints weigh there.
      start: a result of ``sim`` (e.g. an earlier plan's ``last``) that the first
        simulation is warm started from; each later one starts from the one before.
    """
    from scipy.optimize import minimize

    from eyefem.eye.variables import MATERIAL_VARIABLES, SURGICAL_VARIABLES

    for n in names:
        if n in MATERIAL_VARIABLES:
            raise ValueError(f"'{n}' is a material constant, not a surgical choice; its gradient "
                             "is for sensitivity studies (SurgerySimulator.gradients)")
        if n not in SURGICAL_VARIABLES:
            raise ValueError(f"unknown design variable '{n}'; choose from {sorted(SURGICAL_VARIABLES)}")
    if not objective_terms and not constraints:
        raise ValueError("no objective: give at least a target or a limit")
    bnd = bounds_for(sim, names, bounds)
    lo = np.array([bnd[n][0] for n in names])
    hi = np.array([bnd[n][1] for n in names])
    d0 = sim.design0()
    z0 = (np.array([d0[n] for n in names]) - lo) / (hi - lo)
    if np.any((z0 < 0) | (z0 > 1)):
        raise ValueError(f"the start {dict(zip(names, (d0[n] for n in names)))} is outside the "
                         f"bounds {bnd}")
    f_total = obj.total(objective_terms) if objective_terms else (lambda o: 0.0 * o["iop_mmhg"])
    history, cache, best, used_ever = [], {}, {}, set()
    last = {"result": start}  # the result the next simulation is warm started from

    def weights(fn, out):
        g = jax.grad(lambda o: fn(o))({k: jax.numpy.asarray(v) for k, v in out.items()})
        return {k: float(v) for k, v in g.items()}

    def evaluate(z):
        key = tuple(np.round(z, 14))
        if key in cache:
            return cache[key]
        if len(history) >= iterations:
            raise _Stop("stopped after the iteration limit")
        design = {**d0, **{n: float(lo[i] + z[i] * (hi[i] - lo[i])) for i, n in enumerate(names)}}
        tic = time.perf_counter()
        res = sim.run(design, start=last.get("result"))
        out = res.outcomes

        # d fn / d z of the objective and every constraint from one block adjoint of the
        # outcomes they weigh (SurgerySimulator.gradients: one right-hand side per outcome)
        w_all = [weights(fn, out) for fn in (f_total, *constraints)]
        used = sorted({k for w in w_all for k, v in w.items() if v} | set(gradient_outcomes))
        g_out = sim.gradients(res, used) if used else {}
        used_ever.update(used)
        last["result"] = _start_only(res)

        def gradient(w):
            return np.array([sum(w[k] * g_out[k][n] for k in used) for n in names]) * (hi - lo)

        f, gf = float(f_total(out)), gradient(w_all[0])
        cv = np.array([float(c(out)) for c in constraints])
        cg = np.array([gradient(w) for w in w_all[1:]]).reshape(len(constraints), len(names))
        feasible = bool(np.all(cv >= -FEASIBLE))
        pg = np.where(((z <= 0) & (gf > 0)) | ((z >= 1) & (gf < 0)), 0.0, gf)
        row = {"iteration": len(history), "objective": f,
               "constraint_violation": float(max(0.0, -cv.min(initial=0.0))),
               **{n: design[n] for n in names}, **out,
               **{f"constraint: {c.name}": v for c, v in zip(constraints, cv)},
               **{f"d_objective/d_{n}": gf[i] / (hi[i] - lo[i]) for i, n in enumerate(names)},
               "projected_gradient": float(np.linalg.norm(pg)),
               "newton_iterations": res.newton_iterations, "wall_s": time.perf_counter() - tic}
        history.append(row)
        merit = (0 if feasible else 1, f if feasible else -cv.min())
        if not best or merit < best["merit"]:
            best.update(merit=merit, objective=f, design=design, outcomes=out, gradients=g_out,
                        constraints=dict(zip((c.name for c in constraints), cv.tolist())))
        if on_iteration is not None:
            on_iteration(row)
        cache[key] = (f, gf, cv, cg)
        if feasible and f < tol:
            raise _Stop("reached the target")
        if feasible and np.linalg.norm(pg) < GRADIENT_TOL:
            raise _Stop("stationary: the objective's projected gradient vanishes")
        return cache[key]

    cons = [{"type": "ineq", "fun": lambda z, i=i: evaluate(z)[2][i],
             "jac": lambda z, i=i: evaluate(z)[3][i]} for i in range(len(constraints))]
    try:
        r = minimize(lambda z: evaluate(z)[0], z0, jac=lambda z: evaluate(z)[1], method="SLSQP",
                     bounds=[(0.0, 1.0)] * len(names), constraints=cons,
                     options={"maxiter": iterations, "ftol": 1e-3 * max(tol, 1e-12)})
        message = f"optimiser: {r.message}"
    except _Stop as stop:
        message = str(stop)
    values = best["constraints"]
    active = tuple(k for k, v in values.items() if -FEASIBLE <= v < FEASIBLE)
    violated = tuple(k for k, v in values.items() if v < -FEASIBLE)
    converged = best["merit"][0] == 0 and (best["objective"] < tol or message.startswith("stationary"))
    return PlanResult(history, {k: v for k, v in best.items() if k != "merit"}, converged,
                      message, active, violated, tuple(sorted(used_ever)), last["result"])


@dataclasses.dataclass
class LevelsResult:
    """A multi-fidelity plan: the search on the cheap level; the trusted level's
    simulations (``trusted``: its best design is the plan's); and per outcome the two
    levels' values at the search's best design (the first trusted simulation): {outcome:
    {"search", "trusted", "difference" (trusted - search), "relative" (difference /
    |trusted|, None at 0)}}; ``corrections``: the corrected searches between the trusted
    simulations."""

    search: PlanResult
    trusted: PlanResult
    levels: tuple[str, str]
    level_difference: dict
    corrections: list = dataclasses.field(default_factory=list)


class _StartedAt:
    """A simulator whose starting design is ``start`` (the rest as the case's)."""

    def __init__(self, sim, start: dict):
        self._sim, self._start = sim, dict(start)

    def design0(self) -> dict:
        return {**self._sim.design0(), **self._start}

    def __getattr__(self, name):
        return getattr(self._sim, name)


def _start_only(res):
    """``res`` as the next simulation's start, its gradients taken: its states without
    their assemblers (eyefem.eye.simulators.states_only), and the linear solver's analyses
    of its sparsity patterns freed (the next design's bites lie on other faces, so other
    patterns): the plan on ``fine`` peaked 0.19 GB higher keeping both
    (docs/performance.md, "Planner and other runs")."""
    from eyefem.eye.simulators import states_only
    from eyefem.solve.linsolve import free_shared_patterns

    free_shared_patterns()
    raw = res.raw if isinstance(res, _CorrectedResult) else res
    # a result without stages (a caller's own simulator's) as it is
    lean = states_only(raw) if hasattr(raw, "stages") else raw
    return dataclasses.replace(res, raw=lean) if raw is not res else lean


@dataclasses.dataclass
class _CorrectedResult:
    raw: object
    outcomes: dict
    newton_iterations: int


class _Corrected(_StartedAt):
    """The search level's simulator with its outcomes corrected to the trusted level's to
    first order at the design x_k (additive output correction): y(x) + d + G (x - x_k),
    d = y_T(x_k) - y(x_k), G = dy_T/dx(x_k) - dy/dx(x_k); so the corrected outcomes and
    their gradients equal the trusted level's at x_k."""

    def __init__(self, sim, start: dict, delta: dict, slope: dict):
        super().__init__(sim, start)
        self._delta, self._slope = delta, slope

    def run(self, design, start=None):
        res = self._sim.run(design, start=getattr(start, "raw", start))
        out = dict(res.outcomes)
        for k, d in self._delta.items():
            out[k] = out[k] + d + sum(g * (design[n] - self._start[n])
                                      for n, g in self._slope[k].items())
        return _CorrectedResult(res, out, res.newton_iterations)

    def gradients(self, res, used):
        g = self._sim.gradients(res.raw, used)
        return {k: {n: v + self._slope.get(k, {}).get(n, 0.0) for n, v in gk.items()}
                for k, gk in g.items()}


def _correction(trusted: dict, search: dict, names) -> tuple[dict, dict]:
    """(d, G) of :class:`_Corrected` from the two levels' best entries at one design
    (outcomes and gradients; the outcomes both have gradients of)."""
    keys = sorted(set(trusted["gradients"]) & set(search["gradients"]))
    delta = {k: float(trusted["outcomes"][k]) - float(search["outcomes"][k]) for k in keys}
    slope = {k: {n: float(trusted["gradients"][k][n]) - float(search["gradients"][k][n])
                 for n in names} for k in keys}
    return delta, slope


def _uncorrected(best: dict, delta: dict, slope: dict, x0: dict) -> dict:
    """The search level's own outcomes and gradients at a corrected search's best design
    (the correction about x0 taken off)."""
    d = best["design"]
    out = {k: v - delta[k] - sum(g * (d[n] - x0[n]) for n, g in slope[k].items())
           if k in delta else v for k, v in best["outcomes"].items()}
    grads = {k: {n: v - slope.get(k, {}).get(n, 0.0) for n, v in gk.items()}
             for k, gk in best["gradients"].items()}
    return {"outcomes": out, "gradients": grads}


def plan_levels(make_sim, levels, objective_terms, names, *, constraints=(), bounds=None,
                iterations=20, finish_iterations=6, tol=1e-2, on_iteration=None) -> LevelsResult:
    """Multi-fidelity planning: :func:`plan` on the cheap level; then, in turn, one trusted
    simulation at the current design and a search on the cheap level whose outcomes are
    corrected to the trusted level's there (value and gradient: :class:`_Corrected`),
    until a trusted simulation meets the goal (or ``finish_iterations`` of them).

    Args:
      make_sim: (level, start) -> a SurgerySimulator of the case on eye mesh ``level`` whose
        design starts at ``start`` (name -> value; {} for the case's own); called once
        per level (each level's simulations warm started from its last one).
      levels: (search level, trusted level), different.
      finish_iterations: the most simulations on the trusted level (its first is at the
        search's best design).
      on_iteration: callback(row) with the row's "mesh" (the level; the corrected
        searches' rows "<level>+correction") and "simulation" (a count over all).
      The other arguments as :func:`plan`'s, for every search.
    """
    search_level, level = levels
    if search_level == level:
        raise ValueError(f"--search-mesh {search_level}: the search level is the trusted level; "
                         "choose a cheaper one (e.g. coarse) or leave --search-mesh out")
    count = [0]

    def tagged(mesh):
        def hook(row):
            row.update(mesh=mesh, simulation=count[0])
            count[0] += 1
            if on_iteration is not None:
                on_iteration(row)
        return hook

    kw = dict(constraints=constraints, bounds=bounds, tol=tol)
    sim_s = make_sim(search_level, {})
    first = plan(sim_s, objective_terms, names, iterations=iterations,
                 on_iteration=tagged(search_level), **kw)
    wanted = first.outcomes_used
    x, cheap = {n: first.best["design"][n] for n in names}, first.best
    warm_s = first.last  # each level's simulations warm started from its last one
    if set(wanted) - set(cheap["gradients"]):  # weighed elsewhere, not at the best design
        warm_s = sim_s.run(first.best["design"], start=warm_s)  # a few Newton iterations
        cheap = {"outcomes": warm_s.outcomes,
                 "gradients": sim_s.gradients(warm_s, list(wanted))}
    sim_t, runs, corrections, warm_t = make_sim(level, x), [], [], None
    while True:
        one = plan(_StartedAt(sim_t, x), objective_terms, names, iterations=1,
                   on_iteration=tagged(level), gradient_outcomes=wanted, start=warm_t, **kw)
        runs.append(one)
        warm_t = one.last
        if one.converged or len(runs) >= finish_iterations:
            break
        delta, slope = _correction(one.best, cheap, names)
        model = _Corrected(sim_s, x, delta, slope)
        fixed = plan(model, objective_terms, names, iterations=iterations,
                     on_iteration=tagged(f"{search_level}+correction"),
                     gradient_outcomes=wanted, start=warm_s, **kw)
        corrections.append(fixed)
        warm_s = getattr(fixed.last, "raw", fixed.last)
        x_new = {n: fixed.best["design"][n] for n in names}
        if all(abs(x_new[n] - x[n]) <= 1e-9 * max(1.0, abs(x[n])) for n in names):
            break  # the corrected search stays where the trusted level was evaluated
        cheap = _uncorrected(fixed.best, delta, slope, x)
        x = x_new
    last = min(runs, key=lambda r: (0 if r.converged else 1, r.best["objective"]))
    history = [r.history[0] for r in runs]
    message = last.message if last.converged else (
        f"{len(runs)} simulations on {level}: " + runs[-1].message)
    trusted = dataclasses.replace(last, history=history, message=message)
    at_start, y0 = runs[0].best["outcomes"], first.best["outcomes"]
    diff = {}
    for k, v in y0.items():
        if k in at_start and isinstance(v, (int, float)) and np.isfinite(v):
            t = float(at_start[k])
            diff[k] = {"search": float(v), "trusted": t, "difference": t - float(v),
                       "relative": (t - float(v)) / abs(t) if t else None}
    return LevelsResult(first, trusted, (search_level, level), diff, corrections)


def study_errors(levels, encircling: bool) -> dict:
    """The mesh study's relative error estimates of each level (the largest over the
    studied cases of the buckle's kind), {outcome: {level: relative or None}}
    (eyefem.eye.mesh_error; None where the study has no estimate, e.g. on coarse)."""
    from eyefem.eye.mesh_error import QUOTED, mesh_error

    out: dict = {k: {} for k in QUOTED}
    for level in levels:
        err = mesh_error(level, encircling).get("outcomes", {})
        for k in QUOTED:
            rel = [e["relative"] for e in err.get(k, {}).values() if e.get("relative") is not None]
            out[k][level] = max(rel) if rel else None
    return out


def plot_history(path: Path, history: list[dict], objective_terms):
    """objective (log), IOP and indentation against iteration (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eyefem.io.output import atomic_path

    it = [r.get("simulation", r["iteration"]) for r in history]
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
    switch = [r["simulation"] for r, q in zip(history[1:], history) if r.get("mesh") != q.get("mesh")]
    ax[0].semilogy(it, [max(r["objective"], 1e-12) for r in history], "o-")
    ax[0].set_title("objective")
    ax[1].plot(it, [r["iop_mmhg"] for r in history], "o-", color="C3")
    ax[1].set_title("IOP, mmHg")
    ax[2].plot(it, [r["indentation_mm"] for r in history], "o-", color="C2")
    ax[2].set_title("indentation, mm")
    for t in objective_terms:
        if t.name.startswith("indentation="):
            ax[2].axhline(float(t.name.split("=")[1].rstrip("mm")), ls="--", color="k", lw=0.8)
    for a in ax:
        a.set_xlabel("simulation")
        a.grid(alpha=0.3)
        for x in switch:  # multi-fidelity: the search level left of the line, trusted right
            a.axvline(x - 0.5, color="0.5", lw=0.8, ls=":")
    if switch:
        ax[0].text(0.02, 0.04, f"{history[0]['mesh']} | {history[-1]['mesh']}",
                   transform=ax[0].transAxes, fontsize=8, color="0.3")
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _objectives_from_args(a) -> tuple[list, list]:
    """(objective terms, constraints) from the command line."""
    terms, cons = [], []
    if a.target_indentation is not None:
        terms.append(obj.target_indentation(a.target_indentation))
    if a.iop_max is not None:
        cons.append(obj.iop_at_most(a.iop_max))
    if a.iop_min is not None:
        cons.append(obj.iop_at_least(a.iop_min))
    if a.iop_max is not None and a.iop_min is not None and not a.iop_min < a.iop_max:
        raise ValueError(f"--iop-min {a.iop_min} and --iop-max {a.iop_max}: the IOP window is empty")
    if a.axial_max is not None:
        cons += obj.axial_change_within(a.axial_max)
    if a.suture_force_max is not None:
        cons.append(obj.suture_force_at_most(a.suture_force_max))
    if a.target_indentation_1w is not None:
        terms.append(obj.target_indentation_at("1w", a.target_indentation_1w))
    if a.target_refraction_1w is not None:
        terms.append(obj.target_refraction_at("1w", a.target_refraction_1w))
    if a.iop_peak_max is not None:
        cons.append(obj.iop_peak_at_most(a.iop_peak_max))
    if a.minutes_above_max is not None:
        cons.append(obj.minutes_above_at_most(a.minutes_above_max))
    return terms, cons


TIMELINE_FLAGS = ("iop_peak_max", "minutes_above_max", "target_indentation_1w",
                  "target_refraction_1w")
"""Options that read the outcomes of the surgery's timeline."""


def _check_timeline(a, params: dict, names) -> None:
    """ValueError for a timeline option or variable on a case off the timeline, or a
    target a week after surgery where the case's follow-up has no week."""
    flags = [f"--{f.replace('_', '-')}" for f in TIMELINE_FLAGS if getattr(a, f) is not None]
    wanted = flags + [n for n in names if n in TIMELINE_ONLY]
    if not params.get("volume_regulation", False):
        if wanted:
            raise ValueError(f"{', '.join(wanted)}: outcomes and variables of the surgery's "
                             "timeline; the case has volume_regulation = false (its cavity is "
                             "closed, no time passes): set volume_regulation = true in its "
                             "[parameters] (cases/surgery/timeline_case1.toml)")
        return
    from eyefem.eye.timeline import parse_followup

    week = [f for f in ("target_indentation_1w", "target_refraction_1w")
            if getattr(a, f) is not None]
    if week and "1w" not in dict(parse_followup(params["followup"])):
        raise ValueError(f"--{week[0].replace('_', '-')}: the case's followup = "
                         f"\"{params['followup']}\" has no 1w; add 1w to it")


TARGET_INDENTATION_MAX = 5.0
"""The deepest indentation a target may ask, mm: scleral buckles indent the wall by about
0.5 to 3 mm; beyond 5 mm no buckle of the catalogue reaches."""


def _check_args(a) -> dict:
    """Validate the numeric options; returns the --bounds overrides name -> (low, high).
    Raises ValueError naming the option, the value and the fix."""
    import math

    if a.iterations < 1:
        raise ValueError(f"--iterations {a.iterations}: need at least 1 (one simulation per "
                         "iteration)")
    if not math.isfinite(a.tol) or a.tol < 0:
        raise ValueError(f"--tol {a.tol}: need a finite value >= 0")
    limits = (("--target-indentation", a.target_indentation, 0.0, TARGET_INDENTATION_MAX, "mm"),
              ("--iop-max", a.iop_max, 0.0, 200.0, "mmHg"),
              ("--iop-min", a.iop_min, 0.0, 200.0, "mmHg"),
              ("--axial-max", a.axial_max, 0.0, 5.0, "mm"),
              ("--suture-force-max", a.suture_force_max, 0.0, 50.0, "N"),
              ("--iop-peak-max", a.iop_peak_max, 0.0, 200.0, "mmHg"),
              ("--minutes-above-max", a.minutes_above_max, 0.0, 600.0, "min"),
              ("--target-indentation-1w", a.target_indentation_1w, 0.0,
               TARGET_INDENTATION_MAX, "mm"),
              ("--target-refraction-1w", a.target_refraction_1w, -15.0, 15.0, "D"))
    for flag, v, lo, hi, unit in limits:
        if v is None:
            continue
        if not math.isfinite(v):
            raise ValueError(f"{flag} {v}: need a finite number of {unit}")
        if not lo < v <= hi:
            raise ValueError(f"{flag} {v:g} {unit} cannot be reached by a buckling surgery "
                             f"(the planner takes {lo:g} < value <= {hi:g} {unit}); check the "
                             "value and its unit")
    if a.iop_min is not None and a.iop_max is not None and not a.iop_min < a.iop_max:
        raise ValueError(f"--iop-min {a.iop_min:g} must be below --iop-max {a.iop_max:g} mmHg")
    names = [v.strip() for v in a.vars.split(",")]
    if not any(names) or not all(names):
        raise ValueError(f"--vars '{a.vars}': give design variables separated by commas, e.g. "
                         "--vars tightening,suture_width")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"--vars '{a.vars}': {', '.join(twice)} given twice; name each "
                         "variable once")
    overrides = {}
    for item in a.bounds:
        name, sep, rng = item.partition("=")
        lo, colon, hi = rng.partition(":")
        try:
            low, high = float(lo), float(hi)
        except ValueError:
            low = high = math.nan
        if not sep or not colon or not (math.isfinite(low) and math.isfinite(high)):
            raise ValueError(f"--bounds '{item}': expected NAME=LOW:HIGH with finite numbers, "
                             "e.g. tightening=2:12")
        if not low < high:
            raise ValueError(f"--bounds '{item}': LOW must be below HIGH")
        overrides[name.strip()] = (low, high)
    return overrides


def _check_start(case, start: dict, bounds: dict):
    """ValueError when a start value (from the case) is outside its bounds: the optimiser
    would clip it silently."""
    for n, (lo, hi) in bounds.items():
        if not lo <= start[n] <= hi:
            raise ValueError(f"the start {n} = {start[n]:g} (from {case}) is outside its bounds "
                             f"[{lo:g}, {hi:g}]; change the case or give --bounds {n}=LOW:HIGH")


def _check_levels(a, level: str) -> tuple[str, ...]:
    """(level,) or, with --search-mesh, (search level, trusted level); ValueError for an
    unknown level, the same level twice or --finish-iterations below 1."""
    if a.search_mesh is None:
        return (level,)
    from eyefem.eye.eyemodel import level_spec

    level_spec(a.search_mesh)
    if a.search_mesh == level:
        raise ValueError(f"--search-mesh {a.search_mesh}: the case already plans on "
                         f"'{level}'; search on a cheaper level (e.g. coarse) or leave "
                         "--search-mesh out")
    if a.finish_iterations < 1:
        raise ValueError(f"--finish-iterations {a.finish_iterations}: need at least 1")
    return (a.search_mesh, level)


QUOTE_DIFFERENCE = ("iop_mmhg", "indentation_mm", "axial_length_change_mm",
                    "refraction_change_D", "max_suture_force_N")
"""The outcomes whose level difference the plan prints (all are in plan_summary.json)."""
STUDY_KEY = {"iop_mmhg": "iop_rise_mmhg"}
"""The mesh study's name of an outcome where it differs (it estimates the IOP's rise)."""


def _levels_summary(r: LevelsResult, encircling: bool) -> dict:
    """plan_summary.json's multi-fidelity entries."""
    s = r.search
    return {"search": {"mesh": r.levels[0], "simulations": len(s.history),
                       "converged": s.converged, "message": s.message,
                       "design": s.best["design"], "outcomes": s.best["outcomes"]},
            "trusted_mesh": r.levels[1], "trusted_simulations": len(r.trusted.history),
            "corrected_search_simulations": sum(len(c.history) for c in r.corrections),
            "level_difference": r.level_difference,
            "mesh_error": study_errors(r.levels, encircling)}


def _levels_lines(summary: dict) -> list[str]:
    """Terminal lines: the levels' outcomes at the search's design, the study's errors."""
    lo, hi = summary["search"]["mesh"], summary["trusted_mesh"]
    lines = [f"  searched on {lo} ({summary['search']['simulations']} simulations), "
             f"{hi} {summary['trusted_simulations']} (with {lo} corrected to it: "
             f"{summary['corrected_search_simulations']}); at the search's design:"]
    for k in QUOTE_DIFFERENCE:
        d = summary["level_difference"].get(k)
        if d is None:
            continue
        study_key = STUDY_KEY.get(k, k)
        est = summary["mesh_error"].get(study_key, {})
        of = " of the rise" if study_key != k else ""
        quote = ", ".join(f"{lv} {100 * est[lv]:.1f} %{of}" if est.get(lv) is not None
                          else f"{lv} not estimated" for lv in (lo, hi))
        rel = f"{100 * d['relative']:+.1f} %" if d["relative"] is not None else "-"
        lines.append(f"    {k:<24} {lo} {d['search']:.4f}, {hi} {d['trusted']:.4f} ({rel}; "
                     f"mesh study: {quote})")
    return lines


def main(argv=None) -> int:
    jax.config.update("jax_enable_x64", True)
    from eyefem.catalog import schemas, solver_defaults
    from eyefem.api import with_material_preset
    from eyefem.eye.simulators import SurgerySimulator
    from eyefem.io.casefile import CaseError, load_case
    from eyefem.io.output import write_case, write_csv, write_text
    from eyefem.solve.device import keep_compiled_by_default
    from eyefem.solve.heap import configure_heap
    from eyefem.solve.solver import ConvergenceError

    keep_compiled_by_default()
    configure_heap()
    ap = argparse.ArgumentParser(prog="python -m optimize.plan", description=__doc__.split("\n")[0])
    ap.add_argument("case", help="surgery case file (TOML)")
    ap.add_argument("--mesh", help="override the case's eye mesh level (coarse, medium, default, fine, finer)")
    ap.add_argument("--materials", metavar="PRESET", choices=("seed", "physiological"),
                    help="tissue constants preset (as eyefem run --materials): replaces the "
                    "case's materials_preset and its own [materials] tables of the eye's tissues")
    ap.add_argument("--vars", default="tightening,suture_width,buckle_shift",
                    help="comma-separated design variables to optimise")
    ap.add_argument("--target-indentation", type=float, help="indentation target, mm")
    ap.add_argument("--iop-max", type=float, help="upper IOP limit, mmHg")
    ap.add_argument("--iop-min", type=float, help="lower IOP limit, mmHg")
    ap.add_argument("--axial-max", type=float, help="limit on |axial length change|, mm")
    ap.add_argument("--suture-force-max", type=float, help="limit on the largest suture force, N")
    ap.add_argument("--iop-peak-max", type=float, metavar="MMHG",
                    help="limit on the peak IOP on the table, mmHg (a case on the timeline)")
    ap.add_argument("--minutes-above-max", type=float, metavar="MIN",
                    help="limit on the minutes above the central retinal artery's closing "
                    "pressure (cra_closing_mmhg), min (a case on the timeline)")
    ap.add_argument("--target-indentation-1w", type=float, metavar="MM",
                    help="buckle height target a week after surgery, mm (a case on the "
                    "timeline)")
    ap.add_argument("--target-refraction-1w", type=float, metavar="D",
                    help="refraction change target a week after surgery, dioptres (negative: "
                    "myopic; a case on the timeline)")
    ap.add_argument("--iterations", type=int, default=20, help="the most simulations")
    ap.add_argument("--search-mesh", metavar="LEVEL",
                    help="multi-fidelity: search on this cheaper eye mesh level first (to "
                    "--iterations simulations), then finish on the case's level (or --mesh)")
    ap.add_argument("--finish-iterations", type=int, default=6, metavar="N",
                    help="with --search-mesh: the most simulations on the trusted level "
                    "(default 6)")
    ap.add_argument("--tol", type=float, default=1e-2,
                    help="stop when the objective is below this with every limit met")
    ap.add_argument("--out", default="results/plan", help="output directory")
    ap.add_argument("--bounds", action="append", metavar="NAME=LOW:HIGH", default=[],
                    help="bounds of a design variable (repeatable), e.g. tightening=2:12")
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu",
                    help="where the element kernels run (default cpu); with gpu the "
                    "factorisations too where cuDSS is installed (eyefem --device)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)-7s %(message)s",
                        datefmt="%H:%M:%S")
    logging.getLogger("eyefem").setLevel(logging.WARNING)
    from eyefem.solve.device import DeviceError, select_device

    try:
        where = select_device(a.device)
    except DeviceError as exc:
        print(f"python -m optimize.plan: {exc}", file=sys.stderr)
        return 2
    if a.device != "cpu":
        from eyefem.solve.linsolve import default_backend

        log.info("element kernels on %s; factorisations: %s", where, default_backend())
    try:
        overrides = _check_args(a)
        case = load_case(a.case, schemas(), solver_defaults())
        if case.problem != "surgery":
            raise CaseError(f"{a.case}: problem '{case.problem}'; the planner needs a surgery case")
        if a.materials:
            case = with_material_preset(case, a.materials)
        params = dict(case.parameters)
        if a.mesh:
            params["mesh"] = a.mesh
        terms, cons = _objectives_from_args(a)
        if not terms and not cons:
            raise CaseError("give an objective: --target-indentation and/or limits (--iop-max ...)")
        names = [v.strip() for v in a.vars.split(",") if v.strip()]
        if "buckle_meridian_deg" in names and params.get("symmetry", "none") == "mirror":
            log.info("symmetry = 'mirror' with the meridian planned: a buckle turned off the "
                     "plane breaks the symmetry, so the whole eye is solved")
            params["symmetry"] = "none"
        _check_timeline(a, params, names)
        levels = _check_levels(a, params["mesh"])
        log.info("planning %s on the %s mesh: %s subject to %s over %s", case.path,
                 params["mesh"], " + ".join(t.name for t in terms) or "no objective",
                 ", ".join(c.name for c in cons) or "no limit", ", ".join(names))
        unknown = [n for n in [*names, *overrides] if n not in BOUNDS]
        if unknown:
            raise CaseError(f"unknown design variable(s) {unknown}; choose from {sorted(BOUNDS)}")
        known = {n: overrides.get(n, BOUNDS[n]) for n in names}  # checked before building
        _check_start(a.case, {n: params[n] for n in names}, {
            n: (-np.inf if lo is None else lo, np.inf if hi is None else hi)
            for n, (lo, hi) in known.items()})
        sim = SurgerySimulator({**params, "mesh": levels[0]}, case.materials, case.solver)
        bounds = bounds_for(sim, names, overrides)
        _check_start(a.case, sim.design0(), bounds)
    except (CaseError, ValueError) as exc:
        print(f"plan: {exc}", file=sys.stderr)
        return 2
    except ConvergenceError as exc:  # the case itself (its pre-operative eye) did not solve
        print(f"plan: {a.case}: the case does not converge before planning starts: {exc}",
              file=sys.stderr)
        return 3
    out = Path(a.out)
    rows = []

    def progress(row):
        beat.news()
        rows.append(row)
        write_csv(out / "plan_history.csv", rows)
        peak = (f"  peak IOP {row['peak_iop_on_table_mmhg']:.2f} mmHg, "
                f"{row['minutes_above_cra_closing']:.2f} min above closing"
                if "peak_iop_on_table_mmhg" in row else "")
        where = f" on {row['mesh']}" if "mesh" in row else ""
        log.info("sim %2d%s  objective %.4g  violation %.3g  %s  IOP %.2f mmHg  indentation %.3f "
                 "mm%s  (%d Newton its, %.1f s)", row.get("simulation", row["iteration"]), where,
                 row["objective"],
                 row["constraint_violation"], "  ".join(f"{n} {row[n]:.3f}" for n in names),
                 row["iop_mmhg"], row["indentation_mm"], peak, row["newton_iterations"],
                 row["wall_s"])

    beat = Heartbeat(lambda: f"simulation {len(rows)} (with its adjoints)", interval=60.0,
                     logger=log)
    levels_result = None

    def make_sim(level, start):
        if level == levels[0] and not start:
            return sim
        return SurgerySimulator({**params, **start, "mesh": level}, case.materials, case.solver)
    try:
        with beat:
            if len(levels) == 2:
                levels_result = plan_levels(make_sim, levels, terms, names, constraints=cons,
                                            bounds=bounds, iterations=a.iterations,
                                            finish_iterations=a.finish_iterations, tol=a.tol,
                                            on_iteration=progress)
                res = dataclasses.replace(levels_result.trusted, history=rows)
            else:
                res = plan(sim, terms, names, constraints=cons, bounds=bounds,
                           iterations=a.iterations, tol=a.tol, on_iteration=progress)
    except (ConvergenceError, ValueError) as exc:
        print(f"plan: {exc}\nthe history so far is in {out / 'plan_history.csv'}", file=sys.stderr)
        return 3
    plot_history(out / "plan.png", res.history, terms)
    best = res.best
    planned = {**case.raw.get("parameters", {}), **{n: round(best["design"][n], 4) for n in names}}
    if a.mesh:
        planned["mesh"] = a.mesh
    write_case(out / "planned_case.toml", "surgery", f"Planned: {case.title}", planned,
               case.raw.get("materials"), "Design found by optimize.plan: "
               + "; ".join(t.name for t in terms))
    summary = {"case": str(case.path), "converged": res.converged, "message": res.message,
               "objective": best["objective"], "constraints": best["constraints"],
               "active_constraints": list(res.active),
               "violated_constraints": list(res.violated), "design": best["design"],
               "outcomes": best["outcomes"], "simulations": len(res.history)}
    if levels_result is not None:
        summary.update(_levels_summary(levels_result, sim.parts.buckle.encircling))
    write_text(out / "plan_summary.json", json.dumps(summary, indent=2) + "\n")
    print(f"\n{res.message}: objective {best['objective']:.4g}")
    for k, v in best["constraints"].items():
        state = ("VIOLATED" if k in res.violated else "active" if k in res.active else "met")
        print(f"  constraint {k:<26} {state} ({v:+.3g} tolerance units)")
    if res.violated:
        print(f"  no design within the bounds meets {', '.join(res.violated)} with this target: "
              "relax the limit or the target, or widen the bounds (--bounds)")
    for n in names:
        print(f"  {n:<20} {best['design'][n]:.4f}")
    for k, v in best["outcomes"].items():
        print(f"  {k:<24} {v:.4f}")
    if levels_result is not None:
        for line in _levels_lines(summary):
            print(line)
    print(f"  results in {out}/")
    return 0 if res.converged else 1


if __name__ == "__main__":
    sys.exit(main())
