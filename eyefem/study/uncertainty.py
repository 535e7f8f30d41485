"""Uncertainty of a planned surgery's outcomes from stated distributions of its inputs.

Two ways, compared by ``eyefem sweep FILE --uncertainty`` (docs/uncertainty.md):

- **first order** (:func:`first_order`): one forward solve and the gradients at the
  centre of the distributions: by the adjoint (eyefem.simulate + jax.jacrev) for the
  design variables of a rigid-buckle surgery case; by central differences for any other
  real-valued input (biometry such as ``parameters.axial_length``, which changes the
  mesh, or any parameter or material coefficient of a non-surgery case): two more solves
  per such input, at x0 +- h, h = fd_step |x0|. For independent inputs x_i with standard
  deviations s_i, an outcome y has

      mean(y) ~ y(x0),   std(y) ~ sqrt(sum_i (dy/dx_i s_i)^2),

  x0 the means (normal), midpoints (uniform, s = (high - low)/sqrt 12) or medians
  (lognormal, linearised in log x: the term is dy/dx_i x0_i sigma_i). The terms
  dy/dx_i s_i are the sensitivities of the tornado chart.
- **sampled** (:func:`sampled`): the mean and standard deviation of the outcomes over
  the sweep's samples (random or Latin hypercube) of the same distributions.

The first-order figures are exact for outcomes linear in the inputs; their gap to the
sampled ones measures the curvature of the response over the stated spread (plus the
sampling error of n samples, about std/sqrt(n) on the mean).
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path

import numpy as np

from eyefem.eye.variables import OUTCOMES
from eyefem.study.spec import (
    ADJOINT,
    CENTRAL,
    FD_STEP,
    Distribution,
    Sweep,
    SweepError,
    case_raw,
    design_variable,  # noqa: F401 - re-exported (was defined here)
    differentiable_input,
    fd_step,
)


def method_of(key: str) -> str:
    """How first_order differentiates by an input key: ADJOINT for a design variable
    name, CENTRAL for a dotted path."""
    return CENTRAL if "." in key else ADJOINT


def first_order(case, dists: dict[str, Distribution], outcomes=None, *,
                rel_step: float = FD_STEP) -> dict:
    """First-order mean and std of the outcomes of a case.

    Args:
      case: a case-file path or Case.
      dists: input -> Distribution (independent inputs); an input is a design variable
        of a rigid-buckle surgery case (the adjoint of eyefem.simulate) or a dotted path
        (parameters.NAME, materials.NAME.cRS) of any case (central differences: two more
        solves each, by eyefem.simulate for a surgery case, else by a run of the case).
      outcomes: the outcome names (default: OUTCOMES for a surgery case, else every
        number of the run at the centre).
      rel_step: relative step of the central differences, h = rel_step |x0|.

    Returns: {"centre": {input: x0}, "method": {input: "adjoint" | "central
    differences"}, "step": {input: h}, "solves": forward solves done, "mean": {outcome:
    y(x0)}, "std": {outcome: std}, "gradient": {outcome: {input: dy/dx}}, "terms":
    {outcome: {input: dy/dx s}}}.
    """
    import jax

    from eyefem.api import load_case, simulate
    from eyefem.study.task import case_with, outcomes_of

    case = load_case(case) if isinstance(case, (str, Path)) else case
    surgery = case.problem == "surgery"
    adjoint = {v: d for v, d in dists.items() if method_of(v) == ADJOINT}
    central = {p: d for p, d in dists.items() if method_of(p) == CENTRAL}
    if adjoint and not surgery:
        raise ValueError(f"{case.path}: adjoint gradients by {', '.join(adjoint)} need a surgery "
                         f"case (eyefem.simulate); the case's problem is '{case.problem}'; give "
                         "dotted paths (parameters.NAME, materials.NAME.cRS) for central "
                         "differences")
    x0 = {v: d.centre for v, d in adjoint.items()}
    steps = {p: fd_step(d.centre, rel_step) for p, d in central.items()}
    res = {"centre": {v: d.centre for v, d in dists.items()},
           "method": {v: method_of(v) for v in dists}, "step": steps, "solves": 1,
           "mean": {}, "std": {}, "gradient": {}, "terms": {}}
    with tempfile.TemporaryDirectory(prefix="eyefem-uq-") as tmp:
        def solve(c, tag):
            return simulate(c, x0) if surgery else outcomes_of(c, Path(tmp) / tag)

        centre = (case_with(case, {p: d.centre for p, d in central.items()}, tmp, "centre")
                  if central else case)
        y0 = solve(centre, "centre")
        outcomes = list(outcomes) if outcomes else (list(OUTCOMES) if surgery else
                                                    [k for k in y0 if k != "wall_s"])
        missing = [o for o in outcomes if o not in y0]
        if missing:
            raise ValueError(f"{case.path}: outcome '{missing[0]}' is not a number of the run; "
                             f"known: {', '.join(sorted(y0))}")
        grad = {o: {} for o in outcomes}
        if adjoint:
            jac = jax.jacrev(lambda d: simulate(centre, d))(x0)
            for o in outcomes:
                grad[o].update({v: float(jac[o][v]) for v in adjoint})
        for p, d in central.items():
            ys = [solve(case_with(centre, {p: d.centre + sign * steps[p]}, tmp, f"{p}_{tag}"),
                        f"{p}_{tag}") for sign, tag in ((1, "plus"), (-1, "minus"))]
            res["solves"] += 2
            for o in outcomes:
                grad[o][p] = float(ys[0][o] - ys[1][o]) / (2 * steps[p])
    for o in outcomes:
        g = {v: grad[o][v] for v in dists}
        terms = {v: g[v] * (d.centre if d.kind == "lognormal" else 1.0) * d.linear_std()
                 for v, d in dists.items()}
        res["mean"][o] = float(y0[o])
        res["std"][o] = math.sqrt(sum(t * t for t in terms.values()))
        res["gradient"][o] = g
        res["terms"][o] = terms
    return res


def sampled(rows: list[dict], outcomes) -> dict:
    """Mean, std (n - 1) and n of each outcome over the successful rows of a table."""
    res = {"mean": {}, "std": {}, "n": {}}
    for o in outcomes:
        v = np.array([r[o] for r in rows if r["status"] == "ok" and isinstance(r.get(o), float)
                      and math.isfinite(r[o])])
        res["n"][o] = int(v.size)
        res["mean"][o] = float(v.mean()) if v.size else math.nan
        res["std"][o] = float(v.std(ddof=1)) if v.size > 1 else math.nan
    return res


def sweep_distributions(sweep: Sweep) -> dict[str, Distribution]:
    """The sweep's sampled distributions by input: a design variable name (adjoint) for
    a design variable of a rigid-buckle surgery case, else the sampled dotted path
    (central differences). ValueError (naming the file, the parameter, the reason and
    the fix) for a sweep without samples or a sampled input that cannot be
    differentiated (a solver option, an integer parameter)."""
    if not sweep.distributions:
        raise ValueError(f"{sweep.path}: --uncertainty propagates the [samples] distributions; "
                         "the sweep has none: add a [samples] section (docs/uncertainty.md)")
    body = str(sweep.fixed.get("parameters.buckle_body",
                               sweep.base.parameters.get("buckle_body", "rigid")))
    out = {}
    for p, d in sweep.distributions.items():
        try:
            key, _ = differentiable_input(p, sweep.base, body, f"{sweep.path} [samples]")
        except SweepError as exc:
            raise ValueError(f"{exc} (--uncertainty needs the derivative of the outcomes by "
                             "every sampled input)") from None
        out[key] = d
    return out


def planned_case(sweep: Sweep):
    """The base case with the sweep's fixed overrides ([set]), parsed."""
    import tomli_w

    from eyefem.api import load_case

    with tempfile.TemporaryDirectory(prefix="eyefem-uq-") as tmp:
        f = Path(tmp) / f"{sweep.case_path.stem}.toml"
        f.write_text(tomli_w.dumps(case_raw(sweep, {})), encoding="utf-8")
        return load_case(f)


def plot(fo: dict, rows: list[dict], outcomes, dists: dict, out_dir: Path) -> list[Path]:
    """uncertainty_hist.png (sampled histograms against the first-order normal) and
    uncertainty_tornado.png (dy/dx_i s_i per input) in ``out_dir``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(outcomes)
    ncol = min(n, 3)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.3 * ncol, 3.2 * nrow), squeeze=False)
    for ax, o in zip(axes.flat, outcomes):
        v = np.array([r[o] for r in rows if r["status"] == "ok" and isinstance(r.get(o), float)])
        m, s = fo["mean"][o], fo["std"][o]
        if v.size:
            ax.hist(v, bins=max(4, int(math.sqrt(v.size)) + 1), density=True, alpha=0.6,
                    label=f"sampled (n={v.size})")
        if s > 0:
            lo = min(m - 4 * s, v.min() if v.size else m)
            hi = max(m + 4 * s, v.max() if v.size else m)
            x = np.linspace(lo, hi, 200)
            ax.plot(x, np.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi)), "k-",
                    lw=1.5, label="first order")
        ax.set_xlabel(o)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.suptitle("outcomes: sampled histogram against the first-order normal")
    fig.tight_layout()
    hist = Path(out_dir) / "uncertainty_hist.png"
    fig.savefig(hist, dpi=90)
    plt.close(fig)
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.3 * ncol, 0.5 * len(dists) * nrow + 1.6 * nrow),
                             squeeze=False)
    for ax, o in zip(axes.flat, outcomes):
        terms = sorted(fo["terms"][o].items(), key=lambda kv: abs(kv[1]))
        names = [k for k, _ in terms]
        vals = np.array([t for _, t in terms])
        ax.barh(names, vals, color=["tab:red" if t < 0 else "tab:blue" for t in vals])
        ax.barh(names, -vals, color="none", edgecolor="0.5")
        ax.axvline(0, color="k", lw=0.8)
        ax.set_title(o, fontsize=9)
        ax.set_xlabel("dy/dx s (change for +1 std)", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.tight_layout()
    tornado = Path(out_dir) / "uncertainty_tornado.png"
    fig.savefig(tornado, dpi=90)
    plt.close(fig)
    return [hist, tornado]


def report(sweep: Sweep, rows: list[dict], out_dir: Path) -> str:
    """Compare first-order and sampled statistics of a sampled sweep; writes
    uncertainty.json and the two plots in ``out_dir`` and returns a Markdown table (and
    how each input was differentiated)."""
    from eyefem.study.plots import outcome_columns

    dists = sweep_distributions(sweep)
    if sweep.base.problem == "surgery":
        outcomes = [o for o in (sweep.outcomes or OUTCOMES) if o in OUTCOMES]
    else:
        outcomes = list(sweep.outcomes) or outcome_columns(rows, sweep.varied)
    fo = first_order(planned_case(sweep), dists, outcomes, rel_step=sweep.fd_step)
    sa = sampled(rows, outcomes)
    Path(out_dir, "uncertainty.json").write_text(json.dumps(
        {"inputs": {v: d.describe() for v, d in dists.items()}, "first_order": fo,
         "sampled": sa}, indent=1) + "\n")
    plot(fo, rows, outcomes, dists, out_dir)
    lines = ["| outcome | first-order mean | sampled mean | first-order std | sampled std | n |",
             "|---|---|---|---|---|---|"]
    for o in outcomes:
        lines.append(f"| {o} | {fo['mean'][o]:.4g} | {sa['mean'][o]:.4g} | {fo['std'][o]:.3g} "
                     f"| {sa['std'][o]:.3g} | {sa['n'][o]} |")
    how = [f"{v} ({m}" + (f", h = {fo['step'][v]:.3g}" if v in fo["step"] else "") + ")"
           for v, m in fo["method"].items()]
    lines.append(f"\nfirst order: {fo['solves']} forward solves; derivatives by "
                 + ", ".join(how))
    return "\n".join(lines)
