"""Problem builders referred to by name in case files."""

from .surgery import PROBLEMS as _SURGERY
from .verification import PROBLEMS as _VERIFICATION

PROBLEMS = {**_VERIFICATION, **_SURGERY}
"""name -> (schema fields, builder(parameters, materials) -> Setup)."""
