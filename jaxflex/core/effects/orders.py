"""The higher orders of the library's friction, spring and lag families (docs/spec.md
section 8): rotor friction with a Stribeck term (``motor_friction``: Coulomb and viscous, then
the Stribeck excess), direction-dependent friction in the Coulomb level and then the static
level too (``asymmetric_friction``), the spring as a polynomial of odd powers
(``hardening_spring``: d^3, then d^5) and a lag of order two (``actuator_lag``: first order,
then a second-order current loop). The ripple's orders are with the ripple
(``jaxflex.core.effects.ripple``).

Each order is one registered final class with its ``family``, ``order`` and the ``higher``
order's name, and ``from_lower``, its first guess from a fitted instance of the order below.
The lag of order two shares its filter state with ``time_delay``
(``AbstractSecondOrderInput``). None is a discovery candidate of its own
(``candidate = False``): ``discover`` reaches an order k + 1 only from an added order k, and
keeps it when it pays by the criterion that adds an effect.
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.effects.base import (
    LEAST_AMPLITUDE,
    STEP_FLOOR,
    AbstractEffect,
    ResidualStart,
    register_effect,
)
from jaxflex.core.effects.library import (
    AbstractSecondOrderInput,
    ActuatorLag,
    AsymmetricFriction,
    HardeningSpring,
    MotorFriction,
    smooth_sign,
)
from jaxflex.core.state import PlantState
from jaxflex.core.validation import as_param, check_nonnegative, check_positive


#: The Stribeck velocities [rad/s] ``MotorFriction2.from_lower`` tries (log-spaced).
STRIBECK_GRID: np.ndarray = np.geomspace(0.005, 1.0, 16)


@register_effect
class MotorFriction2(AbstractEffect):
    """``motor_friction`` of order 2: Coulomb, viscous and Stribeck friction on the rotor
    side (the static map of eq. 35 on the rotor velocity q2'),

        rotor_torque = -((Fm + Fsm exp(-(q2' / vsm)^2)) tanh(q2' / width) + bm q2')   [N m]

    Fm [N m] >= 0 the Coulomb level, Fsm [N m] >= 0 the static excess over it (breakaway
    Fm + Fsm), vsm [rad/s] > 0 the Stribeck velocity, bm [N m s/rad] >= 0 viscous (all
    link-referred); width [rad/s] > 0 smoothing of sign(q2'), not fitted."""

    name: ClassVar[str] = "motor_friction_2"
    where: ClassVar[str] = "rotor torque"
    constraints: ClassVar[dict[str, str]] = {"Fm": "positive", "bm": "positive",
                                             "Fsm": "positive", "vsm": "positive",
                                             "width": "fixed"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "rotor velocity"
    family: ClassVar[str] = "motor_friction"
    order: ClassVar[int] = 2
    Fm: Float[Array, " n"] = eqx.field(converter=as_param)
    bm: Float[Array, " n"] = eqx.field(converter=as_param)
    Fsm: Float[Array, " n"] = eqx.field(converter=as_param)
    vsm: Float[Array, " n"] = eqx.field(converter=as_param)
    width: Float[Array, " n"] = eqx.field(converter=as_param, default=0.01)

    def __check_init__(self) -> None:
        check_nonnegative("motor_friction_2", Fm=self.Fm, bm=self.bm, Fsm=self.Fsm)
        check_positive("motor_friction_2", vsm=self.vsm, width=self.width)

    @classmethod
    def typical(cls, n: int) -> MotorFriction2:
        return cls(Fm=np.full(n, 2e-3), bm=np.full(n, 1e-3), Fsm=np.full(n, 1e-3),
                   vsm=np.full(n, 0.05))

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> MotorFriction2:
        """For each Stribeck velocity of ``STRIBECK_GRID``, the linear fit of the rotor
        residual by the three friction columns (-tanh(q2'/width), -q2', -tanh(q2'/width)
        exp(-(q2'/vsm)^2)); the best fit with all three levels positive gives Fm, bm, Fsm and
        vsm. Where none has, ``lower``'s fitted Fm and bm with a Stribeck excess of a third
        of Fm at the model's link Stribeck velocity."""
        if not isinstance(lower, MotorFriction):
            raise TypeError(f"{cls.name}.from_lower: expected a MotorFriction, got {type(lower).__name__}")
        width = float(np.ravel(lower.width)[0])
        best: tuple[float, np.ndarray, float] | None = None
        for vs in STRIBECK_GRID:
            def columns(q: np.ndarray, v: np.ndarray, vs: float = float(vs)) -> np.ndarray:
                sgn = np.tanh(v / width)
                return -np.column_stack([sgn, v, sgn * np.exp(-((v / vs) ** 2))])
            e, c = data.column_fits("rotor", columns)
            if e > 0 and np.all(c > 0) and (best is None or e > best[0]):
                best = (e, c, float(vs))
        if best is None:
            Fm = float(np.ravel(lower.Fm)[0])
            return cls(Fm=np.ravel(lower.Fm), bm=np.ravel(lower.bm),
                       Fsm=np.full(1, max(Fm / 3.0, LEAST_AMPLITUDE)),
                       vsm=np.ravel(data.nominal("vs")), width=np.ravel(lower.width))
        _, c, vs = best
        return cls(Fm=np.full(1, c[0]), bm=np.full(1, c[1]), Fsm=np.full(1, c[2]),
                   vsm=np.full(1, vs), width=np.ravel(lower.width))

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"]:
        v = x.dq2
        level = self.Fm + self.Fsm * jnp.exp(-jnp.square(v / self.vsm))
        return -(level * smooth_sign(v, self.width) + self.bm * v)


@register_effect
class ActuatorLag2(AbstractSecondOrderInput):
    """``actuator_lag`` of order 2: a second-order lag between commanded and applied torque
    (a current loop of natural frequency 1/T and damping zeta),

        T^2 a'' + 2 zeta T a' + a = tau,     applied torque = a      [N m]

    with the same mean delay 2 zeta T [s] as a first-order lag of that time constant.
    T [s] > 0 (fitted with T >= 1.5e-3, in ``discover`` T >= 1.5 h: RK4 keeps the poles
    (-zeta +- sqrt(zeta^2 - 1)) / T stable for zeta up to the bound); zeta [-] in
    (0.2, 1.5). Aux state (a, a') per joint."""

    name: ClassVar[str] = "actuator_lag_2"
    where: ClassVar[str] = "input (applied torque, internal state)"
    constraints: ClassVar[dict[str, str]] = {"T": "positive>=1.5e-3", "zeta": "bounded:0.2,1.5"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "frequency"
    step_bounded: ClassVar[tuple[str, ...]] = ("T",)
    family: ClassVar[str] = "actuator_lag"
    order: ClassVar[int] = 2
    T: Float[Array, " n"] = eqx.field(converter=as_param)
    zeta: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_positive("actuator_lag_2", T=self.T, zeta=self.zeta)

    @classmethod
    def typical(cls, n: int) -> ActuatorLag2:
        return cls(T=np.full(n, 3e-3), zeta=np.full(n, 0.9))

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> ActuatorLag2:
        """The fitted first-order time constant T1 as the mean delay 2 zeta T: critically
        damped (T = T1 / 2, zeta = 1), or, where T1 / 2 is below twice the step bound
        (``STEP_FLOOR``), T at that and zeta = T1 / (2 T) (within its bounds)."""
        if not isinstance(lower, ActuatorLag):
            raise TypeError(f"{cls.name}.from_lower: expected a ActuatorLag, got {type(lower).__name__}")
        T1 = float(np.ravel(lower.T)[0])
        T = max(T1 / 2.0, 2.0 * STEP_FLOOR * data.h)
        zeta = min(max(T1 / (2.0 * T), 0.3), 1.4)
        return cls(T=np.full(1, T), zeta=np.full(1, zeta))

    def filter_coefficients(self) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """(2 zeta T [s], T^2 [s^2])."""
        return 2.0 * self.zeta * self.T, self.T**2

    def applied_torque(self, tau: Array, aux: Array) -> Float[Array, " n"]:
        return aux[0]


@register_effect
class AsymmetricFriction2(AbstractEffect):
    """``asymmetric_friction`` of order 2: the Coulomb and the static level each shifted by
    direction, Fc + dF and Fs + dS forward, Fc - dF and Fs - dS backward, a ``friction_level``
    shift of the LuGre level g(v) (eq. 6)

        Delta(v) = dF + (dS - dF) exp(-(v / vs)^2)      [N m]

    with vs the plant's own Stribeck velocity (the LuGre's, as fitted). dF, dS [N m] any
    sign; dS = dF is order 1."""

    name: ClassVar[str] = "asymmetric_friction_2"
    where: ClassVar[str] = "link friction level"
    constraints: ClassVar[dict[str, str]] = {"dF": "free", "dS": "free"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "link velocity"
    signed: ClassVar[tuple[str, ...]] = ("dF", "dS")
    family: ClassVar[str] = "asymmetric_friction"
    order: ClassVar[int] = 2
    dF: Float[Array, " n"] = eqx.field(converter=as_param)
    dS: Float[Array, " n"] = eqx.field(converter=as_param)

    @classmethod
    def typical(cls, n: int) -> AsymmetricFriction2:
        return cls(dF=np.zeros(n), dS=np.zeros(n))

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> AsymmetricFriction2:
        """``lower``'s fitted dF for both levels (dS = dF: order 1's own friction, so the fit
        starts where order 1 ended). The static shift acts where the link nearly sticks,
        which the localisation's steady-state residual (read on sliding samples only) does
        not show, so it is left to the fit."""
        if not isinstance(lower, AsymmetricFriction):
            raise TypeError(f"{cls.name}.from_lower: expected an AsymmetricFriction, "
                            f"got {type(lower).__name__}")
        return cls(dF=np.ravel(lower.dF), dS=np.ravel(lower.dF))

    def friction_level(self, v: Array, friction: Any) -> Float[Array, " n"]:
        return self.dF + (self.dS - self.dF) * jnp.exp(-jnp.square(v / friction.vs))


@register_effect
class HardeningSpring2(AbstractEffect):
    """``hardening_spring`` of order 2: the joint spring as a polynomial of odd powers up to
    the fifth, K d + K3 d^3 + K5 d^5, added as

        spring_torque = K3 d^3 + K5 d^5      [N m],   d = q2 - q1 [rad]

    K3 [N m/rad^3] >= 0, K5 [N m/rad^5] >= 0 (a spring that stiffens with its deflection)."""

    name: ClassVar[str] = "hardening_spring_2"
    where: ClassVar[str] = "spring torque"
    constraints: ClassVar[dict[str, str]] = {"K3": "positive", "K5": "positive"}
    candidate: ClassVar[bool] = False
    telling: ClassVar[str | None] = "deflection"
    family: ClassVar[str] = "hardening_spring"
    order: ClassVar[int] = 2
    K3: Float[Array, " n"] = eqx.field(converter=as_param)
    K5: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_nonnegative("hardening_spring_2", K3=self.K3, K5=self.K5)

    @classmethod
    def typical(cls, n: int) -> HardeningSpring2:
        return cls(K3=np.full(n, 10.0), K5=np.full(n, 100.0))

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> HardeningSpring2:
        """K3 and K5 from the linear fit of the link residual by d^3 and d^5 (the nominal
        K d cleared) where both come out positive; else ``lower``'s fitted K3 and a K5 whose
        d^5 term is a tenth of the d^3 term at the log's 95th-percentile |d| (a positive
        parameter is fitted through exp and needs a start of its own size)."""
        if not isinstance(lower, HardeningSpring):
            raise TypeError(f"{cls.name}.from_lower: expected a HardeningSpring, "
                            f"got {type(lower).__name__}")
        e, c = data.deflection_fits(lambda d, dd: np.column_stack([d**3, d**5]))
        if e > 0 and np.all(c > 0):
            return cls(K3=np.full(1, c[0]), K5=np.full(1, c[1]))
        K3 = max(float(np.ravel(lower.K3)[0]), LEAST_AMPLITUDE)
        d95 = max(float(np.percentile(np.abs(data.deflection()), 95)), 1e-6)
        return cls(K3=np.full(1, K3), K5=np.full(1, 0.1 * K3 / d95**2))

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"]:
        return self.K3 * d**3 + self.K5 * d**5


__all__ = ["ActuatorLag2", "AsymmetricFriction2", "HardeningSpring2", "MotorFriction2"]
