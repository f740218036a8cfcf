"""Optional physical effects that augment a plant without forking it (STYLE: 'a plant is composed').

An effect says where it acts by overriding one or more hooks; the defaults do nothing:

- ``link_torque(x)``   torque added to the right-hand side of the link equation [N m]
- ``rotor_torque(x)``  torque added to the right-hand side of the rotor equation [N m]
- ``spring_torque(d, dd)`` extra elastic torque added to K (q2 - q1) (acts on both sides) [N m]
- ``applied_torque(tau, aux)`` maps the commanded motor torque to the applied one [N m]
- ``aux_init(n)``, ``aux_rhs(aux, tau, x)``  internal states (e.g. an actuator lag), if any

Plant equations with effects (SPEC section 1 plus effects):

    M q1'' + C q1' + G + F = T_s + sum link_torque
    J q2''                 = tau_a - T_s + sum rotor_torque
    T_s = K (q2 - q1) + sum spring_torque,  tau_a = applied_torque(tau)

Concrete effects register themselves by their SPEC section 8 name in ``EFFECTS``; the
discrepancy workflow looks them up there. Every effect's parameters are array leaves so that
``grad`` reaches them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.friction import _as_param, check_positive

if TYPE_CHECKING:
    from jaxflex.plant import PlantState

EFFECTS: dict[str, type["Effect"]] = {}


def register_effect(cls: type["Effect"]) -> type["Effect"]:
    """Class decorator: make an effect known by its ``name`` (SPEC section 8)."""
    if not getattr(cls, "name", None):
        raise ValueError(f"effect class {cls.__name__} has no name")
    EFFECTS[cls.name] = cls
    return cls


class Effect(eqx.Module):
    """Abstract effect. Subclasses set ``name`` and override the hooks where they act."""

    name: ClassVar[str] = ""

    def link_torque(self, x: "PlantState") -> Float[Array, " n"] | float:
        """Torque added to the link equation's right-hand side [N m]."""
        return 0.0

    def rotor_torque(self, x: "PlantState") -> Float[Array, " n"] | float:
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

    def aux_rhs(self, aux: Any, tau: Array, x: "PlantState") -> Any:
        """Time derivative of the internal state."""
        return None

    def params(self) -> dict[str, list[float]]:
        """The effect's parameters as plain lists (SPEC section 7 'effects' entry)."""
        out = {}
        for k, v in self.__dict__.items():
            if eqx.is_array(v):
                out[k] = np.asarray(v).tolist()
        return out


@register_effect
class Gravity(Effect):
    """Link gravity m g l sin(q1) in a vertical plane: link_torque = -mgl sin(q1 - q0) [N m].

    ``mgl`` [N m] is mass times g times the centre-of-mass distance; ``q0`` [rad] the angle of
    the hanging rest position (0 by default).
    """

    name: ClassVar[str] = "gravity"
    mgl: Float[Array, " n"] = eqx.field(converter=_as_param)
    q0: Float[Array, " n"] = eqx.field(converter=_as_param, default=0.0)

    def __check_init__(self) -> None:
        check_positive("gravity", mgl=self.mgl)

    def link_torque(self, x: "PlantState") -> Float[Array, " n"]:
        return -self.mgl * jnp.sin(x.q1 - self.q0)


@register_effect
class TorqueOffset(Effect):
    """Constant bias between commanded and applied torque: tau_a = tau + offset [N m]."""

    name: ClassVar[str] = "torque_offset"
    offset: Float[Array, " n"] = eqx.field(converter=_as_param)

    def applied_torque(self, tau: Array, aux: Any) -> Float[Array, " n"]:
        return tau + self.offset
