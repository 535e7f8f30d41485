"""The problems a case file can name: ``problem = "surgery"`` and the rest.

Each entry maps a problem name to its schema (the fields of the case file's
``[parameters]`` table) and its builder ``(parameters, materials) -> Setup``.
"""

from __future__ import annotations


def problems() -> dict:
    """name -> (schema fields, builder(parameters, materials) -> Setup)."""
    from eyefem.eye.surgery import PROBLEMS as surgery
    from eyefem.eye.validation import PROBLEMS as validation
    from eyefem.problems.examples import PROBLEMS as examples
    from eyefem.problems.user_mesh import PROBLEMS as user_mesh
    from eyefem.problems.verification import PROBLEMS as verification

    return {**verification, **examples, **surgery, **validation, **user_mesh}


def schemas() -> dict:
    """name -> the schema fields of its ``[parameters]`` table."""
    return {k: v[0] for k, v in problems().items()}


def solver_defaults() -> dict:
    """name -> ``f(parameters) -> dict``: the ``[solver]`` settings a problem wants for the
    parameters of a case that leaves them out (eyefem.io.casefile.load_case)."""
    return {k: v[1].solver_settings for k, v in problems().items()
            if getattr(v[1], "solver_settings", None) is not None}
