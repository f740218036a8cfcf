"""Value checks and the array converter shared by every physical module.

Checks run on concrete values only, so a model is validated when a user builds it and the
checks stay out of the way under ``jit``/``vmap``/``grad`` (STYLE: two tiers of bad input).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


def as_param(x: ArrayLike) -> Array:
    """A per-joint parameter as a float array of shape (n,) (scalars become (1,))."""
    return jnp.atleast_1d(jnp.asarray(x, dtype=jnp.result_type(float)))


def is_concrete(x: Any) -> bool:
    """Whether ``x`` is a concrete value (not a JAX tracer), i.e. can be checked now."""
    return not isinstance(x, jax.core.Tracer)


def check_positive(owner: str, allow_inf: bool = False, **values: ArrayLike) -> None:
    """Raise ``ValueError`` naming the first parameter that is not finite and > 0
    (``allow_inf``: +inf is accepted, e.g. for 'no limit').

    Only concrete (non-traced) values are checked, so the check runs when a user builds a
    model and stays out of the way under ``jit``/``vmap``/``grad``.
    """
    for name, v in values.items():
        if not is_concrete(v):
            continue
        a = np.asarray(v, dtype=float)
        ok = np.isfinite(a) | (allow_inf & (a == np.inf))
        if not np.all(ok):
            raise ValueError(f"{owner}: parameter {name} must be finite, got {a.tolist()}")
        if np.any(a <= 0):
            raise ValueError(f"{owner}: parameter {name} must be > 0, got {a.tolist()}")


def check_nonnegative(owner: str, **values: ArrayLike) -> None:
    """Raise ``ValueError`` naming the first parameter that is not finite and >= 0."""
    for name, v in values.items():
        if not is_concrete(v):
            continue
        a = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{owner}: parameter {name} must be finite, got {a.tolist()}")
        if np.any(a < 0):
            raise ValueError(f"{owner}: parameter {name} must be >= 0, got {a.tolist()}")
