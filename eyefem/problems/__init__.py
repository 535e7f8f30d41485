"""Problem builders referred to by name in case files."""

from .examples import PROBLEMS as _EXAMPLES
from .surgery import PROBLEMS as _SURGERY
from .verification import PROBLEMS as _VERIFICATION

PROBLEMS = {**_VERIFICATION, **_EXAMPLES, **_SURGERY}
"""name -> (schema fields, builder(parameters, materials) -> Setup)."""
