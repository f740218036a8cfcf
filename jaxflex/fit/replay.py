"""Replays of a problem at its unknowns (simulated outputs, residuals, the normalised gap),
each compiled once per problem shape, a free-start shooting problem once per bucket of
segment slots (``Padding``): one program serves all three.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from jaxflex.fit.padding import Padding
from jaxflex.fit.problem import Problem
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device


def simulated_outputs(prob: Problem, y: Any) -> jax.Array:
    """Simulated outputs (S, L, n_out) [rad] of ``prob`` at ``y`` (compiled once per shape;
    a free-start shooting problem once per bucket of segment slots, ``Padding``; one program
    with ``residuals`` and ``gap``, ``Problem.replay``)."""
    out, pad = _replay_in_slots(prob, y)
    if pad is None:
        return out["outputs"]
    return to_device(np.asarray(out["outputs"])[: pad.count])


def gap(prob: Problem, y: Any) -> jax.Array:
    """``prob.gap(y)`` (normalised RMS output error), compiled once per problem shape (a
    free-start shooting problem once per bucket of segment slots, ``Padding``; one program
    with ``simulated_outputs`` and ``residuals``)."""
    return _replay_in_slots(prob, y)[0]["gap"]


def residuals(prob: Problem, y: Any) -> jax.Array:
    """``prob.residuals(y)``, compiled once per problem shape (a free-start shooting problem
    once per bucket of segment slots, ``Padding``; one program with ``simulated_outputs`` and
    ``gap``)."""
    out, pad = _replay_in_slots(prob, y)
    return out["residuals"] if pad is None else pad.rows_back(out["residuals"])


def _replay_in_slots(prob: Problem, y: Any) -> tuple[dict[str, jax.Array], Padding | None]:
    """``Problem.replay`` of ``prob`` at ``y``, a free-start shooting problem in its bucket of
    segment slots (the padding then returned with it, else None)."""
    pad = Padding.of(prob, y)
    if pad is None:
        return _replay(prob, y), None
    return _replay(prob.padded(pad.slots), pad.unknowns(y)), pad


@persistent_jit(fast_compile=True)
def _replay(prob: Problem, y: Any) -> dict[str, jax.Array]:
    return prob.replay(y)
