"""The linear solvers' errors (shared by eyefem.solve.linsolve and its backends)."""


class LinearSolveError(RuntimeError):
    """A linear solve failed or its residual is too large."""


class NegativeCurvature(LinearSolveError):
    """The displacement block is indefinite on the incompressible modes (raised when the
    solver was asked to report it rather than solve the indefinite system exactly)."""
