"""Test configuration: float64 everywhere and strict dtype promotion, as the entry points do."""

import jax

jax.config.update("jax_enable_x64", True)
