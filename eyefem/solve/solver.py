"""The solver's public names in one place: the load path (:func:`solve`, :class:`Stage`),
its options and results. The pieces live in eyefem.solve.loadpath (stages, steps,
cutting), newton (one step), globalisation (direction, line search, damping),
contact_strategy (freeze, re-pair, look-ahead), options and records."""

from eyefem.solve.loadpath import Stage, interpolate, solve
from eyefem.solve.options import NewtonOptions
from eyefem.solve.records import (
                                  ACCEPTED_FLAGS,
                                  ConvergenceError,
                                  Solution,
                                  StepFailed,
                                  StepRecord,
                                  StepResult,
                                  StepStatus,
)

__all__ = ["ACCEPTED_FLAGS", "ConvergenceError", "NewtonOptions", "Solution", "Stage",
           "StepFailed", "StepRecord", "StepResult", "StepStatus", "interpolate", "solve"]
