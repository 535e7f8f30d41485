"""The solver: model, assembly, linear solves, Newton load path, adjoint.

``eyefem.solve.solve``, ``Stage``, ``NewtonOptions``, ``Solution`` and ``ConvergenceError``
are eyefem.solve.solver's, loaded on first use (PEP 562).
"""

_SOLVER_NAMES = ("solve", "Stage", "NewtonOptions", "Solution", "ConvergenceError")


def __getattr__(name: str):
    if name in _SOLVER_NAMES:
        from eyefem.solve import solver

        return getattr(solver, name)
    raise AttributeError(f"module 'eyefem.solve' has no attribute '{name}'")
