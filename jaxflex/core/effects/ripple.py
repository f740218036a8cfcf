"""The ripple family (docs/spec.md section 8): position-periodic torque ripple (cogging) on
the link (``cogging``) or on the rotor (``motor_cogging``), as a harmonic series whose order
grows in discovery (the fundamental, then the 2nd and 3rd harmonics: ``cogging_2``,
``cogging_3``, ``motor_cogging_2``, ``motor_cogging_3``).

``AbstractRipple`` evaluates the series of a class's order and holds its checks, starts,
draws and ``from_lower``; the family bases (``AbstractCogging``, ``AbstractMotorCogging``)
say the side and the hook; each order is a final class that declares its name, constraints
and fields. The orders above the first are not discovery candidates of their own
(``candidate = False``).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.effects.base import LEAST_AMPLITUDE, AbstractEffect, ResidualStart, register_effect
from jaxflex.core.state import PlantState
from jaxflex.core.validation import as_param, check_nonnegative, check_positive


#: A ripple start searches spatial frequencies from this many periods over the angle's travel:
#: a slower "ripple" is a smooth trend, not cogging.
RIPPLE_MIN_PERIODS: float = 2.0

#: The amplitudes [N m] of a ``typical`` ripple's harmonics 1, 2, 3.
TYPICAL_HARMONIC_A: tuple[float, ...] = (0.01, 0.005, 0.003)


def harmonic_fields(k: int) -> tuple[str, str]:
    """The fields (amplitude, phase) of a ripple's harmonic ``k``: ("A", "phi") for the
    fundamental, ("A<k>", "phi<k>") above it."""
    return ("A", "phi") if k == 1 else (f"A{k}", f"phi{k}")


class AbstractRipple(AbstractEffect):
    """Position-periodic torque ripple against one side's angle q (``side``: the link angle q1
    or the link-referred rotor angle q2): cogging, as the harmonic series of its ``order``,

        ripple(q) = sum_{k=1..order} A_k sin(k N q + phi_k)      [N m]

    with (A_1, phi_1) the fields ``A``, ``phi`` and (A_k, phi_k) the fields ``A<k>``,
    ``phi<k>`` above (``harmonic_fields``). The family bases say the side, the hook it acts
    through and the frequencies they start and draw; each order is a final class that
    declares its fields.

    A_k [N m] >= 0 amplitudes; N [1/rad] > 0 the fundamental's spatial frequency (not fitted
    by gradient, chosen from the residual's spectrum against q); phi_k [rad] phases.
    """

    side: eqx.AbstractClassVar[Literal["link", "rotor"]]
    typical_N: eqx.AbstractClassVar[float]
    """N [1/rad] of the ``typical`` start."""
    highest_N: eqx.AbstractClassVar[float]
    """The highest N [1/rad] a start from the residual searches."""
    drawn_N: eqx.AbstractClassVar[tuple[float, ...]]
    """The N [1/rad] a synthetic log draws from."""
    A: eqx.AbstractVar[Float[Array, " n"]]
    N: eqx.AbstractVar[Float[Array, " n"]]
    phi: eqx.AbstractVar[Float[Array, " n"]]

    def __check_init__(self) -> None:
        check_nonnegative(self.name, **{a: getattr(self, a) for a, _ in
                                        map(harmonic_fields, range(1, self.order + 1))})
        check_positive(self.name, N=self.N)

    @classmethod
    def typical(cls, n: int) -> AbstractRipple:
        """A ripple at ``typical_N`` with harmonic k of amplitude ``TYPICAL_HARMONIC_A[k - 1]``
        and phase 0."""
        kw = {"N": np.full(n, cls.typical_N)}
        for k in range(1, cls.order + 1):
            a, p = harmonic_fields(k)
            kw[a], kw[p] = np.full(n, TYPICAL_HARMONIC_A[k - 1]), np.zeros(n)
        return cls(**kw)

    @classmethod
    def start_from_residual(cls, data: ResidualStart) -> AbstractRipple:
        """A ripple of order 1 fitted to the ``side``'s residual against its angle by linear
        least squares over a grid of N [1/rad] (gradient cannot find a frequency): a coarse
        one from ``RIPPLE_MIN_PERIODS`` periods over the travel to ``highest_N``, then a fine
        one about its best. The residual is cleared of what a refit of the nominal model
        absorbs anyway (``ResidualStart.ripple_fits``), the Stribeck term included: a nominal
        refit can raise Fs to absorb a ripple, after which the raw residual peaks elsewhere.
        The typical start where the angle travels too little for the grid, or the grid
        explains nothing; a higher order (reached by ``from_lower``, not as a candidate)
        starts as ``AbstractEffect.start_from_residual``."""
        if cls.order > 1:
            return super().start_from_residual(data)  # type: ignore[return-value]
        q = data.angle(cls.side)
        lowest = max(5.0, 2.0 * math.pi * RIPPLE_MIN_PERIODS / max(float(np.ptp(q)), 1e-9))
        coarse = np.arange(lowest, cls.highest_N, 0.5)
        if not coarse.size:
            return cls.typical(1)
        expl, a_s, a_c = data.ripple_fits(cls.side, coarse, 0.5)
        j = int(np.argmax(expl))
        if not expl[j] > 0:
            return cls.typical(1)
        N, s_, c_ = float(coarse[j]), a_s[j], a_c[j]
        fine = N + np.arange(-0.5, 0.51, 0.02)
        e, fs, fc = data.ripple_fits(cls.side, fine, 0.02)
        k = int(np.argmax(e))
        if e[k] > expl[j]:
            N, s_, c_ = float(fine[k]), fs[k], fc[k]
        # the residual equals the missing torque A sin(N q + phi), on either side with its own sign
        A, phi = max(math.hypot(s_, c_), LEAST_AMPLITUDE), math.atan2(c_, s_)
        return cls(A=np.full(1, A), N=np.full(1, N), phi=np.full(1, phi))

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> AbstractRipple:
        """Order k from a fitted order k - 1 ``lower`` of the same family: its fundamental
        and harmonics as fitted, the new harmonic at k N from the joint linear fit of the
        sines and cosines of j N q, j = 1..k, and of a viscous and a Coulomb column, to the
        ``side``'s residual (``ResidualStart.column_fits``; fitted together, since over an
        angle that does not travel evenly the harmonics are not orthogonal; the residual
        equals the missing torque, A_k sin(k N q + phi_k) with phi_k = atan2(a_c, a_s)).

        **Raises:** ``NotImplementedError`` for the family's order 1; ``TypeError`` where
        ``lower`` is not the family's order k - 1."""
        k = cls.order
        if k == 1:
            return super().from_lower(lower, data)  # type: ignore[return-value]
        if type(lower).family_name() != cls.family_name() or type(lower).order != k - 1:
            raise TypeError(f"{cls.name}.from_lower: expected the {cls.family_name()} of order "
                            f"{k - 1}, got {type(lower).__name__}")
        N = float(np.ravel(lower.N)[0])  # type: ignore[attr-defined]

        def columns(q: np.ndarray, v: np.ndarray) -> np.ndarray:
            ripple = [f(j * N * q) for j in range(1, k + 1) for f in (np.sin, np.cos)]
            return np.column_stack([*ripple, v, np.tanh(v / 0.01)])

        e, c = data.column_fits(cls.side, columns)
        a_s, a_c = c[2 * k - 2], c[2 * k - 1]
        A, phi = (math.hypot(a_s, a_c), math.atan2(a_c, a_s)) if e > 0 else (0.0, 0.0)
        kw = {p: v for p, v in lower.__dict__.items() if eqx.is_array(v)}
        a, p = harmonic_fields(k)
        kw[a], kw[p] = np.full(1, max(A, LEAST_AMPLITUDE)), np.full(1, phi)
        return cls(**kw)

    @classmethod
    def draw(cls, rng: np.random.Generator, scale: float = 1.0) -> dict[str, Any]:
        """``AbstractEffect.draw`` plus N one of ``drawn_N`` [1/rad] and a uniform phase."""
        kw = super().draw(rng, scale)
        kw["N"] = float(rng.choice(list(cls.drawn_N)))
        kw["phi"] = rng.uniform(-math.pi, math.pi)
        return kw

    def harmonics(self) -> tuple[tuple[Array, Array], ...]:
        """((A_1, phi_1), ..., (A_order, phi_order)): each harmonic's amplitude [N m] and
        phase [rad]."""
        return tuple((getattr(self, a), getattr(self, p))
                     for a, p in map(harmonic_fields, range(1, self.order + 1)))

    def ripple(self, q: Array) -> Float[Array, " n"]:
        """sum_k A_k sin(k N q + phi_k) [N m] at the angle ``q`` [rad]."""
        (A, phi), *higher = self.harmonics()
        out = A * jnp.sin(self.N * q + phi)
        for k, (A, phi) in enumerate(higher, start=2):
            out = out + A * jnp.sin(k * self.N * q + phi)
        return out


class AbstractCogging(AbstractRipple):
    """The ``cogging`` family: a ripple on the link, link_torque = ripple(q1) [N m]
    (``AbstractRipple``; N started below 80 1/rad, drawn from 20, 30, 45 1/rad)."""

    where: ClassVar[str] = "link torque"
    telling: ClassVar[str | None] = "position"
    family: ClassVar[str] = "cogging"
    side: ClassVar[Literal["link", "rotor"]] = "link"
    typical_N: ClassVar[float] = 25.0
    highest_N: ClassVar[float] = 80.0
    drawn_N: ClassVar[tuple[float, ...]] = (20.0, 30.0, 45.0)

    def link_torque(self, x: PlantState) -> Float[Array, " n"]:
        return self.ripple(x.q1)


class AbstractMotorCogging(AbstractRipple):
    """The ``motor_cogging`` family: a ripple on the rotor (the motor's magnets),
    rotor_torque = ripple(q2) [N m], q2 the link-referred rotor angle (``AbstractRipple``;
    amplitudes link-referred; a motor with p cogging periods per revolution behind a 1:r gear
    has N = p r; N started below 400 1/rad, drawn from 60, 90, 150 1/rad)."""

    where: ClassVar[str] = "rotor torque"
    telling: ClassVar[str | None] = "rotor position"
    family: ClassVar[str] = "motor_cogging"
    side: ClassVar[Literal["link", "rotor"]] = "rotor"
    typical_N: ClassVar[float] = 60.0
    highest_N: ClassVar[float] = 400.0
    drawn_N: ClassVar[tuple[float, ...]] = (60.0, 90.0, 150.0)

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"]:
        return self.ripple(x.q2)


@register_effect
class Cogging(AbstractCogging):
    """Position-periodic torque ripple on the link: link_torque = A sin(N q1 + phi) [N m].

    A [N m] >= 0 amplitude; N [1/rad] > 0 spatial frequency (cycles per radian times 2 pi; not
    fitted by gradient, chosen from the residual's spectrum against position); phi [rad]
    phase.
    """

    name: ClassVar[str] = "cogging"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "fixed", "phi": "free"}
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"A": (0.03, 0.06)}
    higher: ClassVar[str | None] = "cogging_2"
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)


@register_effect
class MotorCogging(AbstractMotorCogging):
    """Position-periodic torque ripple on the rotor (the motor's magnets): rotor_torque =
    A sin(N q2 + phi) [N m], q2 the link-referred rotor angle.

    A [N m] >= 0 amplitude (link-referred); N [1/rad] > 0 spatial frequency in the rotor angle
    (not fitted by gradient, chosen from the rotor-side residual's spectrum against q2);
    phi [rad] phase.
    """

    name: ClassVar[str] = "motor_cogging"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "positive", "phi": "free"}
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = {"A": (0.02, 0.04)}
    higher: ClassVar[str | None] = "motor_cogging_2"
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)


@register_effect
class Cogging2(AbstractCogging):
    """``cogging`` of order 2: a link ripple and its 2nd harmonic, link_torque =
    A sin(N q1 + phi) + A2 sin(2 N q1 + phi2) [N m]. A, A2 [N m] >= 0; N [1/rad] > 0 (fixed,
    the fundamental of the order below); phi, phi2 [rad]."""

    name: ClassVar[str] = "cogging_2"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "fixed", "phi": "free",
                                             "A2": "positive", "phi2": "free"}
    candidate: ClassVar[bool] = False
    order: ClassVar[int] = 2
    higher: ClassVar[str | None] = "cogging_3"
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param)
    A2: Float[Array, " n"] = eqx.field(converter=as_param)
    phi2: Float[Array, " n"] = eqx.field(converter=as_param)


@register_effect
class Cogging3(AbstractCogging):
    """``cogging`` of order 3: ``cogging_2`` plus the 3rd harmonic A3 sin(3 N q1 + phi3)
    [N m] on the link. A3 [N m] >= 0, phi3 [rad]; the rest as ``cogging_2``."""

    name: ClassVar[str] = "cogging_3"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "fixed", "phi": "free",
                                             "A2": "positive", "phi2": "free",
                                             "A3": "positive", "phi3": "free"}
    candidate: ClassVar[bool] = False
    order: ClassVar[int] = 3
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param)
    A2: Float[Array, " n"] = eqx.field(converter=as_param)
    phi2: Float[Array, " n"] = eqx.field(converter=as_param)
    A3: Float[Array, " n"] = eqx.field(converter=as_param)
    phi3: Float[Array, " n"] = eqx.field(converter=as_param)


@register_effect
class MotorCogging2(AbstractMotorCogging):
    """``motor_cogging`` of order 2: a rotor ripple and its 2nd harmonic, rotor_torque =
    A sin(N q2 + phi) + A2 sin(2 N q2 + phi2) [N m], q2 the link-referred rotor angle.
    A, A2 [N m] >= 0; N [1/rad] > 0 (fitted, as in ``motor_cogging``); phi, phi2 [rad]."""

    name: ClassVar[str] = "motor_cogging_2"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "positive", "phi": "free",
                                             "A2": "positive", "phi2": "free"}
    candidate: ClassVar[bool] = False
    order: ClassVar[int] = 2
    higher: ClassVar[str | None] = "motor_cogging_3"
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param)
    A2: Float[Array, " n"] = eqx.field(converter=as_param)
    phi2: Float[Array, " n"] = eqx.field(converter=as_param)


@register_effect
class MotorCogging3(AbstractMotorCogging):
    """``motor_cogging`` of order 3: ``motor_cogging_2`` plus the 3rd harmonic
    A3 sin(3 N q2 + phi3) [N m] on the rotor. A3 [N m] >= 0, phi3 [rad]."""

    name: ClassVar[str] = "motor_cogging_3"
    constraints: ClassVar[dict[str, str]] = {"A": "positive", "N": "positive", "phi": "free",
                                             "A2": "positive", "phi2": "free",
                                             "A3": "positive", "phi3": "free"}
    candidate: ClassVar[bool] = False
    order: ClassVar[int] = 3
    A: Float[Array, " n"] = eqx.field(converter=as_param)
    N: Float[Array, " n"] = eqx.field(converter=as_param)
    phi: Float[Array, " n"] = eqx.field(converter=as_param)
    A2: Float[Array, " n"] = eqx.field(converter=as_param)
    phi2: Float[Array, " n"] = eqx.field(converter=as_param)
    A3: Float[Array, " n"] = eqx.field(converter=as_param)
    phi3: Float[Array, " n"] = eqx.field(converter=as_param)
