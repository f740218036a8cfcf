"""How a plant composes its effects: every hook summed over the effects that define it
(``effect_torque``, ``spring_state_torque``, ``applied_torque``, ``link_input``,
``link_measurement``), effects behind a run-time gate (``Gated``) so that candidates share one
program, and which hooks change a replay (``REPLAY_HOOKS``, ``acts_on_replay``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
from jaxtyping import Array

from jaxflex.core.effects.base import EFFECTS, AbstractEffect
from jaxflex.core.state import PlantState


class Gated(AbstractEffect):
    """An effect switched by ``gate`` (0 or 1, an array so it is data, not structure): every
    hook's contribution times the gate, the applied torque tau + gate (inner(tau) - tau).

    A wrapper, not a registered effect: it lets one compiled model hold several candidate
    effects at once, inactive ones gated off, so the discrepancy workflow fits every candidate
    with one XLA compilation (``jaxflex.fit``). Its ``name`` and ``constraints`` are those of
    the wrapped effect."""

    inner: AbstractEffect
    gate: Array

    @property
    def name(self) -> str:  # type: ignore[override]
        return self.inner.name

    @property
    def constraints(self) -> dict[str, str]:  # type: ignore[override]
        return type(self.inner).constraints

    def _switched(self, on: Callable[[], Any], off: Callable[[], Any]) -> Any:
        # a gate that is data but not batched (the discrepancy workflow's) is a run-time
        # branch: an inactive effect costs nothing per substep (computed and masked, the
        # gated candidates would make a replay many times dearer); a batched gate
        # (vmap over models) falls back to computing both (lax.cond becomes a select)
        return jax.lax.cond(self.gate != 0, on, off)

    def _gated(self, name: str, *args: Any) -> Any:
        if not _overrides(self.inner, name):
            return 0.0  # the effect has no such hook
        hook = getattr(self.inner, name)
        out = jax.eval_shape(lambda: jnp.asarray(hook(*args)))
        return self._switched(lambda: self.gate * jnp.asarray(hook(*args)),
                              lambda: jnp.zeros(out.shape, out.dtype))

    def link_torque(self, x: PlantState):
        return self._gated("link_torque", x)

    def rotor_torque(self, x: PlantState):
        return self._gated("rotor_torque", x)

    def spring_torque(self, d: Array, dd: Array):
        return self._gated("spring_torque", d, dd)

    def spring_state_torque(self, aux: Any, d: Array, dd: Array):
        return self._gated("spring_state_torque", aux, d, dd)

    def friction_level(self, v: Array, friction: Any):
        return self._gated("friction_level", v, friction)

    def applied_torque(self, tau: Array, aux: Any):
        return self._switched(lambda: tau + self.gate * (self.inner.applied_torque(tau, aux) - tau),
                              lambda: jnp.asarray(tau))

    def link_measured(self, q1: Array, dq1: Array):
        if not _overrides(self.inner, "link_measured"):
            return q1
        return self._switched(
            lambda: q1 + self.gate * (self.inner.link_measured(q1, dq1) - q1),
            lambda: jnp.asarray(q1))

    def link_reading(self, q1: Array, dq1: Array, ddq1: Array):
        if not _overrides(self.inner, "link_reading"):
            return q1, dq1

        def on():
            a, v = self.inner.link_reading(q1, dq1, ddq1)
            return q1 + self.gate * (a - q1), dq1 + self.gate * (v - dq1)

        return self._switched(on, lambda: (jnp.asarray(q1), jnp.asarray(dq1)))

    def aux_init(self, n: int):
        return self.inner.aux_init(n)

    def aux_steady(self, tau: Array):
        return self.inner.aux_steady(tau)

    def aux_rhs(self, aux: Any, tau: Array, x: PlantState):
        # gated off, the state stays where it started (``warm_effects`` leaves it at
        # equilibrium too): the applied torque of an effect off does not read it
        return self._switched(lambda: self.inner.aux_rhs(aux, tau, x),
                              lambda: jax.tree_util.tree_map(jnp.zeros_like, aux))

    def params(self) -> dict[str, list[float]]:
        return self.inner.params()


def _class_overrides(cls: type[AbstractEffect], hook: str) -> bool:
    """Whether effect class ``cls`` defines its own ``hook`` (not ``AbstractEffect``'s)."""
    return getattr(cls, hook) is not getattr(AbstractEffect, hook)


def _overrides(effect: AbstractEffect, hook: str) -> bool:
    """Whether ``effect`` (unwrapped) contributes through ``hook``."""
    return _class_overrides(type(unwrap(effect)), hook)


#: The hooks through which an effect changes what a flexible-joint replay outputs (the replay
#: that ``jaxflex.discover`` fits): the motion, or the link encoder's reading of it
#: (``link_measured``); ``link_reading`` is not one (a sensor map of a measured *input*).
REPLAY_HOOKS: tuple[str, ...] = ("link_torque", "rotor_torque", "spring_torque",
                                 "spring_state_torque", "friction_level", "applied_torque",
                                 "aux_rhs", "link_measured")


def acts_on_replay(name: str) -> bool:
    """Whether the registered effect ``name`` changes a flexible replay's outputs (any of
    ``REPLAY_HOOKS``); an effect that does not has no derivative there, so the discrepancy
    workflow cannot test it. Raises ``KeyError`` for an unknown name."""
    return any(_class_overrides(EFFECTS[name], h) for h in REPLAY_HOOKS)


def link_input(effects: Sequence[AbstractEffect], q1: Array, dq1: Array, ddq1: Array
               ) -> tuple[Array, Array]:
    """The link angle [rad] and velocity [rad/s] the effects' input maps (``link_reading``,
    in order; gated ones too) make of a measured link motion ``q1``, ``dq1``, ``ddq1``
    [rad, rad/s, rad/s^2]; unchanged when no effect has such a map."""
    for e in effects:
        if _overrides(e, "link_reading"):
            q1, dq1 = e.link_reading(q1, dq1, ddq1)
    return q1, dq1


def link_measurement(effects: Sequence[AbstractEffect], q1: Array, dq1: Array) -> Array:
    """The logged link angle [rad] the effects' link-encoder maps (``link_measured``, in
    order) make of the replayed link angle ``q1`` [rad] and velocity ``dq1`` [rad/s]; ``q1``
    itself (no operation traced) when no effect has such a map."""
    for e in effects:
        if _overrides(e, "link_measured"):
            q1 = e.link_measured(q1, dq1)
    return q1


def uses_hook(effects: Sequence[AbstractEffect], hook: str) -> bool:
    """Whether any of ``effects`` (gated ones included) contributes through ``hook``."""
    return any(_overrides(e, hook) for e in effects)


def _one_branch(effects: Sequence[AbstractEffect], hook: str) -> bool:
    """Whether the ``hook`` contributions of ``effects`` are taken in one run-time branch:
    every effect that has the hook is ``Gated`` and there are at least two."""
    hooked = [e for e in effects if _overrides(e, hook)]
    return len(hooked) > 1 and all(isinstance(e, Gated) for e in hooked)


def _any_on(effects: Sequence[Gated]) -> Array:
    return jnp.any(jnp.stack([jnp.asarray(e.gate) != 0 for e in effects]))


def effect_torque(effects: Sequence[AbstractEffect], hook: str, *args: Any) -> Array | float:
    """The sum of the effects' ``hook`` contributions [N m] (``link_torque``, ``rotor_torque``,
    ``spring_torque`` or ``friction_level``, with that hook's arguments): what the plant adds
    to its equations.

    Gated effects (``Gated``, the discrepancy workflow's candidates) are taken together in
    one run-time branch, entered when any of them is on; inside it each contributes only
    when its own gate is on (``jnp.where``, so an inactive effect's value never enters). One
    branch per hook instead of one per effect: each branch is a kernel boundary in every
    evaluation, so one per hook keeps their count per substep small whatever the number of
    candidates. The numbers are those of the effects taken one by one (a test checks)."""
    if not _one_branch(effects, hook):
        return sum((getattr(e, hook)(*args) for e in effects), 0.0)
    # effects without the hook contribute nothing (AbstractEffect's default)
    gated = [e for e in effects if _overrides(e, hook)]

    def on():
        return sum(jnp.where(e.gate != 0, e.gate * jnp.asarray(getattr(e.inner, hook)(*args)),
                             0.0) for e in gated)

    out = jax.eval_shape(on)
    return jax.lax.cond(_any_on(gated), on, lambda: jnp.zeros(out.shape, out.dtype))


def spring_state_torque(effects: Sequence[AbstractEffect], aux: Sequence[Any] | None,
                        d: Array, dd: Array) -> Array | None:
    """The sum of the effects' ``spring_state_torque`` contributions [N m] from their internal
    states ``aux`` at deflection ``d`` [rad] and rate ``dd`` [rad/s]; None (no operation
    traced) when no effect has one or there are no states."""
    if aux is None:
        return None
    terms = [e.spring_state_torque(a, d, dd) for e, a in zip(effects, aux)
             if _overrides(e, "spring_state_torque")]
    return sum(terms[1:], terms[0]) if terms else None


def applied_torque(effects: Sequence[AbstractEffect], tau: Array, aux: Sequence[Any]) -> Array:
    """Motor torque [N m] reaching the rotor: ``tau`` through the effects' input paths in
    their order (``AbstractEffect.applied_torque``, ``aux``: their internal states). Gated
    input-path effects are taken in one run-time branch (``effect_torque``)."""
    if not _one_branch(effects, "applied_torque"):
        for e, a in zip(effects, aux):
            tau = e.applied_torque(tau, a)
        return tau
    gated = [e for e in effects if _overrides(e, "applied_torque")]

    def on():
        t = jnp.asarray(tau)
        for e, a in zip(effects, aux):
            if _overrides(e, "applied_torque"):
                t = jnp.where(e.gate != 0, t + e.gate * (e.inner.applied_torque(t, a) - t), t)
        return t

    return jax.lax.cond(_any_on(gated), on, lambda: jnp.asarray(tau, jax.eval_shape(on).dtype))


def state_in_use(effects: Sequence[AbstractEffect]) -> Array | bool:
    """Whether the effects' internal states (``aux``) can act on the plant: False when no
    effect has one, True when some effect with one is not ``Gated``, else a run-time flag,
    any gated effect with a state on (the discrepancy workflow's candidates:
    ``jaxflex.sim.step.warm_effects`` then skips the warm-up while the actuator lag and the delay
    are gated off)."""
    stateful = [e for e in effects if _overrides(e, "aux_rhs")]
    if not stateful:
        return False
    if not all(isinstance(e, Gated) for e in stateful):
        return True
    return _any_on(stateful)


def unwrap(effect: AbstractEffect) -> AbstractEffect:
    """The effect inside any wrappers (``Gated``)."""
    while isinstance(effect, Gated):
        effect = effect.inner
    return effect
