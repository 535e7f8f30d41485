"""Benchmark of the linear algebra of one Newton iteration on the eye model.

Builds a surgery case (default: case 4 on its own mesh level), solves its first stage
(pressurisation), assembles the tangent of the first tightening increment and times,
as medians of repeats: the assembly, one numerical factorisation, back-solves with
1 ... 200 right-hand sides at once (the cost of a Woodbury update of the contact
look-ahead, one right-hand side per node) and the saddle-point solve (Schur CG
iterations) for several augmentation strengths beta, and the same saddle point factorised
whole instead (symmetric indefinite, the Schur CG's fallback: factorisation, one solve with
0, 1 or 2 refinements and its residual).

    python benchmarks/bench_eye_linear.py                       # case 4 on its level (fine)
    python benchmarks/bench_eye_linear.py --mesh coarse --repeats 3
    python benchmarks/bench_eye_linear.py --not-reproducible    # Pardiso without MKL's CNR
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from eyefem.solve import linsolve  # noqa: E402
from eyefem.catalog import (
    problems,  # noqa: E402
    schemas,  # noqa: E402
)
from eyefem.io.casefile import load_case, with_mesh  # noqa: E402
from eyefem.solve.assembly import Assembler  # noqa: E402
from eyefem.solve.solver import NewtonOptions, interpolate, solve  # noqa: E402


def _median_time(f, repeats):
    out = []
    for _ in range(repeats):
        tic = time.perf_counter()
        f()
        out.append(time.perf_counter() - tic)
    return statistics.median(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="cases/surgery/case4.toml")
    ap.add_argument("--mesh", default=None, help="mesh level (default: the case's)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", default=None, help="also write the figures to this file")
    ap.add_argument("--not-reproducible", action="store_true",
                    help="leave MKL's conditional numerical reproducibility off")
    args = ap.parse_args(argv)
    linsolve.REPRODUCIBLE = not args.not_reproducible

    case = load_case(args.case, schemas())
    if args.mesh:
        case = with_mesh(case, args.mesh)
    setup = problems()[case.problem][1](case.parameters, case.materials)
    sol = solve(setup.model, setup.stages[:1], options=NewtonOptions())
    model, q, theta = sol.model, sol.q, sol.theta
    stage = setup.stages[1]
    if stage.before is not None:
        model, q, theta = stage.before(model, q, theta)
    prescribed = np.zeros(model.n_dof, bool)
    prescribed[stage.prescribed[0]] = True
    end = {**theta, **{k: {**theta[k], **v} for k, v in stage.params.items()}}
    th = interpolate(theta, end, 1.0 / stage.n_steps)
    model = model.update(q, th)
    out = {"case": args.case, "mesh": case.parameters.get("mesh"), "machine": platform.machine(),
           "elements": model.mesh.n_elem, "mkl_reproducible": linsolve.REPRODUCIBLE}

    asm = Assembler(model, prescribed)
    asm.assemble(q, th, stage.active, False)  # compile
    out["assemble_s"] = _median_time(lambda: asm.assemble(q, th, stage.active, False), args.repeats)
    r, K, B, D, lr = asm.assemble(q, th, stage.active, False)
    out.update(free_dofs=K.shape[0], nnz=K.nnz, multipliers=B.shape[1])
    out["factorise_s"] = _median_time(lambda: asm.solver(K, B, D, lr, indefinite="raise"), args.repeats)
    slv = asm.solver(K, B, D, lr, indefinite="raise")
    rng = np.random.default_rng(0)
    out["backsolve_s"] = {}
    for m in (1, 10, 50, 100, 200):
        R = rng.standard_normal((K.shape[0], m))
        out["backsolve_s"][m] = _median_time(lambda: slv.fact.solve(R), args.repeats)
    f, g = -r[asm.free_primal], -r[asm.mult]
    out["saddle_solve"] = {}
    for beta in (1e4, 1e5, 1e6):
        a = Assembler(model, prescribed, beta=beta)
        s = a.solver(*a.assemble(q, th, stage.active, False)[1:], indefinite="raise")
        t = _median_time(lambda: s.solve(f, g), args.repeats)
        x, y = s.solve(f, g)
        out["saddle_solve"][f"{beta:g}"] = {"s": t, "cg_iterations": s.iterations,
                                           "relative_residual": s._residual(f, g, x, y)[2]}
    # the saddle point without the cavity's low-rank term, solved by the Schur CG and
    # factorised whole (the CG's fallback, SaddlePointSolver._kkt_solve)
    s = asm.solver(K, B, D, [])
    whole = {"schur_solve_s": _median_time(lambda: s.solve(f, g), args.repeats),
             "schur_cg_iterations": s.iterations,
             "factorise_s": _median_time(
                 lambda: (s.__dict__.pop("_kkt", None), s._kkt_solve(f, g)), args.repeats)}
    out["whole_saddle_point"] = whole
    s._kkt_solve(f, g)
    kkt = s._kkt
    n = len(f)
    rhs = np.concatenate([f + B @ (D * g), g])
    for refine in (0, 1, 2):
        def solve_refined():
            z = kkt.solve(rhs)
            for _ in range(refine):
                z = z + kkt.solve(rhs - np.concatenate([s.K_aug @ z[:n] + B @ z[n:], B.T @ z[:n]]))
            return z
        z = solve_refined()
        whole[f"solve_{refine}_refinements"] = {
            "s": _median_time(solve_refined, args.repeats),
            "relative_residual": s._residual(f, g, z[:n], z[n:])[2]}
    whole["factorise_s"] -= whole["solve_2_refinements"]["s"]  # _kkt_solve's own solve
    if hasattr(kkt, "entry"):  # Pardiso: (positive, negative, perturbed) pivots
        iparm = kkt.entry["solver"].iparm
        whole["inertia"] = [int(iparm[21]), int(iparm[22]), int(iparm[13])]
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        with open(args.json, "w") as fh:
            fh.write(text + "\n")


if __name__ == "__main__":
    main()
