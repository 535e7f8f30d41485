"""Fit the Prony constants (g_i, tau_i) of eyefem.fem.viscoelastic to a published
stress-relaxation curve, and say which of them the test identifies (issue 74, item 3).

Input: a CSV with columns ``time_s`` (seconds from the end of the loading ramp) and
``G`` (the stress divided by the stress at the first sample, or by the peak stress), a
comment header (lines starting with '#') naming its source: the figure or table it was
read from, the species, tissue, strain level and ramp time. No curve is shipped yet
(docs/formulation.md, "Quasi-linear viscoelastic tissue": the published curves were not
reachable; eyefem/eye/relaxation.py lists what was searched); the script runs on any such
file:

    python benchmarks/fit_prony.py curve.csv [--per-decade 1] [--out fit.json]

The fit: time constants fixed one per decade (or ``--per-decade`` of them) across the
sampled window [t_min, t_max], the fractions g_i >= 0 with sum g_i < 1 found by bounded
linear least squares on G(t) = G_0 [1 - sum g_i (1 - exp(-t / tau_i))] (G_0 the
normalisation's instantaneous value, fitted too: the first sample is taken after a
ramp, not at t = 0). Linear in (G_0, G_0 g_i), so the fit is unique for fixed tau_i.

Identifiability, stated by the script: a tau_i well inside the window is identified with
its g_i; the relaxation faster than the ramp is lumped into G_0 (the instantaneous
response the model takes from the living eye); the equilibrium fraction g_inf = 1 -
sum g_i is only the fraction left at t_max: every relaxation slower than t_max
(hours to months, what the eye's shape at three months depends on) is an extrapolation
the test does not constrain. The script reports the singular values of the fit's
sensitivity matrix and the parameter standard errors from the residual.

Why scipy's bounded linear least squares and not optimize.calibrate's adjoint: a uniaxial
relaxation test at a held stretch is the Prony series itself (G(t) times the elastic
stress; tests/test_viscoelastic.py checks the finite-element relaxation against it to
1e-9), so a finite-element model of the strip adds nothing to the fit, and with the time
constants fixed the fractions enter linearly: the least-squares problem is convex with a
unique minimiser, which the adjoint's gradient descent would only approximate. The
adjoint through time (eyefem.solve.transient) is the tool where the data are not a
strip's relaxation (an inflation creep test of a whole globe: python -m optimize.calibrate
fits through the eye model).

The fitted (g_i, tau_i in minutes) go into a case as tissue_relaxation = "custom",
relaxation_g and relaxation_tau_min (eyefem/eye/relaxation.py).

A paper that gives Fung's quasi-linear constants instead of a curve (C, tau1, tau2: the
box spectrum of Downs et al., J Biomech Eng 125:124, 2003, for one) gives its reduced
relaxation function in closed form, :func:`qlv_curve`; ``--qlv C TAU1 TAU2 --window T0 T1
--source TEXT --write CSV`` samples it over the test's window into a CSV with its source,
then fits that:

    python benchmarks/fit_prony.py --qlv C TAU1_S TAU2_S --window 1 1000 \
        --source "paper, table, species, strain" --write curve.csv
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from scipy.optimize import lsq_linear


def read_curve(path: str):
    lines = open(path).read().splitlines()
    src = [ln[1:].strip() for ln in lines if ln.startswith("#")]
    # the column names: the first line that is not a comment (np.genfromtxt would read
    # them from the source comment above it)
    data = np.genfromtxt([ln for ln in lines if not ln.startswith("#")], delimiter=",",
                         names=True)
    return np.asarray(data["time_s"], float), np.asarray(data["G"], float), src


def qlv_curve(t, C: float, tau1: float, tau2: float) -> np.ndarray:
    """Fung's reduced relaxation function with a box spectrum between tau1 and tau2,

        G(t) = [1 + C (E1(t / tau2) - E1(t / tau1))] / [1 + C ln(tau2 / tau1)],

    E1 the exponential integral: G(0+) = 1 (the instantaneous response), G(inf) = 1 / (1 +
    C ln(tau2 / tau1)) (the equilibrium fraction). t (n,) > 0, tau1 < tau2, in one unit
    (seconds here); C >= 0 dimensionless. ValueError naming the constant otherwise."""
    from scipy.special import exp1

    t = np.asarray(t, np.float64)
    if not (np.isfinite(C) and C >= 0):
        raise ValueError(f"qlv_curve: C = {C}; must be a number >= 0")
    if not (np.isfinite(tau1) and np.isfinite(tau2) and 0 < tau1 < tau2):
        raise ValueError(f"qlv_curve: tau1 = {tau1}, tau2 = {tau2}; need 0 < tau1 < tau2")
    if not np.all(t > 0):
        raise ValueError("qlv_curve: the times must be above 0 (G jumps at t = 0)")
    return (1.0 + C * (exp1(t / tau2) - exp1(t / tau1))) / (1.0 + C * np.log(tau2 / tau1))


def write_curve(path: str, t, G, source: list[str]) -> None:
    """A CSV read_curve reads: the source lines as '#' comments, then time_s, G."""
    if not source or not any(s.strip() for s in source):
        raise ValueError("write_curve: give the curve's source (paper, table or figure, "
                         "species, tissue, strain, ramp)")
    lines = [f"# {s}" for s in source] + ["time_s,G"]
    lines += [f"{float(a)!r},{float(b)!r}" for a, b in zip(t, G)]
    open(path, "w").write("\n".join(lines) + "\n")


def fit(t, G, per_decade: int = 1) -> dict:
    """Prony fractions for time constants fixed across the sampled window (seconds)."""
    lo, hi = np.log10(max(t[t > 0].min(), 1e-3)), np.log10(t.max())
    n = max(int(np.ceil((hi - lo) * per_decade)), 1)
    tau = 10.0 ** (lo + (np.arange(n) + 0.5) / per_decade)  # mid-decade, inside the window
    # G = G0 - sum_i a_i (1 - exp(-t/tau_i)), a_i = G0 g_i >= 0
    A = np.column_stack([np.ones_like(t)] + [-(1 - np.exp(-t / ti)) for ti in tau])
    res = lsq_linear(A, G, bounds=(np.r_[0.0, np.zeros(n)], np.r_[np.inf, np.full(n, np.inf)]))
    G0, a = res.x[0], res.x[1:]
    g = a / G0
    r = A @ res.x - G
    dof = max(len(t) - len(res.x), 1)
    s2 = float(r @ r) / dof
    sv = np.linalg.svd(A, compute_uv=False)
    cov = s2 * np.linalg.pinv(A.T @ A)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    return {"G0": float(G0), "tau_s": tau.tolist(), "tau_min": (tau / 60.0).tolist(),
            "g": g.tolist(), "g_inf": float(1 - g.sum()), "rms": float(np.sqrt(s2)),
            "singular_values": sv.tolist(), "se_G0": float(se[0]),
            "se_g": (se[1:] / G0).tolist(), "window_s": [float(t.min()), float(t.max())],
            "note": ("g_inf is the fraction left at the end of the test; relaxation slower "
                     f"than {t.max():.0f} s is not constrained by this curve")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("csv", nargs="?", help="the relaxation curve (time_s, G) to fit")
    ap.add_argument("--per-decade", type=int, default=1)
    ap.add_argument("--out")
    ap.add_argument("--qlv", nargs=3, type=float, metavar=("C", "TAU1_S", "TAU2_S"),
                    help="sample Fung's QLV reduced relaxation function instead of reading")
    ap.add_argument("--window", nargs=2, type=float, metavar=("T0_S", "T1_S"),
                    help="the test's window for --qlv, seconds")
    ap.add_argument("--source", help="where --qlv's constants were read (required)")
    ap.add_argument("--write", help="the CSV --qlv writes (then fitted)")
    a = ap.parse_args(argv)
    if a.qlv:
        if not (a.window and a.source and a.write):
            ap.error("--qlv needs --window T0 T1, --source TEXT and --write CSV")
        t0, t1 = a.window
        if not 0 < t0 < t1:
            ap.error(f"--window {t0} {t1}: need 0 < T0 < T1 seconds")
        t = np.geomspace(t0, t1, int(np.ceil(20 * np.log10(t1 / t0))) + 1)
        C, tau1, tau2 = a.qlv
        write_curve(a.write, t, qlv_curve(t, C, tau1, tau2),
                    [a.source, f"Fung QLV reduced relaxation function, C = {C!r}, tau1 = "
                     f"{tau1!r} s, tau2 = {tau2!r} s, sampled {t0!r} to {t1!r} s "
                     "(benchmarks/fit_prony.py --qlv)"])
        a.csv = a.write
    elif not a.csv:
        ap.error("give a curve CSV, or --qlv C TAU1 TAU2 with --window, --source, --write")
    t, G, src = read_curve(a.csv)
    out = {"source": src, **fit(t, G, a.per_decade)}
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        open(a.out, "w").write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
