"""Cascade controller with LuGre friction compensation (paper eq. 9-22, 41-42; docs/spec.md section 3).

    e1 = q1 - q1d,  qr1' = q1d' - L1 e1,  s1 = e1' + L1 e1                       (eq. 9)
    ud  = M(q1) qr1'' + C(q1, q1') qr1' + G(q1) - KD1 s1 + F_hat                (eq. 13)
    q2d = K^-1 ud + q1                                                           (eq. 11)
    e2 = q2 - q2d,  s2 = e2' + L2 e2
    tau = J (q2d'' - L2 e2') - KD2 s2 + K (q2 - q1)                              (eq. 16)

q2d' and q2d'' are not measurable; ``q2d_method`` chooses how to get them (docs/spec.md section 3):

- ``"model"``: differentiate q2d along the controller's own estimate of the closed-loop vector
  field (q1'' from the model with F_hat, z_hat' from the observer) with ``jax.jvp``;
- ``"filtered"``: two cascaded dirty derivatives of q2d at the sample rate (sampled-data only);
- ``"reference"``: differentiate q2d as in "model" but with the reference's acceleration
  q1d'' (and so its jerk) where the link's appear, as the paper's eq. 41-42 say.

The same control law serves the continuous closed loop (``continuous``) and the sampled-data
controller (``init``/``step``), which also estimates velocities from encoder angles when they
are not given and saturates the torque. Every sampled control law of jaxflex (this cascade, a
log's declared loop in ``jaxflex.validate``, the data generator's PD) implements
``AbstractControlLaw``, the one interface the sampled-data loops call.
"""

from __future__ import annotations

import abc
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.estimator import EstimatorState
from jaxflex.core.validation import as_param, check_nonnegative, check_positive
from jaxflex.core.observer import FrictionObserver
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.trajectory import Trajectory

Q2DMethod = Literal["model", "filtered", "reference"]
Q2D_METHODS: tuple[str, ...] = ("model", "filtered", "reference")
GAIN_NAMES: tuple[str, ...] = ("Ke", "KD1", "KD2", "kv", "L1", "L2")


class CascadeGains(eqx.Module):
    """Controller gains per joint (Table 3), each of shape (n,), all > 0.

    Ke [rad/(N m)] observer gain; KD1 [N m s/rad] link damping; KD2 [N m s/rad] rotor damping;
    kv [s/rad] smoothing of |v| in the observer; L1, L2 [1/s] sliding-surface slopes.

    leak [rad/s] (>= 0, default 0 = the paper's observer): the observer's leakage, a floor
    under its smooth |v| (``jaxflex.core.observer``). Not one of the six tuned gains
    (``GAIN_NAMES``, ``to_vector``): a search keeps it fixed at its start value.
    """

    Ke: Float[Array, " n"] = eqx.field(converter=as_param)
    KD1: Float[Array, " n"] = eqx.field(converter=as_param)
    KD2: Float[Array, " n"] = eqx.field(converter=as_param)
    kv: Float[Array, " n"] = eqx.field(converter=as_param)
    L1: Float[Array, " n"] = eqx.field(converter=as_param)
    L2: Float[Array, " n"] = eqx.field(converter=as_param)
    leak: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)

    def __check_init__(self) -> None:
        shapes = {k: getattr(self, k).shape for k in GAIN_NAMES}
        if len(set(shapes.values())) > 1 or len(self.Ke.shape) != 1:
            raise ValueError(f"CascadeGains: every gain must have the same shape (n,), got {shapes}")
        if self.leak.shape not in ((1,), self.Ke.shape):
            raise ValueError(f"CascadeGains: leak must be one value or one per joint "
                             f"{self.Ke.shape}, got shape {self.leak.shape}")
        check_positive("CascadeGains", **{k: getattr(self, k) for k in GAIN_NAMES})
        check_nonnegative("CascadeGains", leak=self.leak)

    @property
    def n(self) -> int:
        """Number of joints."""
        return int(self.Ke.shape[0])

    def to_dict(self) -> dict[str, list[float]]:
        """Gains as plain lists (docs/spec.md section 7 'gains' entry); ``leak`` only where it
        is not 0 (the paper's observer)."""
        out = {k: [float(v) for v in getattr(self, k)] for k in GAIN_NAMES}
        leak = jnp.broadcast_to(self.leak, self.Ke.shape)
        if bool(jnp.any(leak != 0)):
            out["leak"] = [float(v) for v in leak]
        return out

    @classmethod
    def from_vector(cls, theta: Float[Array, " 6n"], leak: ArrayLike = 0.0) -> CascadeGains:
        """Gains from a flat vector ordered (Ke, KD1, KD2, kv, L1, L2), each block (n,), with
        the observer leakage ``leak`` [rad/s]."""
        theta = jnp.asarray(theta)
        if theta.ndim != 1 or theta.shape[0] % 6:
            raise ValueError(
                f"CascadeGains.from_vector: need a flat vector of 6n gains ordered "
                f"{GAIN_NAMES}, got shape {theta.shape}"
            )
        return cls(*jnp.split(theta, 6), leak=leak)

    def to_vector(self) -> Float[Array, " 6n"]:
        """Flat vector ordered (Ke, KD1, KD2, kv, L1, L2) (``leak`` is not in it)."""
        return jnp.concatenate([getattr(self, k) for k in GAIN_NAMES])


def dirty_derivative(y_prev: ArrayLike, x: ArrayLike, x_prev: ArrayLike, tc: ArrayLike,
                     h: float) -> Array:
    """One sample of the filtered ("dirty") derivative of a sampled signal x, backward Euler:
    y = (tc y_prev + x - x_prev) / (tc + h), time constant ``tc`` [s] (0: the backward
    difference), sample period ``h`` [s]; units of x per second."""
    return (tc * y_prev + x - x_prev) / (tc + h)


def pd_torque(kp: ArrayLike, kd: ArrayLike, tau_max: ArrayLike, r: ArrayLike, q: ArrayLike,
              dq: ArrayLike) -> Array:
    """PD law toward a set point: tau = clip(kp (r - q) - kd q', -tau_max, tau_max) [N m],
    with kp [N m/rad], kd [N m s/rad], angles [rad] and q' [rad/s]."""
    return jnp.clip(kp * (r - q) - kd * dq, -tau_max, tau_max)


class ControllerState(eqx.Module):
    """State of the sampled-data controller (all (n,)).

    z_hat [rad] observer state; q1_prev, q2_prev [rad] last angles; dq1, dq2 [rad/s] filtered
    velocity estimates; q2d_prev [rad], dq2d [rad/s], ddq2d [rad/s^2] filtered q2d derivatives;
    estimator: the Kalman filter's prediction for the next sample where the sensing selects
    it (``jaxflex.core.estimator``; set by the sampled-data loop, passed through by ``step``),
    None otherwise (no leaves, so the state of the other velocity sources is unchanged).
    """

    z_hat: Array
    q1_prev: Array
    q2_prev: Array
    dq1: Array
    dq2: Array
    q2d_prev: Array
    dq2d: Array
    ddq2d: Array
    estimator: EstimatorState | None = None

    @classmethod
    def at_rest(cls, q1: Array, q2: Array, dq2: Array | None = None) -> ControllerState:
        """The state of a law at the angles q1, q2 [rad] (its last samples), every estimate
        zero but the rotor velocity ``dq2`` [rad/s] where given."""
        q1, q2 = jnp.asarray(q1, float), jnp.asarray(q2, float)
        zero = jnp.zeros_like(q1)
        return cls(z_hat=zero, q1_prev=q1, q2_prev=q2, dq1=zero,
                   dq2=zero if dq2 is None else jnp.asarray(dq2, float), q2d_prev=zero,
                   dq2d=zero, ddq2d=zero)


class LawOutput(eqx.Module):
    """Control-law result with its intermediate signals (for logging and plots)."""

    tau: Array
    z_hat_dot: Array
    F_hat: Array
    q2d: Array
    s1: Array
    e1: Array

    @classmethod
    def of_torque(cls, tau: Array, *, q2d: Array | None = None,
                  e1: Array | None = None) -> LawOutput:
        """The output of a law that has only a torque [N m] (and, where it has them, a
        rotor set point q2d [rad] and a link error e1 [rad]); the cascade's other signals
        are zero."""
        zero = jnp.zeros_like(tau)
        return cls(tau=tau, z_hat_dot=zero, F_hat=zero, q2d=zero if q2d is None else q2d,
                   s1=zero, e1=zero if e1 is None else e1)


class AbstractControlLaw(eqx.Module):
    """A sampled control law: what every sampled-data loop of jaxflex calls once per sample
    (``jaxflex.sim.simulate.simulate_sampled``, ``jaxflex.validate.sampled_loop``).

    ``init(t0, q1, q2, dq1=None, dq2=None)`` gives the law's state at the first sample from the
    link and rotor angles [rad] (and velocities [rad/s] where a sensor gives them);
    ``step(state, t, q1, q2, dq1=None, dq2=None)`` the next state and a ``LawOutput`` whose
    ``tau`` [N m] is held over the sample. The law reads its reference itself (a trajectory
    or logged samples), so every loop passes it only the time and the measurements.
    """

    @abc.abstractmethod
    def init(self, t0: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> Any:
        """The law's state at the first sample, time ``t0`` [s]."""

    @abc.abstractmethod
    def step(self, state: Any, t: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> tuple[Any, LawOutput]:
        """One sample at time ``t`` [s]: (next state, output)."""


class AbstractTrackingLaw(AbstractControlLaw):
    """A sampled control law that follows a ``Trajectory`` with a nominal plant ``model``,
    at the sample period ``dt`` [s], its torque saturated at ``tau_max`` [N m]: what
    ``jaxflex.sim.simulate.simulate_sampled`` runs (it starts the plant at the trajectory's
    first point, checks the model's joint count against the plant's, records the state's
    z_hat and velocities and keeps a Kalman estimator's state in it: the law's state is a
    ``ControllerState``, ``ControllerState.at_rest`` where it needs none of them). A subclass
    declares the four as its fields (``model: FlexibleJointPlant``, ``trajectory: Trajectory``,
    ``dt: float``, ``tau_max: Array``), in the order its constructor takes them."""


class CascadeController(AbstractTrackingLaw):
    """The paper's cascade controller for a ``FlexibleJointPlant`` model and a ``Trajectory``.

    ``model`` is the controller's nominal plant (its links, J, K and LuGre parameters; its
    effects are ignored). ``compensation=False`` gives F_hat = 0 (observer off). ``dt`` [s] is
    the sample period of the sampled-data form; ``velocity_tc`` [s] the time constant of the
    filtered differentiation of encoder angles; ``derivative_tc`` [s] that of the filtered q2d
    derivatives; ``tau_max`` [N m] the torque saturation (inf: none).
    """

    model: FlexibleJointPlant
    gains: CascadeGains
    trajectory: Trajectory
    compensation: bool = eqx.field(static=True, default=True)
    q2d_method: str = eqx.field(static=True, default="model")
    dt: float = eqx.field(static=True, default=1e-3)
    velocity_tc: Array = eqx.field(converter=as_param, default=0.002)
    derivative_tc: Array = eqx.field(converter=as_param, default=0.002)
    tau_max: Array = eqx.field(converter=as_param, default=float("inf"))

    def __check_init__(self) -> None:
        if self.q2d_method not in Q2D_METHODS:
            raise ValueError(
                f"CascadeController: q2d_method must be one of {Q2D_METHODS}, got {self.q2d_method!r}"
            )
        if self.gains.n != self.model.n:
            raise ValueError(
                f"CascadeController: gains are for {self.gains.n} joint(s) but the model has "
                f"{self.model.n}"
            )
        if self.compensation and self.model.friction is None:
            raise ValueError(
                "CascadeController: compensation=True needs LuGre parameters in the model"
            )
        if not self.dt > 0:
            raise ValueError(f"CascadeController: dt must be > 0 s, got {self.dt}")
        check_positive("CascadeController", allow_inf=True, tau_max=self.tau_max)
        check_nonnegative(
            "CascadeController", velocity_tc=self.velocity_tc, derivative_tc=self.derivative_tc
        )

    @property
    def observer(self) -> FrictionObserver:
        """The friction observer built from the model's LuGre parameters and Ke, kv, leak."""
        return FrictionObserver(self.model.friction, self.gains.Ke, self.gains.kv,
                                self.gains.leak)

    # ----- the law (eq. 9-16) -----------------------------------------------------------------

    def _link(self, t: Array, q1: Array, dq1: Array, z_hat: Array):
        """Link loop: (q2d, F_hat, z_hat', s1, e1) for eq. 9, 13, 11, 20, 22."""
        g, links, K = self.gains, self.model.links, self.model.K
        ref = self.trajectory.derivatives(t, order=2)
        e1, de1 = q1 - ref[0], dq1 - ref[1]
        dqr1, ddqr1 = ref[1] - g.L1 * e1, ref[2] - g.L1 * de1
        s1 = de1 + g.L1 * e1
        if self.compensation:
            obs = self.observer
            z_hat_dot = obs.z_hat_dot(dq1, z_hat, s1)
            F_hat = obs.force(dq1, z_hat, z_hat_dot)
        else:
            z_hat_dot = jnp.zeros_like(q1)
            F_hat = jnp.zeros_like(q1)
        ud = (
            links.mass_matrix(q1) @ ddqr1 + links.coriolis(q1, dq1, dqr1) + links.gravity(q1)
            - g.KD1 * s1 + F_hat
        )
        return ud / K + q1, F_hat, z_hat_dot, s1, e1

    def _q2d_flow(self, t, q1, dq1, q2, dq2, z_hat, accel: str):
        """q2d, q2d', q2d'' by differentiating q2d along an estimated flow (jvp).

        X = (t, q1, q1', z_hat) flows with X' = (1, q1', a, z_hat'). With ``accel="model"``
        a = M^-1 (K (q2 - q1) - C q1' - G - F_hat), the controller's own estimate; a depends
        on q2, whose derivative along the flow is the measured q2', so q2d'' is the
        derivative of q2d' = <grad q2d, X'> along (X', q2'). With ``accel="reference"``
        a = q1d''(t): the reference's acceleration (and, differentiated, jerk) stand where
        the link's appear (paper eq. 41-42).
        """
        links, K = self.model.links, self.model.K

        def q2d_of(X):
            return self._link(*X)[0]

        def first(X, q2v):
            tt, a, da, zh = X
            _, F_hat, z_hat_dot, _, _ = self._link(tt, a, da, zh)
            if accel == "model":
                rhs = K * (q2v - a) - links.coriolis(a, da, da) - links.gravity(a) - F_hat
                dda = links.solve_mass(a, rhs)
            else:
                dda = self.trajectory.derivatives(tt, order=2)[2]
            flow = (jnp.ones_like(tt), da, dda, z_hat_dot)
            return jax.jvp(q2d_of, (X,), (flow,)), flow

        X = (jnp.asarray(t, q1.dtype), q1, dq1, z_hat)
        _, flow = first(X, q2)
        (q2d, dq2d), (_, ddq2d) = jax.jvp(lambda X_, q2v: first(X_, q2v)[0], (X, q2), (flow, dq2))
        return q2d, dq2d, ddq2d

    def _q2d_feedforward(self, t: Array) -> tuple[Array, Array]:
        """q2d' and q2d'' of the feedforward rotor set point q1d + K^-1 (M q1d'' + C q1d' + G)
        (reference only, no feedback terms); used to start the filtered derivatives."""
        links, K = self.model.links, self.model.K

        def q2d_ref(tt):
            r = self.trajectory.derivatives(tt, order=2)
            ud = links.mass_matrix(r[0]) @ r[2] + links.coriolis(r[0], r[1], r[1]) + links.gravity(r[0])
            return ud / K + r[0]

        d1 = lambda tt: jax.jvp(q2d_ref, (tt,), (jnp.ones_like(tt),))[1]
        t = jnp.asarray(t, jnp.result_type(float))
        dq2d, ddq2d = jax.jvp(d1, (t,), (jnp.ones_like(t),))
        return dq2d, ddq2d

    def _rotor(self, q1, q2, dq2, q2d, dq2d, ddq2d) -> Array:
        """Rotor loop torque (eq. 16), saturated at tau_max."""
        g, J, K = self.gains, self.model.J, self.model.K
        e2, de2 = q2 - q2d, dq2 - dq2d
        s2 = de2 + g.L2 * e2
        tau = J * (ddq2d - g.L2 * de2) - g.KD2 * s2 + K * (q2 - q1)
        return jnp.clip(tau, -self.tau_max, self.tau_max)

    def continuous(
        self, t: ArrayLike, q1: Array, dq1: Array, q2: Array, dq2: Array, z_hat: Array
    ) -> LawOutput:
        """Continuous-time law with exact velocities: tau [N m] and the observer's z_hat'.

        ``q2d_method="filtered"`` has no continuous form and raises ``ValueError``.
        """
        t = jnp.asarray(t, q1.dtype)
        if self.q2d_method == "filtered":
            raise ValueError(
                "q2d_method='filtered' differentiates q2d at the sample rate; use the "
                "sampled-data simulation (simulate_sampled) or q2d_method 'model'/'reference'"
            )
        q2d, F_hat, z_hat_dot, s1, e1 = self._link(t, q1, dq1, z_hat)
        _, dq2d, ddq2d = self._q2d_flow(t, q1, dq1, q2, dq2, z_hat, self.q2d_method)
        tau = self._rotor(q1, q2, dq2, q2d, dq2d, ddq2d)
        return LawOutput(tau=tau, z_hat_dot=z_hat_dot, F_hat=F_hat, q2d=q2d, s1=s1, e1=e1)

    # ----- sampled-data form ------------------------------------------------------------------

    def init(
        self, t0: ArrayLike, q1: Array, q2: Array, dq1: Array | None = None,
        dq2: Array | None = None,
    ) -> ControllerState:
        """Controller state at the first sample: observer at rest (z_hat = 0), velocity filters
        at the given velocities (zero if not given), q2d filters at their reference values."""
        q1 = jnp.asarray(q1, jnp.result_type(float))
        q2 = jnp.asarray(q2, q1.dtype)
        zero = jnp.zeros_like(q1)
        dq1 = zero if dq1 is None else jnp.asarray(dq1, q1.dtype)
        dq2 = zero if dq2 is None else jnp.asarray(dq2, q1.dtype)
        q2d = self._link(jnp.asarray(t0, q1.dtype), q1, dq1, zero)[0]
        dq2d, ddq2d = self._q2d_feedforward(t0)
        return ControllerState(
            z_hat=zero, q1_prev=q1, q2_prev=q2, dq1=dq1, dq2=dq2, q2d_prev=q2d, dq2d=dq2d,
            ddq2d=ddq2d,
        )

    def step(
        self, state: ControllerState, t: ArrayLike, q1: Array, q2: Array,
        dq1: Array | None = None, dq2: Array | None = None,
    ) -> tuple[ControllerState, LawOutput]:
        """One controller sample at time t [s] from angles q1, q2 [rad].

        Velocities [rad/s] are used as given, or else estimated by filtered differentiation
        (dirty derivative with time constant ``velocity_tc``, backward Euler) of the angles.
        Returns the next state and the law's output (tau [N m], saturated).
        """
        h = self.dt
        dirty = lambda y_prev, x, x_prev, tc: dirty_derivative(y_prev, x, x_prev, tc, h)
        if dq1 is None:
            dq1 = dirty(state.dq1, q1, state.q1_prev, self.velocity_tc)
        if dq2 is None:
            dq2 = dirty(state.dq2, q2, state.q2_prev, self.velocity_tc)
        t = jnp.asarray(t, q1.dtype)
        q2d, F_hat, z_hat_dot, s1, e1 = self._link(t, q1, dq1, state.z_hat)
        dq2d_f = dirty(state.dq2d, q2d, state.q2d_prev, self.derivative_tc)
        ddq2d_f = dirty(state.ddq2d, dq2d_f, state.dq2d, self.derivative_tc)
        if self.q2d_method == "filtered":
            dq2d, ddq2d = dq2d_f, ddq2d_f
        else:
            _, dq2d, ddq2d = self._q2d_flow(t, q1, dq1, q2, dq2, state.z_hat, self.q2d_method)
        tau = self._rotor(q1, q2, dq2, q2d, dq2d, ddq2d)
        if self.compensation:
            z_hat = self.observer.step(state.z_hat, dq1, s1, h)
        else:
            z_hat = state.z_hat
        new = ControllerState(
            z_hat=z_hat, q1_prev=q1, q2_prev=q2, dq1=dq1, dq2=dq2, q2d_prev=q2d, dq2d=dq2d_f,
            ddq2d=ddq2d_f, estimator=state.estimator,
        )
        return new, LawOutput(tau=tau, z_hat_dot=z_hat_dot, F_hat=F_hat, q2d=q2d, s1=s1, e1=e1)

