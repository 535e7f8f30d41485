"""Test configuration: float64 everywhere and strict dtype promotion, as the entry points do.

The CLI's persistent compilation cache is off here (``EYEFEM_JAX_CACHE``), so that the
tests that call the CLI write nothing outside their temporary directories.
"""

import os

import jax

os.environ.setdefault("EYEFEM_JAX_CACHE", "off")
jax.config.update("jax_enable_x64", True)
