"""The interface of an effect (``AbstractEffect``: its hooks, constraints and typical
values) and the registry of effects by name (``EFFECTS``, ``register_effect``)."""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.state import PlantState

EFFECTS: dict[str, type[AbstractEffect]] = {}


def candidate_effects() -> list[str]:
    """Names of the effects the discrepancy workflow tries by default (``candidate``)."""
    return sorted(k for k, c in EFFECTS.items() if c.candidate)


def register_effect(cls: type[AbstractEffect]) -> type[AbstractEffect]:
    """Class decorator: make an effect known by its ``name`` (docs/spec.md section 8)."""
    if not getattr(cls, "name", None):
        raise ValueError(f"effect class {cls.__name__} has no name")
    EFFECTS[cls.name] = cls
    return cls


class AbstractEffect(eqx.Module):
    """The interface of an effect: where it acts (the hooks below, each contributing nothing
    unless a subclass says otherwise), its ``name`` (docs/spec.md section 8), its fitting
    ``constraints`` and a ``typical`` start. Concrete effects are final classes; variants are
    made by wrapping (``Gated``), never by subclassing a concrete effect."""

    name: ClassVar[str] = ""
    where: ClassVar[str] = ""
    constraints: ClassVar[dict[str, str]] = {}
    #: Whether the discrepancy workflow tries it by default.
    candidate: ClassVar[bool] = True

    @classmethod
    def typical(cls, n: int) -> AbstractEffect:
        """A small instance to start a fit from (all parameters within their constraints)."""
        raise NotImplementedError(f"effect {cls.name!r} has no typical() start")

    def link_torque(self, x: PlantState) -> Float[Array, " n"] | float:
        """Torque added to the link equation's right-hand side [N m]."""
        return 0.0

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"] | float:
        """Torque added to the rotor equation's right-hand side [N m]."""
        return 0.0

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"] | float:
        """Extra elastic torque [N m] given deflection d = q2 - q1 [rad] and its rate dd."""
        return 0.0

    def applied_torque(self, tau: Array, aux: Any) -> Float[Array, " n"]:
        """Applied motor torque [N m] from the commanded torque ``tau`` and the effect's state."""
        return tau

    def aux_init(self, n: int) -> Any:
        """Initial internal state (``None`` for effects without state)."""
        return None

    def aux_rhs(self, aux: Any, tau: Array, x: PlantState) -> Any:
        """Time derivative of the internal state."""
        return None

    def link_measured(self, q1: Array, dq1: Array) -> Array:
        """The link encoder's reading [rad] of the link angle ``q1`` [rad] moving at ``dq1``
        [rad/s] (an output map: what a replay compares with the logged q1)."""
        return q1

    def link_reading(self, q1: Array, dq1: Array, ddq1: Array) -> tuple[Array, Array]:
        """The link angle [rad] and velocity [rad/s] behind a *measured* link motion ``q1``,
        ``dq1``, ``ddq1`` [rad, rad/s, rad/s^2] (an input map, the inverse of
        ``link_measured``: used where a model takes the measured link motion as an input)."""
        return q1, dq1

    def aux_steady(self, tau: Float[Array, " n"]) -> Any:
        """Internal state in equilibrium with a constant commanded torque ``tau`` (used to
        start a simulation segment from a log); defaults to ``aux_init``."""
        return self.aux_init(int(jnp.shape(tau)[-1]))

    def params(self) -> dict[str, list[float]]:
        """The effect's parameters as plain lists (docs/spec.md section 7 'effects' entry)."""
        out = {}
        for k, v in self.__dict__.items():
            if eqx.is_array(v):
                out[k] = np.asarray(v).tolist()
        return out
