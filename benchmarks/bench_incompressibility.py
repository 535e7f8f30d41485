"""The exactly incompressible saddle point against the augmented Lagrangian, in one run.

Solves the same load path with NewtonOptions.incompressibility = "exact" (one multiplier
per Q1P0 element, a factorisation of K + B D B^T with a Schur-complement CG around it)
and "augmented_lagrangian" (a penalty on each element's volume change and Uzawa updates
of its multiplier estimate after each converged step: one positive definite factorisation
and one back-solve per iteration; eyefem.solve.augmented), alternating the two, on:

- ``shell``: the core benchmark's inflated shell (benchmarks/bench_core.py, ``--sizes``);
- ``eye``: a surgical case on a mesh level through the public API (every stage).

For each run: Newton iterations, Uzawa updates, numeric factorisations (by kind:
Cholesky, indefinite, failed Cholesky), wall time in total and per iteration, the peak
resident memory of the run (the kernel's high-water mark, reset before each run as
benchmarks/bench_memory.py does), the largest element volume error max |Jbar - 1| of the
augmented state and the relative difference of the outcomes (displacements, multipliers,
the model's reported scalars: IOP...) against the exact run. Medians over ``--repeats``
runs of each (the first run of each problem also compiles: a warm-up run is made first).

    python benchmarks/bench_incompressibility.py              # shell 20:5, case 1 on coarse
    python benchmarks/bench_incompressibility.py --problems shell --sizes 8:2 --repeats 1
    python benchmarks/bench_incompressibility.py --penalty-factor 10,100  # several penalties

Test-free: it checks nothing, it measures (docs/performance.md, "One positive definite
solve per iteration").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_memory import _status_kb, reset_hwm  # noqa: E402

from eyefem.solve import augmented, linsolve  # noqa: E402
from eyefem.solve.solver import NewtonOptions, solve  # noqa: E402


def shell(size: str):
    from eyefem.problems.verification import SHELL_FIELDS, inflated_shell

    n, t = (int(v) for v in size.split(":"))
    p = {f.name: f.default for f in SHELL_FIELDS}
    p.update(n_per_edge=n, n_thick=t)
    setup = inflated_shell(p, {})
    return f"shell {size}", setup.model, setup.stages, NewtonOptions()


def eye(case_path: str, mesh: str):
    from eyefem.catalog import problems, schemas
    from eyefem.io.casefile import load_case, with_mesh

    case = load_case(case_path, schemas())
    case = with_mesh(case, mesh)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    return f"{Path(case_path).stem} on {mesh}", setup.model, setup.stages, case.solver


def run(model, stages, opts) -> dict:
    f0, u0 = dict(linsolve.FACTORISATIONS), augmented.UZAWA_UPDATES["updates"]
    hwm = reset_hwm()
    tic = time.perf_counter()
    sol = solve(model, stages, options=opts)
    wall = time.perf_counter() - tic
    peak = _status_kb("VmHWM") if hwm else None
    its = sum(r.iterations for r in sol.history)
    fact = {k: linsolve.FACTORISATIONS[k] - f0[k] for k in f0}
    res = sol.model.gradient(sol.q, sol.theta, sol.active)
    vol = max([float(np.max(np.abs(res[t.dofs[:, 24]]) / (2.0 * t.data["dv"].sum(axis=1))))
               for t in sol.model.terms if t.multiplier_slots == (24,)], default=0.0)
    return {"wall_s": wall, "iterations": its, "s_per_iteration": wall / max(its, 1),
            "uzawa": augmented.UZAWA_UPDATES["updates"] - u0,
            "factorisations": fact["cholesky"] + fact["indefinite"],
            "cholesky": fact["cholesky"], "indefinite": fact["indefinite"],
            "cholesky_failed": fact["cholesky_failed"],
            "peak_rss_MB": None if peak is None else peak / 1024.0,
            "max_volume_error": vol,
            "_q": sol.q, "_report": sol.model.report(sol.q, sol.theta, sol.active),
            "_n_u": sol.model.n_u}


def rel(a, b) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def compare(name, model, stages, opts, repeats, factors) -> list[dict]:
    variants = [("exact", opts)] + [
        (f"augmented (kappa = {f:g} mu)", dataclasses.replace(
            opts, incompressibility="augmented_lagrangian", penalty_factor=f))
        for f in factors]
    for _, o in variants[:2]:  # warm-up: compiles the kernels of both (the first stage)
        solve(model, stages[:1], options=o)
    runs = {v: [] for v, _ in variants}
    for _ in range(repeats):  # alternating, so that the machine's load hits both alike
        for v, o in variants:
            runs[v].append(run(model, stages, o))
    ref = runs["exact"][0]
    n_u = ref["_n_u"]
    rows = []
    for v, _ in variants:
        rs, last = runs[v], runs[v][-1]
        row = {"problem": name, "variant": v, "hexahedra": model.mesh.n_elem,
               "repeats": repeats}
        for k in ("wall_s", "s_per_iteration", "peak_rss_MB"):
            vals = [r[k] for r in rs if r[k] is not None]
            row[k] = round(statistics.median(vals), 4) if vals else None
        for k in ("iterations", "uzawa", "factorisations", "cholesky", "indefinite",
                  "cholesky_failed", "max_volume_error"):
            row[k] = last[k]
        row["rel_diff_u"] = rel(last["_q"][:n_u], ref["_q"][:n_u])
        row["rel_diff_multipliers"] = rel(last["_q"][n_u:], ref["_q"][n_u:])
        keys = [k for k in ref["_report"] if np.ndim(ref["_report"][k]) == 0]
        row["reported_exact"] = {k: float(ref["_report"][k]) for k in keys}
        row["abs_diff_reported"] = {k: abs(float(last["_report"][k] - ref["_report"][k]))
                                    for k in keys}
        # relative where the output is not nearly zero (1e-3 in its unit: mmHg, mm, N,
        # degrees); a twist of 1e-5 degrees differs by a large fraction of itself
        row["rel_diff_reported"] = {k: row["abs_diff_reported"][k] / abs(ref["_report"][k])
                                    for k in keys if abs(ref["_report"][k]) >= 1e-3}
        rows.append(row)
    for row in rows:
        row["wall_ratio_to_exact"] = round(row["wall_s"] / rows[0]["wall_s"], 3)
    return rows


def table(rows) -> str:
    lines = ["| problem | variant | Newton its | Uzawa | factorisations (Cholesky / indefinite; "
             "failed Cholesky) "
             "| s / it | total s | x exact | peak RSS MB | max abs(J - 1) | rel. diff u | "
             "largest rel. diff of a reported output (abs >= 1e-3) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        rep = max(r["rel_diff_reported"].values(), default=0.0)
        lines.append(f"| {r['problem']} ({r['hexahedra']} hex) | {r['variant']} | "
                     f"{r['iterations']} | {r['uzawa']} | {r['factorisations']} "
                     f"({r['cholesky']} / {r['indefinite']}; "
                     f"{r['cholesky_failed']}) | "
                     f"{r['s_per_iteration']:.3f} | {r['wall_s']:.2f} | "
                     f"{r['wall_ratio_to_exact']:.2f} | "
                     f"{r['peak_rss_MB'] or float('nan'):.0f} | {r['max_volume_error']:.1e} | "
                     f"{r['rel_diff_u']:.1e} | {rep:.1e} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default="shell,eye", help="comma-separated: shell, eye")
    ap.add_argument("--sizes", default="20:5", help="shell n_per_edge:n_thick (bench_core.py)")
    ap.add_argument("--case", default="cases/surgery/case1.toml")
    ap.add_argument("--mesh", default="coarse")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--eye-repeats", type=int, default=None,
                    help="repeats of the eye case (default: --repeats)")
    ap.add_argument("--penalty-factor", default=str(NewtonOptions().penalty_factor),
                    help="comma-separated kappa / mu of the augmented runs")
    ap.add_argument("--json", default=None, help="also write the rows to this file")
    args = ap.parse_args(argv)
    factors = [float(v) for v in args.penalty_factor.split(",")]
    rows = []
    for prob in args.problems.split(","):
        if prob == "shell":
            name, model, stages, opts = shell(args.sizes)
            rows += compare(name, model, stages, opts, args.repeats, factors)
        elif prob == "eye":
            name, model, stages, opts = eye(args.case, args.mesh)
            rows += compare(name, model, stages, opts, args.eye_repeats or args.repeats, factors)
        else:
            raise SystemExit(f"--problems: unknown '{prob}'; choose from shell, eye")
        print(table([r for r in rows if r["problem"] == name]), flush=True)
    out = {"machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
           "backend": linsolve.default_backend(), "rows": rows}
    print(json.dumps(out, indent=1))
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
