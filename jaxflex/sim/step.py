"""One integration step of the plant, and the replay of a torque sequence through it.

This is the only place where the plant is integrated: the closed loop (``jaxflex.sim.simulate``),
the replay of identification and discovery (``jaxflex.fit``), the simulated rig
(``jaxflex.app.hardware``) and the data generators all call ``plant_step`` / ``replay``.

Plant integrator: Strang splitting per substep h, z-half-step / mechanics RK4 step /
z-half-step (the half-steps that meet between substeps taken as one step). The LuGre bristle
state z is advanced exactly with the link velocity frozen (eq. 5 is linear in z at fixed v,
``LuGre.step_z``), so the stiff rate sigma0 |v| / g(v) never limits the step (docs/spec.md
section 9); the mechanical part has no such stiffness. The scheme is second order in h;
``tests/test_simulate.py`` shows convergence to the diffrax reference ``plant_step_diffrax``.

Two model structures share that step (``ModelKind``):

- ``"flexible"``: the full plant of eq. 3 (``FlexibleJointPlant.vector_field``);
- ``"rigid"``: the rigid model of the paper's identification step (eq. 37-39),
  ``Jx q1'' = u - F`` with ``Jx = I + J`` (rotor locked to the link, q2 = q1). Effects act
  through their link, rotor and input hooks; spring effects have no meaning there.
- ``"rotor"``: the rotor subsystem alone, ``J q2'' + K (q2 - q1) - rotor effects = tau_a``
  (the rotor line of eq. 3), driven by the *measured* link motion: no model of the link side
  is needed (the paper's cascade idea applied to fitting). Its input per sample is
  an array (4, n): tau [N m], q1 [rad], q1' [rad/s], q1'' [rad/s^2] measured; within a sample
  q1 follows the measured velocity and acceleration. Friction on the motor side is the
  ``motor_friction`` effect (the plant's LuGre acts on the link and is not used); a link
  encoder's time skew and offset are the ``encoder_skew`` effect (its ``link_reading``,
  applied by ``jaxflex.core.effects.link_input``).
- ``"link"``: the link subsystem alone, ``M q1'' + C q1' + G + F(q1', z) - link effects =
  K (q2 - q1)`` (the link line of eq. 3 with eq. 4-6), driven by the *measured* rotor motion
  through the spring: no model of the motor, its friction or its torque constant is needed.
  Its input per sample is an array (3, n): q2 [rad], q2' [rad/s], q2'' [rad/s^2] measured
  (``LINK_INPUTS``); within a sample q2 follows the measured velocity and acceleration. The
  plant's LuGre acts here, as in the paper. Input-path effects (lag, delay) have no torque to
  act on and are not used.

All are ``lax.scan`` loops, so forward-mode Jacobians work (docs/spec.md section 9).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from jaxflex.core.effects import effect_torque, link_input, state_in_use
from jaxflex.core.plant import DiagonalInertia, FlexibleJointPlant
from jaxflex.core.state import PlantState

ModelKind = Literal["flexible", "rigid", "rotor", "link"]
MODEL_KINDS: tuple[str, ...] = ("flexible", "rigid", "rotor", "link")
#: Rows of the per-sample input of the "rotor" kind: tau, measured q1, q1', q1''.
ROTOR_INPUTS: tuple[str, ...] = ("tau", "q1", "dq1", "ddq1")
#: Rows of the per-sample input of the "link" kind: measured q2, q2', q2''.
LINK_INPUTS: tuple[str, ...] = ("q2", "dq2", "ddq2")

_tmap = jax.tree_util.tree_map


def rk4(f: Callable, x, h: float | Array, rolled: bool = False):
    """One classical Runge-Kutta step of x' = f(x) over ``h`` (x any pytree).

    ``rolled``: the four stages as a loop of four trips (one copy of ``f`` in the compiled
    program instead of four), with the same operations in the same order: the numbers agree
    to rounding (XLA fuses them differently: 8e-14 relative on the rotor velocity after
    2,000 steps of the paper's plant with an actuator lag). For large forward-mode programs
    under XLA's small-loop option: ``discover``'s Jacobian blocks carry the plant and every
    candidate effect per stage (``jaxflex.fit.Problem``'s ``rolled_stages``, with the
    measurements). Elsewhere the stages stay unrolled: XLA fuses across them, and without
    the small-loop option a loop pays a dispatch per kernel and trip."""
    if rolled:
        c = jnp.array([0.0, 0.5, 0.5, 1.0])
        w = jnp.array([1.0, 2.0, 2.0, 1.0])

        def stage(i, carry):
            k, acc = carry
            k = f(_tmap(lambda a, b: a + c[i] * h * b, x, k))
            return k, _tmap(lambda s, b: s + w[i] * b, acc, k)

        zero = _tmap(jnp.zeros_like, x)
        _, acc = jax.lax.fori_loop(0, 4, stage, (zero, zero))
        return _tmap(lambda a, s: a + h / 6.0 * s, x, acc)
    k1 = f(x)
    k2 = f(_tmap(lambda a, b: a + 0.5 * h * b, x, k1))
    k3 = f(_tmap(lambda a, b: a + 0.5 * h * b, x, k2))
    k4 = f(_tmap(lambda a, b: a + h * b, x, k3))
    return _tmap(lambda a, b, c, d, e: a + h / 6.0 * (b + 2 * c + 2 * d + e), x, k1, k2, k3, k4)


def rigid_inertia(plant: FlexibleJointPlant) -> Float[Array, " n"]:
    """Jx = I + J [kg m^2] of the rigid model (eq. 37); needs decoupled links (eq. 40)."""
    if not isinstance(plant.links, DiagonalInertia):
        raise ValueError("rigid model: needs DiagonalInertia links (M = diag(I), eq. 40)")
    return plant.links.I + plant.J


def rigid_vector_field(plant: FlexibleJointPlant, x: PlantState, tau: Array) -> PlantState:
    """Time derivative of the rigid model Jx q1'' = u - F (eq. 37) [rad/s^2].

    The rotor follows the link (q2 = q1, q2' = q1'); ``u`` [N m] is the applied torque after
    the plant's input effects plus the effects' link and rotor torques; z follows eq. 5.
    """
    u = plant.applied_torque(x, tau)
    u = u + effect_torque(plant.effects, "link_torque", x)
    u = u + effect_torque(plant.effects, "rotor_torque", x)
    acc = (u - plant.friction_torque(x)) / rigid_inertia(plant)
    dz = jnp.zeros_like(x.z) if plant.friction is None else plant.lugre.z_dot(x.dq1, x.z)
    daux = (
        None if x.aux is None
        else tuple(e.aux_rhs(a, tau, x) for e, a in zip(plant.effects, x.aux))
    )
    return PlantState(q1=x.dq1, dq1=acc, q2=x.dq1, dq2=acc, z=dz, aux=daux)


def rotor_vector_field(plant: FlexibleJointPlant, x: PlantState, u: Array) -> PlantState:
    """Time derivative of the rotor subsystem (module docstring) under the input ``u`` (4, n)
    (``ROTOR_INPUTS``): q2'' [rad/s^2] from the rotor line of eq. 3
    (``FlexibleJointPlant.accelerations``) with the link state ``x.q1``, ``x.dq1`` taken from
    the measurement; the link moves with the measured acceleration; z is frozen."""
    tau = u[0]
    _, ddq2 = plant.accelerations(x, tau)
    daux = (
        None if x.aux is None
        else tuple(e.aux_rhs(a, tau, x) for e, a in zip(plant.effects, x.aux))
    )
    return PlantState(q1=x.dq1, dq1=u[3], q2=x.dq2, dq2=ddq2, z=jnp.zeros_like(x.z), aux=daux)


def link_vector_field(plant: FlexibleJointPlant, x: PlantState, u: Array) -> PlantState:
    """Time derivative of the link subsystem (module docstring) under the input ``u`` (3, n)
    (``LINK_INPUTS``): q1'' [rad/s^2] from the link line of eq. 3
    (``FlexibleJointPlant.accelerations``) with the rotor state ``x.q2``, ``x.dq2`` taken from
    the measurement; the rotor moves with the measured acceleration; z follows eq. 5."""
    ddq1, _ = plant.accelerations(x, jnp.zeros_like(x.q1))
    dz = jnp.zeros_like(x.z) if plant.friction is None else plant.lugre.z_dot(x.dq1, x.z)
    daux = None if x.aux is None else tuple(jnp.zeros_like(a) for a in x.aux)
    return PlantState(q1=x.dq1, dq1=ddq1, q2=x.dq2, dq2=u[2], z=dz, aux=daux)


def _vector_field(kind: ModelKind, plant: FlexibleJointPlant) -> Callable:
    if kind == "flexible":
        return plant.vector_field
    if kind == "rigid":
        return lambda x, tau: rigid_vector_field(plant, x, tau)
    if kind == "rotor":
        return lambda x, u: rotor_vector_field(plant, x, u)
    if kind == "link":
        return lambda x, u: link_vector_field(plant, x, u)
    raise ValueError(f"model must be one of {MODEL_KINDS}, got {kind!r}")


def model_step(
    kind: ModelKind, plant: FlexibleJointPlant, x: PlantState, tau: Float[Array, " n"],
    h: float | Array, substeps: int, unroll: bool | int = False, rolled: bool = False,
) -> PlantState:
    """Advance the chosen model structure by ``h`` [s] under constant torque ``tau`` [N m].

    Strang splitting per substep: exact z half-step (velocity frozen), RK4 on the rest with z
    frozen, exact z half-step; the half-steps that meet between substeps are taken as one
    step. Without friction this is plain RK4. ``unroll``: unroll the substep loop (an int k:
    k substeps per trip of the loop, a static count only); on a CPU faster under ``vmap``
    (batched sweeps) when ``tau`` is cheap to compute, slower when it is not (XLA copies its
    computation into every unrolled substep; the sweep engine decides per controller:
    ``jaxflex.sweep.engine.loop_unrolls``) and for a single run. The numbers are the same either
    way. ``rolled``: the RK4 stages as a loop (``rk4``; the same to rounding).
    """
    f = _vector_field(kind, plant)
    hs = h / substeps
    fr = plant.lugre
    if kind == "rotor":  # the measured link motion sets the link state at each sample
        if tau.ndim != 2 or tau.shape[0] != len(ROTOR_INPUTS):
            raise ValueError(f"rotor model: input per sample must be {ROTOR_INPUTS} stacked "
                             f"as (4, n), got shape {tau.shape}")
        q1, dq1 = link_input(plant.effects, tau[1], tau[2], tau[3])
        x = eqx.tree_at(lambda s: (s.q1, s.dq1), x, (q1, dq1))
        fr = None  # the plant's LuGre acts on the link, which is not modelled here
    if kind == "link":  # the measured rotor motion sets the rotor state at each sample
        if tau.ndim != 2 or tau.shape[0] != len(LINK_INPUTS):
            raise ValueError(f"link model: input per sample must be {LINK_INPUTS} stacked "
                             f"as (3, n), got shape {tau.shape}")
        x = eqx.tree_at(lambda s: (s.q2, s.dq2), x, (tau[0], tau[1]))

    def mech(xx):
        d = f(xx, tau)
        return eqx.tree_at(lambda s: s.z, d, jnp.zeros_like(d.z))

    def z_step(xx, hz):
        return eqx.tree_at(lambda s: s.z, xx, fr.step_z(xx.dq1, xx.z, hz))

    # the loop carries the state as one flat array: a pytree of (n,)-arrays as the carry costs
    # a copy per leaf and a kernel per field each substep on a CPU
    flat, unravel = ravel_pytree(x)
    if fr is None:
        flat = _substeps(substeps, unroll, hs, flat, lambda hz, s: ravel_pytree(
            rk4(lambda xx: f(xx, tau), unravel(s), hs, rolled))[0])
        return unravel(flat)

    # Strang splitting with the half-steps of neighbouring substeps merged: z is advanced with
    # the velocity frozen, so the closing half-step of one substep and the opening half-step of
    # the next (same velocity, nothing in between) are one exact step of hs. The z steps are
    # hs/2, hs, ..., hs before each RK4 step and hs/2 after the last.
    flat = _substeps(substeps, unroll, hs, flat,
                     lambda hz, s: ravel_pytree(rk4(mech, z_step(unravel(s), hz), hs, rolled))[0])
    return z_step(unravel(flat), 0.5 * hs)


def _substeps(substeps: int | Array, unroll: bool | int, hs: float | Array, init: Array,
              body: Callable[[Array, Array], Array]) -> Array:
    """``body(hz, x)`` applied ``substeps`` times from ``init``, hz = hs / 2 [s] on the first
    trip and ``hs`` after. A Python int: a ``lax.scan`` of that length over the hz values
    (differentiable in reverse mode; ``unroll``: unrolled, or k per trip). A traced count (an integer
    array: the fitting engine's ``dynamic_substeps``, one compiled program for every level
    of refinement): a loop of that many trips (forward mode only)."""
    if isinstance(substeps, int):
        hz = jnp.full((substeps,), hs).at[0].multiply(0.5)
        return jax.lax.scan(lambda x, h: (body(h, x), None), init, hz, unroll=unroll)[0]
    return jax.lax.fori_loop(0, substeps,
                             lambda i, x: body(jnp.where(i == 0, 0.5 * hs, hs), x), init)


def plant_step(
    plant: FlexibleJointPlant, x: PlantState, tau: Float[Array, " n"], h: float | Array,
    substeps: int, unroll: bool | int = False,
) -> PlantState:
    """Advance the flexible plant (eq. 3-5) by ``h`` [s] under constant torque ``tau`` [N m]
    (the Strang-split step of the module docstring, ``substeps`` substeps; ``unroll`` as in
    ``model_step``)."""
    return model_step("flexible", plant, x, tau, h, substeps, unroll)


def rigid_step(
    plant: FlexibleJointPlant, x: PlantState, tau: Float[Array, " n"], h: float | Array,
    substeps: int,
) -> PlantState:
    """Advance the rigid model (eq. 37) by ``h`` [s] under constant ``tau`` [N m]."""
    return model_step("rigid", plant, x, tau, h, substeps)


def plant_step_diffrax(
    plant: FlexibleJointPlant, x: PlantState, tau: Float[Array, " n"], h: float,
    rtol: float = 1e-10, atol: float = 1e-12,
) -> PlantState:
    """Advance the plant by ``h`` [s] under constant ``tau`` [N m] with an adaptive stiff
    solver (diffrax Kvaerno5, PID step control); an accurate reference for ``plant_step``."""
    import diffrax  # here, not at the top: importing it takes 0.25 s of every command's start

    term = diffrax.ODETerm(lambda t, y, args: plant.vector_field(y, tau))
    sol = diffrax.diffeqsolve(
        term, diffrax.Kvaerno5(), 0.0, h, h / 10, x,
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=100_000,
    )
    return _tmap(lambda a: a[-1], sol.ys)


#: RK4 substeps per sample of ``warm_effects``: an input-path state with a time constant of
#: a sample or two (a Pade delay of 2 ms has poles at 1.7 / ms) needs them; one step per
#: sample left the delay's state wrong at every segment start (a torque transient that the
#: replay integrates into a drift).
WARM_SUBSTEPS: int = 16


def warm_effects(
    plant: FlexibleJointPlant, x0: PlantState, tau_pre: Float[Array, "W n"], dt: float,
    substeps: int = WARM_SUBSTEPS,
) -> PlantState:
    """``x0`` with the effects' internal states (actuator lag, delay, ...) brought into line
    with a torque history: they start in equilibrium with ``tau_pre[0]`` [N m]
    (``aux_steady``) and follow the held torque over the W samples of ``tau_pre`` (``substeps``
    RK4 steps per sample of period ``dt`` [s], the mechanical state frozen). Exact for
    input-path effects up to the RK4 error; a plant without effects is returned unchanged.
    States that cannot act are left at equilibrium without the W x ``substeps`` steps
    (``jaxflex.core.effects.state_in_use``: gated-off candidates of the discrepancy workflow,
    whose states then cost no integration)."""
    if not plant.effects:
        return x0
    aux0 = tuple(e.aux_steady(tau_pre[0]) for e in plant.effects)
    rhs = lambda a, u: tuple(e.aux_rhs(ai, u, x0) for e, ai in zip(plant.effects, a))
    h = dt / substeps

    def sample(a, u):
        a, _ = jax.lax.scan(lambda b, _: (rk4(lambda s: rhs(s, u), b, h), None), a, None,
                            length=substeps)
        return a, None

    def warm():
        return jax.lax.scan(sample, aux0, tau_pre)[0]

    in_use = state_in_use(plant.effects)
    if in_use is False:
        aux = aux0
    elif in_use is True:
        aux = warm()
    else:
        aux = jax.lax.cond(in_use, warm, lambda: aux0)
    return eqx.tree_at(lambda s: s.aux, x0, aux, is_leaf=lambda v: v is None)


def replay(
    kind: ModelKind, plant: FlexibleJointPlant, x0: PlantState, tau: Float[Array, "L n"],
    dt: float, substeps: int, unroll: bool = False, rolled: bool = False,
) -> tuple[PlantState, PlantState]:
    """Replay a torque sequence [N m] (held over each sample of ``dt`` s) from ``x0``
    (for the "rotor" and "link" kinds, ``tau`` is the (L, 4, n) or (L, 3, n) input of the
    module docstring).

    ``unroll``: unroll each sample's substep loop (``model_step``; faster where the replay runs
    batched, e.g. segments and Jacobian columns of the fitting engine); ``rolled``: the RK4
    stages as a loop (``rk4``).

    Returns (states at the L sample instants, before each step; state after the last step).
    """

    def body(x, u):
        return model_step(kind, plant, x, u, dt, substeps, unroll, rolled), x

    x_end, xs = jax.lax.scan(body, x0, tau)
    return xs, x_end
