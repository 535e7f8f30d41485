"""Benchmark of the core solver: a thin spherical shell inflated to 15 mmHg in 10 steps.

Reports, per mesh size: compile time, the split of one Newton iteration into element
kernels / their scatter into the sparse system / linear solve / residual, each part timed
on its own (median of repeats at the converged state; the solve of the residual 1% off
that state, with the Schur CG stopped where a Newton direction's is,
``NewtonOptions.cg_rtol``), Newton
iterations, total wall time of the load path and peak memory (max RSS): of the process
when the load path has been solved (import, compilation, the 10 steps: what a run of the
problem takes) and at the end (the timings' second assembler and kernels included).

    python benchmarks/bench_core.py                 # ~1,500 and ~12,000 hexahedra
    python benchmarks/bench_core.py --sizes 11:2    # n_per_edge:n_thick pairs
    python benchmarks/bench_core.py --sizes 32:2 --extras   # + cost of a cavity, of contact
    python benchmarks/bench_core.py --sizes 20:5 --device gpu --no-path   # kernels on a GPU
    python benchmarks/bench_core.py --sizes 20:5 --no-tangent-predictor  # steps as before it
    python benchmarks/bench_core.py --sizes 20:5 --quasi-newton off,bfgs  # full Newton, then BFGS

``--quasi-newton`` (NewtonOptions.quasi_newton; a comma-separated list solves the load path
once per setting in one process, in that order, after one warm-up compilation) adds
the numeric factorisations of the load path (``factorisations``, counted on the backend:
deterministic, like ``newton_iterations``); the per-iteration timings are those of a
full Newton iteration whatever the setting.

``--device gpu`` runs the element kernels on a GPU (a CUDA jaxlib); ``--backend cudss``
the factorisation and back-solves there too (eyefem.solve.cudss). ``--no-path`` skips the 10-step load path and times the iteration at
a 1% uniform dilation of the shell (for a quick kernel comparison where the linear
solver is slow, e.g. SuperLU on a machine without PARDISO).

With ``--extras``, at the converged inflated state the cost of one Newton iteration
(contact search + residual + assembly + solve) is also measured with a closed fluid
cavity added (the inner surface, closed at that state), and with a rigid body pressed
(a plate) into the outer surface so that about 1,000 nodes are paired; the ratios to the base
iteration are reported (issues 3 and 4: <= 1.20 and <= 1.25).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from eyefem.fem.cavity import FluidCavity, close_cavity  # noqa: E402
from eyefem.fem.rigid import plane  # noqa: E402
from eyefem.fem.rigid_contact import RigidContact  # noqa: E402
from eyefem.problems.verification import SHELL_FIELDS, inflated_shell  # noqa: E402
from eyefem.solve.assembly import Assembler  # noqa: E402
from eyefem.solve.linsolve import available_backends  # noqa: E402
from eyefem.solve.solver import NewtonOptions, solve  # noqa: E402

NEWTON_CG_RTOL = NewtonOptions().cg_rtol
"""The Schur CG's stopping test of a Newton direction (the timed solves are the ones a
Newton iteration makes, not the 1e-12 of an adjoint's)."""


def _median(f, repeats):
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def _iteration(model, q, theta, pres, backend):
    """One full Newton iteration at q: re-pairing, residual, assembly, factorisation, solve."""
    model = model.update(q, theta)
    asm = Assembler(model, pres)
    r = model.gradient(q, theta)
    _, K, B, D, lr = asm.assemble(q, theta)
    s = asm.solver(K, B, D, lr, backend, cg_rtol=NEWTON_CG_RTOL)
    s.solve(-r[asm.free_primal], -r[asm.mult])


def _extras(model, q, theta, pres, backend, repeats):
    """Iteration time with a closed cavity and with rigid contact, ratios to the base."""
    mesh = model.mesh
    cav = FluidCavity("cavity", mesh, "inner")
    m_cav = model.with_terms([*model.terms, cav])
    th_cav = {**theta, "cavity": cav.params}
    m_cav, _, th_cav = close_cavity(m_cav, q, th_cav, "cavity", "pressure")
    x = mesh.nodes + q[: 3 * mesh.n_nodes].reshape(-1, 3)
    outer = mesh.node_set("outer")
    ro = np.linalg.norm(x[outer], axis=1).max()
    # a rigid plate cutting the +z cap of the shell deep enough to pair ~1,000 nodes (only
    # the cost of an iteration at this state is measured, not a converged solution)
    depth = 0.4 * ro
    body = plane("press", (0.0, 0.0, ro - depth), (0.0, 0.0, -1.0), 4 * ro, n=8)
    con = RigidContact("contact", mesh, "outer", (body,), modulus=0.5, search_gap=0.2,
                       max_initial_penetration=depth + 1.0)
    m_con = model.with_terms([*model.terms, con])
    th_con = {**theta, "contact": con.params}
    paired = m_con.update(q, th_con).term("contact").report(q, th_con["contact"])
    rows = {}
    for key, (m, th) in {"base": (model, theta), "cavity": (m_cav, th_cav),
                         "contact": (m_con, th_con)}.items():
        _iteration(m, q, th, pres, backend)  # compile, first pattern analysis
        rows[key] = _median(lambda: _iteration(m, q, th, pres, backend), repeats)
    return {"iter_base_s": rows["base"], "iter_cavity_s": rows["cavity"],
            "iter_contact_s": rows["contact"], "contact_active_nodes": paired.get("active", 0),
            "cavity_ratio": rows["cavity"] / rows["base"],
            "contact_ratio": rows["contact"] / rows["base"]}


def _dilated_state(model):
    """A 1% uniform dilation of the shell (the kernels' cost does not depend on the state)."""
    q = np.zeros(model.n_dof)
    q[: 3 * model.mesh.n_nodes] = 0.01 * model.mesh.nodes.ravel()
    return q, model.theta0()


class _FactorisationCounter:
    """Counts numeric factorisations (Pardiso's phase 22, SuperLU's and cuDSS's factor
    objects) while active: the deterministic cost measure of a load path."""

    def __init__(self):
        from eyefem.solve import linsolve

        self.n, self.linsolve = 0, linsolve
        self.originals = {}

    def __enter__(self):
        ls = self.linsolve
        self.originals = {"p": ls._Pardiso._factorize, "f": ls.factorize}
        counter = self

        def pardiso_factorize(obj):
            counter.n += 1
            return counter.originals["p"](obj)

        def factorize(A, backend=None, *args, **kwargs):
            kind = (backend or "").removesuffix(ls.SPD) or ls.default_backend()
            if kind != "pardiso":  # Pardiso's are counted in its phase 22 above
                counter.n += 1
            return counter.originals["f"](A, backend, *args, **kwargs)

        ls._Pardiso._factorize, ls.factorize = pardiso_factorize, factorize
        return self

    def __exit__(self, *exc):
        self.linsolve._Pardiso._factorize = self.originals["p"]
        self.linsolve.factorize = self.originals["f"]


def bench(n_per_edge, n_thick, backend, repeats=5, extras=False, path=True, solve_too=True,
          tangent_predictor=True, quasi_newton=("off",)):
    p = {f.name: f.default for f in SHELL_FIELDS}
    p.update(n_per_edge=n_per_edge, n_thick=n_thick)
    tic = time.perf_counter()
    setup = inflated_shell(p, {})
    model = setup.model
    t_build = time.perf_counter() - tic
    theta = model.theta0()
    q = np.zeros(model.n_dof)
    tic = time.perf_counter()
    for t in model.terms:
        model.local_grad_hess(t, q, theta)
    model.gradient(q, theta)
    model.hvp(q, q, theta)
    t_compile = time.perf_counter() - tic
    paths = {}
    for qn in (quasi_newton if path else ("off",)):
        tic = time.perf_counter()
        if path:
            with _FactorisationCounter() as fc:
                sol = solve(model, setup.stages, options=NewtonOptions(
                    backend=backend, tangent_predictor=tangent_predictor, quasi_newton=qn))
            its, steps = sum(r.iterations for r in sol.history), len(sol.history)
            q, theta, n_fact = sol.q, sol.theta, fc.n
            del sol
        else:
            (q, theta), its, steps, n_fact = _dilated_state(model), 0, 0, 0
        paths[qn] = {"quasi_newton": qn, "newton_iterations": its, "factorisations": n_fact,
                     "steps": steps, "total_s": time.perf_counter() - tic,
                     "peak_rss_path_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
        if len(paths) > 1:
            paths[qn]["state_rel_diff"] = float(np.abs(q - q_first).max() / np.abs(q_first).max())
        else:
            q_first = q
    dofs, _ = setup.stages[0].prescribed
    pres = np.zeros(model.n_dof, bool)
    pres[dofs] = True
    asm = Assembler(model, pres)
    # the assembly's two parts, each timed on its own: the kernels, then the scatter
    t_kernel = _median(lambda: asm.local_blocks(q, theta), repeats)
    blocks = asm.local_blocks(q, theta)
    t_scatter = _median(lambda: asm.scatter(model.n_dof, blocks), repeats)
    _, K, B, D, lr = asm.assemble(q, theta)
    # the solve's right-hand side: the residual 1% off the converged state (a Newton
    # direction's; at equilibrium the residual is round-off and the CG's count is noise)
    r = model.gradient(0.99 * q, theta)
    t_grad = _median(lambda: model.gradient(q, theta), repeats)

    cg = []

    def lin():
        s = asm.solver(K, B, D, lr, backend, cg_rtol=NEWTON_CG_RTOL)
        s.solve(-r[asm.free_primal], -r[asm.mult])
        cg.append(s.iterations)

    t_solve = _median(lin, max(2, repeats // 2)) if solve_too else float("nan")
    extra = _extras(model, q, theta, pres, backend, repeats) if extras else {}
    common = {**extra,
        "n_elem": model.mesh.n_elem, "n_dof": model.n_dof, "backend": backend,
        "build_s": t_build, "compile_s": t_compile,
        "kernel_s": t_kernel, "scatter_s": t_scatter, "solve_s": t_solve,
        "schur_cg_iterations": cg[-1] if cg else None,
        "residual_s": t_grad, "iteration_s": t_kernel + t_scatter + t_solve + t_grad,
        "device": jax.devices()[0].platform,
        "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    return [{**common, **p} for p in paths.values()]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="11:2,32:2", help="n_per_edge:n_thick list")
    ap.add_argument("--backend", default=available_backends()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", help="write the rows to this file")
    ap.add_argument("--extras", action="store_true", help="also the cost of a cavity and of contact")
    ap.add_argument("--device", choices=("cpu", "gpu"), default="cpu",
                    help="where the element kernels run (--backend cudss: the solve too)")
    ap.add_argument("--no-path", dest="path", action="store_false",
                    help="skip the load path; time the iteration near the unloaded state")
    ap.add_argument("--no-solve", dest="solve", action="store_false",
                    help="with --no-path: leave the linear solve out (kernels and scatter only)")
    ap.add_argument("--no-tangent-predictor", dest="tangent_predictor", action="store_false",
                    help="load steps start without the tangent predictor (the code before it)")
    ap.add_argument("--quasi-newton", default="off",
                    help="NewtonOptions.quasi_newton of the load path: off, bfgs, or a list "
                         "(off,bfgs) solved in turn in one process")
    args = ap.parse_args()
    from eyefem.solve.device import select_device
    from eyefem.solve.heap import configure_heap

    where = select_device(args.device)
    configure_heap()
    rows = []
    for s in args.sizes.split(","):
        a, b = (int(x) for x in s.split(":"))
        rows.extend(bench(a, b, args.backend, args.repeats, args.extras, args.path,
                          args.solve, args.tangent_predictor, args.quasi_newton.split(",")))
    print(f"machine: {platform.processor() or platform.machine()}, "
          f"{__import__('os').cpu_count()} cores, jax {jax.__version__}, kernels on {where}")
    keys = list(dict.fromkeys(k for r in rows for k in r))
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        print("| " + " | ".join("" if k not in r else f"{r[k]:.3g}" if isinstance(r[k], float)
                                else str(r[k]) for k in keys) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
