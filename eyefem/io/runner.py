"""Moved: the problem contract is :class:`eyefem.solve.problem.Setup`, the runner
:mod:`eyefem.run.runner`."""

from eyefem.solve.problem import Setup  # noqa: F401
