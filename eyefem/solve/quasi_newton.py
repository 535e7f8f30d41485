"""Quasi-Newton iterations on a reused factorisation (NewtonOptions.quasi_newton).

An iteration of a load step without contact may reuse the last factorised tangent (the
step's own, or the previous step's that the tangent predictor took) instead of
assembling and factorising a new one: the direction is d = -H r with H the inverse
tangent of that factorisation corrected by BFGS updates, applied through back-solves by
the two-loop recursion of Matthies and Strang (1979) with the saddle-point solve as H0.

Why BFGS and not Broyden on the indefinite saddle point: the Jacobian of the residual is
the energy's Hessian, symmetric (indefinite only through the multipliers), and the BFGS
inverse update H+ = V^T H V + rho s s^T (V = I - rho y s^T, rho = 1 / y.s) is a symmetric
secant update for any symmetric H0, definite or not; it needs no descent property here,
because the line search is on the residual norm, not the energy. Its two-loop form holds
only the pairs (s, y) and applies them around whatever H0 is current, so H0 may change
from one iteration to the next: the closed cavities' rank-one terms alpha v v^T are
refreshed at every iterate on the same factorisation (Woodbury, one back-solve per
cavity) and the stiff liquid's change of dV/dq is not left to the updates. Good
Broyden's product form needs one fixed H0 (its correction vectors were computed with
it) and gives up the symmetry. A pair with |y.s| below QN_CURVATURE |y||s| is skipped.
s.y pairs the displacements with forces and the multipliers with the volume residuals:
energy in both, so the update needs no scaling of the two blocks.

The reformation rule (docs/formulation.md): a new tangent is assembled and factorised
(a full Newton iteration, eyefem.solve.globalisation) when the quasi-Newton step's line
search finds no trial that lowers the merit (force residual / reference and volume
residual / solid volume) below ``quasi_newton_ratio`` x its value (the step is then not
taken), after ``quasi_newton_updates`` updates, and when a solve
on the old factorisation fails. The convergence test is Newton's, on the true residual.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from eyefem.solve.globalisation import Restoration, line_search
from eyefem.solve.linsolve import LinearSolveError
from eyefem.solve.records import StepFailed

log = logging.getLogger(__name__)

QN_CURVATURE = 1e-10
"""A pair (s, y) whose |y.s| is below this x |y| |s| is not used (rho would blow up)."""

QN_ALPHAS = (1.0, 0.5)
"""Step lengths of a quasi-Newton step's line search; none lowering the merit
quasi_newton_ratio-fold, the tangent is reformed (shorter trials rarely do: each costs a
residual evaluation)."""


def _dot(a, b) -> float:
    """a . b of two vectors without BLAS: OpenBLAS threads its ddot on long vectors, and
    on shared cores one 30,000-long product took 11 ms against 15 us (einsum's own loop);
    the recursion takes a few dozen per iteration."""
    return float(np.einsum("i,i", a, b))


def quasi_newton_stage(model, active) -> bool:
    """Whether a stage may take quasi-Newton iterations: no contact or re-paired term is
    active (their forces switch with the state, the look-ahead and the freeze of the
    pairing act on each Newton step: out of scope, as for the tangent predictor)."""
    return not any(t.contact or t.dynamic for t in model._active(active))


class QuasiNewton:
    """BFGS updates around one factorised tangent ``solver`` (a SaddlePointSolver of
    ``asm``'s layout). Vectors are reduced: (free primal dofs, multipliers)."""

    def __init__(self, solver, asm):
        self.solver, self.asm = solver, asm
        self.pairs: list = []  # (s, y, rho)
        self.pending = None  # (s, r) of the last step, awaiting the residual at its end
        self.steps = 0  # quasi-Newton steps taken on this factorisation
        self._core = None

    def reduce(self, v):
        return np.concatenate([v[self.asm.free_primal], v[self.asm.mult]])

    def record(self, s_full, r_red):
        """A step s_full (n_dof,) from a state of reduced residual r_red: its pair is
        completed by the next state's residual (:meth:`direction`)."""
        self.pending = (self.reduce(s_full), r_red)

    def _take_pending(self, r_red):
        if self.pending is None:
            return
        s, r_prev = self.pending
        self.pending = None
        y = r_red - r_prev
        sy = _dot(s, y)
        if abs(sy) > QN_CURVATURE * np.sqrt(_dot(s, s) * _dot(y, y)):
            self.pairs.append((s, y, 1.0 / sy))
        else:
            log.debug("  quasi-Newton: pair skipped (s.y = %.2e)", sy)

    def h0_solver(self, model, q, theta, active):
        """The factorisation with the closed cavities' rank-one terms of the state q
        (Woodbury on the same factorisation: one back-solve per cavity), or itself where
        it has none."""
        if not self.solver.low_rank:
            return self.solver
        free = self.asm.free_primal
        lr = [(al, np.asarray(v)[free]) for t in model._active(active)
              for al, v in t.low_rank(q, theta[t.name], t.data, t.dofs)]
        if not lr:
            return self.solver
        if self._core is None:
            self._core = dataclasses.replace(self.solver, low_rank=[], reuse=self.solver)
        # negative curvature met on the old factorisation reforms the tangent (raise)
        # instead of factorising the whole saddle point for this iterate alone (kkt)
        return dataclasses.replace(self.solver, low_rank=lr, reuse=self._core,
                                   indefinite="raise")

    def direction(self, h0, r_red):
        """d = -H r (reduced) by the two-loop recursion with H0 = ``h0``'s solve."""
        self._take_pending(r_red)
        n_p = len(self.asm.free_primal)
        v = r_red.copy()
        alphas = []
        for s, y, rho in reversed(self.pairs):
            a = rho * _dot(s, v)
            v -= a * y
            alphas.append(a)
        x, yv = h0.solve(v[:n_p], v[n_p:])
        z = np.concatenate([x, yv])
        for (s, y, rho), a in zip(self.pairs, reversed(alphas)):
            b = rho * _dot(y, z)
            z += (a - b) * s
        return -z


def quasi_newton_step(qn: QuasiNewton, model, asm, q, theta, active, opts, r, nf, nm,
                      fref, vref):
    """One quasi-Newton update from q (n_dof,) with residual r (n_dof,) (force norm nf, N;
    volume residual nm, relative): (new state, its Evaluated residual), or None where the
    reformation rule asks for a new tangent (the reason logged)."""
    m0 = np.hypot(nf / max(fref, 1e-300), nm)
    if len(qn.pairs) + (qn.pending is not None) > opts.quasi_newton_updates:
        log.debug("  quasi-Newton: %d updates; tangent reformed", opts.quasi_newton_updates)
        return None
    r_red = qn.reduce(r)
    try:
        h0 = qn.h0_solver(model, q, theta, active)
        d = qn.direction(h0, r_red)
    except LinearSolveError as exc:
        log.debug("  quasi-Newton: the old factorisation does not solve (%s); reformed", exc)
        return None
    n_p = len(asm.free_primal)
    dq = asm.expand(d[:n_p], d[n_p:])
    restore = Restoration(model, q, dq, theta, active, asm, h0) if opts.restore else None
    alphas = QN_ALPHAS if opts.line_search else (1.0,)
    try:
        # sufficient decrease: a trial is taken only below ratio x the merit; a lesser
        # decrease is not taken (Newton goes on from q, not from a state the stale
        # tangent chose: on the coarse eye's injection such steps left Newton wandering)
        q_new, lowered, ev = line_search(model, q, dq, theta, active, asm,
                                         opts.quasi_newton_ratio * m0, fref, vref, alphas,
                                         restore)
    except StepFailed:
        lowered = False
    if not lowered:
        log.debug("  quasi-Newton step (%d updates): no trial lowers the merit %g-fold; "
                  "tangent reformed", len(qn.pairs), 1.0 / opts.quasi_newton_ratio)
        return None
    qn.record(q_new - q, r_red)
    qn.steps += 1
    log.debug("  quasi-Newton step (%d updates)", len(qn.pairs))
    return q_new, ev
