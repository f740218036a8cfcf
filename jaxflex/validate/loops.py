"""The controllers that ran during a log, as a parameter file declares them (its
``loop_controller`` section): the sampled laws (``PPLaw``, ``PDLaw``, ``CascadeLaw``, each a
``jaxflex.core.controller.AbstractControlLaw``), their file records (``LOOP_TYPES``:
``PPCascade``, ``PDLoop``, ``CascadeLoop``) and the one sampled-data loop that runs any of them around
``jaxflex.sim.step.model_step`` (``simulate_loop``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.controller import (
    GAIN_NAMES,
    Q2D_METHODS,
    AbstractControlLaw,
    CascadeController,
    CascadeGains,
    ControllerState,
    LawOutput,
    dirty_derivative,
    pd_torque,
)
from jaxflex.io.params import Params, ParamsError
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.state import PlantState
from jaxflex.sim.step import model_step
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.trajectory import HeldSamples, SampledReference
from jaxflex.core.validation import check_keys

#: Top-level parameter-file section declaring the controller that ran during a log.
LOOP_SECTION = "loop_controller"


def _numbers(d: Mapping[str, Any], kind: str, required: tuple[str, ...],
             optional: tuple[str, ...], others: tuple[str, ...] = (),
             nonnegative: tuple[str, ...] = ()) -> dict[str, float]:
    """Check a ``loop_controller`` section of type ``kind``: its keys among ``type``,
    ``required``, ``optional`` and ``others`` (checked by the caller), each of ``required``
    present, and each number of ``required`` and ``optional`` > 0 (>= 0 for ``nonnegative``);
    returns those numbers. Raises ``ParamsError`` naming the key."""
    if not isinstance(d, Mapping) or d.get("type") != kind:
        raise ParamsError(f"{LOOP_SECTION}: expected an object with \"type\": \"{kind}\", got {d!r}")
    check_keys(d, ("type", *required, *optional, *others), where=f"{LOOP_SECTION}: ",
               error=ParamsError)
    out = {}
    for k in (*required, *optional):
        if k not in d:
            if k in required:
                raise ParamsError(f"{LOOP_SECTION}.{k} is missing")
            continue
        v = d[k]
        ok = not isinstance(v, bool) and isinstance(v, (int, float)) and not math.isnan(v)
        if not ok or not (v >= 0 if k in nonnegative else v > 0):
            bound = ">= 0" if k in nonnegative else "> 0"
            raise ParamsError(f"{LOOP_SECTION}.{k}: expected a number {bound}, got {v!r}")
        out[k] = float(v)
    return out


class PPLaw(AbstractControlLaw):
    """``PPCascade``'s law (its docstring) with constants kp [1/s], kv [V s/m], gtau [N/V],
    vmax [V]; on the link position q1 toward the held reference samples ``r``, with the
    held disturbance ``d`` [V] added to its output; sample period dt [s]."""

    kp: Array
    kv: Array
    gtau: Array
    vmax: Array
    r: HeldSamples
    d: HeldSamples
    dt: float = eqx.field(static=True)

    def init(self, t0: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Array, Array]:
        """(last position, last filtered position) [m or rad], both the current position."""
        return q1, q1

    def step(self, state: Any, t: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Any, LawOutput]:
        """EMPS P/P cascade: the half-sum filter, the velocity P loop, the saturation in V."""
        q_prev, qf_prev = state
        r = self.r.at(t)
        qf = 0.5 * q1 + 0.5 * q_prev
        v = jnp.clip(self.kp * self.kv * (r - q1) - self.kv * (qf - qf_prev) / self.dt,
                     -self.vmax, self.vmax) + self.d.at(t)
        return (q1, qf), LawOutput.of_torque(self.gtau * v, e1=q1 - r)


class PDLaw(AbstractControlLaw):
    """``PDLoop``'s law: ``jaxflex.core.controller.pd_torque`` on the angle ``on`` ("q1" or "q2")
    toward the held reference samples ``r``, with its dirty derivative
    (``jaxflex.core.controller.dirty_derivative``, time constant velocity_tc [s]); kp [N m/rad],
    kd [N m s/rad], tau_max [N m]; the held disturbance ``d`` [N m] added; sample period
    dt [s]."""

    kp: Array
    kd: Array
    tau_max: Array
    velocity_tc: Array
    r: HeldSamples
    d: HeldSamples
    on: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    def init(self, t0: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Array, Array]:
        """(last angle [rad], velocity estimate [rad/s]): the current angle, at rest."""
        q = q1 if self.on == "q1" else q2
        return q, jnp.zeros_like(q)

    def step(self, state: Any, t: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Any, LawOutput]:
        """The PD torque toward the reference sample, plus the disturbance [N m]."""
        q = q1 if self.on == "q1" else q2
        q_prev, dq_prev = state
        r = self.r.at(t)
        dq = dirty_derivative(dq_prev, q, q_prev, self.velocity_tc, self.dt)
        tau = pd_torque(self.kp, self.kd, self.tau_max, r, q, dq) + self.d.at(t)
        return (q, dq), LawOutput.of_torque(tau, e1=q1 - r)


class CascadeLaw(AbstractControlLaw):
    """``CascadeLoop``'s law: jaxflex's ``CascadeController`` (its reference a
    ``jaxflex.core.trajectory.SampledReference`` of the logged q1d) with velocities by its own
    filtered differentiation of the angles, plus the held disturbance ``d`` [N m]."""

    controller: CascadeController
    d: HeldSamples

    def init(self, t0: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> ControllerState:
        """``CascadeController.init`` at the angles, at rest."""
        return self.controller.init(t0, q1, q2)

    def step(self, state: Any, t: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Any, LawOutput]:
        """``CascadeController.step`` (saturated at its tau_max), plus the disturbance."""
        state, out = self.controller.step(state, t, q1, q2)
        return state, eqx.tree_at(lambda o: o.tau, out, out.tau + self.d.at(t))


def _held(x: Float[Array, "N n"] | None, like: Float[Array, "N n"], dt: float) -> HeldSamples:
    """A disturbance ``x`` (zeros shaped as ``like`` when None) as held samples of period
    ``dt`` [s]."""
    return HeldSamples(samples=jnp.zeros_like(like) if x is None else x, dt=dt)


@dataclasses.dataclass(frozen=True)
class PPCascade:
    """The EMPS benchmark controller (Janot et al. 2019): P position / P velocity cascade.

        qf(k) = 0.5 q(k) + 0.5 q(k-1),  qf'(k) = (qf(k) - qf(k-1)) / dt
        v(k) = clip(kp kv (r(k) - q(k)) - kv qf'(k), -vmax, vmax) + d(k)       [V]
        tau(k) = gtau v(k)                                                      [N or N m]

    kp [1/s], kv [V s/m or V s/rad], gtau [N/V], vmax [V]; d: a disturbance in volts (the
    EMPS pulses enter here). Declared in a parameter file as
    ``"loop_controller": {"type": "pp_cascade", "kp": ..., "kv": ..., "gtau": ..., "vmax": 10}``.
    """

    kp: float
    kv: float
    gtau: float
    vmax: float = 10.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PPCascade:
        """Validate a ``loop_controller`` section; raises ``ParamsError`` naming the key."""
        return cls(**_numbers(d, "pp_cascade", ("kp", "kv", "gtau"), ("vmax",)))

    def to_dict(self) -> dict[str, Any]:
        """The ``loop_controller`` section."""
        return {"type": "pp_cascade", **dataclasses.asdict(self)}

    def constants(self) -> jax.Array:
        """[kp, kv, gtau, vmax] as the simulated loop takes them."""
        return jnp.asarray([self.kp, self.kv, self.gtau, self.vmax], float)

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float,
            disturbance: Float[Array, "N n"] | None = None) -> PPLaw:
        """The sampled law for a loop of period ``dt`` [s] following the samples ``q_ref``
        [m or rad] (N, n), ``disturbance`` [V] (N, n) added to its output (none when None);
        ``params`` unused."""
        kp, kv, gtau, vmax = self.constants()
        return PPLaw(kp=kp, kv=kv, gtau=gtau, vmax=vmax, r=HeldSamples(samples=q_ref, dt=dt),
                     d=_held(disturbance, q_ref, dt), dt=float(dt))


@dataclasses.dataclass(frozen=True)
class PDLoop:
    """A PD loop toward the link reference on one measured angle (the rotor's, as
    ``jaxflex.identify.datagen.RotorPD``, or the link's):

        q'(k) = (tc q'(k-1) + q(k) - q(k-1)) / (tc + dt)        (tc = 0: backward difference)
        tau(k) = clip(kp (q1d(k) - q(k)) - kd q'(k), -tau_max, tau_max) + d(k)   [N m]

    kp [N m/rad], kd [N m s/rad], on: "q2" (rotor angle, default) or "q1" (link angle),
    tau_max [N m] (default: no saturation), velocity_tc [s] (default 0); d a disturbance in
    N m. Declared as ``"loop_controller": {"type": "pd", "kp": 8, "kd": 0.4, "on": "q2",
    "tau_max": 2, "velocity_tc": 0.005}``. A rigid model has q2 = q1.
    """

    kp: float
    kd: float
    on: str = "q2"
    tau_max: float = math.inf
    velocity_tc: float = 0.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> PDLoop:
        """Validate a ``loop_controller`` section; raises ``ParamsError`` naming the key."""
        out: dict[str, Any] = _numbers(d, "pd", ("kp", "kd"), ("tau_max", "velocity_tc"),
                                       ("on",), nonnegative=("velocity_tc",))
        if "on" in d:
            if d["on"] not in ("q1", "q2"):
                raise ParamsError(f"{LOOP_SECTION}.on: expected \"q1\" or \"q2\", got {d['on']!r}")
            out["on"] = d["on"]
        return cls(**out)

    def to_dict(self) -> dict[str, Any]:
        """The ``loop_controller`` section (an unsaturated loop without ``tau_max``)."""
        d = {"type": "pd", **dataclasses.asdict(self)}
        if math.isinf(self.tau_max):
            del d["tau_max"]
        return d

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float,
            disturbance: Float[Array, "N n"] | None = None) -> PDLaw:
        """The sampled law for a loop of period ``dt`` [s] following the samples ``q_ref``
        [rad] (N, n), ``disturbance`` [N m] (N, n) added to its output (none when None);
        ``params`` unused."""
        c = jnp.asarray([self.kp, self.kd, self.tau_max, self.velocity_tc], float)
        return PDLaw(kp=c[0], kd=c[1], tau_max=c[2], velocity_tc=c[3],
                     r=HeldSamples(samples=q_ref, dt=dt), d=_held(disturbance, q_ref, dt),
                     on=self.on, dt=float(dt))


#: Keys of a ``{"type": "cascade"}`` section besides the numbers.
_CASCADE_OTHERS: tuple[str, ...] = ("gains", "model", "q2d_method", "compensation")


@dataclasses.dataclass(frozen=True)
class CascadeLoop:
    """jaxflex's own cascade (``jaxflex.core.controller.CascadeController``, paper eq. 9-22) as
    the loop that ran, sampled at the log's period, following the logged q1d (interpolated
    by ``jaxflex.core.trajectory.SampledReference`` for the reference's derivatives).

    Declared as ``"loop_controller": {"type": "cascade"}`` with optional keys: ``gains``
    (a ``gains`` section, docs/spec.md section 7; default the parameter file's own),
    ``model`` (``{"plant": {...}, "friction": {...}}``: the controller's nominal model;
    default the parameter file's plant and friction, without effects), ``q2d_method`` and
    ``compensation`` (default the file's ``controller`` section, else "model" and true),
    ``tau_max`` [N m] (default the ``controller`` section's, else none), ``velocity_tc`` and
    ``derivative_tc`` [s] (the controller's filter time constants, default 0.002).
    """

    gains: Mapping[str, Any] | None = None
    model: Mapping[str, Any] | None = None
    q2d_method: str | None = None
    compensation: bool | None = None
    tau_max: float | None = None
    velocity_tc: float = 0.002
    derivative_tc: float = 0.002

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CascadeLoop:
        """Validate a ``loop_controller`` section; raises ``ParamsError`` naming the key."""
        out: dict[str, Any] = _numbers(d, "cascade", (), ("tau_max", "velocity_tc", "derivative_tc"),
                                       _CASCADE_OTHERS, nonnegative=("velocity_tc", "derivative_tc"))
        if "gains" in d:
            g = d["gains"]
            if not isinstance(g, Mapping):
                raise ParamsError(f"{LOOP_SECTION}.gains: expected an object, got {g!r}")
            check_keys(g, (*GAIN_NAMES, "leak"), where=f"{LOOP_SECTION}.gains: ",
                       error=ParamsError)
            try:
                CascadeGains(**g)
            except (TypeError, ValueError) as e:
                raise ParamsError(f"{LOOP_SECTION}.gains: {e}") from None
            out["gains"] = dict(g)
        if "model" in d:
            m = d["model"]
            if not isinstance(m, Mapping) or "plant" not in m:
                raise ParamsError(f"{LOOP_SECTION}.model: expected {{\"plant\": {{...}}, "
                                  f"\"friction\": {{...}}}}, got {m!r}")
            check_keys(m, ("plant", "friction"), where=f"{LOOP_SECTION}.model: ",
                       error=ParamsError)
            try:
                Params.from_dict(dict(m))
            except ValueError as e:
                raise ParamsError(f"{LOOP_SECTION}.model: {e}") from None
            out["model"] = dict(m)
        if "q2d_method" in d:
            if d["q2d_method"] not in Q2D_METHODS:
                raise ParamsError(f"{LOOP_SECTION}.q2d_method: expected one of "
                                  f"{list(Q2D_METHODS)}, got {d['q2d_method']!r}")
            out["q2d_method"] = d["q2d_method"]
        if "compensation" in d:
            if not isinstance(d["compensation"], bool):
                raise ParamsError(f"{LOOP_SECTION}.compensation: expected true or false, got "
                                  f"{d['compensation']!r}")
            out["compensation"] = d["compensation"]
        return cls(**out)

    def to_dict(self) -> dict[str, Any]:
        """The ``loop_controller`` section (entries left to their defaults are omitted)."""
        d = {k: v for k, v in dataclasses.asdict(self).items() if v is not None}
        return {"type": "cascade", **d}

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float,
            disturbance: Float[Array, "N n"] | None = None) -> CascadeLaw:
        """The sampled law for a loop of period ``dt`` [s] following the samples ``q_ref``
        [rad] (N, n), with the gains and nominal model of the class docstring,
        ``disturbance`` [N m] (N, n) added to its output (none when None). Raises
        ``ValueError`` when no gains are declared here or in the parameter file."""
        cfg = params.controller
        if self.gains is not None:
            gains = CascadeGains(**self.gains)
        elif params.gains is not None:
            gains = params.to_gains()
        else:
            raise ValueError(f"{LOOP_SECTION}: the cascade needs gains (its 'gains' key or the "
                             "parameter file's 'gains' section)")
        model = (params if self.model is None else Params.from_dict(dict(self.model)))
        pick = lambda mine, field, default: (
            mine if mine is not None
            else getattr(cfg, field) if cfg is not None and getattr(cfg, field) is not None
            else default)
        controller = CascadeController(
            model=model.to_plant(with_effects=False), gains=gains,
            trajectory=SampledReference(samples=q_ref, dt=float(dt)),
            compensation=pick(self.compensation, "compensation", True),
            q2d_method=pick(self.q2d_method, "q2d_method", "model"), dt=float(dt),
            velocity_tc=self.velocity_tc, derivative_tc=self.derivative_tc,
            tau_max=pick(self.tau_max, "tau_max", math.inf))
        return CascadeLaw(controller=controller, d=_held(disturbance, q_ref, dt))


DeclaredLoop = PPCascade | PDLoop | CascadeLoop
#: ``loop_controller`` types -> the class that reads the section.
LOOP_TYPES: dict[str, type[PPCascade] | type[PDLoop] | type[CascadeLoop]] = {
    "pp_cascade": PPCascade, "pd": PDLoop, "cascade": CascadeLoop}


def loop_controller(params: Params) -> DeclaredLoop | None:
    """The controller a parameter file declares for its logs (None if none): the class of
    ``LOOP_TYPES`` its ``loop_controller`` section's "type" names. Raises ``ParamsError`` for
    an unknown type (listing the known ones) or a bad section."""
    d = params.extra.get(LOOP_SECTION)
    if d is None:
        return None
    kind = d.get("type") if isinstance(d, Mapping) else None
    if kind not in LOOP_TYPES:
        raise ParamsError(f"{LOOP_SECTION}.type: unknown loop {kind!r}; known types: "
                          f"{list(LOOP_TYPES)}")
    return LOOP_TYPES[kind].from_dict(d)


def need_float64(what: str) -> None:
    """Refuse to run ``what`` in float32 (the closed loop and the replays are ill-conditioned
    there).

    **Arguments:**

    - `what`: the function's name, for the message.

    **Raises:**

    ``ValueError`` when ``jax_enable_x64`` is off.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(f"{what} needs float64: call jax.config.update('jax_enable_x64', True) "
                         "first (the jaxflex command does)")


@persistent_jit
def sampled_loop(plant: FlexibleJointPlant, kind: str, law: AbstractControlLaw, x0: PlantState,
                 dt: float, substeps: int, n_samples: int) -> tuple[jax.Array, jax.Array]:
    """The sampled-data loop of a control law around the model ``kind``: at t_k = k dt
    (k < ``n_samples``) the law reads the plant's angles and its torque is held over the
    sample while ``jaxflex.sim.step.model_step`` advances the plant in ``substeps`` steps.
    Returns (q1 before each step, torque), each (N, n)."""
    def body(carry, t):
        x, c = carry
        c, out = law.step(c, t, x.q1, x.q2)
        return (model_step(kind, plant, x, out.tau, dt, substeps), c), (x.q1, out.tau)

    ts = jnp.arange(n_samples) * dt
    c0 = law.init(ts[0], x0.q1, x0.q2)
    _, (q, tau) = jax.lax.scan(body, (x0, c0), ts)
    return q, tau


def simulate_loop(
    params: Params, ctrl: DeclaredLoop, q_ref: np.ndarray, dt: float, *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed loop of a declared controller ``ctrl`` (``loop_controller``) around the model of
    ``params`` (one joint, ``kind`` "rigid" or "flexible") following ``q_ref`` [rad or m],
    sample period ``dt`` [s], ``disturbance`` added to the controller output (V for the P/P
    cascade, N m for the others); the plant starts at rest at q_ref[0] and is advanced by
    ``jaxflex.sim.step.model_step`` in ``substeps`` substeps. Returns (position (N,), torque (N,)
    [N m or N]) at the sample instants (position before each step)."""
    need_float64("simulate_loop")
    check_loop_kind(kind)
    plant = params.to_plant()
    if plant.n != 1:
        raise ValueError(f"closed loop: the declared loop drives one joint, parameters have "
                         f"{plant.n}")
    r = jnp.asarray(q_ref, float).reshape(-1, 1)
    d = None if disturbance is None else jnp.asarray(disturbance, float).reshape(-1, 1)
    law = ctrl.law(params, r, float(dt), d)
    q, tau = sampled_loop(plant, kind, law, loop_start(plant, r[0]), float(dt), int(substeps),
                          r.shape[0])
    return np.asarray(q[:, 0]), np.asarray(tau[:, 0])


def simulate_pp_cascade(
    params: Params, ctrl: PPCascade, q_ref: np.ndarray, dt: float, *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """``simulate_loop`` for the EMPS P/P cascade (``disturbance`` [V]); kept for callers of
    the P/P-only interface."""
    return simulate_loop(params, ctrl, q_ref, dt, kind=kind, disturbance=disturbance,
                         substeps=substeps)


def check_loop_kind(kind: str) -> None:
    """Refuse a model kind a declared loop cannot run around (only "rigid" or "flexible").

    **Arguments:**

    - `kind`: the model kind.

    **Raises:**

    ``ValueError`` for another kind.
    """
    if kind not in ("rigid", "flexible"):
        raise ValueError(f"closed loop: model must be 'rigid' or 'flexible', got {kind!r}")


def loop_start(plant: FlexibleJointPlant, q0: jax.Array) -> PlantState:
    """The plant at rest at ``q0`` [rad or m] with the bristles in their steady state."""
    x0 = plant.init_state(q1=q0)
    if plant.friction is not None:
        x0 = eqx.tree_at(lambda s: s.z, x0, plant.lugre.z_steady(x0.dq1))
    return x0

