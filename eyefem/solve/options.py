"""Settings of the Newton solver (case files: the ``[solver]`` table)."""

from __future__ import annotations

import dataclasses


QUASI_NEWTON = ("off", "bfgs")
"""Values of NewtonOptions.quasi_newton."""

INCOMPRESSIBILITY = ("exact", "augmented_lagrangian")
"""Values of NewtonOptions.incompressibility."""


@dataclasses.dataclass(frozen=True)
class NewtonOptions:
    """Settings of the Newton solver, by what they do (why the defaults are what they are:
    docs/formulation.md and the git log).

    Convergence:
      rtol: force residual tolerance, relative to the load the state carries (the largest
        of the terms' forces on the free dofs and the reactions, evaluated at the iterate;
        StepResult.load_N), so it means the same in every step of every stage.
      vtol: constraint (volume) residual tolerance, relative to the solid volume.
      atol: absolute force tolerance, N.

    Load stepping:
      max_iter: Newton iterations of a step before it is cut.
      max_cuts: successive halvings of a step before the solve stops (ConvergenceError).
      grow_iterations: after a cut the increment doubles again (up to the nominal one)
        after each step converged in at most this many iterations.
      extrapolate: start a step from the secant extrapolation of the two previous states of
        the stage (from the last state if that fails).
      tangent_predictor: start a step (after the first of its stage; not in stages with
        contact) from the tangent predictor on the last factorisation of the stage's
        previous step: one solve, no assembly (eyefem.solve.newton); off: the first
        iterate of a load-driven step is a fresh Newton step, that of a
        displacement-driven one the consistent predictor on a fresh factorisation.
      quasi_newton: "off" (a new factorisation every iteration) or "bfgs": iterations
        of a stage without contact reuse the last factorisation (the step's, or the
        previous step's through the tangent predictor) with BFGS updates applied by
        back-solves (eyefem.solve.quasi_newton), and reform it (a full Newton
        iteration) when no trial of a step's line search lowers the merit below
        quasi_newton_ratio x its value, or after quasi_newton_updates updates. The same
        convergence test; the adjoint still refines against the exact tangent.
      quasi_newton_updates: updates on one factorisation before it is reformed.
      quasi_newton_ratio: a quasi-Newton step must lower the merit (force and volume
        residual) below this x its start's, else it is not taken and the tangent reformed.

    Incompressibility (the Q1P0 elements' volume constraint):
      incompressibility: "exact" (one multiplier per element, a saddle-point solve) or
        "augmented_lagrangian": a penalty kappa = penalty_factor x the element's shear
        modulus on its volume change plus a multiplier estimate updated (Uzawa) after each
        converged step until max |Jbar - 1| <= uzawa_tol; one positive definite solve per
        iteration (eyefem.solve.augmented).
      penalty_factor: kappa over the shear modulus.
      uzawa_tol: the largest element volume error |Jbar - 1| a step may leave.
      uzawa_max: Uzawa updates of one step before it is cut.

    Linear solves:
      backend: linear solver backend (None: the default, eyefem.solve.linsolve).
      beta: strength of the element-wise augmentation of the saddle-point solve.
      cg_rtol: relative constraint residual at which the Schur-complement CG of a Newton
        direction stops.

    Globalisation (eyefem.solve.globalisation):
      line_search: backtrack on the residual norm when a full step does not lower it.
      modified_newton: above this x the step's first residual, an indefinite tangent is
        shifted to positive definite (a descent direction); below it the tangent is exact.
      pressure_stiffness: keep the follower pressures' load stiffness in the tangent above
        modified_newton x the first residual too (off: only near convergence).
      restore: restore the trial points' cavity volumes to their linear prediction when a
        full step does not lower the residual (second-order correction).
      max_step: a step moving a node more than this (mm) whose line search fails is solved
        again with Levenberg-Marquardt shifts (globalisation.SHIFTS); at the last shift it
        is scaled down to this length.

    Contact (eyefem.solve.contact_strategy):
      contact_freeze: contact pairs are re-paired every iteration until the force residual
        falls below this x the step's first residual, then frozen (quadratic convergence);
        a converged state is re-paired once more.
      contact_rtol: after that re-pairing the residual must be below this x the load,
        else Newton goes on.
      contact_cycle_rtol: a pairing that cycles (the same force left by two re-pairings) or
        has not settled after UNSETTLED_REPAIRS re-pairings is accepted, flagged, when the
        force it leaves is below this x the load.
      contact_lookahead: re-solve a Newton step with the penalty model of the contact nodes
        it would push into contact from out of the penalty's reach.
      contact_curvature: above this x the step's first residual, penalty contacts use their
        Gauss-Newton tangent (without the surface's curvature term); 0: always exact.

    Stalls (a step whose best residual of its last ``stall_iterations`` is not 10% below
    the best before them):
      stall_iterations: the window of iterations that decides a stall.
      stall_rtol, stall_vtol: a stalled step inside a stage (never its last) is accepted,
        flagged, at its best iterate when its force residual is below stall_rtol x the
        load (and its volume residual below stall_vtol).
      stall_repair_rtol: a best iterate found with the pairs frozen is accepted only if,
        re-paired, its force residual is below this x the load (default: no bound;
        the warning says the force).
      stall_cut: cut a stalled step that is not accepted at once, instead of iterating on
        to max_iter.
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
    tangent_predictor: bool = True
    quasi_newton: str = "off"
    quasi_newton_updates: int = 10
    quasi_newton_ratio: float = 0.5
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
    incompressibility: str = "exact"
    penalty_factor: float = 100.0
    uzawa_tol: float = 1e-6
    uzawa_max: int = 20

    def __post_init__(self):
        for f in ("rtol", "vtol", "atol", "beta", "cg_rtol", "contact_freeze", "contact_rtol",
                  "contact_cycle_rtol", "modified_newton",
                  "stall_rtol", "stall_vtol", "stall_repair_rtol", "max_step", "penalty_factor",
                  "uzawa_tol"):
            if not getattr(self, f) > 0:
                raise ValueError(f"NewtonOptions.{f} = {getattr(self, f)}; must be > 0")
        if not self.contact_curvature >= 0:
            raise ValueError(f"NewtonOptions.contact_curvature = {self.contact_curvature}; "
                             "must be >= 0 (0: always the exact contact tangent)")
        if self.quasi_newton not in QUASI_NEWTON:
            raise ValueError(f"NewtonOptions.quasi_newton = {self.quasi_newton!r}; choose from "
                             f"{', '.join(map(repr, QUASI_NEWTON))}")
        if self.incompressibility not in INCOMPRESSIBILITY:
            raise ValueError(f"NewtonOptions.incompressibility = {self.incompressibility!r}; "
                             f"choose from {', '.join(map(repr, INCOMPRESSIBILITY))}")
        if self.uzawa_max < 1:
            raise ValueError(f"NewtonOptions.uzawa_max = {self.uzawa_max}; must be >= 1")
        if self.quasi_newton_updates < 1 or not 0 < self.quasi_newton_ratio < 1:
            raise ValueError(f"NewtonOptions: quasi_newton_updates = {self.quasi_newton_updates}, "
                             f"quasi_newton_ratio = {self.quasi_newton_ratio}; need updates >= 1 "
                             "and 0 < ratio < 1")
        if self.max_iter < 1 or self.max_cuts < 0 or self.stall_iterations < 2:
            raise ValueError(f"NewtonOptions: max_iter = {self.max_iter}, max_cuts = "
                             f"{self.max_cuts}, stall_iterations = {self.stall_iterations}; "
                             "need max_iter >= 1, max_cuts >= 0 and stall_iterations >= 2")
