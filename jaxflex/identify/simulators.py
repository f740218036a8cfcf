"""Replaying a log through a model (used by identification; no physics is restated here).

Two model structures, both built from a ``FlexibleJointPlant`` so that friction, inertias and
effects come from the core modules:

- ``"flexible"``: the full plant of eq. 3, advanced over each sample interval under the logged
  (zero-order-held) torque by ``jaxflex.simulate.plant_step``;
- ``"rigid"``: the rigid model of the paper's dynamic identification step (eq. 37-39),
  ``Jx x'' = u - F`` with ``Jx = I + J`` (rotor locked to the link, q2 = q1). It uses the same
  Strang splitting as ``plant_step``: exact LuGre bristle half-steps (``LuGre.step_z``) around an
  RK4 step of the mechanics with z frozen. Effects act through their link, rotor and input
  hooks; spring effects have no meaning here and are ignored.

Both are ``lax.scan`` loops, so forward-mode Jacobians (optimistix Levenberg-Marquardt's
default) work (SPEC section 9, second pitfall).
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxflex.plant import DiagonalInertia, FlexibleJointPlant, PlantState
from jaxflex.simulate import _rk4, plant_step

ModelKind = Literal["flexible", "rigid"]
MODEL_KINDS: tuple[str, ...] = ("flexible", "rigid")


def rigid_inertia(plant: FlexibleJointPlant) -> Float[Array, " n"]:
    """Jx = I + J [kg m^2] of the rigid model (eq. 37); needs decoupled links (eq. 40)."""
    if not isinstance(plant.links, DiagonalInertia):
        raise ValueError("rigid model: needs DiagonalInertia links (M = diag(I), eq. 40)")
    return plant.links.I + plant.J


def rigid_vector_field(plant: FlexibleJointPlant, x: PlantState, tau: Array) -> PlantState:
    """Time derivative of the rigid model Jx q1'' = u - F (eq. 37), z frozen (dz = 0).

    The rotor follows the link (q2 = q1, q2' = q1'); ``u`` is the applied torque after the
    plant's input effects plus effects' link and rotor torques.
    """
    u = plant.applied_torque(x, tau)
    u = u + sum((e.link_torque(x) for e in plant.effects), 0.0)
    u = u + sum((e.rotor_torque(x) for e in plant.effects), 0.0)
    acc = (u - plant.friction_torque(x)) / rigid_inertia(plant)
    daux = (
        None if x.aux is None
        else tuple(e.aux_rhs(a, tau, x) for e, a in zip(plant.effects, x.aux))
    )
    return PlantState(q1=x.dq1, dq1=acc, q2=x.dq1, dq2=acc, z=jnp.zeros_like(x.z), aux=daux)


def rigid_step(
    plant: FlexibleJointPlant, x: PlantState, tau: Array, h: float | Array, substeps: int
) -> PlantState:
    """Advance the rigid model (eq. 37) by ``h`` seconds under constant ``tau``: per substep an
    exact z half-step, RK4 of the mechanics, an exact z half-step (as ``plant_step``)."""
    hs = h / substeps
    fr = plant.friction

    def sub(xx, _):
        if fr is not None:
            xx = eqx.tree_at(lambda s: s.z, xx, fr.step_z(xx.dq1, xx.z, 0.5 * hs))
        xx = _rk4(lambda s: rigid_vector_field(plant, s, tau), xx, hs)
        if fr is not None:
            xx = eqx.tree_at(lambda s: s.z, xx, fr.step_z(xx.dq1, xx.z, 0.5 * hs))
        return xx, None

    x, _ = jax.lax.scan(sub, x, None, length=substeps)
    return x


def model_step(
    kind: ModelKind, plant: FlexibleJointPlant, x: PlantState, tau: Array, h: float | Array,
    substeps: int,
) -> PlantState:
    """One zero-order-hold interval of the chosen model structure."""
    if kind == "flexible":
        return plant_step(plant, x, tau, h, substeps)
    if kind == "rigid":
        return rigid_step(plant, x, tau, h, substeps)
    raise ValueError(f"model must be one of {MODEL_KINDS}, got {kind!r}")


def replay(
    kind: ModelKind, plant: FlexibleJointPlant, x0: PlantState, tau: Float[Array, "L n"],
    dt: float, substeps: int,
) -> tuple[PlantState, PlantState]:
    """Replay a torque sequence (held over each sample) from ``x0``.

    Returns (states at the L sample instants, before each step; state after the last step).
    """

    def body(x, u):
        return model_step(kind, plant, x, u, dt, substeps), x

    x_end, xs = jax.lax.scan(body, x0, tau)
    return xs, x_end
