"""Validation of a parameter set on measured logs: a workflow on the engine.

Per log, three numbers (each from the one implementation of its equation), each beside its
**noise floor**: what the log's measurement noise alone gives a perfect model, so that an error
at its floor says "as good as this log can tell", not "97% wrong":

- **segment replay gap** (open loop): the log cut into segments, each replayed under the
  logged torque from its measured start (``jaxflex.fit.Problem`` with ``free_starts=False``,
  ``jaxflex.fit.gap``): 0 is perfect, 1 as bad as predicting no motion (floor:
  ``segment_gap_floor``);
- **torque prediction error** from the measured motion, ``100 ||tau - tau_hat|| / ||tau||``
  [%], with ``tau_hat`` from the inverse dynamics ``FlexibleJointPlant.torque_residuals``
  (velocities and accelerations by Savitzky-Golay, ``jaxflex.fit.savgol``; LuGre z at its
  steady state, eq. 35): rigid model ``tau_hat = tau + r_link + r_rotor`` with q2 = q1;
  flexible and rotor models ``tau_hat = tau + r_rotor`` (the rotor line of eq. 3 with the
  measured q1 and q2; for "rotor" the link reading passes the ``encoder_skew`` effect);
  (floor: ``torque_noise_floor``, the measurement noise and the torque content faster than
  the measured motion resolves);
- **closed-loop simulation error** in the benchmark metric ``100 ||y - y_sim|| / ||y||`` [%]
  for position, velocity and torque, when the parameters declare the controller that ran
  (the parameter file's top-level ``loop_controller`` section, ``LOOP_TYPES``: ``PPCascade``,
  the EMPS P position / P velocity cascade; ``PDLoop``, a PD on the rotor or link angle;
  ``CascadeLoop``, jaxflex's own cascade) and the log has a reference ``q1d``. Every declared
  loop is a ``SampledLaw`` run by one sampled-data scan around ``jaxflex.step.model_step``
  (rigid or flexible model), the log's q1d sampled as the reference (floors:
  ``closed_loop_noise_floor``).

Beside them, the segment replay's residual analysis as MATLAB's ``resid`` gives it
(``replay_residual_analysis``: autocorrelation and torque cross-correlation with 99% bands,
Ljung-Box whiteness).

Returns plain dicts; figures and files are written by ``jaxflex.cli.validate``.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxflex.controller import (
    GAIN_NAMES, Q2D_METHODS, CascadeController, CascadeGains, ControllerState, dirty_derivative,
    pd_torque,
)
from jaxflex.effects import link_input
from jaxflex.fit import (ParamSpace, Problem, gap, make_segments, noise_level, output_columns,
                         savgol, savgol_coeffs, simulated_outputs)
from jaxflex.fit.residual_analysis import CONFIDENCE, analyse_segments
from jaxflex.logs import Log
from jaxflex.params import Params, ParamsError
from jaxflex.plant import FlexibleJointPlant
from jaxflex.state import PlantState
from jaxflex.step import MODEL_KINDS, model_step
from jaxflex.tracecache import persistent_jit
from jaxflex.trajectory import SampledReference
from jaxflex.validation import check_keys

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


class SampledLaw(eqx.Module):
    """A declared loop's controller at the sample instants, as ``_sampled_loop`` runs it:
    ``init(t0, q1, q2)`` gives its state at the first sample, ``step(state, t, r, q1, q2, d)``
    its next state and the torque [N m or N] applied over the sample, from the time t [s],
    the reference sample r, the plant's angles q1, q2 [rad or m] (each (n,)) and the
    disturbance d added to the controller output (in the controller's output unit)."""

    @abc.abstractmethod
    def init(self, t0: Array, q1: Array, q2: Array) -> Any:
        """The controller state at the first sample."""

    @abc.abstractmethod
    def step(self, state: Any, t: Array, r: Array, q1: Array, q2: Array,
             d: Array) -> tuple[Any, Array]:
        """One sample: (next state, applied torque)."""


class PPLaw(SampledLaw):
    """``PPCascade``'s law (its docstring) with constants kp [1/s], kv [V s/m], gtau [N/V],
    vmax [V]; on the link position q1; sample period dt [s]."""

    kp: Array
    kv: Array
    gtau: Array
    vmax: Array
    dt: float = eqx.field(static=True)

    def init(self, t0: Array, q1: Array, q2: Array) -> tuple[Array, Array]:
        """(last position, last filtered position) [m or rad], both the current position."""
        return q1, q1

    def step(self, state: Any, t: Array, r: Array, q1: Array, q2: Array,
             d: Array) -> tuple[Any, Array]:
        """EMPS P/P cascade: the half-sum filter, the velocity P loop, the saturation in V."""
        q_prev, qf_prev = state
        qf = 0.5 * q1 + 0.5 * q_prev
        v = jnp.clip(self.kp * self.kv * (r - q1) - self.kv * (qf - qf_prev) / self.dt,
                     -self.vmax, self.vmax) + d
        return (q1, qf), self.gtau * v


class PDLaw(SampledLaw):
    """``PDLoop``'s law: ``jaxflex.controller.pd_torque`` on the angle ``on`` ("q1" or "q2")
    with its dirty derivative (``jaxflex.controller.dirty_derivative``, time constant
    velocity_tc [s]); kp [N m/rad], kd [N m s/rad], tau_max [N m]; sample period dt [s]."""

    kp: Array
    kd: Array
    tau_max: Array
    velocity_tc: Array
    on: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)

    def init(self, t0: Array, q1: Array, q2: Array) -> tuple[Array, Array]:
        """(last angle [rad], velocity estimate [rad/s]): the current angle, at rest."""
        q = q1 if self.on == "q1" else q2
        return q, jnp.zeros_like(q)

    def step(self, state: Any, t: Array, r: Array, q1: Array, q2: Array,
             d: Array) -> tuple[Any, Array]:
        """The PD torque toward the reference sample, plus the disturbance [N m]."""
        q = q1 if self.on == "q1" else q2
        q_prev, dq_prev = state
        dq = dirty_derivative(dq_prev, q, q_prev, self.velocity_tc, self.dt)
        return (q, dq), pd_torque(self.kp, self.kd, self.tau_max, r, q, dq) + d


class CascadeLaw(SampledLaw):
    """``CascadeLoop``'s law: jaxflex's ``CascadeController`` (its reference a
    ``jaxflex.trajectory.SampledReference`` of the logged q1d, so r is not read here) with
    velocities by its own filtered differentiation of the angles; plus the disturbance [N m]."""

    controller: CascadeController

    def init(self, t0: Array, q1: Array, q2: Array) -> ControllerState:
        """``CascadeController.init`` at the angles, at rest."""
        return self.controller.init(t0, q1, q2)

    def step(self, state: Any, t: Array, r: Array, q1: Array, q2: Array,
             d: Array) -> tuple[Any, Array]:
        """``CascadeController.step`` (saturated at its tau_max), plus the disturbance."""
        state, out = self.controller.step(state, t, q1, q2)
        return state, out.tau + d


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

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float) -> PPLaw:
        """The sampled law for a loop of period ``dt`` [s] (``params``, ``q_ref`` unused)."""
        kp, kv, gtau, vmax = self.constants()
        return PPLaw(kp=kp, kv=kv, gtau=gtau, vmax=vmax, dt=float(dt))


@dataclasses.dataclass(frozen=True)
class PDLoop:
    """A PD loop toward the link reference on one measured angle (the rotor's, as
    ``jaxflex.datagen.RotorPD``, or the link's):

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

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float) -> PDLaw:
        """The sampled law for a loop of period ``dt`` [s] (``params``, ``q_ref`` unused)."""
        c = jnp.asarray([self.kp, self.kd, self.tau_max, self.velocity_tc], float)
        return PDLaw(kp=c[0], kd=c[1], tau_max=c[2], velocity_tc=c[3], on=self.on, dt=float(dt))


#: Keys of a ``{"type": "cascade"}`` section besides the numbers.
_CASCADE_OTHERS: tuple[str, ...] = ("gains", "model", "q2d_method", "compensation")


@dataclasses.dataclass(frozen=True)
class CascadeLoop:
    """jaxflex's own cascade (``jaxflex.controller.CascadeController``, paper eq. 9-22) as
    the loop that ran, sampled at the log's period, following the logged q1d (interpolated
    by ``jaxflex.trajectory.SampledReference`` for the reference's derivatives).

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

    def law(self, params: Params, q_ref: Float[Array, "N n"], dt: float) -> CascadeLaw:
        """The sampled law for a loop of period ``dt`` [s] following the samples ``q_ref``
        [rad] (N, n), with the gains and nominal model of the class docstring. Raises
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
        return CascadeLaw(controller=controller)


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


def _need_x64(what: str) -> None:
    if not jax.config.jax_enable_x64:
        raise ValueError(f"{what} needs float64: call jax.config.update('jax_enable_x64', True) "
                         "first (the jaxflex command does)")


@persistent_jit
def _sampled_loop(plant: FlexibleJointPlant, kind: str, law: SampledLaw, r: jax.Array,
                  d: jax.Array, x0: PlantState, dt: float,
                  substeps: int) -> tuple[jax.Array, jax.Array]:
    """The sampled-data loop of a declared controller around the model ``kind``: at t_k = k dt
    the law reads the plant's angles and its torque is held over the sample while
    ``jaxflex.step.model_step`` advances the plant. Returns (q1 before each step, torque),
    each (N, n)."""
    def body(carry, inp):
        x, c = carry
        t, rk, dk = inp
        c, tau = law.step(c, t, rk, x.q1, x.q2, dk)
        return (model_step(kind, plant, x, tau, dt, substeps), c), (x.q1, tau)

    ts = jnp.arange(r.shape[0]) * dt
    c0 = law.init(ts[0], x0.q1, x0.q2)
    _, (q, tau) = jax.lax.scan(body, (x0, c0), (ts, r, d))
    return q, tau


def simulate_loop(
    params: Params, ctrl: DeclaredLoop, q_ref: np.ndarray, dt: float, *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """Closed loop of a declared controller ``ctrl`` (``loop_controller``) around the model of
    ``params`` (one joint, ``kind`` "rigid" or "flexible") following ``q_ref`` [rad or m],
    sample period ``dt`` [s], ``disturbance`` added to the controller output (V for the P/P
    cascade, N m for the others); the plant starts at rest at q_ref[0] and is advanced by
    ``jaxflex.step.model_step`` in ``substeps`` substeps. Returns (position (N,), torque (N,)
    [N m or N]) at the sample instants (position before each step)."""
    _need_x64("simulate_loop")
    _check_loop_kind(kind)
    plant = params.to_plant()
    if plant.n != 1:
        raise ValueError(f"closed loop: the declared loop drives one joint, parameters have "
                         f"{plant.n}")
    r = jnp.asarray(q_ref, float).reshape(-1, 1)
    d = jnp.zeros_like(r) if disturbance is None else jnp.asarray(disturbance, float).reshape(-1, 1)
    law = ctrl.law(params, r, float(dt))
    q, tau = _sampled_loop(plant, kind, law, r, d, _loop_start(plant, r[0]), float(dt),
                           int(substeps))
    return np.asarray(q[:, 0]), np.asarray(tau[:, 0])


def simulate_pp_cascade(
    params: Params, ctrl: PPCascade, q_ref: np.ndarray, dt: float, *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2,
) -> tuple[np.ndarray, np.ndarray]:
    """``simulate_loop`` for the EMPS P/P cascade (``disturbance`` [V]); kept for callers of
    the P/P-only interface."""
    return simulate_loop(params, ctrl, q_ref, dt, kind=kind, disturbance=disturbance,
                         substeps=substeps)


def _check_loop_kind(kind: str) -> None:
    if kind not in ("rigid", "flexible"):
        raise ValueError(f"closed loop: model must be 'rigid' or 'flexible', got {kind!r}")


def _loop_start(plant: FlexibleJointPlant, q0: jax.Array) -> PlantState:
    """The plant at rest at ``q0`` [rad or m] with the bristles in their steady state."""
    x0 = plant.init_state(q1=q0)
    if plant.friction is not None:
        x0 = eqx.tree_at(lambda s: s.z, x0, plant.friction.z_steady(x0.dq1))
    return x0


def benchmark_derivative(q: np.ndarray, dt: float) -> np.ndarray:
    """Velocity of a measured position as the EMPS benchmark computes it: 4th-order 100 Hz
    (or 0.4 x Nyquist, whichever is lower) Butterworth filtfilt, then central differences."""
    from scipy.signal import butter, filtfilt

    b, a = butter(4, min(100.0 / (0.5 / dt), 0.4))
    return np.gradient(filtfilt(b, a, q), dt)


#: Coefficients of ``rigid_torque_fit``, in the order of its regressors.
RIGID_TERMS: tuple[str, ...] = ("Jt", "Fv", "Fc", "offset")


def _rigid_regressors(log: Log, joint: int, window: int) -> np.ndarray:
    if not 0 <= joint < log.n:
        raise ValueError(f"rigid torque model: joint {joint} not in a {log.n}-joint log")
    q = (log.q2 if log.q2 is not None else log.q1)[:, joint]
    v, a = savgol(q, log.dt, 1, window), savgol(q, log.dt, 2, window)
    return np.stack([a, v, np.sign(v), np.ones_like(v)], axis=1)


def rigid_torque_fit(log: Log, joint: int = 0, window: int = 31) -> dict[str, float]:
    """Rigid least-squares torque model of one joint on the motor encoder (q2, else q1):
    ``tau = Jt q'' + Fv q' + Fc sign(q') + offset`` (the rigid model of eq. 37 with Coulomb
    and viscous friction and a constant, linear in its coefficients), the derivatives by
    zero-phase Savitzky-Golay differentiation over ``window`` samples (``jaxflex.fit.savgol``).
    The baseline a flexible model must beat on real data, and a starting point for
    a model of a log no one has identified yet. Returns ``RIGID_TERMS``: Jt [kg m^2],
    Fv [N m s/rad], Fc [N m], offset [N m]. Raises ``ValueError`` for a joint the log lacks
    or a log without torque."""
    if log.tau is None:
        raise ValueError("rigid_torque_fit: the log has no torque column")
    coef, *_ = np.linalg.lstsq(_rigid_regressors(log, joint, window), log.tau[:, joint],
                               rcond=None)
    return dict(zip(RIGID_TERMS, map(float, coef)))


def rigid_torque(coef: Mapping[str, float], log: Log, joint: int = 0,
                 window: int = 31) -> np.ndarray:
    """Torque [N m] (N,) of ``rigid_torque_fit``'s model ``coef`` for the measured motion of
    ``log``'s ``joint``. Raises ``ValueError`` for a joint the log lacks."""
    return _rigid_regressors(log, joint, window) @ np.array([coef[k] for k in RIGID_TERMS])


def rel_error_pct(y: np.ndarray, y_hat: np.ndarray, drop: int = 0) -> float:
    """``100 ||y - y_hat|| / ||y||`` [%] after dropping the first ``drop`` samples."""
    y, y_hat = np.asarray(y)[drop:], np.asarray(y_hat)[drop:]
    return float(100.0 * np.linalg.norm(y - y_hat) / np.linalg.norm(y))


def closed_loop_errors(
    params: Params, log: Log, *, kind: str = "rigid", disturbance: np.ndarray | None = None,
    substeps: int = 2, drop: int = 49,
) -> dict[str, Any] | None:
    """The benchmark metric of the declared closed loop on ``log`` (None when the parameters
    declare no controller or the log has no reference ``q1d``): position, velocity and
    torque errors [%] (``drop`` first samples left out, as the EMPS benchmark does), and the
    simulated series under ``"series"``."""
    ctrl = loop_controller(params)
    if ctrl is None or log.q1d is None:
        return None
    q_sim, tau_sim = simulate_loop(params, ctrl, log.q1d[:, 0], log.dt, kind=kind,
                                   disturbance=disturbance, substeps=substeps)
    q, tau = log.q1[:, 0], log.tau[:, 0]
    v, v_sim = benchmark_derivative(q, log.dt), np.gradient(q_sim, log.dt)
    return {"position_pct": rel_error_pct(q, q_sim, drop),
            "velocity_pct": rel_error_pct(v, v_sim, drop),
            "torque_pct": rel_error_pct(tau, tau_sim, drop),
            "noise_floor": closed_loop_noise_floor(log, drop),
            "series": {"q": q_sim, "v": v_sim, "v_meas": v, "tau": tau_sim}}


def closed_loop_noise_floor(log: Log, drop: int = 49, seed: int = 0) -> dict[str, float]:
    """The benchmark metric's errors [%] (``closed_loop_errors``) that the log's measurement
    noise alone gives a perfect closed-loop model of joint 0 (``noise_std`` of q1 and tau,
    white): position ``100 sigma_q1 sqrt(N) / ||q1||``, velocity that noise through
    ``benchmark_derivative``, torque ``100 sigma_tau sqrt(N) / ||tau||``; the first ``drop``
    samples left out. (A simulated loop holds the torque's fast content, unlike the inverse
    dynamics of ``torque_noise_floor``.)"""
    q, tau = log.q1[:, 0], log.tau[:, 0]
    rng = np.random.default_rng(seed)
    n_q = rng.standard_normal(q.shape) * float(noise_std(q)[0])
    n_tau = rng.standard_normal(tau.shape) * float(noise_std(tau)[0])
    v = benchmark_derivative(q, log.dt)
    return {"position_pct": rel_error_pct(q, q + n_q, drop),
            "velocity_pct": rel_error_pct(v, v + benchmark_derivative(n_q, log.dt), drop),
            "torque_pct": rel_error_pct(tau, tau + n_tau, drop)}


class ClosedLoopFit(eqx.Module):
    """Data of a closed-loop output-error fit (``closed_loop_fit``): the parameter space, the
    declared loop's sampled law, the reference and disturbance (N, 1), the measured position
    and torque, the weights of the two outputs and the simulation settings."""

    space: ParamSpace
    law: SampledLaw
    r: jax.Array
    d: jax.Array
    q: jax.Array
    tau: jax.Array
    w: jax.Array
    kind: str = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    drop: int = eqx.field(static=True)


def closed_loop_residuals(theta: dict, data: ClosedLoopFit) -> jax.Array:
    """Residuals of the declared closed loop simulated with the parameters ``theta``:
    [(q - q_sim) w_q, (tau - tau_sim) w_tau] after the first ``drop`` samples (the benchmark
    metric's two outputs, each weighted by ``w``)."""
    plant = data.space.plant(theta)
    q_sim, tau_sim = _sampled_loop(plant, data.kind, data.law, data.r, data.d,
                                   _loop_start(plant, data.r[0]), data.dt, data.substeps)
    q_sim, tau_sim = q_sim[:, 0], tau_sim[:, 0]
    k = data.drop
    return jnp.concatenate([(data.q[k:] - q_sim[k:]) * data.w[0],
                            (data.tau[k:] - tau_sim[k:]) * data.w[1]])


#: ``closed_loop_fit``'s standard errors: consecutive blocks of the log taken as independent
#: clusters (EMPS: 20 blocks of 1.2 s; its closed-loop errors are correlated over ~0.4 s)
ROBUST_BLOCKS: int = 20


def closed_loop_fit(
    params: Params, log: Log, free: list[str], *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2, drop: int = 49,
    max_steps: int = 100, rtol: float = 1e-8, atol: float = 1e-8,
) -> dict[str, Any]:
    """Output-error identification *in closed loop*: the parameters ``free`` (names of
    ``jaxflex.fit.ParamSpace``) that minimise the benchmark metric's position and torque
    errors of the declared controller (``loop_controller``: the P/P cascade, a PD loop or
    jaxflex's cascade, held fixed while the plant's parameters move) simulated on ``log``'s
    reference, with ``disturbance`` injected as in ``closed_loop_errors``, by
    the project's one engine (``jaxflex.fit.least_squares``, Levenberg-Marquardt, gradients
    through the whole simulated loop).

    Each output is weighted by the inverse of its error norm at ``params`` (the start), so
    that both enter equally however different their scales (a position error of 1e-5 of the
    stroke and a torque error of 5% are both "1" at the start). Start from an identified
    model (an equation-error or multiple-shooting fit): the closed loop's error surface is
    smooth near a good model but not far from it. ``max_steps``, ``rtol``, ``atol``: the
    engine's step cap and termination tolerances (``jaxflex.fit.least_squares``).

    Returns a dict: ``params`` (the refined ``Params``), ``stderr`` (name -> physical
    standard error: cluster-robust over ``ROBUST_BLOCKS`` consecutive blocks of the log,
    ``jaxflex.fit.cluster_robust_covariance``, since a closed loop's errors are correlated
    over hundreds of samples; the white-residual ones where there are too few blocks for the
    parameters), ``stderr_kind`` (which), ``converged``, ``steps``, ``cost_start``, ``cost``
    (0.5 ||r||^2, weighted), ``reason``. Raises ``ValueError`` when the parameters declare no controller,
    the log has no reference, or ``free`` names an unknown parameter.
    """
    from jaxflex.fit import cluster_robust_covariance, covariance, least_squares, set_values

    _need_x64("closed_loop_fit")
    ctrl = loop_controller(params)
    if ctrl is None:
        raise ValueError("closed_loop_fit: the parameters declare no controller "
                         "('loop_controller' section)")
    if log.q1d is None:
        raise ValueError("closed_loop_fit: the log has no reference q1d")
    _check_loop_kind(kind)
    if not free:
        raise ValueError("closed_loop_fit: no parameter to fit")
    plant = params.to_plant()
    space = ParamSpace.build(plant, list(free))
    r = jnp.asarray(log.q1d[:, :1], float)
    d = jnp.zeros_like(r) if disturbance is None else jnp.asarray(disturbance, float).reshape(-1, 1)
    q, tau = jnp.asarray(log.q1[:, 0], float), jnp.asarray(log.tau[:, 0], float)
    data = ClosedLoopFit(space=space, law=ctrl.law(params, r, float(log.dt)), r=r, d=d, q=q, tau=tau, w=jnp.ones(2),
                         kind=kind, dt=float(log.dt), substeps=int(substeps), drop=int(drop))
    r0 = np.asarray(closed_loop_residuals(space.theta0(), data))
    m = len(r0) // 2
    norms = [np.linalg.norm(r0[:m]), np.linalg.norm(r0[m:])]
    if not all(np.isfinite(norms)) or min(norms) == 0:
        raise ValueError(f"closed_loop_fit: the start's closed-loop errors are {norms}; start "
                         "from parameters whose closed loop runs (finite, non-zero errors)")
    data = eqx.tree_at(lambda x: x.w, data, jnp.asarray([1.0 / norms[0], 1.0 / norms[1]]))
    sol = least_squares(data, space.theta0(), fn=closed_loop_residuals, max_steps=max_steps,
                        rtol=rtol, atol=atol, scaling="marquardt")
    # m position rows, then m torque rows, one per sample: a block takes both at its samples
    edges = np.linspace(0, m, ROBUST_BLOCKS + 1).astype(int)
    cov = cluster_robust_covariance(
        data, sol, [np.r_[a:b, m + a:m + b] for a, b in zip(edges[:-1], edges[1:])])
    kind_se = f"block-robust ({ROBUST_BLOCKS} blocks of the log as clusters)"
    if cov is None:
        cov = covariance(data, sol.y, fn=closed_loop_residuals, solution=sol)
        kind_se = "white residuals"
    phys = space.physical_values(sol.y)
    return {"params": set_values(params, phys),
            "stderr": {k: np.asarray(v).tolist() for k, v in cov["stderr"].items()},
            "stderr_kind": kind_se,
            "converged": bool(sol.converged), "steps": int(sol.steps),
            "cost_start": 1.0, "cost": float(sol.cost), "reason": sol.reason}


def motion_of(log: Log, kind: str = "flexible", window: int = 31) -> dict[str, np.ndarray]:
    """The measured motion of a log for ``predicted_torque``: q1, q2 [rad] and their first
    and second Savitzky-Golay derivatives (``jaxflex.fit.savgol``), and tau [N m]; (N, n)
    each (q2 = q1 for the rigid model)."""
    if kind not in MODEL_KINDS:
        raise ValueError(f"validate: model must be one of {MODEL_KINDS}, got {kind!r}")
    if kind != "rigid" and log.q2 is None:
        raise ValueError(f"validate: the {kind} model needs the motor angle q2 in the log")
    dt = log.dt
    q1 = log.q1
    q2 = q1 if kind == "rigid" else log.q2
    return {"q1": q1, "d1": savgol(q1, dt, 1, window), "dd1": savgol(q1, dt, 2, window),
            "q2": q2, "d2": savgol(q2, dt, 1, window), "dd2": savgol(q2, dt, 2, window),
            "tau": log.tau}


def predicted_torque(plant: FlexibleJointPlant, kind: str,
                     motion: Mapping[str, Any]) -> jax.Array:
    """Torque [N m] (N, n) the model needs for a measured ``motion`` (``motion_of``), from
    ``FlexibleJointPlant.torque_residuals`` (module docstring); traceable in the plant."""
    def one(a1, v1, ac1, a2, v2, ac2, tau):
        if kind == "rotor":
            a1, v1 = link_input(plant.effects, a1, v1, ac1)
        z = plant.friction.z_steady(v1) if plant.friction is not None else jnp.zeros_like(v1)
        aux = tuple(e.aux_steady(tau) for e in plant.effects) if plant.effects else None
        x = PlantState(q1=a1, dq1=v1, q2=a2, dq2=v2, z=z, aux=aux)
        r_link, r_rotor = plant.torque_residuals(x, ac1, ac2, tau)
        return tau + (r_link + r_rotor if kind == "rigid" else r_rotor)

    keys = ("q1", "d1", "dd1", "q2", "d2", "dd2", "tau")
    return jax.vmap(one)(*[jnp.asarray(motion[k]) for k in keys])


def torque_prediction(params: Params, log: Log, *, kind: str = "flexible",
                      window: int = 31) -> np.ndarray:
    """Torque [N m] the model needs for the measured motion of ``log`` (module docstring),
    (N, n)."""
    _need_x64("torque_prediction")
    motion = motion_of(log, kind, window)
    return np.asarray(eqx.filter_jit(predicted_torque)(params.to_plant(), kind, motion))


def _replay_problem(params: Params, log: Log, kind: str, length: int | None,
                    substeps: int) -> tuple[Problem, Any]:
    """``segment_gap``'s problem (segments of ``length`` samples, default 0.5 s and at least
    20, started from the measured state) and its coordinates (the parameters as given)."""
    plant = params.to_plant()
    L = min(log.N, length or max(20, int(round(0.5 / log.dt))))
    outputs = output_columns(log, kind, None)
    segs = make_segments(log, kind=kind, outputs=outputs, length=L,
                         friction=plant.friction)
    space = ParamSpace.build(plant, ["J"])  # evaluated at the base values: nothing is fitted
    n_state = segs.x0.shape[1]
    prob = Problem(space=space, segs=segs, w_y=jnp.asarray(1.0), w_def=jnp.zeros(n_state),
                   dt=log.dt, kind=kind, substeps=substeps, outputs=outputs, free_starts=False)
    return prob, space.theta0()


def segment_gap(params: Params, log: Log, *, kind: str = "flexible", length: int | None = None,
                substeps: int = 4) -> float:
    """Open-loop segment replay gap of ``params`` on ``log`` (module docstring): segments of
    ``length`` samples (default: 0.5 s, at least 20 samples) started from the measured state."""
    _need_x64("segment_gap")
    prob, theta = _replay_problem(params, log, kind, length, substeps)
    return float(gap(prob, theta))


def segment_gap_floor(params: Params, log: Log, *, kind: str = "flexible",
                      length: int | None = None, substeps: int = 4, seed: int = 0) -> float:
    """The segment replay gap (``segment_gap``) that the log's noise alone gives a perfect model.

    The model's own replays from the measured starts stand for the truth; they are measured
    with fresh white noise of the log's (``noise_std`` of each angle) and replayed again from
    start states estimated from the log with that noise added (noise in the measured starts,
    velocities included, carried forward by the replay).

    **Arguments:**

    - ``params``: the model, standing in for the truth.
    - ``log``: the log.
    - ``kind``, ``length``, ``substeps``: as ``segment_gap``.
    - ``seed``: of the noise drawn.

    **Returns:**

    The gap (0 perfect, 1 as bad as predicting no motion).
    """
    _need_x64("segment_gap_floor")
    prob, theta = _replay_problem(params, log, kind, length, substeps)
    truth = np.asarray(simulated_outputs(prob, theta))
    rng = np.random.default_rng(seed)
    std = {c: noise_std(getattr(log, c)) for c in ("q1", "q2") if getattr(log, c) is not None}
    noisy = dataclasses.replace(log, **{c: getattr(log, c) + rng.standard_normal(
        getattr(log, c).shape) * s for c, s in std.items()})
    again, _ = _replay_problem(params, noisy, kind, length, substeps)
    sig = np.concatenate([std[o] for o in prob.outputs])  # (n_out,) as the outputs' columns
    measured = truth + rng.standard_normal(truth.shape) * sig
    again = eqx.tree_at(lambda p: p.segs.y_meas, again, jnp.asarray(measured))
    return float(gap(again, theta))


def noise_std(x: np.ndarray) -> np.ndarray:
    """Measurement noise standard deviation of each column of a logged signal ``x`` (N,) or
    (N, n): ``jaxflex.fit.noise_level``'s total (white noise by differencing, at least the
    quantisation's step / sqrt(12))."""
    x = np.asarray(x, float).reshape(np.shape(x)[0], -1)
    return np.array([noise_level(x[:, j])["total_std"] for j in range(x.shape[1])])


def fast_energy(x: np.ndarray, dt: float, window: int = 31, order: int = 3) -> np.ndarray:
    """Energy ``sum x^2`` of each column of ``x`` (N,) or (N, n) above the band that a
    Savitzky-Golay smoothing of ``window`` samples and degree ``order`` passes (``savgol``:
    the derivatives of the measured motion): the spectrum of ``x - savgol(x)`` (no slow part
    to leak) divided by the smoother's stop response ``|1 - H(f)|^2`` at the frequencies where
    ``H(f)^2 < 1/2``, summed by Parseval."""
    x = np.asarray(x, float)
    N = x.shape[0]
    w = min(window, N - (1 - N % 2))
    c = savgol_coeffs(w, order)
    f = np.fft.rfftfreq(N, dt)
    k = np.arange(w) - w // 2
    H = np.cos(2.0 * np.pi * f[:, None] * dt * k[None, :]) @ c  # zero phase: real
    above = np.cumsum(H**2 < 0.5) > 0  # from the first frequency past half power on
    R = np.fft.rfft((x - savgol(x, dt, 0, w, order)).reshape(N, -1), axis=0)
    weight = np.full(f.shape, 2.0)
    weight[0] = 1.0
    if N % 2 == 0:
        weight[-1] = 1.0
    gain = np.where(above, weight / np.maximum((1.0 - H) ** 2, 1e-12), 0.0)
    return (gain @ np.abs(R) ** 2 / N).reshape(x.shape[1:])


def torque_noise_floor(params: Params, log: Log, *, kind: str = "flexible", window: int = 31,
                       seed: int = 0, tau_hat: np.ndarray | None = None) -> dict[str, Any]:
    """The torque prediction error [%] that what the log cannot resolve gives a perfect model.

    ``100 sqrt(E_tau + ||tau_hat(q + n_q) - tau_hat(q)||^2) / ||tau||``: ``E_tau``, the
    torque's own share, is the larger of its energy faster than the measured motion resolves
    (``fast_energy`` above the Savitzky-Golay band of the derivatives: a controller's chatter
    on quantised angles, say) and ``N sigma_tau^2`` (white noise, part of which lies inside
    that band); the angles' share propagates white noise ``n_q`` of the standard deviations
    ``noise_std`` finds on q1 and q2 through ``torque_prediction`` (to first order).

    **Arguments:**

    - ``params``: the model, standing in for the truth.
    - ``log``: the log (tau, q1 and, but for the rigid model, q2).
    - ``kind``: the model kind of ``torque_prediction``.
    - ``window``: Savitzky-Golay window [samples] of the derivatives.
    - ``seed``: of the noise drawn for the angles.
    - ``tau_hat``: ``torque_prediction`` on ``log``, when already computed.

    **Returns:**

    ``{"pct": floor [%], "std": {"tau": [...], "q1": [...], "q2": [...]}}``, the noise
    standard deviations in the log's units.
    """
    if tau_hat is None:
        tau_hat = torque_prediction(params, log, kind=kind, window=window)
    rng = np.random.default_rng(seed)
    std = {c: noise_std(getattr(log, c)) for c in ("tau", "q1", "q2")
           if getattr(log, c) is not None}
    noisy = {c: getattr(log, c) + rng.standard_normal(getattr(log, c).shape) * std[c]
             for c in ("q1", "q2") if c in std}
    moved = torque_prediction(params, dataclasses.replace(log, **noisy), kind=kind,
                              window=window)
    own = np.maximum(fast_energy(log.tau, log.dt, window), log.tau.shape[0] * std["tau"] ** 2)
    energy = np.sum(own) + np.sum((moved - tau_hat) ** 2)
    pct = float(100.0 * np.sqrt(energy) / np.linalg.norm(log.tau))
    return {"pct": pct, "std": {c: np.asarray(v).tolist() for c, v in std.items()}}


def replay_residual_analysis(params: Params, log: Log, *, kind: str = "flexible",
                             length: int | None = None, substeps: int = 4,
                             lags: int = 25) -> dict[str, Any]:
    """MATLAB ``resid`` of ``params`` on ``log``: the residual (measured - simulated) of the
    open-loop segment replay of ``segment_gap``, per output and joint, its autocorrelation
    and its cross-correlation with the logged torque (the link subsystem's input: the
    measured rotor angle), each with its 99% band, and the Ljung-Box whiteness test
    (``jaxflex.fit.residual_analysis.analyse_segments``, the lagged products pooled within
    the segments).

    **Arguments:**

    - `params`: the parameters judged.
    - `log`: the log.
    - `kind`: the model structure (``jaxflex.step.MODEL_KINDS``).
    - `length`: samples per segment (default: 0.5 s, at least 20).
    - `substeps`: integrator substeps per sample.
    - `lags`: the largest lag [samples] (at most a segment's half less one; MATLAB's
      ``resid``: 25).

    **Returns:**

    ``{"part", "input", "residual", "lags", "confidence", "channels": {name: summary}}``,
    names "q1", "q2" (with "[j]" per joint on an n-joint log), each summary
    ``ResidualAnalysis.summary``; ``{"error": message}`` when the replay is not finite or
    the segments are too short for the statistics.

    **Raises:**

    `ValueError` for a model kind the log cannot replay (a rotor or link model without q2)."""
    _need_x64("replay_residual_analysis")
    prob, theta = _replay_problem(params, log, kind, length, substeps)
    y = np.asarray(simulated_outputs(prob, theta))
    meas = np.asarray(prob.segs.y_meas)
    u = np.asarray(prob.segs.tau)
    u = u[..., 0, :] if u.ndim == 4 else u  # a subsystem's inputs: the torque, or the rotor
    # angle that drives the link subsystem, first
    n = log.n
    lags = max(1, min(lags, prob.segs.length // 2 - 1))
    channels = {}
    try:
        for c, o in enumerate(prob.outputs):
            for j in range(n):
                name = o if n == 1 else f"{o}[{j}]"
                channels[name] = analyse_segments(meas[..., c * n + j] - y[..., c * n + j],
                                                  u[..., j], lags=lags).summary()
    except ValueError as e:  # a replay that diverged: said so, not raised
        return {"error": str(e)}
    return {"part": "open-loop segment replay", "input": "q2" if kind == "link" else "tau",
            "lags": lags, "residual": "measured - simulated", "confidence": CONFIDENCE,
            "channels": channels}


def validate(
    params: Params, log: Log, *, kind: str = "flexible", segment: int | None = None,
    substeps: int = 4, disturbance: np.ndarray | None = None,
) -> dict[str, Any]:
    """All validation numbers of ``params`` on one ``log`` (module docstring), each beside
    what the log's noise alone gives a perfect model: ``gap`` and ``gap_noise``
    (``segment_gap_floor``), ``torque_pct`` and ``torque_noise_pct`` (``torque_noise_floor``;
    ``noise_std`` the noise found on each column), and ``closed_loop`` (dict of
    position/velocity/torque errors [%] with their ``noise_floor``,
    ``closed_loop_noise_floor``; or None), and ``residual_analysis``
    (``replay_residual_analysis``). ``series`` holds the measured and predicted
    signals for figures."""
    tau_hat = torque_prediction(params, log, kind=kind)
    floor = torque_noise_floor(params, log, kind=kind, tau_hat=tau_hat)
    out: dict[str, Any] = {
        "model": kind, "samples": log.N, "dt": log.dt,
        "gap": segment_gap(params, log, kind=kind, length=segment, substeps=substeps),
        "gap_noise": segment_gap_floor(params, log, kind=kind, length=segment,
                                       substeps=substeps),
        "torque_pct": rel_error_pct(log.tau, tau_hat),
        "torque_noise_pct": floor["pct"], "noise_std": floor["std"],
        "residual_analysis": replay_residual_analysis(params, log, kind=kind, length=segment,
                                                      substeps=substeps),
    }
    loop_kind = {"rotor": "rigid", "link": "flexible"}.get(kind, kind)
    cl = closed_loop_errors(params, log, kind=loop_kind,
                            disturbance=disturbance, substeps=max(2, substeps // 2))
    out["closed_loop"] = None if cl is None else {k: v for k, v in cl.items() if k != "series"}
    out["series"] = {"t": log.t, "tau": log.tau, "tau_hat": tau_hat, "q": log.q1,
                     "closed_loop": None if cl is None else cl["series"]}
    return out
