"""The interface of an effect (``AbstractEffect``: its hooks, constraints, typical values and
its discovery and synthetic-log metadata, its family and order), what discovery offers it for
a first guess (``ResidualStart``) and the registry of effects by name (``EFFECTS``,
``register_effect``, ``family_orders``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, ClassVar, Literal, Protocol

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.core.state import PlantState

EFFECTS: dict[str, type[AbstractEffect]] = {}

#: The lower bound of a step-bounded time constant (``AbstractEffect.step_bounded``) as a
#: multiple of a replay's integration step h = dt / substeps: T >= STEP_FLOOR h. RK4 keeps the
#: delay's Pade poles (-3 +- j sqrt(3)) / T stable for T > 1.22 h and the lag's pole -1 / T
#: for T > 0.36 h; the classes' own bound, 1.5 ms, is this at 1 ms samples.
STEP_FLOOR: float = 1.5

#: The least amplitude [N m] a fitted amplitude starts from: a positive parameter is fitted
#: as exp(u), whose slope vanishes with the value.
LEAST_AMPLITUDE: float = 1e-3


class ResidualStart(Protocol):
    """What a discovery run offers an effect class for its first guess
    (``AbstractEffect.start_from_residual``): the replay's step, the model's nominal values
    and linear least-squares fits of a position ripple to the inverse-dynamics torque residual
    of the model the effect is added to (``jaxflex.discover.localisation`` implements it)."""

    @property
    def h(self) -> float:
        """The replay's integration step [s] (dt / substeps)."""
        ...

    def nominal(self, name: str) -> np.ndarray:
        """The model's nominal plant or friction parameter ``name`` (e.g. ``"K"``), per joint."""
        ...

    def angle(self, side: Literal["link", "rotor"]) -> np.ndarray:
        """The angle samples [rad] the ripple fits use: q1 for ``"link"``, q2 for ``"rotor"``."""
        ...

    def ripple_fits(self, side: Literal["link", "rotor"], grid: np.ndarray, step: float,
                    trend: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every spatial frequency N [1/rad] of the evenly spaced ``grid`` (spacing
        ``step``), the least-squares fit r ~ a_s sin(N q) + a_c cos(N q) of the ``side``'s
        torque residual r [N m] against its angle q, both cleared of what a refit of the
        nominal model absorbs anyway (with ``trend``, a term linear in q too): the explained
        sum of squares (-1 where the fit cannot be solved), a_s and a_c [N m]."""
        ...

    def column_fits(self, side: Literal["link", "rotor"],
                    columns: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    ) -> tuple[float, np.ndarray]:
        """The least-squares fit of the ``side``'s torque residual r [N m] by the columns
        ``columns(angle, velocity)`` (samples, k) of its angle [rad] and velocity [rad/s]
        (q1, q1' for ``"link"``, q2, q2' for ``"rotor"``), beside a constant, the deflection
        and the acceleration (what a refit of the nominal spring and inertia absorbs), on the
        link over its sliding samples only (as ``ripple_fits``): the sum of squares the
        columns explain beyond those (-1 where the fit cannot be solved) and their k
        coefficients (a missing torque T appears as r = T)."""
        ...

    def deflection(self) -> np.ndarray:
        """The spring deflection samples d = q2 - q1 [rad] of the residual's motion."""
        ...

    def deflection_fits(self, columns: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        ) -> tuple[float, np.ndarray]:
        """As ``column_fits`` on the link, the columns ``columns(d, d')`` (samples, k) of
        the deflection d [rad] and its rate d' [rad/s] (a missing spring torque T appears on
        the link as r = T; the nominal spring K d is cleared)."""
        ...


def candidate_effects() -> list[str]:
    """Names of the effects the discrepancy workflow tries by default (``candidate``)."""
    return sorted(k for k, c in EFFECTS.items() if c.candidate)


def family_orders(name: str, highest: int | None = None) -> list[str]:
    """The registered names of effect ``name``'s family from ``name`` up (``name`` first, then
    each ``higher`` in turn), at most up to order ``highest`` (None: every order)."""
    out = [name]
    while (nxt := EFFECTS[out[-1]].higher) is not None and (
            highest is None or EFFECTS[nxt].order <= highest):
        out.append(nxt)
    return out


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
    #: The quantity against which its residual signature is most telling (discover's report,
    #: ``telling_quantity``); None where none stands out.
    telling: ClassVar[str | None] = None
    #: Time constants [s] whose lower bound scales with a replay's integration step h:
    #: T >= ``STEP_FLOOR`` h (discover's workspace bounds them so; ``typical_at_step``).
    step_bounded: ClassVar[tuple[str, ...]] = ()
    #: Axis kinds a parameter file may declare (its ``axis``) on which the effect cannot act;
    #: discover does not try it there.
    cannot_act_on: ClassVar[tuple[str, ...]] = ()
    #: Ranges (low, high) of the moderate magnitudes a synthetic log draws (``draw``,
    #: ``jaxflex.identify.datagen``); None: the generator cannot hide this effect.
    moderate: ClassVar[dict[str, tuple[float, float]] | None] = None
    #: Parameters of ``moderate`` drawn with a random sign.
    signed: ClassVar[tuple[str, ...]] = ()
    #: An effect of the logging, not of the plant: a synthetic log applies it to its recorded
    #: link channel (``recorded_link``) and never simulates it.
    recording: ClassVar[bool] = False
    #: The family the effect is an order of, named by its order-1 member ("": the effect's
    #: own name). Discovery names the family and the order it needed (docs/spec.md
    #: section 8).
    family: ClassVar[str] = ""
    #: Its order in the family: 1 for the simplest member, k + 1 for the member that
    #: ``from_lower`` builds from a fitted order k.
    order: ClassVar[int] = 1
    #: The registered name of the family's next order (None: the highest order, or a family
    #: of one). Discovery fits it, started by its ``from_lower``, in place of this effect once
    #: this one is added, and keeps it when it pays by the criterion that adds an effect.
    higher: ClassVar[str | None] = None

    @classmethod
    def family_name(cls) -> str:
        """The name of the family the effect belongs to (``family``, else its ``name``)."""
        return cls.family or cls.name

    @classmethod
    def label(cls) -> str:
        """How discovery's answer names the effect: ``"<family> order <k>"`` for a family's
        order above 1, else its name (a family's order 1 is named as the family)."""
        return cls.name if cls.order == 1 else f"{cls.family_name()} order {cls.order}"

    @classmethod
    def from_lower(cls, lower: AbstractEffect, data: ResidualStart) -> AbstractEffect:
        """This order's first guess (one joint) from a fitted instance ``lower`` of the
        family's order below, warm-started from its values, the new parameters from the
        residual ``data`` of the model it is added to (``ResidualStart``).

        **Raises:** ``NotImplementedError`` for an effect that is no family's higher order."""
        raise NotImplementedError(f"effect {cls.name!r} is not a higher order of a family")

    @classmethod
    def typical(cls, n: int) -> AbstractEffect:
        """A small instance to start a fit from (all parameters within their constraints)."""
        raise NotImplementedError(f"effect {cls.name!r} has no typical() start")

    @classmethod
    def typical_at_step(cls, n: int, h: float) -> AbstractEffect:
        """``typical(n)`` with each ``step_bounded`` time constant at twice its bound at the
        integration step ``h`` [s], 2 ``STEP_FLOOR`` h (a start on the bound has a dead
        coordinate; a start far above a short delay does not reach it in a screen's few
        steps): 3 ms at 1 ms samples, 12 ms at 4 ms."""
        e = cls.typical(n)
        if not cls.step_bounded:
            return e
        return dataclasses.replace(e, **{  # type: ignore[type-var]
            p: np.full_like(np.asarray(getattr(e, p)), 2.0 * STEP_FLOOR * h)
            for p in cls.step_bounded})

    @classmethod
    def start_from_residual(cls, data: ResidualStart) -> AbstractEffect:
        """Discovery's first guess of this effect (one joint) added to a model, from that
        model's torque residual (``ResidualStart``). By default ``typical_at_step(1, h)`` with
        each ``tied:X`` parameter at the model's nominal X (a backlash on the model's own
        spring); an effect whose parameters a residual shows directly overrides it."""
        e = cls.typical_at_step(1, data.h)
        tied = {p: data.nominal(c.removeprefix("tied:")) for p, c in cls.constraints.items()
                if c.startswith("tied:")}
        return dataclasses.replace(e, **tied) if tied else e  # type: ignore[type-var]

    @classmethod
    def draw(cls, rng: np.random.Generator, scale: float = 1.0) -> dict[str, Any]:
        """Keyword arguments of a moderate instance for a synthetic log: each ``moderate``
        parameter uniform in its range times ``scale`` (with a random sign if ``signed``), each
        ``tied:X`` parameter None (the generator sets it from the true plant).

        **Raises:** ``ValueError`` for an effect without ``moderate`` ranges."""
        if cls.moderate is None:
            raise ValueError(f"effect {cls.name!r} has no moderate magnitudes to draw")
        kw: dict[str, Any] = {}
        for p, (lo, hi) in cls.moderate.items():
            v = scale * rng.uniform(lo, hi)
            if p in cls.signed:
                v *= rng.choice([-1.0, 1.0])
            kw[p] = v
        kw.update({p: None for p, c in cls.constraints.items() if c.startswith("tied:")})
        return kw

    @classmethod
    def recorded_link(cls, t: np.ndarray, q1: np.ndarray, kw: dict[str, Any]) -> np.ndarray:
        """A ``recording`` effect's link channel [rad] (N, n): what the recorder reads of the
        true link angle ``q1`` (N, n) sampled at ``t`` [s] (N,), with the effect's parameters
        ``kw``, before the encoder's noise and quantisation."""
        raise NotImplementedError(f"effect {cls.name!r} is not an effect of the recording")

    def link_torque(self, x: PlantState) -> Float[Array, " n"] | float:
        """Torque added to the link equation's right-hand side [N m]."""
        return 0.0

    def rotor_torque(self, x: PlantState) -> Float[Array, " n"] | float:
        """Torque added to the rotor equation's right-hand side [N m]."""
        return 0.0

    def spring_torque(self, d: Array, dd: Array) -> Float[Array, " n"] | float:
        """Extra elastic torque [N m] given deflection d = q2 - q1 [rad] and its rate dd."""
        return 0.0

    def friction_level(self, v: Array, friction: Any) -> Float[Array, " n"] | float:
        """Shift Delta(v) [N m] of the link friction's level g(v) (eq. 6) by the direction of
        the link velocity ``v`` [rad/s]: the LuGre of eq. 4-5 runs with g(v) + Delta(v) while
        the link moves forward and g(v) - Delta(v) backward (a direction-dependent friction;
        ``friction``: the plant's LuGre, whose parameters a shift may follow)."""
        return 0.0

    def spring_state_torque(self, aux: Any, d: Array, dd: Array) -> Float[Array, " n"] | float:
        """Extra elastic torque [N m] from the effect's internal state ``aux`` (a hysteresis in
        the spring) at deflection d = q2 - q1 [rad] and its rate dd [rad/s]; acts on both
        sides like ``spring_torque``."""
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
