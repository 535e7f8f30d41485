"""Newton's method for one load step: the predictors (the tangent predictor on the
previous step's factorisation, the consistent linear predictor), the iterations with
their convergence test, the contact strategy (eyefem.solve.contact_strategy), the
acceptance of a stalled step, and the globalised update (eyefem.solve.globalisation)."""

from __future__ import annotations

import dataclasses
import logging

import jax
import numpy as np

from eyefem.solve.assembly import Assembler
from eyefem.solve.contact_strategy import has_contact, repaired, settle_pairing
from eyefem.solve.globalisation import (Evaluated, Restoration, evaluate,
                                        globalised_update, line_search, merit)
from eyefem.solve.linsolve import LinearSolveError
from eyefem.solve.model import Model
from eyefem.solve.options import NewtonOptions
from eyefem.solve.quasi_newton import QuasiNewton, quasi_newton_stage, quasi_newton_step
from eyefem.solve.records import StepFailed, StepResult, StepStatus

log = logging.getLogger(__name__)

PREDICTOR_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0)
"""Fractions of the linear predictor's correction tried in turn (:func:`predicted`)."""

PREDICTOR_ALPHAS = (1.0, 0.5, 0.25)
"""Step lengths of a load-driven step's tangent predictor tried in turn (a line search on
the merit, :func:`_tangent_predict`); none lowering it, the step starts at the last state."""


def predicted(q_prescribed, correction, residual):
    """The start of a step with prescribed increments: q_prescribed (n_dof,) (the last
    state with the prescribed dofs moved) plus the largest fraction of the consistent
    linear predictor's ``correction`` (n_dof,) in PREDICTOR_SCALES at which ``residual``
    (q -> (n_dof,)) is finite. Far from linear (a stiff tire pulled by its ends and held by
    a penalty contact that the tangent at the fit linearises at a fraction of its
    stiffness) the full correction pushed the default eye's sclera into inverted
    elements, and the step was cut twice before Newton could start."""
    for s in PREDICTOR_SCALES:
        q = q_prescribed + s * correction
        if np.all(np.isfinite(residual(q))):
            if s < 1.0:
                log.debug("  predictor scaled to %g (the full one inverts an element)", s)
            return q
    return q_prescribed + correction  # the iterations report the inverted element



@dataclasses.dataclass
class _Iterate:
    """What Newton carries from one iteration of a step to the next (private, mutable)."""

    model: Model
    q: np.ndarray
    fref: float  # the progress reference: the step's first residual (module docstring)
    load: float = 0.0  # the force the current iterate carries, N (the tolerances' scale)
    solver: object = None
    frozen: bool = False  # contact pairs frozen
    history: list = dataclasses.field(default_factory=list)  # force residuals, N
    best: tuple | None = None  # (force residual, q, model, paired earlier, load) of the best
    flips: list = dataclasses.field(default_factory=list)  # forces left by re-pairings
    evaluated: object = None  # the line search's residual at q (globalisation.Evaluated)
    qn: object = None  # quasi-Newton updates on the last factorisation (QuasiNewton)


def newton(model: Model, asm: Assembler, q, theta, dq_prescribed, opts: NewtonOptions,
           active=None, vref=1.0, fscale=0.0, final=True, predictor=None,
           previous=None) -> StepResult:
    """Solve one load step from q (n_dof,), the state at the previous step (arguments and
    result: :func:`_newton`). A model with augmented-Lagrangian Q1P0 terms
    (eyefem.solve.augmented) has its multiplier estimates updated (Uzawa) after each
    converged solve, and the step solved again from the tangent predictor on its last
    factorisation, until its volume error is below ``uzawa_tol`` (StepFailed after
    ``uzawa_max`` updates); the iterations reported are all of them."""
    from eyefem.solve.augmented import is_augmented, uzawa_update, volume_errors

    done = _newton(model, asm, q, theta, dq_prescribed, opts, active, vref, fscale, final,
                   predictor, previous)
    if not is_augmented(done.model, active):
        return done
    its, zero = done.iterations, np.zeros_like(dq_prescribed)
    for _ in range(opts.uzawa_max):
        updated = uzawa_update(done.model, done.q, opts.uzawa_tol, active)
        if updated is None:
            return dataclasses.replace(done, iterations=its)
        done = _newton(updated, asm, done.q, theta, zero, opts, active, vref,
                       max(fscale, done.fref), final, done.solver, None)
        its += done.iterations
    err = volume_errors(done.model, done.q, active)
    if err <= opts.uzawa_tol:
        return dataclasses.replace(done, iterations=its)
    raise StepFailed(f"volume error max |J - 1| = {err:.2e} after {opts.uzawa_max} Uzawa "
                     f"updates (uzawa_tol {opts.uzawa_tol:g}; raise uzawa_max or "
                     "penalty_factor, or set incompressibility = \"exact\")")


def _newton(model: Model, asm: Assembler, q, theta, dq_prescribed, opts: NewtonOptions,
            active=None, vref=1.0, fscale=0.0, final=True, predictor=None,
            previous=None) -> StepResult:
    """Solve one load step from q (n_dof,), the state at the previous step.

    dq_prescribed (n_dof,): the increment of the prescribed dofs (zero elsewhere), taken
    with the consistent linear predictor. ``predictor``: the last factorised tangent of
    the stage's previous step (a SaddlePointSolver of ``asm``'s layout), or None; with it
    the step starts from the tangent predictor on that factorisation
    (:func:`_tangent_predict`), without an assembly. ``previous``: (theta, r (n_dof,)) of
    the converged state q (its residual is not evaluated again where the load is the
    same), or None. The force tolerance is relative to the load the
    iterate carries (:meth:`Model.gradient_and_load` on the free dofs, or the reactions if
    larger), so it means the same in every step: a step whose first residual is huge (a
    volume injected into a stiff cavity, a stiff band moved by its ends) is not accepted
    at a residual its first one made look small. The globalisation and the contact freeze
    measure progress against the step's reference, the largest of its first out-of-balance
    force, the reactions and ``fscale`` (the stage's typical step reference). Contact pairs
    are re-paired every iteration until frozen (NewtonOptions.contact_freeze). A step that
    stalls below ``stall_rtol`` x the load is accepted unless it is ``final`` (it ends a
    stage). The returned model carries the step's pairing. Raises StepFailed (the load path
    cuts the step). With ``NewtonOptions.quasi_newton`` (a stage without contact)
    iterations reuse the last factorisation (the predictor's too) with BFGS updates until
    the reformation rule asks for a new one (eyefem.solve.quasi_newton)."""
    free, mult = asm.free_primal, asm.mult
    s = _Iterate(model, q.copy(), fscale)
    asm.model = model  # after a failed try the assembler holds that try's contact pairing
    qn_on = opts.quasi_newton != "off" and quasi_newton_stage(model, active)
    if predictor is not None:
        _tangent_predict(s, asm, theta, dq_prescribed, opts, active, predictor, vref, previous)
        if qn_on and s.solver is None:  # (not a fresh one where it fell back)
            s.solver = predictor
            predictor.stale = True  # not the adjoint's at this step's state (loadpath)
    elif np.any(dq_prescribed):
        _predict(s, asm, theta, dq_prescribed, opts, active)
    if qn_on and s.solver is not None:
        s.qn = QuasiNewton(s.solver, asm)
    for it in range(opts.max_iter + 1):
        paired_here = not s.frozen  # this iterate is re-paired at its own state
        if paired_here:
            s.model = s.model.update(s.q, theta)
        asm.model = s.model
        known = s.evaluated.at(s.model, s.q) if s.evaluated is not None else None
        r, fload = known or s.model.gradient_and_load(s.q, theta, free, active)
        if not np.all(np.isfinite(r)):
            raise StepFailed("non-finite residual (an element inverted?)")
        rf, rm, nf = r[free], r[mult], np.linalg.norm(r[free])
        reactions = np.linalg.norm(r[asm.prescribed])
        s.fref = max(s.fref, nf if it == 0 else 0.0, reactions)
        s.load = max(fload, reactions)
        nm = np.linalg.norm(rm) / vref if len(rm) else 0.0
        log.debug("  iter %d |r_u| %.3e (load %.3e, ref %.3e) |r_vol| %.3e%s", it, nf, s.load,
                  s.fref, nm, " (pairs frozen)" if s.frozen else "")
        if nf <= opts.rtol * s.load + opts.atol and nm <= opts.vtol:
            if not s.frozen:
                return StepResult(s.model, s.q, it, nf, s.solver, s.fref, load_N=s.load, r=r)
            done, goes_on = settle_pairing(s.model, s.q, theta, active, asm, opts, s.fref,
                                           s.load, nf, it, s.flips, s.solver)
            if done is not None:
                return done
            s.model, r, nf = goes_on
            rf, s.frozen, paired_here, asm.model = r[free], False, True, s.model
        elif nf <= opts.contact_freeze * s.fref and has_contact(s.model):
            s.frozen = True
        s.history.append(nf)
        if nm <= opts.stall_vtol and (s.best is None or nf < s.best[0]):
            s.best = (nf, s.q, s.model, not paired_here, s.load)
        stalled = _stalled(s.history, opts.stall_iterations)
        if (not final and stalled and s.best is not None
                and s.best[0] <= opts.stall_rtol * s.best[4]):
            accepted = _accept_stall(s, asm, theta, active, opts, it)
            if accepted is not None:
                return accepted
            continue
        if stalled and not s.frozen and nf <= opts.modified_newton * s.fref and has_contact(s.model):
            # re-paired at every iterate, the pairing flips back and forth above the
            # freeze threshold (the residual alternates between two values): freeze it,
            # converge, and let the re-pairing decide (contact_rtol, contact_cycle_rtol)
            log.debug("  stalled with the pairs re-paired at every iterate: pairs frozen")
            s.frozen, s.history = True, []
        if opts.stall_cut and stalled and min(s.history) <= opts.modified_newton * s.fref:
            raise StepFailed(f"stalled at |r_u| = {nf:.3e} N (load {s.load:.3e} N, volume "
                             f"residual {nm:.2e}) after {it} iterations")
        if it == opts.max_iter:
            break
        if s.qn is not None:
            stepped = quasi_newton_step(s.qn, s.model, asm, s.q, theta, active, opts, r, nf, nm,
                                        s.fref, vref)
            if stepped is not None:
                s.q, s.evaluated = stepped
                s.solver.stale = True  # the state moved on: no adjoint's factorisation
                continue
        s.solver = s.qn = None  # its K, B and Pardiso copy: not kept alive through the next assembly
        q_old = s.q
        s.q, s.solver, s.evaluated = globalised_update(s.model, asm, s.q, theta, active, opts,
                                                       rf, rm, nf, nm, s.fref, vref, s.frozen)
        if qn_on and _newton_step_contracted(s, asm, opts, nf, nm, vref):
            # a tangent whose own step lowered the merit quasi_newton_ratio-fold is reused,
            # that step the first pair of its updates; after a weaker one (far from the
            # solution, on a plateau) quasi-Newton attempts only cost residuals: Newton goes on
            s.qn = QuasiNewton(s.solver, asm)
            s.qn.record(s.q - q_old, s.qn.reduce(r))
    raise StepFailed(f"no convergence in {opts.max_iter} iterations (|r_u| = {nf:.3e} N, "
                     f"load {s.load:.3e} N, volume residual {nm:.2e})")


def _newton_step_contracted(s: _Iterate, asm, opts: NewtonOptions, nf, nm, vref) -> bool:
    """Whether the Newton update just taken (to s.evaluated) lowered the merit below
    quasi_newton_ratio x its start's (force nf, volume nm)."""
    m1 = merit(s.evaluated, asm, s.fref, vref) if s.evaluated is not None else None
    return m1 is not None and m1 < opts.quasi_newton_ratio * np.hypot(nf / max(s.fref, 1e-300), nm)


def _predict(s: _Iterate, asm: Assembler, theta, dq_prescribed, opts: NewtonOptions, active):
    """The step's start: the prescribed increment with the consistent linear predictor
    (:func:`predicted`); the reference force becomes the predictor's right-hand side."""
    free, mult, model, q = asm.free_primal, asm.mult, s.model, s.q
    r, K, B, D, lr = asm.assemble(q, theta, active)
    hv = model.hvp(q, dq_prescribed, theta, active)
    s.solver = asm.solver(K, B, D, lr, opts.backend, cg_rtol=opts.cg_rtol)
    rhs = r + hv
    x, y = s.solver.solve(-rhs[free], -rhs[mult])
    s.q, s.evaluated = _prescribed_start(asm, model, q, theta, active, dq_prescribed,
                                         asm.expand(x, y))
    s.fref = np.linalg.norm(rhs[free])


def _prescribed_start(asm, model, q, theta, active, dq_prescribed, correction):
    """q + dq_prescribed plus the largest finite fraction of ``correction`` (n_dof,)
    (:func:`predicted`), and its :class:`Evaluated` residual (None if not evaluated)."""
    tried = []

    def residual(z):
        tried.append(evaluate(model, z, theta, active, asm))
        return tried[-1].r if tried[-1] is not None else np.full(1, np.nan)

    q_new = predicted(q + dq_prescribed, correction, residual)
    return q_new, tried[-1] if tried else None


def _tangent_predict(s: _Iterate, asm: Assembler, theta, dq_prescribed, opts: NewtonOptions,
                     active, solver, vref, previous=None):
    """The step's start from the tangent predictor on ``solver``, the factorised tangent K
    of the stage's previous step: the implicit-function derivative of the path taken over
    the increment, dq = -K^-1 (r(q, theta) + K_q dq_prescribed) (r at the new load, K_q dq
    the exact tangent's product with the prescribed increment), one solve and no assembly.
    A displacement-driven step takes it as :func:`_predict` takes its own (the largest
    finite fraction); a load-driven one at the first of :data:`PREDICTOR_ALPHAS` that
    lowers the merit (force and volume residual) of the last state at the new load, its
    trials restored to the linearised cavity volumes (:class:`Restoration`, as a Newton
    step's), else the iterations start at the last state. Falls back to :func:`_predict`
    when the old factorisation does not solve. The reference force becomes at least the
    predictor's right-hand side. ``previous`` (theta, r): the residual r at q under that
    load, used where ``theta`` is the same (no state evaluated twice)."""
    free, mult, model, q = asm.free_primal, asm.mult, s.model, s.q
    prescribed = bool(np.any(dq_prescribed))
    if prescribed and previous is not None and _same_load(previous[0], theta):
        start = Evaluated(model, q, previous[1], 0.0)
    else:
        start = evaluate(model, q, theta, active, asm)
    if start is None:  # the last state's residual at the new load is not finite
        return _predict(s, asm, theta, dq_prescribed, opts, active) if prescribed else None
    rhs = start.r + (model.hvp(q, dq_prescribed, theta, active) if prescribed else 0.0)
    fref = float(np.linalg.norm(rhs[free]))
    try:
        x, y = solver.solve(-rhs[free], -rhs[mult])
    except LinearSolveError as exc:
        log.debug("  tangent predictor: the previous step's factorisation fails (%s)", exc)
        if prescribed:
            return _predict(s, asm, theta, dq_prescribed, opts, active)
        s.evaluated = start
        return None
    s.fref = max(s.fref, fref)
    dq = asm.expand(x, y)
    if prescribed:
        s.q, s.evaluated = _prescribed_start(asm, model, q, theta, active, dq_prescribed, dq)
        return None
    restore = Restoration(model, q, dq, theta, active, asm, solver) if opts.restore else None
    try:
        q_new, lowered, ev = line_search(model, q, dq, theta, active, asm,
                                         merit(start, asm, fref, vref), fref, vref,
                                         PREDICTOR_ALPHAS, restore)
    except StepFailed:  # every trial inverts an element
        lowered = False
    if not lowered:
        log.debug("  tangent predictor does not lower the residual: not taken")
        s.q, s.evaluated = q, start
        return None
    s.q, s.evaluated = q_new, ev
    return None


def _same_load(a, b) -> bool:
    """Whether the parameter pytrees a and b hold the same values."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(np.array_equal(x, y) for x, y in zip(la, lb))


def _stalled(history: list, k: int) -> bool:
    """Whether the best residual of the last k iterations is not 10% below the best before
    them (on a plateau the residual wanders up and down)."""
    return len(history) > k and min(history[-k:]) > 0.9 * min(history[:-k])


def _accept_stall(s: _Iterate, asm: Assembler, theta, active, opts: NewtonOptions, it: int):
    """A stalled step's best iterate, flagged STALLED; None if it was found with the pairs
    frozen and re-paired is out of balance by more than stall_repair_rtol (the pairs are
    then released and Newton goes on)."""
    nf_best, q_best, model_best, paired_earlier, load = s.best
    note, unbalanced = "", nf_best
    if paired_earlier:  # in balance with earlier pairs: accepted if nearly so re-paired
        _, _, nf2, fc = repaired(model_best, q_best, theta, active, asm.free_primal)
        if nf2 > opts.stall_repair_rtol * max(load, fc):
            log.debug("  stalled; its best iterate, re-paired, is %.3e N out of balance: "
                      "pairs released", nf2)
            s.frozen, s.history, s.best = False, [], None
            return None
        note, unbalanced = f"; re-paired, {nf2:.3e} N out of balance", max(nf_best, nf2)
    log.warning("step accepted on a stall: |r_u| = %.3e N, the best of %d iterations (%.1e of "
                "the load %.3e N it carries; tolerance %.1e)%s", nf_best, it, nf_best / load,
                load, opts.rtol, note)
    asm.model = model_best
    return StepResult(model_best, q_best, it, nf_best, s.solver, s.fref, StepStatus.STALLED,
                      unbalanced, load)
