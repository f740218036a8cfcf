"""Measurement and actuation of the sampled-data loop: encoders, velocity source, DAC.

``AbstractSensing`` declares what the closed loop (``jaxflex.sim.simulate.simulate_sampled``)
uses: the encoder resolutions and noise levels [rad], where the controller's velocities come
from (exact, filtered differentiation of the sensed angles, or the model-based Kalman filter
of ``jaxflex.core.estimator`` with its ``kalman`` tuning), the DAC's resolution and range, and the
two maps ``measure`` (true angle -> sensed angle) and ``dac`` (commanded -> applied torque).
``Sensing`` is the concrete, final model of a rig. Variants wrap a sensing instead of
overriding its methods (as diffrax's ``HalfSolver`` wraps a solver): ``StraightThrough``
keeps the wrapped sensing's values and gives its quantisers a straight-through gradient.
"""

# no ``from __future__ import annotations``: equinox reads ``AbstractVar`` annotations at
# class creation and refuses stringified ones
import abc
from typing import Literal

import equinox as eqx
from equinox import AbstractVar
import jax
import jax.numpy as jnp
from jaxtyping import Array

from jaxflex.core.estimator import KalmanTuning, tuning_of
from jaxflex.core.validation import as_param, check_nonnegative

VELOCITY_SOURCES: tuple[str, ...] = ("exact", "filtered", "kalman")
VelocitySource = Literal["exact", "filtered", "kalman"]
SENSING_FIELDS: tuple[str, ...] = (
    "q1_resolution", "q2_resolution", "q1_noise", "q2_noise", "velocity", "dac_bits", "dac_range",
    "kalman",
)


class AbstractSensing(eqx.Module):
    """What the sampled-data loop needs from its sensors and actuator.

    q1_resolution, q2_resolution [rad]: encoder quantisation steps (0: none);
    q1_noise, q2_noise [rad]: standard deviation of white angle noise (0: none);
    velocity: "exact" passes true velocities to the controller, "filtered" lets it
    differentiate the sensed angles, "kalman" gives it the estimates of the steady-state
    Kalman filter on its own model (``jaxflex.core.estimator``), driven by the applied torque and
    both encoders; dac_bits: DAC resolution (0: none) over +-dac_range [N m]; kalman: the
    filter's tuning (``KalmanTuning``; None: its defaults), used only with "kalman".
    """

    q1_resolution: AbstractVar[Array]
    q2_resolution: AbstractVar[Array]
    q1_noise: AbstractVar[Array]
    q2_noise: AbstractVar[Array]
    velocity: AbstractVar[VelocitySource]
    dac_bits: AbstractVar[int]
    dac_range: AbstractVar[Array]
    kalman: AbstractVar[KalmanTuning | None]

    @abc.abstractmethod
    def measure(self, q: Array, resolution: Array, noise: Array) -> Array:
        """Sensed angle [rad] of the true angle ``q`` [rad] with ``noise`` [rad] (already
        scaled) added, at encoder step ``resolution`` [rad]."""

    @abc.abstractmethod
    def dac(self, tau: Array) -> Array:
        """Torque [N m] that reaches the plant when ``tau`` [N m] is commanded."""


class Sensing(AbstractSensing):
    """A rig's sensors and DAC (fields as in ``AbstractSensing``); all zeros: ideal."""

    q1_resolution: Array = eqx.field(converter=as_param, default=0.0)
    q2_resolution: Array = eqx.field(converter=as_param, default=0.0)
    q1_noise: Array = eqx.field(converter=as_param, default=0.0)
    q2_noise: Array = eqx.field(converter=as_param, default=0.0)
    velocity: VelocitySource = eqx.field(static=True, default="exact")
    dac_bits: int = eqx.field(static=True, default=0)
    dac_range: Array = eqx.field(converter=as_param, default=2.0)
    # None (no leaves) unless given, so that the pytree of an "exact"/"filtered" sensing is
    # what it was before the Kalman filter existed (sweeps vmap over its leaves)
    kalman: KalmanTuning | None = eqx.field(converter=tuning_of, default=None)

    def __check_init__(self) -> None:
        if self.velocity not in VELOCITY_SOURCES:
            raise ValueError(
                f"Sensing: velocity must be one of {VELOCITY_SOURCES}, got {self.velocity!r}")
        if self.kalman is not None and self.velocity != "kalman":
            raise ValueError(
                f"Sensing: kalman tuning given but velocity is {self.velocity!r}; set "
                "velocity='kalman' to use the Kalman filter, or leave kalman out")
        check_nonnegative(
            "Sensing", q1_resolution=self.q1_resolution, q2_resolution=self.q2_resolution,
            q1_noise=self.q1_noise, q2_noise=self.q2_noise, dac_range=self.dac_range,
        )
        if self.dac_bits < 0:
            raise ValueError(f"Sensing: dac_bits must be >= 0, got {self.dac_bits}")

    def measure(self, q: Array, resolution: Array, noise: Array) -> Array:
        """Sensed angle [rad]: add noise (already scaled), then quantise to ``resolution``."""
        q = q + noise
        safe = jnp.where(resolution > 0, resolution, 1.0)
        return jnp.where(resolution > 0, jnp.round(q / safe) * safe, q)

    def dac(self, tau: Array) -> Array:
        """Torque [N m] after the DAC: quantised to 2 dac_range / 2^dac_bits, clipped to the
        range."""
        if self.dac_bits == 0:
            return tau
        lsb = 2.0 * self.dac_range / (2**self.dac_bits)
        return jnp.clip(jnp.round(tau / lsb) * lsb, -self.dac_range, self.dac_range)


class StraightThrough(AbstractSensing):
    """``inner`` with straight-through gradients through its quantisers: the values are
    ``inner``'s, the derivative of ``measure`` is 1 and that of ``dac`` is 1 inside the DAC
    range and 0 where it clips. Rounding has zero derivative almost everywhere and would cut
    every feedback path out of a gradient through the loop; with this wrapper the
    quantisation error acts on the gradient like exogenous noise, which is what it is on the
    rig (used by ``jaxflex.tune``)."""

    inner: AbstractSensing

    @property
    def q1_resolution(self) -> Array:
        return self.inner.q1_resolution

    @property
    def q2_resolution(self) -> Array:
        return self.inner.q2_resolution

    @property
    def q1_noise(self) -> Array:
        return self.inner.q1_noise

    @property
    def q2_noise(self) -> Array:
        return self.inner.q2_noise

    @property
    def velocity(self) -> VelocitySource:
        return self.inner.velocity

    @property
    def kalman(self) -> KalmanTuning | None:
        return self.inner.kalman

    @property
    def dac_bits(self) -> int:
        return self.inner.dac_bits

    @property
    def dac_range(self) -> Array:
        return self.inner.dac_range

    def measure(self, q: Array, resolution: Array, noise: Array) -> Array:
        """``inner.measure`` with derivative 1 in ``q`` and ``noise``."""
        exact = q + noise
        return exact + jax.lax.stop_gradient(self.inner.measure(q, resolution, noise) - exact)

    def dac(self, tau: Array) -> Array:
        """``inner.dac`` with derivative 1 inside +-dac_range and 0 where it clips."""
        if self.dac_bits == 0:
            return self.inner.dac(tau)
        clipped = jnp.clip(tau, -self.dac_range, self.dac_range)
        return clipped + jax.lax.stop_gradient(self.inner.dac(tau) - clipped)
