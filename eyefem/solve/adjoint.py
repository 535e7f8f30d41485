"""Adjoint (implicit) gradients of outputs of a converged simulation.

At equilibrium R(q*, theta) = dPi/dq = 0 on the free dofs. For an output J(q, theta):

    dJ/dtheta = dJ/dtheta|_q - lam^T dR/dtheta,      K lam = dJ/dq      (K symmetric)

one transposed solve (reusing the last Newton factorisation, refined against the exact
tangent-vector product) and one vector-Jacobian product of the residual with respect
to theta. Newton's iterations are never differentiated.

Contact pairing (which face), active sets and sticking points are frozen at the
converged state: the gradient is exact for the realised contact state. Within a paired
face the target point follows the state (:func:`following`), as re-pairing makes it
(see docs/adjoint.md).
"""

from __future__ import annotations

import logging
import weakref
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from eyefem.solve.errors import LinearSolveError
from eyefem.solve.model import Model, non_potential

log = logging.getLogger(__name__)


ASSEMBLED_FROM = 4
"""From this many adjoints at once, their refinement multiplies by the exact tangent
assembled at the solution (one assembly, then sparse products) instead of k autodiff
tangent-vector products per sweep (on the default eye one assembly costs about as much
as the products of 8 vectors; the two agree to 1e-12 relative)."""


SWEEP_CG_RTOL = 1e-8
"""The Schur-complement CG of one refinement sweep stops at this constraint residual,
relative (whatever the factorisation's own ``cg_rtol``): on the eye each sweep then lowers
the residual by 1e-4..1e-8 (the factorisation is the last Newton iteration's), so two or
three sweeps reach ``tol``."""


def check_potential(model: Model, active=None) -> None:
    """ValueError if an active term is not a potential (a follower pressure on an open
    surface): its tangent is not symmetric, and the adjoint (K lam = dJ/dq with K
    symmetric) would be that of another problem."""
    loads = non_potential(model._active(active))
    if loads:
        raise ValueError(f"adjoint gradients: {loads} are follower pressures on open surfaces "
                         "(not potentials; their tangent is not symmetric), which the adjoint "
                         "does not handle; take finite differences of full solves instead")


def adjoint_solve(model: Model, solver, asm, q, theta, rhs, *, active=None, tol=1e-10,
                  max_refine=20):
    """Solve K lam = rhs on the free dofs with a (possibly slightly stale) factorisation.

    The factorisation preconditions a refinement against the exact tangent at q (autodiff
    tangent-vector products, or the tangent assembled at q for ASSEMBLED_FROM or more
    right-hand sides), so the result is the adjoint at q itself. rhs (n_dof,) or
    (n_dof, k): k adjoints at once (one block back-solve per sweep, each column refined
    to ``tol`` relative). Each sweep is one pass of the saddle-point solve without its own
    residual check (``SaddlePointSolver.approximate_solve``): the sweep's residual against
    the exact tangent is that check. Returns lam like rhs, zero on prescribed dofs.

    Raises ValueError for a model with a term that is not a potential
    (:func:`check_potential`), LinearSolveError when a sweep's residual is not finite;
    stops with a warning when a sweep lowers no column's residual (a singular or
    indefinite tangent) or after ``max_refine`` sweeps.
    """
    check_potential(model, active)
    one = np.ndim(rhs) == 1
    rhs = np.asarray(rhs, float).reshape(model.n_dof, -1)
    free, mult = asm.free_primal, asm.mult
    b = np.zeros_like(rhs)
    b[free], b[mult] = rhs[free], rhs[mult]
    lam = np.zeros_like(b)
    nb = np.linalg.norm(b, axis=0)
    nb[nb == 0] = 1.0
    todo = np.ones(b.shape[1], bool)
    rel = np.zeros(b.shape[1])
    if b.shape[1] >= ASSEMBLED_FROM:
        apply = assembled_tangent(model, asm, q, theta, active)
    else:
        def apply(V):
            return _apply(model, q, V, theta, active, asm)
    for it in range(max_refine):
        res = b[:, todo] - (apply(lam[:, todo]) if it else 0.0)
        before = rel[todo].copy()
        rel[todo] = np.linalg.norm(res, axis=0) / nb[todo]
        if log.isEnabledFor(logging.DEBUG):
            log.debug("adjoint sweep %d: relative residuals %s", it,
                      np.array2string(rel, precision=1))
        if not np.all(np.isfinite(rel)):
            raise LinearSolveError(f"adjoint solve: the residual of sweep {it} is not finite; "
                                   "the tangent at the converged state is singular")
        done = rel[todo] <= tol
        if done.all():
            break
        if it and not np.any(rel[todo] < before):
            log.warning("adjoint refinement stalled at relative residual %.2e after %d "
                        "sweeps (a singular or indefinite tangent)", float(rel.max()), it)
            break
        cols = np.nonzero(todo)[0]
        todo[cols[done]] = False
        res = res[:, ~done]
        x, y = solver.approximate_solve(res[free], res[mult], SWEEP_CG_RTOL)
        lam[:, todo] += asm.expand(x.reshape(len(free), -1), y.reshape(len(mult), -1))
    else:
        log.warning("adjoint refinement stopped at relative residual %.2e", float(rel.max()))
    return lam[:, 0] if one else lam


def following(model: Model) -> Model:
    """The model whose tangent the adjoint takes: each re-paired (contact) term that can
    have its target points follow the state (``following_pairing``, e.g.
    eyefem.fem.contact.SurfaceContact) replaced by that term. Its residual at the
    converged state, paired at itself, is the model's; its tangent adds the target points'
    sliding over the faces, which the re-pairing of every Newton iterate gives the
    converged state and the held pairing's tangent lacks."""
    terms = [t.following_pairing() if getattr(t, "dynamic", False)
             and hasattr(t, "following_pairing") else t for t in model.terms]
    if all(a is b for a, b in zip(terms, model.terms)):
        return model
    return model.with_terms(terms)


def _apply(model, q, V, theta, active, asm):
    """K V (n_dof, k) on the free primal and multiplier rows (zero elsewhere)."""
    kv = model.hvp_many(q, V, theta, active)
    out = np.zeros_like(kv)
    out[asm.free_primal] = kv[asm.free_primal]
    out[asm.mult] = kv[asm.mult]
    return out


def assembled_tangent(model: Model, asm, q, theta, active=None) -> Callable:
    """V (n_dof, k) -> K V on the free primal and multiplier rows (zero elsewhere), K the
    exact tangent of ``model`` assembled at q (the saddle point [[K_pp, B], [B^T, 0]],
    assembled without the augmentation B D B^T, whose cancellation would leave a
    roundoff floor near 1e-10, and with the low-rank terms)."""
    _, K, B, _, low_rank = asm.assemble(q, theta, active, beta=0.0, model=model)
    free, mult = asm.free_primal, asm.mult
    if low_rank:
        W = np.stack([v for _, v in low_rank], axis=1)
        a = np.array([al for al, _ in low_rank])[:, None]

    def apply(V):
        x = V[free]
        kx = K @ x
        out = np.zeros_like(V)
        if B is not None:
            y = V[mult]
            kx += B @ y
            out[mult] = B.T @ x
        if low_rank:
            kx += W @ (a * (W.T @ x))
        out[free] = kx
        return out

    return apply


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
    vals, grads = values_and_grads(lambda q, theta: jnp.reshape(objective(q, theta), (1,)),
                                   solution, active=active)
    return float(vals[0]), grads[0]


_KEPT: "weakref.WeakKeyDictionary[Callable, dict]" = weakref.WeakKeyDictionary()


def kept(fn: Callable, kind: str, build: Callable) -> Callable:
    """The wrapper ``build(fn)`` of kind ``kind`` (its compiled Jacobians, its compiled
    self, its contraction with a stage's cotangent), one per function object, so that what
    it compiles is reused, and forgotten with the function: the wrapper reaches ``fn``
    through a weak reference (:func:`_weakly`), so the entry does not keep ``fn``, and what
    it closes over (a simulator's model and mesh), alive."""
    per = _KEPT.setdefault(fn, {})
    if kind not in per:
        per[kind] = build(_weakly(fn))
    return per[kind]


def _weakly(fn: Callable) -> Callable:
    """``fn`` called through a weak reference (valid while ``fn`` lives: its _KEPT entry
    goes with it)."""
    ref = weakref.ref(fn)

    def call(*args, **kwargs):
        return ref()(*args, **kwargs)
    return call


def jacobians_of(objectives: Callable) -> Callable:
    """(q, theta, data) -> (values (k,), d/dq (k, n_dof), d/dtheta (theta-like, each leaf
    with a leading k)) of objectives(q, theta, data), compiled (jax.jit, once per argument
    shapes) and kept as long as the function lives (:func:`kept`)."""
    def build(objectives):
        def jacobians(q, theta, data):
            vals, pullback = jax.vjp(lambda q, theta: objectives(q, theta, data), q, theta)
            gq, gth = jax.vmap(pullback)(jnp.eye(vals.shape[0], dtype=vals.dtype))
            return vals, gq, gth
        return jax.jit(jacobians)
    return kept(objectives, "jacobians", build)


def values_and_grads(objectives: Callable[..., Any], solution, *, active=None, data=None):
    """Values and theta-gradients of k objectives at one converged solution.

    ``objectives(q, theta)`` returns the k values (k,) (JAX-traceable): their q- and
    theta-gradients come from one reverse-mode Jacobian, their k adjoints are solved
    together (:func:`adjoint_solve`) and the residual's design derivative is contracted
    with all of them at once (compiled per term class): the cost of one objective's
    gradient and a little per further objective. Warns as :func:`value_and_grad`.

    With ``data`` (a pytree of arrays), ``objectives(q, theta, data)`` is called instead:
    a function of its arguments alone (what it closes over the same at every call), whose
    Jacobian is then compiled once per function object and argument shapes
    (:func:`jacobians_of`) and reused by later calls with new data (pass the same function
    object each time), where a closure over the data is traced anew at every call.

    Returns (values (k,), gradients: list of k pytrees like theta).
    """
    last = solution.history[-1] if solution.history else None
    if last is not None and last.info.get("unbalanced_N"):
        log.warning("adjoint gradient at stage '%s' step %d (t = %.4g), accepted with %.3e N "
                    "out of balance: the gradient is that of the nearby converged pairing",
                    last.stage, last.step, last.t, last.info["unbalanced_N"])
    active = solution.active if active is None else active
    check_potential(solution.model, active)
    solution = solution.factorised()
    model, q, theta = following(solution.model), solution.q, solution.theta
    theta_j = jax.tree_util.tree_map(jnp.asarray, theta)
    q_j = jnp.asarray(q)
    if data is None:
        vals, pullback = jax.vjp(objectives, q_j, theta_j)
        gq, gth = jax.vmap(pullback)(jnp.eye(vals.shape[0]))  # (k, n_dof), theta-like, leading k
    else:
        vals, gq, gth = jacobians_of(objectives)(q_j, theta_j, data)
    lam = adjoint_solve(model, solution.solver, solution.assembler, q, theta,
                        np.asarray(gq).T, active=active)
    gRs = model.params_vjp_many(q_j, jnp.asarray(lam), theta_j, active)
    gth = jax.tree_util.tree_map(np.asarray, gth)  # to the host once, then sliced
    grads = [jax.tree_util.tree_map(lambda a, b, j=j: a[j] - b, gth, gR)
             for j, gR in enumerate(gRs)]
    return np.asarray(vals), grads
