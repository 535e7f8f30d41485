"""Surgical planning: optimise the design of a surgery case with optax and adjoint gradients.

    python -m optimize.plan cases/surgery/case1.toml --mesh coarse \\
        --target-indentation 1.0 --iop-max 21 --vars tightening,suture_width

Each iteration solves the case at the current design (warm started from the previous
converged states), computes the adjoint gradients of the outcomes the objective reads,
and takes a projected Adam step (decaying step size) on the design variables scaled
to [0, 1] by their bounds. Writes into --out: plan_history.csv (every iteration), plan.png (objective,
IOP and indentation against iteration), planned_case.toml (the case with the best
design) and plan_summary.json.
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
}


@dataclasses.dataclass
class PlanResult:
    """History rows, the best design and its outcomes."""

    history: list[dict]
    best: dict
    converged: bool


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


def plan(sim, objective_terms, names, *, bounds=None, iterations=20, learning_rate=0.08,
         tol=1e-2, on_iteration=None) -> PlanResult:
    """Projected Adam on the design variables ``names`` of a SurgerySimulator.

    Args:
      sim: eyefem.eye.design.SurgerySimulator (its case gives the starting design).
      objective_terms: list of optimize.objectives.Objective.
      names: design variables to optimise (others stay at the case's values).
      bounds: name -> (low, high); default BOUNDS.
      iterations: maximum number of simulations.
      learning_rate: first Adam step in the [0, 1]-scaled variables (decays by 0.8 per
        iteration to 5% of it).
      tol: stop when the objective falls below tol.
      on_iteration: callback(row) after every iteration (progress, files).
    """
    import optax

    from eyefem.eye.design import MATERIAL_VARIABLES, SURGICAL_VARIABLES

    for n in names:
        if n in MATERIAL_VARIABLES:
            raise ValueError(f"'{n}' is a material constant, not a surgical choice; its gradient "
                             "is for sensitivity studies (SurgerySimulator.gradients)")
        if n not in SURGICAL_VARIABLES:
            raise ValueError(f"unknown design variable '{n}'; choose from {sorted(SURGICAL_VARIABLES)}")
    bnd = bounds_for(sim, names, bounds)
    lo = np.array([bnd[n][0] for n in names])
    hi = np.array([bnd[n][1] for n in names])
    d0 = sim.design0()
    z = np.clip((np.array([d0[n] for n in names]) - lo) / (hi - lo), 0.0, 1.0)
    f_total = obj.total(objective_terms)
    uses = sorted({u for t in objective_terms for u in t.uses})
    df_do = jax.grad(lambda o: f_total(o))
    # the step decays (x 0.8 per iteration) so that Adam's momentum settles on the target
    # instead of circling it
    opt = optax.adam(optax.exponential_decay(learning_rate, transition_steps=1, decay_rate=0.8,
                                             end_value=0.05 * learning_rate))
    state = opt.init(z)
    history, best = [], None
    for it in range(iterations):
        design = {**d0, **{n: float(lo[i] + z[i] * (hi[i] - lo[i])) for i, n in enumerate(names)}}
        tic = time.perf_counter()
        res = sim.run(design)
        out = res.outcomes
        f = float(f_total(out))
        grads = sim.gradients(res, uses)
        w = df_do({k: out[k] for k in out})
        g_design = np.array([sum(float(w[o]) * grads[o][n] for o in uses) for n in names])
        g_z = g_design * (hi - lo)
        row = {"iteration": it, "objective": f, **{n: design[n] for n in names}, **out,
               **{f"d_objective/d_{n}": g_design[i] for i, n in enumerate(names)},
               "newton_iterations": res.newton_iterations, "wall_s": time.perf_counter() - tic}
        history.append(row)
        if best is None or f < best["objective"]:
            best = {"objective": f, "design": design, "outcomes": out}
        if on_iteration is not None:
            on_iteration(row)
        if f < tol:
            return PlanResult(history, best, True)
        updates, state = opt.update(g_z, state, z)
        z = np.clip(np.asarray(optax.apply_updates(z, updates)), 0.0, 1.0)
    return PlanResult(history, best, False)


def plot_history(path: Path, history: list[dict], objective_terms):
    """objective (log), IOP and indentation against iteration (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eyefem.io.output import atomic_path

    it = [r["iteration"] for r in history]
    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
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
        a.set_xlabel("iteration")
        a.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(Path(path)) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _objectives_from_args(a) -> list:
    terms = []
    if a.target_indentation is not None:
        terms.append(obj.target_indentation(a.target_indentation))
    if a.iop_max is not None or a.iop_min is not None:
        terms.append(obj.iop_window(a.iop_min if a.iop_min is not None else 0.0,
                                    a.iop_max if a.iop_max is not None else 1e9))
    if a.axial_max is not None:
        terms.append(obj.axial_length_limit(a.axial_max))
    if a.suture_force_max is not None:
        terms.append(obj.suture_force_limit(a.suture_force_max))
    return terms


def main(argv=None) -> int:
    jax.config.update("jax_enable_x64", True)
    from eyefem.catalog import schemas
    from eyefem.cli.dialogue import write_case
    from eyefem.eye.design import SurgerySimulator
    from eyefem.io.casefile import CaseError, load_case
    from eyefem.io.output import write_csv, write_text
    from eyefem.solve.solver import ConvergenceError

    ap = argparse.ArgumentParser(prog="python -m optimize.plan", description=__doc__.split("\n")[0])
    ap.add_argument("case", help="surgery case file (TOML)")
    ap.add_argument("--mesh", help="override the case's eye mesh level (coarse, medium, default)")
    ap.add_argument("--vars", default="tightening,suture_width,buckle_shift",
                    help="comma-separated design variables to optimise")
    ap.add_argument("--target-indentation", type=float, help="indentation target, mm")
    ap.add_argument("--iop-max", type=float, help="upper IOP limit, mmHg")
    ap.add_argument("--iop-min", type=float, help="lower IOP limit, mmHg")
    ap.add_argument("--axial-max", type=float, help="limit on |axial length change|, mm")
    ap.add_argument("--suture-force-max", type=float, help="limit on the largest suture force, N")
    ap.add_argument("--iterations", type=int, default=20)
    ap.add_argument("--lr", type=float, default=0.08, help="Adam step in bound-scaled variables")
    ap.add_argument("--tol", type=float, default=1e-2, help="stop when the objective is below")
    ap.add_argument("--out", default="results/plan", help="output directory")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)-7s %(message)s",
                        datefmt="%H:%M:%S")
    logging.getLogger("eyefem").setLevel(logging.WARNING)
    try:
        case = load_case(a.case, schemas())
        if case.problem != "surgery":
            raise CaseError(f"{a.case}: problem '{case.problem}'; the planner needs a surgery case")
        params = dict(case.parameters)
        if a.mesh:
            params["mesh"] = a.mesh
        terms = _objectives_from_args(a)
        if not terms:
            raise CaseError("give an objective: --target-indentation and/or limits (--iop-max ...)")
        names = [v.strip() for v in a.vars.split(",") if v.strip()]
        log.info("planning %s on the %s mesh: %s over %s", case.path, params["mesh"],
                 " + ".join(t.name for t in terms), ", ".join(names))
        sim = SurgerySimulator(params, case.materials, case.solver)
    except (CaseError, ValueError) as exc:
        print(f"plan: {exc}", file=sys.stderr)
        return 2
    out = Path(a.out)
    rows = []

    def progress(row):
        rows.append(row)
        write_csv(out / "plan_history.csv", rows)
        log.info("iter %2d  objective %.4g  %s  IOP %.2f mmHg  indentation %.3f mm  (%d Newton its, "
                 "%.1f s)", row["iteration"], row["objective"],
                 "  ".join(f"{n} {row[n]:.3f}" for n in names), row["iop_mmhg"],
                 row["indentation_mm"], row["newton_iterations"], row["wall_s"])

    try:
        res = plan(sim, terms, names, iterations=a.iterations, learning_rate=a.lr, tol=a.tol,
                   on_iteration=progress)
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
    summary = {"case": str(case.path), "converged": res.converged, "objective": best["objective"],
               "design": best["design"], "outcomes": best["outcomes"],
               "iterations": len(res.history)}
    write_text(out / "plan_summary.json", json.dumps(summary, indent=2) + "\n")
    print(f"\n{'reached the target' if res.converged else 'stopped after the iteration limit'}: "
          f"objective {best['objective']:.4g}")
    for n in names:
        print(f"  {n:<20} {best['design'][n]:.4f}")
    for k, v in best["outcomes"].items():
        print(f"  {k:<24} {v:.4f}")
    print(f"  results in {out}/")
    return 0 if res.converged else 1


if __name__ == "__main__":
    sys.exit(main())
