"""Globalisation of Newton's method: the direction (exact, modified or shifted
tangent), the line search with the restoration of cavity volumes, Levenberg-Marquardt
damping of long steps, and the fallback when no trial lowers the residual."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from eyefem.fem.terms import Term
from eyefem.solve.contact_strategy import lookahead
from eyefem.solve.linsolve import LinearSolveError, NegativeCurvature
from eyefem.solve.options import NewtonOptions
from eyefem.solve.records import StepFailed

log = logging.getLogger(__name__)

FALLBACK_RISE = 10.0
"""With the contact pairs frozen, a Newton step none of whose trials (undamped or
shifted) lowers the residual, and whose fallback trial raises it this many times, cuts
the load step (NewtonOptions.max_step)."""


SHIFTS = (0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)
"""Levenberg-Marquardt shifts mu of the modified Newton tangent K + mu |diag K|."""


def longest_move(model, dq):
    """Largest nodal displacement (mm) of a step dq (n_dof,)."""
    return float(np.linalg.norm(dq[:model.n_u].reshape(-1, 3), axis=1).max(initial=0.0))


def newton_direction(asm, tangent, rf, rm, opts, far, cache=None, min_shift=0.0, extra=None):
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


class Restoration:
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
        G = [np.asarray(v) for t in Restoration._terms(model, active)
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


@dataclasses.dataclass(frozen=True)
class Evaluated:
    """The residual (n_dof,) of ``model`` at the state q (n_dof,) and the load it carries
    on the free dofs, N (:meth:`Model.gradient_and_load`): what the line search computed
    at the point it returns, so that Newton's next iteration need not compute it again."""

    model: object
    q: np.ndarray
    r: np.ndarray
    load: float

    def at(self, model, q):
        """(r, load) if this is the evaluation of ``model`` at ``q`` (the same objects), else
        None."""
        return (self.r, self.load) if model is self.model and q is self.q else None


def evaluate(model, q, theta, active, asm) -> Evaluated | None:
    """The residual and load at q (:class:`Evaluated`); None where the residual is not
    finite (an inverted element)."""
    r, load = model.gradient_and_load(q, theta, asm.free_primal, active)
    return Evaluated(model, q, r, load) if np.all(np.isfinite(r)) else None


def merit(ev: Evaluated | None, asm, fref, vref):
    """Line-search merit of an evaluated point: force residual / reference and volume
    residual / solid volume, combined; None where the residual is not finite."""
    if ev is None:
        return None
    r = ev.r
    return np.hypot(_norm(r[asm.free_primal]) / max(fref, 1e-300),
                    _norm(r[asm.mult]) / vref if len(asm.mult) else 0.0)


def _norm(v) -> float:
    """|v| without BLAS (OpenBLAS threads its ddot on long vectors: on shared cores one
    norm of 30,000 entries took milliseconds, einsum's own loop microseconds)."""
    return float(np.sqrt(np.einsum("i,i", v, v)))


def line_search(model, q, dq, theta, active, asm, m0, fref, vref, alphas, restore=None):
    """Backtracking on the residual norm (merit: force residual / reference, volume
    residual / solid volume) over the step lengths ``alphas``. When the full step fails
    and the model has stiff low-rank terms (closed cavities), the trials are restored to
    the linearised volumes (:class:`Restoration`). Returns (the first trial that lowers
    the merit, True, its :class:`Evaluated`), else (the best trial, False, its
    :class:`Evaluated`)."""
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
        ev = evaluate(model, qa, theta, active, asm)
        m = merit(ev, asm, fref, vref)
        if m is None:
            continue
        if m < m0:
            if alpha < 1.0 or restored:
                log.debug("  line search: step length %g%s", alpha,
                          " (volumes restored)" if restored else "")
            return qa, True, ev
        if best is None or m < best[0]:
            best = (m, qa, ev)
    if best is None:
        raise StepFailed("every line-search trial gave non-finite values (inverted elements)")
    return best[1], False, best[2]


def globalised_update(model, asm, q, theta, active, opts: NewtonOptions, rf, rm, nf: float,
                      nm: float, fref: float, vref: float, frozen: bool):
    """One globalised Newton update from q (n_dof,) with free residuals rf, rm (norms nf, N,
    and nm, relative): the direction (with the contact look-ahead), a line search, then
    Levenberg-Marquardt shifts while no trial lowers the residual; with the contact pairs
    ``frozen``, a fallback trial that raises the residual FALLBACK_RISE-fold cuts the load
    step (StepFailed). Returns (the new state, the last factorised tangent, the new
    state's :class:`Evaluated` residual)."""
    cache = {}

    gn = nf > opts.contact_curvature * fref if opts.contact_curvature else False
    # the restoration's K^-1 dV/dq, solved with each Newton direction (same back-solves)
    vgrad = Restoration.gradients(model, q, theta, active) if opts.restore else None
    extra = vgrad[:, asm.free_primal].T if vgrad is not None else None

    def direction(far, shift):
        return newton_direction(asm, lambda exact: asm.assemble(q, theta, active, exact, gn)[1:],
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
                xl, yl, la_solver, n_la = lookahead(model, asm, q, theta, active, solver,
                                                     rf, rm, x, y,
                                                     end_gap=opts.contact_curvature > 0)
        except LinearSolveError as exc:
            raise StepFailed(str(exc)) from exc
        if n_la:
            # the look-ahead's model of a node can be wrong (it stays outside): then
            # no trial of its step lowers the residual and the plain step is tried
            log.debug("  contact look-ahead: %d nodes", n_la)
            dq = asm.expand(xl, yl)
            restore = Restoration(model, q, dq, theta, active, asm, la_solver) if opts.restore else None
            try:
                q_try, lowered, ev = line_search(model, q, dq, theta, active, asm, m0, fref,
                                                  vref, alphas[:3], restore)
            except StepFailed:
                lowered = False
            if lowered:
                return q_try, solver, ev
            log.debug("  look-ahead step: no trial lowers the residual; the plain step")
        dq = asm.expand(x, y)
        longest = longest_move(model, dq)
        last = (max(shift, solver.shift) >= SHIFTS[-1] or not opts.line_search
                or (shift == 0.0 and longest <= opts.max_step))
        if last and longest > opts.max_step:
            log.debug("  step of %.3g mm scaled to max_step = %g mm", longest, opts.max_step)
            dq *= opts.max_step / longest
        restore = (Restoration(model, q, dq, theta, active, asm, solver, (vgrad, W))
                   if opts.restore else None)
        try:
            q_try, lowered, ev = line_search(model, q, dq, theta, active, asm, m0, fref, vref,
                                              alphas, restore)
        except StepFailed:
            if last and undamped is None:
                raise
            q_try, lowered, ev = None, False, None
        if undamped is None and shift == 0.0 and q_try is not None:
            undamped = (q_try, ev)
        if lowered or last:
            # no damped step lowers the residual either: the undamped step's best trial
            # (the last shift's if every undamped trial inverted an element), unless the
            # pairs are frozen (Newton near convergence on one pairing) and that trial
            # raises the residual FALLBACK_RISE-fold: then the load step is cut
            fallback, ev = (q_try, ev) if lowered or undamped is None else undamped
            if not lowered and frozen:
                m1 = merit(ev, asm, fref, vref)
                if m1 is None or m1 > FALLBACK_RISE * m0:
                    raise StepFailed(
                        f"no trial of a Newton step lowers the residual |r_u| = {nf:.3e} N "
                        f"(reference {fref:.3e} N; the best raises it "
                        f"{'to non-finite values' if m1 is None else f'{m1 / m0:.0f}-fold'}"
                        "; near-singular modes of the tangent, -v names their nodes)")
            return fallback, solver, ev
        # no trial lowers the residual, or every trial inverts an element (a
        # near-singular tangent: the soft retina's tangential modes): damp the step
        far, shift = True, min(mu for mu in SHIFTS if mu > max(shift, solver.shift))
        if log.isEnabledFor(logging.DEBUG):
            moves = dq[:model.n_u].reshape(-1, 3)
            norms = np.linalg.norm(moves, axis=1)
            log.debug("  line search failed on a %.3g mm step (at node %d; nodes over "
                      "half of it: %d; mean motion %s mm, a rigid shift if near the "
                      "longest): shift %g", longest, int(np.argmax(norms)),
                      int(np.sum(norms > 0.5 * longest)),
                      np.array2string(moves.mean(axis=0), precision=3), shift)
