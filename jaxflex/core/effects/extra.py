"""Effects of real flexible joints beyond the paper's model: the load-dependent friction of a
strain-wave or cycloid gear, a hysteresis in the joint spring and a dead zone in the actuator
(docs/spec.md section 8).

Each is one registered class of ``jaxflex.core.effects`` (hooks, ``constraints``, ``typical`` and
its discovery and synthetic-log metadata on the class), kept in this module so that
``jaxflex.core.effects.library`` stays a readable list of the paper's effects. None is a default discovery candidate
(``candidate = False``): ``discover`` tries them when they are named in its candidates
(``DiscoverConfig.candidates``, the command line's ``--candidates``), so the default
universe, its compiled program and its answers stay those of the paper's effects.
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.effects.base import AbstractEffect, register_effect
from jaxflex.core.effects.library import smooth_sign, softplus
from jaxflex.core.state import PlantState
from jaxflex.core.validation import as_param, check_nonnegative, check_positive


@register_effect
class LoadFriction(AbstractEffect):
    """Load-dependent friction of a strain-wave (harmonic drive) or cycloid gear: a Coulomb
    friction on the gear's input whose level is a share of the torque the gear transmits,

        rotor_torque = -mu |K (q2 - q1)| tanh(q2' / width)      [N m]

    with q2' [rad/s] the link-referred rotor velocity, the gear input's velocity relative to
    its housing. mu [-] >= 0 the share of the transmitted torque |K (q2 - q1)| [N m] lost to
    friction; K [N m/rad] > 0 the joint stiffness it acts through (tied to the plant's K in a
    fit); width [rad/s] > 0 smoothing of sign(q2'), not fitted.
    """

    name: ClassVar[str] = "load_friction"
    where: ClassVar[str] = "rotor torque"
    constraints: ClassVar[dict[str, str]] = {"mu": "positive", "K": "tied:K", "width": "fixed"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "rotor velocity"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"mu": (0.05, 0.1)}
    mu: Float[Array, " n"] = eqx.field(converter=as_param)
    K: Float[Array, " n"] = eqx.field(converter=as_param)
    width: Float[Array, " n"] = eqx.field(converter=as_param, default=0.01)

    def __check_init__(self) -> None:
        check_nonnegative("load_friction", mu=self.mu)
        check_positive("load_friction", K=self.K, width=self.width)

    @classmethod
    def typical(cls, n: int) -> LoadFriction:
        return cls(mu=np.full(n, 0.02), K=np.full(n, 6.77), width=np.full(n, 0.01))

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"]:
        return -self.mu * jnp.abs(self.K * (x.q2 - x.q1)) * smooth_sign(x.dq2, self.width)


@register_effect
class SpringHysteresis(AbstractEffect):
    """Hysteresis in the joint spring, Dahl's model on the deflection d = q2 - q1: a torque z
    [N m] added to the spring torque (acts on both sides), with

        z' = Kh (d' - |d'| z / Th)                                 [N m/s]

    so that z grows with the deflection at the slope Kh (1 - sgn(d') z / Th) and saturates at
    +-Th while the deflection keeps growing; a deflection cycle traces a loop 2 Th high.
    Kh [N m/rad] > 0 the hysteresis stiffness (the slope at z = 0; 2 Kh just after a reversal
    from saturation); Th [N m] > 0 the saturation torque. Internal state z (n,), zero at
    rest.
    """

    name: ClassVar[str] = "spring_hysteresis"
    where: ClassVar[str] = "spring torque (internal state)"
    constraints: ClassVar[dict[str, str]] = {"Kh": "positive", "Th": "positive"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "deflection"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"Kh": (2.0, 4.0),
                                                                  "Th": (0.03, 0.06)}
    Kh: Float[Array, " n"] = eqx.field(converter=as_param)
    Th: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_positive("spring_hysteresis", Kh=self.Kh, Th=self.Th)

    @classmethod
    def typical(cls, n: int) -> SpringHysteresis:
        return cls(Kh=np.full(n, 1.0), Th=np.full(n, 0.01))

    def aux_init(self, n: int) -> Array:
        return jnp.zeros(n)

    def aux_rhs(self, aux: Array, tau: Array, x: PlantState) -> Array:
        dd = x.dq2 - x.dq1
        return self.Kh * (dd - jnp.abs(dd) * aux / self.Th)

    def spring_state_torque(self, aux: Array, d: Array, dd: Array) -> Float[Array, " n"]:
        return aux


@register_effect
class ActuatorDeadZone(AbstractEffect):
    """Dead zone of the actuator (a drive's deadband, a gear's static friction seen through
    a current loop): the applied torque is the commanded torque u less a band, smoothed so
    that gradients exist,

        tau_a = softplus_w(u - b) - softplus_w(-u - b)  ~  sign(u) max(|u| - b, 0)   [N m]

    with softplus_w(x) = w log(1 + exp(x / w)). b [N m] > 0 the half-width of the band;
    w [N m] > 0 its corner width, not fitted.
    """

    name: ClassVar[str] = "actuator_dead_zone"
    where: ClassVar[str] = "input (applied torque)"
    constraints: ClassVar[dict[str, str]] = {"b": "positive", "w": "fixed"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "commanded torque"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"b": (0.03, 0.06)}
    b: Float[Array, " n"] = eqx.field(converter=as_param)
    w: Float[Array, " n"] = eqx.field(converter=as_param, default=2e-3)

    def __check_init__(self) -> None:
        check_positive("actuator_dead_zone", b=self.b, w=self.w)

    @classmethod
    def typical(cls, n: int) -> ActuatorDeadZone:
        return cls(b=np.full(n, 0.01), w=np.full(n, 2e-3))

    def applied_torque(self, tau: Array, aux: Any) -> Float[Array, " n"]:
        return softplus(tau - self.b, self.w) - softplus(-tau - self.b, self.w)


__all__ = ["ActuatorDeadZone", "LoadFriction", "SpringHysteresis"]
