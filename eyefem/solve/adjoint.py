"""Adjoint (implicit) gradients of outputs of a converged simulation.

At equilibrium R(q*, theta) = dPi/dq = 0 on the free dofs. For an output J(q, theta):

    dJ/dtheta = dJ/dtheta|_q - lam^T dR/dtheta,      K lam = dJ/dq      (K symmetric)

one transposed solve (reusing the last Newton factorisation, refined against the exact
tangent-vector product) and one vector-Jacobian product of the residual with respect
to theta. Newton's iterations are never differentiated.

Contact pairing, active sets and sticking points are frozen at the converged state:
the gradient is exact for the realised contact state (see docs/adjoint.md).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.solve.model import Model

log = logging.getLogger(__name__)


def residual_fn(model: Model, active=None) -> Callable:
    """R(q, theta) (n_dof,) as a JAX function (sum of the active terms' gradients)."""
    terms = model._active(active)

    def R(q, theta):
        return sum(jax.grad(t.energy)(q, theta[t.name], t.data, t.dofs) for t in terms)

    return R


def adjoint_solve(model: Model, solver, asm, q, theta, rhs, *, active=None, tol=1e-10,
                  max_refine=20):
    """Solve K lam = rhs on the free dofs with a (possibly slightly stale) factorisation.

    The factorisation preconditions a refinement against the exact K v (autodiff), so the
    result is the adjoint at q itself. Returns lam (n_dof,), zero on prescribed dofs.
    """
    free, mult = asm.free_primal, asm.mult
    b = np.zeros(model.n_dof)
    b[free], b[mult] = rhs[free], rhs[mult]
    lam = np.zeros(model.n_dof)
    nb = np.linalg.norm(b) or 1.0
    for it in range(max_refine):
        res = b - _apply(model, q, lam, theta, active, asm)
        if np.linalg.norm(res) <= tol * nb:
            break
        x, y = solver.solve(res[free], res[mult])
        lam = lam + asm.expand(x, y)
    else:
        log.warning("adjoint refinement stopped at relative residual %.2e",
                    np.linalg.norm(res) / nb)
    return lam


def _apply(model, q, v, theta, active, asm):
    kv = model.hvp(q, v, theta, active)
    out = np.zeros_like(kv)
    out[asm.free_primal] = kv[asm.free_primal]
    out[asm.mult] = kv[asm.mult]
    return out


def value_and_grad(objective: Callable[[Any, Any], Any], solution, *, active=None):
    """Value and theta-gradient of objective(q, theta) at a converged solution.

    Args:
      objective: JAX-traceable scalar function of (q (n_dof,), theta).
      solution: a :class:`eyefem.solve.solver.Solution` (holds model, q, theta, last
        assembler and factorisation).
    Returns: (value, gradient pytree like theta).

    The gradient is that of an equilibrium: a solution whose last step was accepted out of
    balance (on a cycling contact pairing) gets a warning naming the step and the force.
    """
    last = solution.history[-1] if solution.history else None
    if last is not None and last.info.get("unbalanced_N"):
        log.warning("adjoint gradient at stage '%s' step %d (t = %.4g), accepted with %.3e N "
                    "out of balance: the gradient is that of the nearby converged pairing",
                    last.stage, last.step, last.t, last.info["unbalanced_N"])
    solution = solution.factorised()
    model, q, theta = solution.model, solution.q, solution.theta
    active = solution.active if active is None else active
    theta_j = jax.tree_util.tree_map(jnp.asarray, theta)
    val, (gq, gth) = jax.value_and_grad(objective, argnums=(0, 1))(jnp.asarray(q), theta_j)
    lam = adjoint_solve(model, solution.solver, solution.assembler, q, theta, np.asarray(gq),
                        active=active)
    R = residual_fn(model, active)
    _, vjp = jax.vjp(lambda th: R(jnp.asarray(q), th), theta_j)
    (gR,) = vjp(jnp.asarray(lam))
    grad = jax.tree_util.tree_map(lambda a, b: np.asarray(a) - np.asarray(b), gth, gR)
    return float(val), grad
