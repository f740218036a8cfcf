"""The plant's state (docs/spec.md section 1): one record shared by the plant, its effects, the
simulator and the fitting engine (its own module so that effects and plant need not import
each other)."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float


class PlantState(eqx.Module):
    """Plant state; every field has shape (n,) except ``aux`` (one entry per effect).

    q1 [rad] link angle, dq1 [rad/s], q2 [rad] rotor angle (link-referred), dq2 [rad/s],
    z [rad] LuGre bristle state, aux: internal states of effects (e.g. actuator lag), one
    entry per effect, or None for a plant without effects (an empty tuple would trip diffrax's
    loop buffers).
    """

    q1: Float[Array, " n"]
    dq1: Float[Array, " n"]
    q2: Float[Array, " n"]
    dq2: Float[Array, " n"]
    z: Float[Array, " n"]
    aux: tuple | None = None
