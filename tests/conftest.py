"""Tests run in float64 (identification and certificates need it)."""

import jax

jax.config.update("jax_enable_x64", True)
