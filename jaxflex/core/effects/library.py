"""The named effects of docs/spec.md section 8, one final class each, registered by name."""

from __future__ import annotations

import abc
import math
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.effects.base import AbstractEffect, ResidualStart, register_effect
from jaxflex.core.state import PlantState
from jaxflex.core.validation import as_param, check_nonnegative, check_positive, is_concrete


@register_effect
class Gravity(AbstractEffect):
    """Link gravity m g l sin(q1) in a vertical plane: link_torque = -mgl sin(q1 - q0) [N m].

    ``mgl`` [N m] is mass times g times the centre-of-mass distance; ``q0`` [rad] the angle of
    the hanging rest position (0 by default).
    """

    name: ClassVar[str] = "gravity"
    where: ClassVar[str] = "link torque"
    constraints: ClassVar[dict[str, str]] = {"mgl": "positive", "q0": "free"}
    telling: ClassVar[str | None] = "position"
    cannot_act_on: ClassVar[tuple[str, ...]] = ("vertical", "prismatic")
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"mgl": (0.3, 0.6)}
    mgl: Float[Array, " n"] = eqx.field(converter=as_param)
    q0: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)

    def __check_init__(self) -> None:
        check_positive("gravity", mgl=self.mgl)

    @classmethod
    def typical(cls, n: int) -> Gravity:
        return cls(mgl=np.full(n, 0.05), q0=np.zeros(n))

    @classmethod
    def start_from_residual(cls, data: ResidualStart) -> Gravity:
        """-mgl sin(q1 - q0) = mgl sin(q1 + pi - q0) is a link ripple of N = 1: mgl [N m] and
        q0 [rad] from the fit of a sine and a cosine of q1 to the link residual, cleared of all
        but the angle (no ``trend``): from how the missing torque varies with the angle, not
        from its mean. The typical start where the fit explains nothing, or puts the hanging
        angle farther from the travel's middle than the travel is wide: over the travel such
        a sine is a constant-like torque, which the residual's variation cannot tell from an
        asymmetric friction or an offset, and a gravity started there can beat the effect it
        mimics."""
        q = data.angle("link")
        e, a_s, a_c = data.ripple_fits("link", np.ones(1), 0.0, trend=False)
        if not e[0] > 0:
            return cls.typical(1)
        q0 = math.remainder(math.pi - math.atan2(a_c[0], a_s[0]), 2.0 * math.pi)
        if abs(q0 - float(np.median(q))) > float(np.ptp(q)):
            return cls.typical(1)
        return cls(mgl=np.full(1, max(math.hypot(a_s[0], a_c[0]), 1e-3)), q0=np.full(1, q0))

    @classmethod
    def draw(cls, rng: np.random.Generator, scale: float = 1.0) -> dict[str, Any]:
        """``AbstractEffect.draw`` plus a hanging angle q0 uniform in +-0.2 rad."""
        kw = super().draw(rng, scale)
        kw["q0"] = rng.uniform(-0.2, 0.2)
        return kw

    def link_torque(self, x: PlantState) -> Float[Array, " n"]:
        return -self.mgl * jnp.sin(x.q1 - self.q0)


@register_effect
class TorqueOffset(AbstractEffect):
    """Constant bias between commanded and applied torque: tau_a = tau + offset [N m]."""

    name: ClassVar[str] = "torque_offset"
    where: ClassVar[str] = "input (applied torque)"
    constraints: ClassVar[dict[str, str]] = {"offset": "free"}
    telling: ClassVar[str | None] = "time"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"offset": (0.03, 0.06)}
    signed: ClassVar[tuple[str, ...]] = ("offset",)
    offset: Float[Array, " n"] = eqx.field(converter=as_param)

    @classmethod
    def typical(cls, n: int) -> TorqueOffset:
        return cls(offset=np.zeros(n))

    def applied_torque(self, tau: Array, aux: Any) -> Float[Array, " n"]:
        return tau + self.offset


def smooth_sign(v: Array, width: Array) -> Array:
    """tanh(v / width): a differentiable sign(v) for Coulomb-type terms."""
    return jnp.tanh(v / width)


def softplus(x: Array, w: Array) -> Array:
    """w log(1 + exp(x / w)), a smooth max(x, 0) with corner width w."""
    return w * jnp.logaddexp(0.0, x / w)


@register_effect
class AsymmetricFriction(AbstractEffect):
    """Direction-dependent friction level on the link: the LuGre of eq. 4-6 runs with the
    level g(v) + dF while the link moves forward and g(v) - dF backward (Coulomb level Fc + dF
    and static level Fs + dF forward, Fc - dF and Fs - dF backward; docs/spec.md section 8),
    a ``friction_level`` shift, so the bristles (eq. 5) follow the level of the direction they
    move in. dF [N m] any sign (|dF| < Fc for a physical plant, not enforced: the nominal Fc
    is refitted alongside; the level is floored, ``jaxflex.core.plant.LEVEL_FLOOR``)."""

    name: ClassVar[str] = "asymmetric_friction"
    where: ClassVar[str] = "link friction level"
    constraints: ClassVar[dict[str, str]] = {"dF": "free"}
    telling: ClassVar[str | None] = "link velocity"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"dF": (0.03, 0.06)}
    signed: ClassVar[tuple[str, ...]] = ("dF",)
    higher: ClassVar[str | None] = "asymmetric_friction_2"
    dF: Float[Array, " n"] = eqx.field(converter=as_param)

    @classmethod
    def typical(cls, n: int) -> AsymmetricFriction:
        return cls(dF=np.zeros(n))

    def friction_level(self, v: Array, friction: Any) -> Float[Array, " n"]:
        return self.dF * jnp.ones_like(v)


@register_effect
class Backlash(AbstractEffect):
    """Smooth dead zone of half-width b [rad] in the spring deflection: the elastic torque is
    K dz(d) instead of K d, with dz(d) = softplus(d - b) - softplus(-d - b) (corner width w).
    As a spring_torque hook: K (dz(d) - d) [N m].

    b [rad] > 0 half gap; K [N m/rad] > 0 the joint stiffness it acts on (the discrepancy fit
    ties it to the plant's K); w [rad] > 0 corner width, not fitted.
    """

    name: ClassVar[str] = "backlash"
    where: ClassVar[str] = "spring torque"
    constraints: ClassVar[dict[str, str]] = {"b": "positive", "K": "tied:K", "w": "fixed"}
    telling: ClassVar[str | None] = "deflection"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"b": (0.004, 0.01)}
    b: Float[Array, " n"] = eqx.field(converter=as_param)
    K: Float[Array, " n"] = eqx.field(converter=as_param)
    w: Float[Array, " n"] = eqx.field(converter=as_param, default=2e-4)

    def __check_init__(self) -> None:
        check_positive("backlash", b=self.b, K=self.K, w=self.w)

    @classmethod
    def typical(cls, n: int) -> Backlash:
        return cls(b=np.full(n, 1e-3), K=np.full(n, 6.77))

    def dead_zone(self, d: Array) -> Array:
        """Smooth dead zone of the deflection d [rad]."""
        return softplus(d - self.b, self.w) - softplus(-d - self.b, self.w)

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"]:
        return self.K * (self.dead_zone(d) - d)


@register_effect
class HardeningSpring(AbstractEffect):
    """Cubic hardening of the joint spring: spring_torque = K3 d^3 [N m], K3 [N m/rad^3] >= 0
    (order 1 of the spring polynomial of odd powers; order 2 adds d^5,
    ``jaxflex.core.effects.orders.HardeningSpring2``)."""

    name: ClassVar[str] = "hardening_spring"
    where: ClassVar[str] = "spring torque"
    constraints: ClassVar[dict[str, str]] = {"K3": "positive"}
    telling: ClassVar[str | None] = "deflection"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"K3": (300.0, 800.0)}
    higher: ClassVar[str | None] = "hardening_spring_2"
    K3: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_nonnegative("hardening_spring", K3=self.K3)

    @classmethod
    def typical(cls, n: int) -> HardeningSpring:
        return cls(K3=np.full(n, 10.0))

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"]:
        return self.K3 * d**3


@register_effect
class JointDamping(AbstractEffect):
    """Viscous damping in the elastic coupling: spring_torque = D (q2' - q1') [N m],
    D [N m s/rad] >= 0."""

    name: ClassVar[str] = "joint_damping"
    where: ClassVar[str] = "spring torque"
    constraints: ClassVar[dict[str, str]] = {"D": "positive"}
    telling: ClassVar[str | None] = "deflection rate"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"D": (0.02, 0.05)}
    D: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_nonnegative("joint_damping", D=self.D)

    @classmethod
    def typical(cls, n: int) -> JointDamping:
        return cls(D=np.full(n, 1e-3))

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"]:
        return self.D * dd


@register_effect
class MotorFriction(AbstractEffect):
    """Coulomb (smoothed) plus viscous friction on the rotor side:
    rotor_torque = -(Fm tanh(q2' / width) + bm q2') [N m].

    Fm [N m] >= 0, bm [N m s/rad] >= 0 (link-referred); width [rad/s] > 0 not fitted.
    """

    name: ClassVar[str] = "motor_friction"
    where: ClassVar[str] = "rotor torque"
    constraints: ClassVar[dict[str, str]] = {"Fm": "positive", "bm": "positive", "width": "fixed"}
    telling: ClassVar[str | None] = "rotor velocity"
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"Fm": (0.02, 0.04),
                                                                  "bm": (0.01, 0.03)}
    higher: ClassVar[str | None] = "motor_friction_2"
    Fm: Float[Array, " n"] = eqx.field(converter=as_param)
    bm: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)
    width: Float[Array, " n"] = eqx.field(converter=as_param, default=0.01)

    def __check_init__(self) -> None:
        check_nonnegative("motor_friction", Fm=self.Fm, bm=self.bm)
        check_positive("motor_friction", width=self.width)

    @classmethod
    def typical(cls, n: int) -> MotorFriction:
        return cls(Fm=np.full(n, 2e-3), bm=np.full(n, 1e-3))

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"]:
        return -(self.Fm * smooth_sign(x.dq2, self.width) + self.bm * x.dq2)


@register_effect
class ActuatorLag(AbstractEffect):
    """First-order lag between commanded and applied torque (e.g. current loop):
    T a' = tau - a, applied torque = a [N m]. T [s] > 0 time constant. Aux state a (n,)."""

    name: ClassVar[str] = "actuator_lag"
    where: ClassVar[str] = "input (applied torque, internal state)"
    constraints: ClassVar[dict[str, str]] = {"T": "positive>=1.5e-3"}
    telling: ClassVar[str | None] = "frequency"
    step_bounded: ClassVar[tuple[str, ...]] = ("T",)
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"T": (0.002, 0.004)}
    higher: ClassVar[str | None] = "actuator_lag_2"
    T: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_positive("actuator_lag", T=self.T)

    @classmethod
    def typical(cls, n: int) -> ActuatorLag:
        # above the constraint's 1.5 ms bound (a start on the bound has a dead coordinate)
        return cls(T=np.full(n, 3e-3))

    def aux_init(self, n: int) -> Array:
        return jnp.zeros(n)

    def aux_steady(self, tau: Array) -> Array:
        return jnp.asarray(tau)

    def aux_rhs(self, aux: Array, tau: Array, x: PlantState) -> Array:
        return (tau - aux) / self.T

    def applied_torque(self, tau: Array, aux: Array) -> Float[Array, " n"]:
        return aux


class AbstractSecondOrderInput(AbstractEffect):
    """An effect on the input through a unit-gain second-order filter p of the commanded
    torque tau,

        c2 p'' + c1 p' + p = tau

    with the coefficients c1 [s] and c2 [s^2] of ``filter_coefficients``. Aux state (p, p')
    per joint: (0, 0) at rest, (tau, 0) in equilibrium with a constant tau. The concrete
    classes say the coefficients and the applied torque from the state."""

    @abc.abstractmethod
    def filter_coefficients(self) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """(c1 [s], c2 [s^2]) of the filter."""

    def aux_init(self, n: int) -> Array:
        return jnp.zeros((2, n))

    def aux_steady(self, tau: Array) -> Array:
        tau = jnp.asarray(tau)
        return jnp.stack([tau, jnp.zeros_like(tau)])

    def aux_rhs(self, aux: Array, tau: Array, x: PlantState) -> Array:
        p, r = aux[0], aux[1]
        c1, c2 = self.filter_coefficients()
        return jnp.stack([r, (tau - p - c1 * r) / c2])


@register_effect
class TimeDelay(AbstractSecondOrderInput):
    """Input delay of T [s] > 0, as a second-order Pade approximant (unit gain, phase close to
    -omega T up to omega ~ 3/T):

        exp(-s T) ~ (1 - s T/2 + (s T)^2/12) / (1 + s T/2 + (s T)^2/12)
                  = 1 - s T / (1 + s T/2 + (s T)^2/12)

    Aux state (p, r) per joint with p'' = (tau - p - (T/2) p') / (T^2/12), r = p'; applied
    torque tau - T r. Chosen over a sample shift so that the delay lives in the plant (the same
    model serves a closed-loop simulation and a log replay) and T is differentiable.
    """

    name: ClassVar[str] = "time_delay"
    where: ClassVar[str] = "input (applied torque, internal state)"
    constraints: ClassVar[dict[str, str]] = {"T": "positive>=1.5e-3"}
    telling: ClassVar[str | None] = "frequency"
    step_bounded: ClassVar[tuple[str, ...]] = ("T",)
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"T": (0.002, 0.004)}
    T: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        check_positive("time_delay", T=self.T)

    @classmethod
    def typical(cls, n: int) -> TimeDelay:
        # above the constraint's 1.5 ms bound (a start on the bound has a dead coordinate)
        return cls(T=np.full(n, 3e-3))

    def filter_coefficients(self) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """(T / 2 [s], T^2 / 12 [s^2]): the Pade approximant's denominator."""
        return 0.5 * self.T, self.T**2 / 12.0

    def applied_torque(self, tau: Array, aux: Array) -> Float[Array, " n"]:
        return tau - self.T * aux[1]


@register_effect
class EncoderSkew(AbstractEffect):
    """Link-encoder reading relative to the motor encoder: a time skew and an offset, the
    per-log sensor nuisances of real two-encoder logs (a KUKA KR300 axis: about 3 ms).
    First order in the skew ``skew`` [s] (skew > 0: the link encoder reads late), both ways:

    - where a model takes the *measured* link motion as an input (the "rotor" model kind of
      ``jaxflex.sim.step``, ``link_reading``), the link angle used is ``q1 + skew q1' + offset``;
    - where a model replays the link motion (the "flexible" and "link" kinds, and so
      ``jaxflex.discover``), the reading it is compared with is ``q1 - skew q1' - offset``
      (``link_measured``; the same map inverted).

    It adds no torque anywhere, but it is a discrepancy candidate: on a two-encoder log a
    skew changes the spring deflection read from the encoders, which a model of the motion
    alone cannot reproduce (the KUKA logs' axis 1: named on all three recordings,
    ``studies/discover_kuka.py``). skew [s], offset [rad]: free (any sign).
    """

    name: ClassVar[str] = "encoder_skew"
    where: ClassVar[str] = "link encoder reading"
    constraints: ClassVar[dict[str, str]] = {"skew": "free", "offset": "free"}
    recording: ClassVar[bool] = True
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"skew": (0.001, 0.003),
                                                                  "offset": (2e-4, 5e-4)}
    signed: ClassVar[tuple[str, ...]] = ("offset",)
    skew: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)
    offset: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)

    @classmethod
    def typical(cls, n: int) -> EncoderSkew:
        return cls(skew=np.zeros(n), offset=np.zeros(n))

    @classmethod
    def recorded_link(cls, t: np.ndarray, q1: np.ndarray, kw: dict[str, Any]) -> np.ndarray:
        """The true link angle at t - skew (linear interpolation of the samples: the exact
        delay, not the first-order map a fit uses) minus the offset [rad]."""
        skew, offset = float(np.ravel(kw["skew"])[0]), float(np.ravel(kw["offset"])[0])
        late = np.stack([np.interp(t - skew, t, q1[:, j]) for j in range(q1.shape[1])], axis=1)
        return late - offset

    def link_measured(self, q1: Array, dq1: Array) -> Array:
        """q1 - skew q1' - offset [rad]: the late link encoder's reading of the motion."""
        return q1 - self.skew * dq1 - self.offset

    def link_reading(self, q1: Array, dq1: Array, ddq1: Array) -> tuple[Array, Array]:
        """(q1 + skew q1' + offset [rad], q1' + skew q1'' [rad/s])."""
        return q1 + self.skew * dq1 + self.offset, dq1 + self.skew * ddq1


@register_effect
class EncoderScale(AbstractEffect):
    """Scale error of the link encoder relative to the motor encoder, a per-log sensor nuisance
    of two-encoder logs: the link encoder reads the angle ``q1`` as
    ``q1 / (1 + scale)``, so a deflection read from the encoders carries ``scale q1`` beside the
    spring's. Exact inverses both ways (``EncoderSkew``'s two directions):

    - input map (kind "rotor", ``link_reading``): ``(1 + scale) q1``, ``(1 + scale) q1'``;
    - output map (replays, ``link_measured``): ``q1 / (1 + scale)``.

    KUKA KR300 axis 1, trajectory A (``studies/kuka_flexible.py``): the deflection left once
    the spring torque of the datasheet rotor inertia is taken out grows with q1 by about
    5e-4 rad/rad over 0-0.8 rad, which no spring, skew or offset reproduces. ``scale``
    [rad/rad]: fitted within |scale| < ``LIMIT`` (a larger value is not an encoder's
    calibration error; the bound keeps a fit in which K runs to 0 from turning ``K scale q1``
    into a free torque term). Not a discrepancy candidate by default (``candidate``): on one
    log it takes any deflection that grows with the angle, so it is named only where a log's
    two encoders are compared.
    """

    #: The largest |scale| [rad/rad]: the fitted range and the check.
    LIMIT: ClassVar[float] = 0.01
    name: ClassVar[str] = "encoder_scale"
    where: ClassVar[str] = "link encoder reading"
    constraints: ClassVar[dict[str, str]] = {"scale": f"bounded:{-LIMIT},{LIMIT}"}
    candidate: ClassVar[bool] = False
    scale: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)

    def __check_init__(self) -> None:
        if is_concrete(self.scale) and not np.all(np.abs(np.asarray(self.scale)) <= self.LIMIT):
            raise ValueError(f"encoder_scale: parameter scale must be finite with |scale| <= "
                             f"{self.LIMIT} (a calibration error), got "
                             f"{np.asarray(self.scale).tolist()}")

    @classmethod
    def typical(cls, n: int) -> EncoderScale:
        return cls(scale=np.zeros(n))

    def link_measured(self, q1: Array, dq1: Array) -> Array:
        """q1 / (1 + scale) [rad]: the link encoder's reading of the angle q1."""
        return q1 / (1.0 + self.scale)

    def link_reading(self, q1: Array, dq1: Array, ddq1: Array) -> tuple[Array, Array]:
        """((1 + scale) q1 [rad], (1 + scale) q1' [rad/s])."""
        return (1.0 + self.scale) * q1, (1.0 + self.scale) * dq1

