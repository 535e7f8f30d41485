"""Problem builders referred to by name in case files."""

from .verification import PROBLEMS as _VERIFICATION

PROBLEMS = dict(_VERIFICATION)
"""name -> (schema fields, builder(parameters, materials) -> Setup)."""
