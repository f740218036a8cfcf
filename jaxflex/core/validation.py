"""Value checks and the array converter shared by every physical module.

Checks run on concrete values only, so a model is validated when a user builds it and the
checks stay out of the way under ``jit``/``vmap``/``grad`` (STYLE: two tiers of bad input).
"""

from __future__ import annotations

import difflib
import functools
from collections.abc import Callable, Iterable, Sequence
from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


_HOST = (np.ndarray, np.generic, int, float)


def to_device(x: ArrayLike, dtype: Any = None) -> Array:
    """A host value (numpy array, number, list of numbers) as a JAX array on the default
    device, through ``jax.device_put``: in JAX 0.10 ``jnp.asarray`` of a numpy array (and
    ``jnp.atleast_1d``, ``jnp.zeros`` ...) compiles a small program per shape, which every new
    process compiles again (docs/architecture.md, "Keeping a second run cheap"). ``dtype``:
    as numpy's (canonicalised by JAX, e.g. float64 -> float32 without x64)."""
    return jax.device_put(np.asarray(x, dtype=dtype))


def as_param(x: ArrayLike) -> Array:
    """A per-joint parameter as a float array of shape (n,) (scalars become (1,))."""
    dtype = jnp.result_type(float)
    if isinstance(x, _HOST) or (isinstance(x, (list, tuple)) and all(isinstance(e, _HOST)
                                                                      for e in x)):
        return to_device(np.atleast_1d(np.asarray(x, dtype=dtype)))
    return jnp.atleast_1d(jnp.asarray(x, dtype=dtype))


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


F = TypeVar("F", bound=Callable[..., Any])


def _to_float64(tree: Any) -> Any:
    """Every floating array leaf of ``tree`` (JAX or numpy) as float64; other leaves as given."""

    def cast(x: Any) -> Any:
        if isinstance(x, (jax.Array, np.ndarray)) and jnp.issubdtype(x.dtype, jnp.floating):
            return jnp.asarray(x, dtype=jnp.float64)
        return x

    return jax.tree_util.tree_map(cast, tree)


def requires_float64(fn: F) -> F:
    """Run ``fn`` in float64 whatever the global JAX setting (docs/spec.md section 9).

    The N2 certificate, identification, tuning and discovery are ill-conditioned in float32
    (``certify`` of the paper's gains gives lambda_min = -6.95, "not certified", instead of
    +0.544). When ``jax_enable_x64`` is off, the call runs inside ``jax.enable_x64(True)``
    (thread-local; the global setting is left as it was) with every floating array leaf of
    its arguments cast to float64, so a model built in float32 is computed in float64 too.
    JIT caches key on the x64 mode, so nothing compiled in one mode is reused in the other.
    Results keep their float64 arrays.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if jax.config.jax_enable_x64:
            return fn(*args, **kwargs)
        with jax.enable_x64(True):
            args, kwargs = _to_float64((args, kwargs))
            return fn(*args, **kwargs)

    wrapper.__requires_float64__ = True  # type: ignore[attr-defined]
    return wrapper  # type: ignore[return-value]


def check_keys(keys: Iterable[str], known: Sequence[str], *, where: str = "",
               what: str = "key", error: type[Exception] = ValueError) -> None:
    """Raise ``error`` naming the first of ``keys`` that is not in ``known``: ``"{where}unknown
    {what} 'k' (did you mean 'K'?); known: [...]"``. The one unknown-key check of the parameter
    and spread files."""
    known = list(known)
    for k in keys:
        if k not in known:
            raise error(f"{where}unknown {what} '{k}'{did_you_mean(k, known)}; known: {known}")


def did_you_mean(key: str, known: Sequence[str]) -> str:
    """`` (did you mean 'X'?)`` with the known name closest to ``key`` (difflib), or ``""``."""
    known = tuple(known)
    same_case = [k for k in known if k.lower() == key.lower()]
    close = (same_case or difflib.get_close_matches(key, known, n=1)
             or [k for k in known if k.startswith(key)])
    return f" (did you mean '{close[0]}'?)" if close else ""
