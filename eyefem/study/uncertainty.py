"""Uncertainty of a planned surgery's outcomes from stated distributions of its inputs.

Two ways, compared by ``eyefem sweep FILE --uncertainty`` (docs/uncertainty.md):

- **first order** (:func:`first_order`): one forward solve and the adjoint gradients
  (eyefem.simulate + jax.jacrev) at the centre of the distributions. For independent
  inputs x_i with standard deviations s_i, an outcome y has

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

from eyefem.eye.variables import DESIGN_VARIABLES, OUTCOMES
from eyefem.study.spec import Distribution, Sweep, case_raw


def design_variable(path: str) -> str | None:
    """The design variable (eyefem.eye.variables) a sweep path sets, or None:
    materials.<m>.c10 -> c10_<m>; parameters.<name> -> <name> for a design variable."""
    parts = path.split(".")
    if len(parts) == 3 and parts[0] == "materials" and parts[2] == "c10":
        name = f"c10_{parts[1]}"
    elif len(parts) == 2 and parts[0] == "parameters":
        name = parts[1]
    else:
        return None
    return name if name in DESIGN_VARIABLES else None


def first_order(case, dists: dict[str, Distribution], outcomes=tuple(OUTCOMES)) -> dict:
    """First-order mean and std of the outcomes of a surgery case.

    Args:
      case: a case-file path or Case (eyefem.simulate).
      dists: design variable -> Distribution (independent inputs).
      outcomes: the outcome names (eyefem.eye.variables.OUTCOMES).

    Returns: {"centre": {var: x0}, "mean": {outcome: y(x0)}, "std": {outcome: std},
    "gradient": {outcome: {var: dy/dx}}, "terms": {outcome: {var: dy/dx s}}}.
    """
    import jax

    from eyefem.api import simulate

    x0 = {v: d.centre for v, d in dists.items()}
    y0 = simulate(case, x0)
    jac = jax.jacrev(lambda d: simulate(case, d))(x0)
    res = {"centre": x0, "mean": {}, "std": {}, "gradient": {}, "terms": {}}
    for o in outcomes:
        g = {v: float(jac[o][v]) for v in dists}
        terms = {v: g[v] * (x0[v] if d.kind == "lognormal" else 1.0) * d.linear_std()
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
    """The sweep's sampled distributions by design variable; ValueError for a sampled
    path that is not a design variable (no gradient) or a sweep without samples."""
    if sweep.base.problem != "surgery":
        raise ValueError(f"{sweep.path}: first-order uncertainty needs a surgery case "
                         f"(eyefem.simulate); the base case is '{sweep.base.problem}'")
    if not sweep.distributions:
        raise ValueError(f"{sweep.path}: no [samples] distributions to propagate")
    out = {}
    for p, d in sweep.distributions.items():
        v = design_variable(p)
        if v is None:
            raise ValueError(f"{sweep.path} [samples] {p}: not a design variable, so it has no "
                             "adjoint gradient; sample materials.<m>.c10 or parameters.<name> "
                             f"for a name in {', '.join(DESIGN_VARIABLES)}")
        out[v] = d
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
    """Compare first-order and sampled statistics of a sampled surgery sweep; writes
    uncertainty.json and the two plots in ``out_dir`` and returns a Markdown table."""
    dists = sweep_distributions(sweep)
    outcomes = [o for o in (sweep.outcomes or OUTCOMES) if o in OUTCOMES]
    fo = first_order(planned_case(sweep), dists, outcomes)
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
    return "\n".join(lines)
