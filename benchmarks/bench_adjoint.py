"""Cost of an adjoint gradient against one Newton iteration, on the eye model.

Solves a surgery case (encircling, flat tire; small tightening so that the forward run
is short), then times at the converged state (median of repeats):
  - one Newton iteration: residual + tangent assembly + factorisation + solve;
  - the gradient of one outcome (IOP) with respect to every design variable (surgical
    and material): three adjoint solves (stages 3, 2 and 1) with the reused
    factorisations + the vector-Jacobian products
    (eyefem.eye.simulators.SurgerySimulator.gradients);
  - the gradients of every outcome (eyefem.eye.variables.OUTCOMES) with respect to every
    design variable: the same three adjoint solves, one right-hand side per outcome;
and reports their ratios.

    python benchmarks/bench_adjoint.py --mesh default --repeats 3
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import jax

jax.config.update("jax_enable_x64", True)


from bench_core import _median  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

from eyefem.eye.simulators import SurgerySimulator  # noqa: E402
from eyefem.eye.variables import DESIGN_VARIABLES, OUTCOMES, default_parameters  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", default="default")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tightening", type=float, default=1.0)
    a = ap.parse_args(argv)
    tic = time.perf_counter()
    sim = SurgerySimulator(default_parameters(mesh=a.mesh, tightening=a.tightening,
                                              steps_tighten=2, steps_suture=1))
    res = sim.run()
    forward = time.perf_counter() - tic
    sol = res.sol3
    asm = sol.assembler

    def newton_iteration():
        r = sol.model.gradient(sol.q, sol.theta, sol.active)
        _, K, B, D, lr = asm.assemble(sol.q, sol.theta, sol.active)
        s = asm.solver(K, B, D, lr)
        s.solve(-r[asm.free_primal], -r[asm.mult])

    sim.gradients(res, ["iop_mmhg"])  # compile
    sim.gradients(res)
    newton_iteration()
    t_newton = _median(newton_iteration, a.repeats)
    t_grad = _median(lambda: sim.gradients(res, ["iop_mmhg"]), a.repeats)
    t_all = _median(lambda: sim.gradients(res), a.repeats)
    out = {"machine": f"{platform.node()} ({platform.processor() or platform.machine()}), "
                      f"{jax.device_count()} JAX device(s)",
           "mesh": a.mesh, "elements": int(sol.model.mesh.n_elem), "dofs": int(sol.model.n_dof),
           "forward_s": round(forward, 1), "newton_iterations": res.newton_iterations,
           "newton_iteration_s": round(t_newton, 3), "gradient_all_variables_s": round(t_grad, 3),
           "ratio_gradient_to_newton_iteration": round(t_grad / t_newton, 2),
           "outcomes": len(OUTCOMES), "variables": len(DESIGN_VARIABLES),
           "gradients_all_outcomes_s": round(t_all, 3),
           "ratio_all_outcomes_to_newton_iteration": round(t_all / t_newton, 2),
           "iop_mmhg": res.outcomes["iop_mmhg"]}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
