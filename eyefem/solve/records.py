"""What the solver returns: a step's result with its status, the record of a converged
step, the solution of a load path, and the errors."""

from __future__ import annotations

import dataclasses
import enum
from typing import Any

import numpy as np

from eyefem.solve.assembly import Assembler
from eyefem.solve.model import Model


class StepStatus(enum.Enum):
    """How a load step ended."""

    CONVERGED = "converged"
    """Force and volume residuals below the tolerances (NewtonOptions.rtol, vtol)."""
    STALLED = "stalled"
    """Accepted at its best iterate on a residual plateau inside a stage
    (NewtonOptions.stall_rtol); its residual is above the tolerance."""
    CONTACT_CYCLE = "contact cycle"
    """Converged with the contact pairs frozen, accepted although re-pairing leaves a small
    force unbalanced (NewtonOptions.contact_cycle_rtol)."""

    @property
    def balanced(self) -> bool:
        """Whether the step is in equilibrium to the stated tolerance."""
        return self is StepStatus.CONVERGED


@dataclasses.dataclass(frozen=True)
class StepResult:
    """One load step solved by Newton.

    Attributes:
      model: the model (contact terms re-paired during the iterations).
      q: (n_dof,) the state.
      iterations: Newton iterations.
      residual: free force residual, N.
      solver: the last factorised tangent (None if no linear solve was needed).
      fref: the step's progress reference, N (its first out-of-balance force; the
        thresholds of the globalisation and the contact freeze are relative to it).
      status: how the step ended.
      unbalanced_N: the force a step accepted without converging leaves out of balance
        (its residual on a stall; re-paired, on a contact cycle), N; 0 when converged.
      load_N: the force the state carries, N (the largest of the terms' forces on the free
        dofs and the reactions): the tolerances are relative to it.
      r: (n_dof,) the residual of ``model`` at q where the step converged (else None): the
        next step's tangent predictor needs it when its load does not change.
    """

    model: Model
    q: np.ndarray
    iterations: int
    residual: float
    solver: Any
    fref: float
    status: StepStatus = StepStatus.CONVERGED
    unbalanced_N: float = 0.0
    load_N: float = 0.0
    r: Any = None


ACCEPTED_FLAGS = {StepStatus.STALLED: "stalled", StepStatus.CONTACT_CYCLE: "contact_cycle"}
"""Flag in ``StepRecord.info`` of a step accepted without converging, by status."""


@dataclasses.dataclass
class StepRecord:
    """Log of one converged (or accepted) step; ``info`` flags an unbalanced one
    (ACCEPTED_FLAGS)."""

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
        if self.assembler is None:
            raise ValueError("this solution keeps its state only (a warm start's, "
                             "eyefem.eye.simulators.states_only): solve the design again for "
                             "its tangent or its gradients")
        asm = self.assembler  # shared by the stages: assemble this solution's own model
        r, K, B, D, lr = asm.assemble(self.q, self.theta, self.active, model=self.model)
        return dataclasses.replace(self, solver=asm.solver(K, B, D, lr))


class StepFailed(Exception):
    """A load step failed (diverged, inverted an element, stalled): the load path cuts it."""
