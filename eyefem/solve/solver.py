"""Load path and Newton's method with line search and automatic step cutting.

A load path is a sequence of :class:`Stage`. Within a stage the load factor t runs
from 0 to 1: prescribed displacements and term params are interpolated linearly from
their values at the stage start to the stage's targets. Each step is solved by Newton
on the reduced saddle-point system; a step that diverges, inverts an element or
produces non-finite values is cut in half and retried; after ``max_cuts`` cuts the
solve stops with :class:`ConvergenceError`, which carries the last converged state.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any, Callable, Sequence

import jax
import numpy as np

from eyefem.fem.terms import Term
from eyefem.solve.assembly import Assembler
from eyefem.solve.linsolve import LinearSolveError, NegativeCurvature
from eyefem.solve.model import Model, check_x64

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class NewtonOptions:
    """Settings of the Newton solver.

    Attributes:
      rtol: force residual tolerance relative to the step's reference force.
      vtol: constraint (volume) residual tolerance relative to the solid volume.
      atol: absolute force tolerance, N.
      max_iter: Newton iterations per step before the step is cut (40: the step of
        coarse case 3's suture stage near t = 0.07 converged in 25 iterations in one run
        and was cut to failure in two others; 40 passes it).
      max_cuts: successive halvings of a step before giving up.
      grow_iterations: after a cut, the increment doubles again (up to the nominal one)
        after each step that converges in at most this many iterations (8; with 12,
        tried in the eighth session, default case 4 failed twice near t = 0.57 of its
        tightening, where larger increments run onto residual plateaus; with 8 it ran
        to the end, its increments staying at 1/64-1/512 of the stage after the cuts).
      line_search: backtrack on the residual norm when a full step does not reduce it.
      backend: linear solver backend (None: the default, see linsolve).
      beta: strength of the element-wise augmentation of the saddle-point solve.
      cg_rtol: the Schur-complement CG of a Newton direction stops at this constraint
        residual, relative (``SaddlePointSolver.cg_rtol``; 1e-12 there, for adjoints). A
        direction needs no more: 1e-8 takes 6 CG iterations on the default eye tangent
        instead of 9, and default case 4 ran the same 78 iterations to the same outcomes
        (IOP 44.78406 mmHg either way) in 8% less time (docs/performance.md).
      contact_freeze: contact pairs (dynamic terms) are re-paired every iteration until
        the force residual falls below contact_freeze x the reference, then frozen for
        quadratic convergence; at convergence they are re-paired once more. They are
        also frozen when the step stalls (``stall_iterations``) below modified_newton x
        the reference while re-paired every iteration: a pairing that flips back and
        forth at every iterate (default-eye sponge, 1.375e-3 and 1.380e-3 N in turn for
        37 iterations, just above the freeze threshold of 1.33e-3 N).
      modified_newton: while the force residual is above modified_newton x the reference,
        an indefinite tangent is shifted to positive definite (modified Newton step).
      pressure_stiffness: keep the follower pressures' load stiffness (-p d2V/dq2) in the
        tangent far from convergence too (above modified_newton x the reference). Off
        (the default), those steps use the tangent without it: on the default eye mesh
        it nearly cancels the very soft retina's stiffness against wrinkling of the
        wetted surface, and the first steps of a buckle's indentation ran along those
        near-singular modes into inverted elements. Near convergence the tangent is exact.
      restore: when a full Newton step does not lower the residual, restore the trial
        points' cavity volumes to their linear prediction (second-order correction; see
        ``_Restoration``).
      extrapolate: start each step's Newton iterations from the secant extrapolation of
        the two previous converged states of the stage (from the last state if that fails).
      contact_rtol: the residual after that final re-pairing must be below contact_rtol x
        max(reference, norm of the contact forces) (a node at a surface edge or on a facet
        edge may flip without end; this bounds the force such a flip leaves unbalanced),
        else Newton continues.
      contact_cycle_rtol: a node on a facet edge (or a corner of the master surface) can
        make the pairing cycle: the state converged with pairing A re-pairs to B, the
        one converged with B re-pairs to A, and the same unbalanced force comes back
        every time. When a re-pairing leaves the same force (within 1%) as an earlier
        one of the step and that force is below contact_cycle_rtol x max(reference,
        norm of the contact forces), the step is accepted, with a warning naming the
        nodes, at the converged state with the pairing it is in equilibrium with (the
        coarse deformable-band case's last suture step cycled at 2e-4 of its reference
        force on one machine and ran to failure through 8 cuts). So is a step whose
        converged state changes pairing for the UNSETTLED_REPAIRS-th time (3) with a
        force below that bound, cycle or not (under the deformable ridged tire on the
        default eye each re-pairing moved 18-50 nodes to other facets and left 1e-3 to
        6e-3 of the reference, never the same twice).
      stall_iterations: a step has stalled when the best force residual of its last this
        many iterations is not 10% below the best before them (on the default eye mesh a
        step can settle on a
        plateau of 1e-7 to 2e-6 of the reference force that no Newton or modified
        Newton step lowers: the retina's near-neutral modes under the cavity pressure).
      stall_rtol, stall_vtol: a stalled step inside a stage is accepted, with a warning,
        at its best iterate (the least force residual among those with a volume residual
        below stall_vtol) when that force residual is below stall_rtol x the reference
        (the load path has no history, so the next step starts
        that close to it and converges to rtol). The step that ends a stage is never
        accepted on a stall (the next stage has its own, often much smaller, reference
        force and cannot start from a stalled state), and a step stalled above these
        goes on to max_iter (or is cut, with ``stall_cut``).
      stall_repair_rtol: a best iterate found with the contact pairs frozen is accepted
        on a stall only if, re-paired, its force residual is below this x the
        reference; else the pairs are released and Newton goes on. Default: no bound
        (the warning gives that force; the stage's last step is always converged, and
        the path has no history, so an intermediate step only steers the path: the
        coarse deformable ridged tire passes t = 0.625 of its tightening on an iterate
        7.6 N out of balance re-paired, and cuts to 1/2048 near t = 0.64 without it;
        the default eye's tire failed the step after one 5 N out of balance).
      stall_cut: a stalled step that is not accepted is cut at once, without spending the
        iterations left to max_iter, once its best force residual is below modified_newton x
        the reference (off by default; default case 3 passed the end of its eight-step
        tightening with it, default case 4 failed with it and grow_iterations = 12:
        docs/performance.md).
      contact_lookahead: re-solve a Newton step with the penalty model of the contact
        nodes it would push into contact from out of the penalty's reach (``_lookahead``).
      max_step: when no line-search trial of a Newton step that moves a node by more
        than max_step (mm) lowers the residual (or every trial inverts an element), the
        step is solved again with Levenberg-Marquardt shifts 1e-4 ... 1 of the modified
        tangent (``SHIFTS``); at the last one a step still longer than max_step is
        scaled down to it. If no damped step lowers the residual either, the undamped
        step's best trial is taken, as without damping (the last shift's if every
        undamped trial inverts an element), unless the contact pairs are frozen and
        that trial raises the residual FALLBACK_RISE-fold: then the load step is cut at
        once. (On the default eye mesh steps of 2-800 mm along near-singular
        modes of the soft retina inverted elements at every trial and the load step was
        cut; under the deformable ridged tire at t = 0.75-0.875 of its tightening the
        fallback took the residual from 0.019 to 1.5 N and 32 more iterations to 11 N
        before the cut that then converged in 8 iterations.)
      contact_curvature: while the force residual is above contact_curvature x the
        reference, penalty contacts that have one use their Gauss-Newton tangent
        (``Term.grad_hess_gauss_newton``), without the term alpha p p' grad^2 g of the
        contact surface's curvature; below it the tangent is exact (quadratic
        convergence). At the ridged tire's flanks and rounded edges that term is a
        negative tangential stiffness of the nodes pressed on them, larger than the soft
        sclera's own: the exact tangent sent Newton steps of 1-5 mm along the sclera
        beside the tire and default case 4 took 193 iterations; with 1e-3, 124 and the
        same outcomes (docs/performance.md, thirteenth session). Off by default (0):
        with 1e-3 and the default eight tightening steps, default case 2 ended its
        tightening on a residual plateau (2.8e-4 N against a 3.3e-6 N tolerance) that
        repeated cuts did not pass; the case files of the ridged-tire cases 2-4 set it
        with four tightening steps (case 2: 88 iterations instead of 327). With it on, the contact look-ahead also admits a node only if its
        exact gap at the step's end penetrates (``_lookahead``). The node-to-segment
        ``SurfaceContact`` has one too (the gap's curvature over a facet); on the coarse
        deformable ridged tire (case 4) it made matters worse (the tightening cut to 1/256
        at t = 0.69, where the exact tangent ran through), so its case file leaves it off.
    """

    rtol: float = 1e-8
    vtol: float = 1e-10
    atol: float = 1e-11
    max_iter: int = 40
    max_cuts: int = 8
    grow_iterations: int = 8
    line_search: bool = True
    backend: str | None = None
    beta: float = 1e4
    cg_rtol: float = 1e-8
    contact_freeze: float = 1e-3
    contact_rtol: float = 1e-4
    contact_cycle_rtol: float = 1e-3
    extrapolate: bool = False
    modified_newton: float = 1e-2
    pressure_stiffness: bool = False
    restore: bool = True
    stall_iterations: int = 8
    stall_rtol: float = 1e-5
    stall_vtol: float = 1e-8
    stall_cut: bool = False
    stall_repair_rtol: float = float("inf")
    contact_lookahead: bool = True
    max_step: float = 0.5
    contact_curvature: float = 0.0

    def __post_init__(self):
        for f in ("rtol", "vtol", "atol", "beta", "cg_rtol", "contact_freeze", "contact_rtol",
                  "contact_cycle_rtol", "modified_newton",
                  "stall_rtol", "stall_vtol", "stall_repair_rtol", "max_step"):
            if not getattr(self, f) > 0:
                raise ValueError(f"NewtonOptions.{f} = {getattr(self, f)}; must be > 0")
        if not self.contact_curvature >= 0:
            raise ValueError(f"NewtonOptions.contact_curvature = {self.contact_curvature}; "
                             "must be >= 0 (0: always the exact contact tangent)")
        if self.max_iter < 1 or self.max_cuts < 0 or self.stall_iterations < 2:
            raise ValueError(f"NewtonOptions: max_iter = {self.max_iter}, max_cuts = "
                             f"{self.max_cuts}, stall_iterations = {self.stall_iterations}; "
                             "need max_iter >= 1, max_cuts >= 0 and stall_iterations >= 2")


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a load path.

    Attributes:
      name: stage name (logs, outputs).
      n_steps: nominal number of load steps.
      prescribed: (dofs (n,), targets (n,)): displacement dofs prescribed during the
        stage and their values (mm) at its end, reached linearly from the start values.
      params: term name -> params at the end of the stage (linear ramp); others held.
      active: names of the terms in the energy (None: all).
      before: optional host-side hook ``f(model, q, theta) -> (model, q, theta)`` run at
        the stage start (closing a cavity, switching contact on...).
    """

    name: str
    n_steps: int
    prescribed: tuple[np.ndarray, np.ndarray]
    params: dict = dataclasses.field(default_factory=dict)
    active: tuple[str, ...] | None = None
    before: Callable | None = None

    def __post_init__(self):
        if self.n_steps < 1:
            raise ValueError(f"stage '{self.name}': n_steps = {self.n_steps}; must be >= 1")
        d, v = self.prescribed
        d = np.asarray(d, np.int64).ravel()
        v = np.broadcast_to(np.asarray(v, np.float64), d.shape).copy()
        if len(np.unique(d)) != len(d):
            raise ValueError(f"stage '{self.name}': a dof is prescribed twice")
        object.__setattr__(self, "prescribed", (d, v))


@dataclasses.dataclass
class StepRecord:
    """Log of one converged step."""

    stage: str
    step: int
    t: float
    iterations: int
    residual: float
    wall: float
    info: dict = dataclasses.field(default_factory=dict)


class ConvergenceError(RuntimeError):
    """Newton failed after all step cuts; ``.q``/``.theta`` hold the last converged state."""

    def __init__(self, msg, q, theta, history):
        super().__init__(msg)
        self.q, self.theta, self.history = q, theta, history


@dataclasses.dataclass
class Solution:
    """Result of a load path: final state and per-step history."""

    model: Model
    q: np.ndarray
    theta: Any
    history: list[StepRecord]
    assembler: Assembler | None = None
    solver: Any = None
    active: tuple[str, ...] | None = None

    def factorised(self) -> "Solution":
        """This solution with a factorisation of the tangent (for adjoints) if it has none."""
        if self.solver is not None:
            return self
        r, K, B, D, lr = self.assembler.assemble(self.q, self.theta, self.active)
        return dataclasses.replace(self, solver=self.assembler.solver(K, B, D, lr))


def _lerp(a, b, t):
    return jax.tree_util.tree_map(lambda x, y: (1.0 - t) * np.asarray(x) + t * np.asarray(y), a, b)


ACCEPTED_FLAGS = {"stall": "stalled", "contact cycle": "contact_cycle"}
"""Flag in ``StepRecord.info`` of a step accepted without converging, by reason."""


class _StepFailed(Exception):
    pass


def newton(model: Model, asm: Assembler, q, theta, dq_prescribed, opts: NewtonOptions,
           active=None, vref=1.0, fscale=0.0, final=True):
    """Solve one step. Returns (model, q, iterations, residual, solver, reference force,
    accepted): ``accepted`` is None for a converged step, "stall" or "contact cycle" for
    one accepted on a stall or on a cycling contact pairing (``NewtonOptions``).

    The model is returned because dynamic terms (contact) are re-paired every iteration.

    q is the state at the previous step; dq_prescribed (n_dof,) the increment of the
    prescribed dofs (zero elsewhere), taken with a consistent linear predictor. The
    force tolerance is relative to the largest of the step's initial out-of-balance
    force, the reactions and ``fscale`` (the stage's typical step force), so a cut step
    is not held to a tighter absolute tolerance than a full one. A step that stalls
    (``NewtonOptions.stall_iterations``) below ``stall_rtol`` x the reference is accepted
    unless it is ``final`` (it ends a stage).
    """
    free = asm.free_primal
    mult = asm.mult
    fref = fscale
    solver = None
    q = q.copy()
    asm.model = model  # after a failed try the assembler holds that try's contact pairing
    if np.any(dq_prescribed):
        r, K, B, D, lr = asm.assemble(q, theta, active)
        hv = model.hvp(q, dq_prescribed, theta, active)
        solver = asm.solver(K, B, D, lr, opts.backend, cg_rtol=opts.cg_rtol)
        rhs = r + hv
        x, y = solver.solve(-rhs[free], -rhs[mult])
        q = _predicted(q + dq_prescribed, asm.expand(x, y),
                       lambda z: model.gradient(z, theta, active))
        fref = np.linalg.norm(rhs[free])
    frozen = False
    history, best = [], None  # best: (force residual, q, model, paired earlier) of the best iterate
    flips = []  # residuals left by re-pairing converged states
    for it in range(opts.max_iter + 1):
        paired_here = not frozen  # this iterate is re-paired at its own state
        if paired_here:
            model = model.update(q, theta)
        asm.model = model
        r = model.gradient(q, theta, active)
        if not np.all(np.isfinite(r)):
            raise _StepFailed("non-finite residual (an element inverted?)")
        rf, rm = r[free], r[mult]
        react = np.linalg.norm(r[asm.prescribed])
        nf = np.linalg.norm(rf)
        fref = max(fref, nf if it == 0 else 0.0, react)
        nm = np.linalg.norm(rm) / vref if len(rm) else 0.0
        log.debug("  iter %d |r_u| %.3e (ref %.3e) |r_vol| %.3e%s", it, nf, fref, nm,
                  " (pairs frozen)" if frozen else "")
        if nf <= opts.rtol * fref + opts.atol and nm <= opts.vtol:
            if not frozen:
                return model, q, it, nf, solver, fref, None
            repaired, r2, nf2, fc = _repaired(model, q, theta, active, free)
            if nf2 <= opts.contact_rtol * max(fref, fc) + opts.atol:
                asm.model = repaired
                return repaired, q, it, nf2, solver, fref, None
            cycles = any(abs(nf2 - f) <= 0.01 * nf2 for f in flips)
            if ((cycles or len(flips) + 1 >= UNSETTLED_REPAIRS)
                    and nf2 <= opts.contact_cycle_rtol * max(fref, fc)):
                nodes = _repaired_nodes(model, repaired)
                log.warning("contact pairing %s at convergence (nodes %s flip between "
                            "facets): accepted with the pairing it is in equilibrium with; "
                            "re-paired, %.3e N is left unbalanced (%.1e of the reference "
                            "%.3e N)", "cycles" if cycles else
                            f"has not settled after {len(flips) + 1} re-pairings",
                            _node_list(nodes), nf2, nf2 / max(fref, fc), max(fref, fc))
                return model, q, it, nf, solver, fref, "contact cycle"
            flips.append(nf2)
            if log.isEnabledFor(logging.DEBUG):
                node, f_node = _largest_nodal_force(r2, free, model.mesh.n_nodes)
                log.debug("  converged with the pairs frozen; re-paired, %.3e N out of balance "
                          "(pairing changed at nodes %s; largest force %.3e N at node %d)",
                          nf2, _node_list(_repaired_nodes(model, repaired)), f_node, node)
            model, r, rf, nf, frozen, paired_here = repaired, r2, r2[free], nf2, False, True
            asm.model = model
        elif nf <= opts.contact_freeze * fref and any(t.dynamic for t in model.terms):
            frozen = True
        history.append(nf)
        if nm <= opts.stall_vtol and (best is None or nf < best[0]):
            best = (nf, q, model, not paired_here)
        k = opts.stall_iterations
        # stalled: the best residual of the last k iterations is not 10% below the best
        # before them (on a plateau the residual wanders up and down)
        stalled = len(history) > k and min(history[-k:]) > 0.9 * min(history[:-k])
        if not final and stalled and best is not None and best[0] <= opts.stall_rtol * fref:
            repaired_note = ""
            if best[3]:  # in balance with earlier pairs: accepted if nearly so re-paired
                _, _, nf2, fc = _repaired(best[2], best[1], theta, active, free)
                if nf2 > opts.stall_repair_rtol * max(fref, fc):
                    log.debug("  stalled; its best iterate, re-paired, is %.3e N out of "
                              "balance: pairs released", nf2)
                    frozen, history, best = False, [], None
                    continue
                repaired_note = f"; re-paired, {nf2:.3e} N out of balance"
            log.warning("step accepted on a stall: |r_u| = %.3e N, the best of %d iterations "
                        "(%.1e of the reference %.3e N; tolerance %.1e)%s", best[0], it,
                        best[0] / fref, fref, opts.rtol, repaired_note)
            asm.model = best[2]
            return best[2], best[1], it, best[0], solver, fref, "stall"
        if (stalled and not frozen and nf <= opts.modified_newton * fref
                and any(t.dynamic for t in model.terms)):
            # re-paired at every iterate, the pairing flips back and forth above the
            # freeze threshold (the residual alternates between two values): freeze it,
            # converge, and let the re-pairing decide (contact_rtol, contact_cycle_rtol)
            log.debug("  stalled with the pairs re-paired at every iterate: pairs frozen")
            frozen, history = True, []
        if opts.stall_cut and stalled and min(history) <= opts.modified_newton * fref:
            raise _StepFailed(f"stalled at |r_u| = {nf:.3e} N (reference {fref:.3e} N, volume "
                              f"residual {nm:.2e}) after {it} iterations")
        if it == opts.max_iter:
            break
        cache = {}

        gn = nf > opts.contact_curvature * fref if opts.contact_curvature else False
        # the restoration's K^-1 dV/dq, solved with each Newton direction (same back-solves)
        vgrad = _Restoration.gradients(model, q, theta, active) if opts.restore else None
        extra = vgrad[:, free].T if vgrad is not None else None

        def direction(far, shift):
            return _direction(asm, lambda exact: asm.assemble(q, theta, active, exact, gn)[1:],
                              rf, rm, opts, far, cache, shift, extra)

        far, shift = nf > opts.modified_newton * fref, 0.0
        m0 = np.hypot(nf / max(fref, 1e-300), nm)
        alphas = (1.0, 0.5, 0.25, 0.125, 0.0625) if opts.line_search else (1.0,)
        undamped = None  # the undamped step's best line-search trial
        while True:
            try:
                x, y, solver, W = direction(far, shift)
                n_la = 0
                if opts.contact_lookahead:
                    xl, yl, la_solver, n_la = _lookahead(model, asm, q, theta, active, solver,
                                                         rf, rm, x, y,
                                                         end_gap=opts.contact_curvature > 0)
            except LinearSolveError as exc:
                raise _StepFailed(str(exc)) from exc
            if n_la:
                # the look-ahead's model of a node can be wrong (it stays outside): then
                # no trial of its step lowers the residual and the plain step is tried
                log.debug("  contact look-ahead: %d nodes", n_la)
                dq = asm.expand(xl, yl)
                restore = _Restoration(model, q, dq, theta, active, asm, la_solver) if opts.restore else None
                try:
                    q_try, lowered = _line_search(model, q, dq, theta, active, asm, m0, fref, vref,
                                                  alphas[:3], restore)
                except _StepFailed:
                    lowered = False
                if lowered:
                    q = q_try
                    break
                log.debug("  look-ahead step: no trial lowers the residual; the plain step")
            dq = asm.expand(x, y)
            longest = _longest(model, dq)
            last = (max(shift, solver.shift) >= SHIFTS[-1] or not opts.line_search
                    or (shift == 0.0 and longest <= opts.max_step))
            if last and longest > opts.max_step:
                log.debug("  step of %.3g mm scaled to max_step = %g mm", longest, opts.max_step)
                dq *= opts.max_step / longest
            restore = (_Restoration(model, q, dq, theta, active, asm, solver, (vgrad, W))
                       if opts.restore else None)
            try:
                q_try, lowered = _line_search(model, q, dq, theta, active, asm, m0, fref, vref, alphas,
                                              restore)
            except _StepFailed:
                if last and undamped is None:
                    raise
                q_try, lowered = None, False
            if undamped is None and shift == 0.0:
                undamped = q_try
            if lowered or last:
                # no damped step lowers the residual either: the undamped step's best trial
                # (the last shift's if every undamped trial inverted an element), unless the
                # pairs are frozen (Newton near convergence on one pairing) and that trial
                # raises the residual FALLBACK_RISE-fold: then the load step is cut
                fallback = q_try if lowered or undamped is None else undamped
                if not lowered and frozen:
                    m1 = _merit(model, fallback, theta, active, asm, fref, vref)
                    if m1 is None or m1 > FALLBACK_RISE * m0:
                        raise _StepFailed(
                            f"no trial of a Newton step lowers the residual |r_u| = {nf:.3e} N "
                            f"(reference {fref:.3e} N; the best raises it "
                            f"{'to non-finite values' if m1 is None else f'{m1 / m0:.0f}-fold'}"
                            "; near-singular modes of the tangent, -v names their nodes)")
                q = fallback
                break
            # no trial lowers the residual, or every trial inverts an element (a
            # near-singular tangent: the soft retina's tangential modes): damp the step
            far, shift = True, min(mu for mu in SHIFTS if mu > max(shift, solver.shift))
            if log.isEnabledFor(logging.DEBUG):
                norms = np.linalg.norm(dq[:model.n_u].reshape(-1, 3), axis=1)
                log.debug("  line search failed on a %.3g mm step (at node %d; nodes over "
                          "half of it: %d): shift %g", longest, int(np.argmax(norms)),
                          int(np.sum(norms > 0.5 * longest)), shift)
    raise _StepFailed(f"no convergence in {opts.max_iter} iterations (|r_u| = {nf:.3e} N, "
                      f"reference {fref:.3e} N, volume residual {nm:.2e})")


UNSETTLED_REPAIRS = 3
"""A step whose state, converged with the contact pairs frozen, changes pairing for the
third time and leaves below contact_cycle_rtol x the reference unbalanced is accepted
as on a contact cycle (NewtonOptions.contact_cycle_rtol)."""

FALLBACK_RISE = 10.0
"""With the contact pairs frozen, a Newton step none of whose trials (undamped or
shifted) lowers the residual, and whose fallback trial raises it this many times, cuts
the load step (NewtonOptions.max_step)."""


PREDICTOR_SCALES = (1.0, 0.5, 0.25, 0.125, 0.0)
"""Fractions of the linear predictor's correction tried in turn (:func:`_predicted`)."""


def _predicted(q_prescribed, correction, residual):
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


def _repaired(model: Model, q, theta, active, free):
    """The model re-paired at q, its residual (n_dof,), free force residual and the free
    force of its contact (dynamic) terms, N."""
    repaired = model.update(q, theta)
    r = repaired.gradient(q, theta, active)
    dyn = [t.name for t in repaired.terms if t.dynamic and (active is None or t.name in active)]
    fc = np.linalg.norm(repaired.gradient(q, theta, dyn)[free]) if dyn else 0.0
    return repaired, r, np.linalg.norm(r[free]), fc


def _repaired_nodes(old: Model, new: Model) -> np.ndarray:
    """Slave nodes whose contact pairing differs between two models of the same terms."""
    nodes = []
    for a, b in zip(old.terms, new.terms):
        if not a.dynamic:
            continue
        rows = []
        for t in (a, b):
            w = np.asarray(t.data.get("w", np.ones(len(t.dofs)))) > 0
            rows.append({tuple(r) for r in np.asarray(t.dofs)[w].tolist()})
        nodes += [r[0] // 3 for r in rows[0] ^ rows[1]]
    return np.unique(np.array(nodes, dtype=np.int64))


def _largest_nodal_force(r, free, n_nodes):
    """(node, force N) of the largest unbalanced free nodal force in the residual r (n_dof,)."""
    f = np.zeros(3 * n_nodes)
    sel = free[free < 3 * n_nodes]
    f[sel] = r[sel]
    norms = np.linalg.norm(f.reshape(-1, 3), axis=1)
    return int(np.argmax(norms)), float(norms.max())


def _node_list(nodes, at_most=8) -> str:
    more = f" and {len(nodes) - at_most} more" if len(nodes) > at_most else ""
    return ", ".join(str(n) for n in nodes[:at_most]) + more if len(nodes) else "none found"


SHIFTS = (0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)
"""Levenberg-Marquardt shifts mu of the modified Newton tangent K + mu |diag K|."""


def _longest(model, dq):
    """Largest nodal displacement (mm) of a step dq (n_dof,)."""
    return float(np.linalg.norm(dq[:model.n_u].reshape(-1, 3), axis=1).max(initial=0.0))


def _direction(asm, tangent, rf, rm, opts, far, cache=None, min_shift=0.0, extra=None):
    """Newton direction (x, y, solver, W); ``tangent(exact)`` assembles (K, B, D,
    low_rank), exact or without the follower pressures' load stiffness; ``extra``
    (n_free, k): further right-hand sides (zero constraint part) solved together with
    the direction, their solutions expanded to W (n_dof, k) (None without).

    Near convergence (force residual below modified_newton x the reference) the exact
    tangent is used when it is positive definite, so the convergence stays quadratic.
    Far from it, or where the exact tangent shows negative curvature, a modified Newton
    step: the tangent without the pressure stiffness (unless
    ``NewtonOptions.pressure_stiffness``), shifted by mu |diag K| with mu = 0, 1e-4, 1e-3,
    ... until it is positive: a descent direction that leaves saddle points. If none is,
    the exact (indefinite) system is solved. ``cache`` (a dict) keeps the assembled
    tangents between calls; ``min_shift``: the smallest shift tried (a damped step after a
    failed line search)."""
    cache = {} if cache is None else cache

    def pieces(exact):
        exact = exact or opts.pressure_stiffness
        if exact not in cache:
            cache[exact] = tangent(exact)
        return cache[exact]

    tries = ([] if far or min_shift else [(True, 0.0)]) + [
        (False, mu) for mu in SHIFTS
        if mu >= min_shift and (mu or far or not opts.pressure_stiffness)]  # not the exact tangent twice
    def solve(solver):
        if extra is None:
            return (*solver.solve(-rf, -rm), solver, None)
        X, Y = solver.solve(np.column_stack([-rf, extra]),
                            np.column_stack([-rm, np.zeros((len(rm), extra.shape[1]))]))
        W = np.zeros((asm.model.n_dof, extra.shape[1]))
        W[asm.free_primal], W[asm.mult] = X[:, 1:], Y[:, 1:]
        return X[:, 0], Y[:, 0], solver, W

    for exact, mu in tries:
        try:
            out = solve(asm.solver(*pieces(exact), opts.backend, shift=mu, indefinite="raise",
                                   cg_rtol=opts.cg_rtol))
            if not exact or mu:
                log.debug("  modified Newton step (%s, shift %g)", "without the pressure stiffness"
                          if not opts.pressure_stiffness else "exact tangent", mu)
            return out
        except NegativeCurvature:
            continue
    return solve(asm.solver(*pieces(True), opts.backend, cg_rtol=opts.cg_rtol))


def _lookahead(model, asm, q, theta, active, solver, rf, rm, x, y, rounds=4, end_gap=False):
    """Active-set look-ahead of the penalty contacts along a Newton step (x, y).

    A smoothed penalty node more than 2 eps outside the surface has almost no stiffness
    in the tangent, so a step that pushes it in runs it deep into the penalty: the
    residual jumps and the line search crawls at 1/8 of the step (observed at the edge of
    the ridged tire, where the sclera bulges out against the tire's rounded edge). Such a
    node (gap g > 2 eps now, g + dg < -eps along the step) enters the system with the
    plain penalty's quadratic model 1/2 alpha (g + G . dq)^2 (force alpha g G, stiffness
    alpha G G^T) and the step is solved again; a node the new step keeps outside
    (g + dg > 0) leaves the set again (a primal-dual active-set update), for at most
    ``rounds`` solves. Each node's stiffness is a rank-one update alpha v v^T (v: G on
    the free dofs) of the step's factorised ``solver`` (Woodbury: no refactorisation).
    With ``end_gap`` the exact gap at the step's end must be below -eps too, which keeps
    out nodes whose linearised gap is meaningless over the step: beyond the edges of an
    encircling buckle the gap grows with the cube of the distance from the edge, and a
    node millimetres away sliding along the sclera had a linearised gap change of -10^2
    to -10^3 mm; on default case 4 up to 762 such nodes entered the look-ahead in one
    iteration. The solver sets it with the Gauss-Newton contact tangent
    (``NewtonOptions.contact_curvature``): with the exact tangent those nodes' stiffness
    alpha |G|^2 happened to hold the soft sliding modes beside the tire, and without
    them default case 4 took more iterations (docs/performance.md, thirteenth session).
    Returns (x, y, solver of the last solve, number of look-ahead nodes)."""
    members = {}
    la_solver = None
    x0, y0 = x, y
    for _ in range(rounds):
        lin = model.gap_linearisations(q, asm.expand(x, y), theta, active)
        changed = False
        for t, g, dg, G, g_end in lin:
            eps = t.smoothing
            m = members.get(t.name, np.zeros(len(g), bool))
            enter = (g > 2 * eps) & (g + dg < -eps) & ((g_end < -eps) if end_gap else True)
            new = (m | enter) & ~(m & (g + dg > 0))
            changed |= bool(np.any(new != m))
            members[t.name] = new
        if not changed:
            break
        gx = np.zeros(model.n_dof)
        terms = []
        for t, g, dg, G, _ in lin:
            m = np.nonzero(members[t.name])[0]
            a = t.data["alpha"][m]
            gx += np.bincount(t.dofs[m].ravel(), ((a * g[m])[:, None] * G[m]).ravel(),
                              minlength=model.n_dof)
            for i, al in zip(m, a):
                v = np.zeros(model.n_dof)
                v[t.dofs[i]] = G[i]
                terms.append((al, v[asm.free_primal]))
        la_solver = solver.plus_low_rank(terms) if terms else solver
        try:
            x, y = la_solver.solve(-(rf + gx[asm.free_primal]), -rm)
        except NegativeCurvature:  # roundoff of the update on a nearly singular tangent
            log.debug("  contact look-ahead dropped: negative curvature")
            return x0, y0, solver, 0
    n = int(sum(np.sum(m) for m in members.values()))
    return x, y, la_solver, n


class _Restoration:
    """Second-order restoration of the stiff low-rank quantities (cavity volumes) along a
    Newton step.

    A step that keeps a cavity's volume to first order changes it to second order, and the
    liquid (K / V ~ 0.4 MPa/mm^3 for the eye) turns that into a pressure jump on every
    wetted face: the residual norm then rejects a good step at every length (the Maratos
    effect of constrained optimisation). The trial point q + a dq is moved along
    w_j = K^-1 v_j (v_j = dV_j/dq, on the step's own factorisation) until every volume is
    back at its linear prediction V_j(q) + a v_j . dq (a few chord iterations on the
    volumes alone). Near convergence the correction is of second order and Newton's
    quadratic convergence is kept.
    """

    def __init__(self, model, q, dq, theta, active, asm, solver, solved=None):
        self.terms = self._terms(model, active)
        self.model, self.active = model, active
        self.q, self.dq, self.theta, self.asm, self.solver = q, dq, theta, asm, solver
        self.ok = bool(self.terms) and solver is not None
        self.W = None
        self.solved = solved if solved is not None and solved[1] is not None else None

    @staticmethod
    def _terms(model, active):
        return [t for t in model.terms if (active is None or t.name in active)
                and type(t).low_rank_values is not Term.low_rank_values]

    @staticmethod
    def gradients(model, q, theta, active):
        """The restored volumes' gradients v_j = dV_j/dq at q (k, n_dof); None if none."""
        G = [np.asarray(v) for t in _Restoration._terms(model, active)
             for _, v in t.low_rank(q, theta[t.name], t.data, t.dofs)]
        return np.stack(G) if G else None

    def _setup(self):
        """Volumes and their gradients at q, and w_j = K^-1 v_j (one solve per cavity,
        unless solved with the Newton direction: ``solved`` = (G, W))."""
        self.c0 = self._values(self.q)
        if self.solved is not None:
            G, self.W = self.solved
        else:
            G = self.gradients(self.model, self.q, self.theta, self.active)
            x, y = self.solver.solve(G[:, self.asm.free_primal].T,
                                     np.zeros((len(self.asm.mult), len(G))))
            self.W = np.zeros((len(self.q), len(G)))
            self.W[self.asm.free_primal], self.W[self.asm.mult] = x, y
        self.J = G @ self.W
        self.slope = G @ self.dq

    def _values(self, q):
        return np.array([c for t in self.terms for c in t.low_rank_values(q, self.theta[t.name])])

    def __call__(self, qa, alpha):
        """qa = q + alpha dq moved back to the linearly predicted volumes (None: failed)."""
        if not self.ok:
            return None
        if self.W is None:
            try:
                self._setup()
            except LinearSolveError as exc:  # e.g. negative curvature met by a new right-hand side
                log.debug("  volume restoration skipped: %s", exc)
                self.ok = False
                return None
        target = self.c0 + alpha * self.slope
        s = np.zeros(len(target))
        tol = 1e-12 * max(np.abs(target).max(), 1e-300)
        for _ in range(6):
            err = self._values(qa + self.W @ s) - target
            if not np.all(np.isfinite(err)):
                return None
            if np.abs(err).max() <= tol:
                break
            try:
                s = s - np.linalg.solve(self.J, err)
            except np.linalg.LinAlgError:  # K^-1 indefinite on the volume gradients
                return None
        return qa + self.W @ s


def _merit(model, q, theta, active, asm, fref, vref):
    """Line-search merit at q: force residual / reference and volume residual / solid
    volume, combined; None where the residual is not finite (an inverted element)."""
    r = model.gradient(q, theta, active)
    if not np.all(np.isfinite(r)):
        return None
    return np.hypot(np.linalg.norm(r[asm.free_primal]) / max(fref, 1e-300),
                    np.linalg.norm(r[asm.mult]) / vref if len(asm.mult) else 0.0)


def _line_search(model, q, dq, theta, active, asm, m0, fref, vref, alphas, restore=None):
    """Backtracking on the residual norm (merit: force residual / reference, volume
    residual / solid volume) over the step lengths ``alphas``. When the full step fails
    and the model has stiff low-rank terms (closed cavities), the trials are restored to
    the linearised volumes (:class:`_Restoration`). Returns (the first trial that lowers
    the merit, True), else (the best trial, False)."""
    if restore is not None and restore.ok and len(alphas) > 0:
        trials = [(alphas[0], False)] + [(a, True) for a in alphas]
    else:
        trials = [(a, False) for a in alphas]
    best, tried = None, set()
    for alpha, restored in trials:
        qa = restore(q + alpha * dq, alpha) if restored else None
        if qa is None:
            qa, restored = q + alpha * dq, False
        if not restored:
            if alpha in tried:  # the restoration failed: this plain trial was evaluated
                continue
            tried.add(alpha)
        m = _merit(model, qa, theta, active, asm, fref, vref)
        if m is None:
            continue
        if m < m0:
            if alpha < 1.0 or restored:
                log.debug("  line search: step length %g%s", alpha,
                          " (volumes restored)" if restored else "")
            return qa, True
        if best is None or m < best[0]:
            best = (m, qa)
    if best is None:
        raise _StepFailed("every line-search trial gave non-finite values (inverted elements)")
    return best[1], False


def solve(model: Model, stages: Sequence[Stage], *, q0=None, theta=None,
          options: NewtonOptions = NewtonOptions(),
          on_step: Callable[[StepRecord, Model, np.ndarray, Any], None] | None = None,
          on_stage_end: Callable[[int, Model, np.ndarray, Any, list], None] | None = None,
          completed: Sequence[tuple[np.ndarray, Any]] = ()) -> Solution:
    """Run a load path from q0 (default zero) with design theta (default model.theta0()).

    ``on_step(record, model, q, theta)`` is called after every converged step (outputs,
    progress); ``on_stage_end(index, model, q, theta, starts)`` after every completed
    stage, with ``starts`` the (q, theta) at the start of every stage so far (what a
    checkpoint needs). To resume, pass ``completed`` = those starts of the stages already
    done and q0/theta = the state at their end: their ``before`` hooks are replayed on
    the model (not re-solved) and the load path goes on with the next stage. Raises
    ConvergenceError with the last converged state on failure.
    """
    check_x64()
    q = np.zeros(model.n_dof) if q0 is None else np.array(q0, dtype=np.float64)
    theta = model.theta0() if theta is None else theta
    history: list[StepRecord] = []
    vref = float(sum(np.sum(t.data["dv"]) for t in model.terms if "dv" in t.data)) or 1.0
    asm, last_solver, stage = None, None, None
    starts = list(completed)
    for (q_s, theta_s), done in zip(completed, stages):
        if done.before is not None:
            model, _, _ = done.before(model, np.array(q_s), theta_s)
    for i_stage, stage in enumerate(stages):
        if i_stage < len(completed):
            continue
        starts.append((q.copy(), theta))
        if stage.before is not None:
            model, q, theta = stage.before(model, q, theta)
        dofs, targets = stage.prescribed
        prescribed = np.zeros(model.n_dof, bool)
        prescribed[dofs] = True
        asm = Assembler(model, prescribed, beta=options.beta)
        start_vals = q[dofs].copy()
        theta_start = theta
        theta_end = dict(theta)
        for name, p in stage.params.items():
            model.term(name)
            theta_end[name] = {**theta[name], **p}
        t, dt, step, cuts, step_refs, prev = 0.0, 1.0 / stage.n_steps, 0, 0, [], None
        while t < 1.0 - 1e-12:
            t_new = min(1.0, t + dt)
            th = _lerp(theta_start, theta_end, t_new)
            tic = time.perf_counter()
            fscale = float(np.median(step_refs)) if step_refs else 0.0
            starts_q = [q]
            if options.extrapolate and prev is not None:  # secant predictor along the path
                starts_q.insert(0, q + (q - prev[0]) * ((t_new - t) / (t - prev[1])))
            try:
                for k, q_start in enumerate(starts_q):
                    dqp = np.zeros(model.n_dof)
                    dqp[dofs] = start_vals + t_new * (targets - start_vals) - q_start[dofs]
                    try:
                        model_new, q_new, its, res, slv, fref, accepted = newton(
                            model, asm, q_start, th, dqp, options, stage.active, vref, fscale,
                            final=t_new >= 1.0 - 1e-12)
                        break
                    except _StepFailed as exc:
                        if k + 1 == len(starts_q):
                            raise
                        log.debug("step from the extrapolated state failed (%s); retrying from "
                                  "the last converged state", exc)
            except _StepFailed as exc:
                cuts += 1
                if cuts > options.max_cuts:
                    msg = (f"stage '{stage.name}': step to t = {t_new:.4g} failed after {cuts - 1} "
                           f"cuts (last increment {dt:.3g}): {exc}. The last converged state "
                           f"(t = {t:.4g}) is kept")
                    log.error(msg)
                    raise ConvergenceError(msg, q, _lerp(theta_start, theta_end, t), history) from None
                dt *= 0.5
                log.warning("stage '%s': step to t = %.4g failed (%s); cutting the increment to %.3g",
                            stage.name, t_new, exc, dt)
                continue
            step += 1
            step_refs.append(fref)
            prev = (q, t)
            t, q, theta, model = t_new, q_new, th, model_new
            last_solver = slv
            rec = StepRecord(stage.name, step, t, its, res, time.perf_counter() - tic,
                             {ACCEPTED_FLAGS[accepted]: True} if accepted else {})
            history.append(rec)
            log.info("stage %-12s step %3d  t = %.4f  iterations %2d  |r| = %.2e N  (%.2f s)",
                     stage.name, step, t, its, res, rec.wall)
            if on_step is not None:
                on_step(rec, model, q, theta)
            if cuts and its <= options.grow_iterations:
                dt = min(1.0 / stage.n_steps, dt * 2.0)
                cuts = max(cuts - 1, 0)
        theta = theta_end
        if on_stage_end is not None:
            on_stage_end(i_stage, model, q, theta, starts)
    if asm is not None:
        asm.model = model
    return Solution(model, q, theta, history, asm, last_solver,
                    stage.active if stage is not None else None)
