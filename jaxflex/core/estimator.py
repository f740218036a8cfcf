"""Model-based velocity estimation for coarse encoders: a steady-state Kalman filter per joint.

The dirty derivative of ``CascadeController.step`` differentiates quantised angles; with the
paper's 0.72 deg link encoder one count in one 1 ms sample is 12.6 rad/s of "velocity". This
module estimates q1' and q2' from both encoders and the applied torque with the controller's
own model of the flexible joint (paper eq. 3, 40; docs/spec.md section 1), per joint i:

    x = (q1, q1', q2, q2', d)                 d [N m]: link-side disturbance torque
    I q1'' = K (q2 - q1) + d                  (eq. 3 with M = I, C = G = 0, eq. 40; d = -F)
    J q2'' = tau - K (q2 - q1)                (eq. 3, rotor side)
    d_{k+1} = d_k + w_d,   var(w_d) = disturbance_rate^2 dt      (random walk)
    y = (q1, q2) + v,      var(v) = r^2 / 12 + noise^2 + floor^2  (quantiser step r)

Friction (eq. 4-7) is not predicted by the model: it is the main part of the disturbance d,
estimated as a random walk (as in a disturbance observer). The LuGre prediction would need
the bristle state, which only the friction observer (eq. 20) estimates from the very
velocities this filter provides, and with compensation off there is none; a random-walk d
makes the velocity estimate unbiased under any slowly varying link torque (friction,
gravity, coupling of an n-link arm, model error). The torque ``tau`` is the applied one
(after the DAC), held over the sample (zero-order hold), so the discrete model (``expm``) is
exact for the linear part; the DAC's rounding enters as rotor-torque noise of variance
lsb^2 / 12.

Steady-state, not time-varying: the model is linear time-invariant per joint and the noise
levels are constant, so the time-varying gain converges to the steady-state one within a
few tens of samples; the steady-state gain keeps the covariance out of the carried state
(the closed-loop Jacobian of ``jaxflex.loop.analyse`` then sees only the estimate, as a hardware
implementation would run it) and costs one 5x5 filter update per joint and sample. The gain
solves the filter's discrete algebraic Riccati equation by the structure-preserving
doubling algorithm (fixed iteration count, so ``jit``/``vmap``/``grad`` reach every
parameter). For an n-link arm each joint uses the diagonal of M(q1) at the start pose as its
inertia; couplings, gravity and the off-diagonal inertia go into d.

Selected by ``Sensing(velocity="kalman", kalman=KalmanTuning(...))``; the sampled-data loop
(``jaxflex.sim.simulate``) builds the filter from the controller's model and period and the
sensing's encoders and DAC (``kalman_estimator``) and carries its state in
``ControllerState.estimator``.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.validation import as_param, check_nonnegative

NX: int = 5
"""Estimator states per joint: q1, q1', q2, q2', d."""
DOUBLING_ITERATIONS: int = 60
"""Doubling steps for the Riccati equation; each squares the closed-loop transition, so 60
steps cover 2^60 samples (far beyond the slowest filter mode)."""
TUNING_FIELDS: tuple[str, ...] = ("disturbance_rate", "torque_noise", "angle_floor", "angles")


class KalmanTuning(eqx.Module):
    """Noise levels of the Kalman filter that the sensing does not give (each (n,) or a scalar
    for every joint, all >= 0).

    disturbance_rate [N m/sqrt(s)]: random-walk intensity of the link disturbance torque d
    (friction changes by 2 Fc ~ 0.2 N m at a reversal within a few ms: a larger value follows
    it faster and lets more encoder noise through); torque_noise [N m]: standard deviation of
    an unmodelled rotor torque held over each sample, added to the DAC's rounding;
    angle_floor [rad]: standard deviation added to both encoders' noise so that exact
    measurements (no quantiser, no noise) still give a well-posed filter; angles: the
    controller also gets the filter's angles q1, q2 instead of the encoder readings (False:
    only the velocities are replaced, as by the other velocity sources).
    """

    disturbance_rate: Array = eqx.field(converter=as_param, default=1.0)
    torque_noise: Array = eqx.field(converter=as_param, default=0.01)
    angle_floor: Array = eqx.field(converter=as_param, default=1e-7)
    angles: bool = eqx.field(static=True, default=False)

    def __check_init__(self) -> None:
        check_nonnegative("KalmanTuning", disturbance_rate=self.disturbance_rate,
                          torque_noise=self.torque_noise, angle_floor=self.angle_floor)


def tuning_of(entry: KalmanTuning | dict[str, Any] | None) -> KalmanTuning | None:
    """``Sensing.kalman`` converter: a ``KalmanTuning``, a mapping of its fields (as a parameter
    file gives it) or None (defaults where the Kalman filter is selected). Raises ``ValueError``
    naming an unknown field."""
    if entry is None or isinstance(entry, KalmanTuning):
        return entry
    if isinstance(entry, dict):
        unknown = sorted(set(entry) - set(TUNING_FIELDS))
        if unknown:
            raise ValueError(f"KalmanTuning: unknown field(s) {unknown}; known: {list(TUNING_FIELDS)}")
        return KalmanTuning(**entry)
    raise ValueError(f"Sensing: kalman must be a KalmanTuning, a mapping of its fields or None, "
                     f"got {entry!r}")


class EstimatorState(eqx.Module):
    """The filter's estimate (all (n,)): q1 [rad], dq1 [rad/s], q2 [rad], dq2 [rad/s], d [N m]
    link disturbance torque. Carried between samples as the prediction for the next sample."""

    q1: Float[Array, " n"]
    dq1: Float[Array, " n"]
    q2: Float[Array, " n"]
    dq2: Float[Array, " n"]
    d: Float[Array, " n"]

    def vector(self) -> Float[Array, "n 5"]:
        return jnp.stack([self.q1, self.dq1, self.q2, self.dq2, self.d], axis=-1)

    @classmethod
    def of(cls, x: Float[Array, "n 5"]) -> EstimatorState:
        return cls(*(x[..., i] for i in range(NX)))


def joint_model(I: Array, J: Array, K: Array, dt: float) -> tuple[Array, Array]:
    """Zero-order-hold discretisation over ``dt`` [s] of one joint's model (module docstring):
    transition A (5, 5) and the column B (5,) of a torque [N m] held over the sample. The
    column of a held link torque is A[:, 4] (d enters as one)."""
    Ac = jnp.zeros((NX, NX), dtype=jnp.result_type(I))
    Ac = Ac.at[0, 1].set(1.0).at[2, 3].set(1.0)
    Ac = Ac.at[1, 0].set(-K / I).at[1, 2].set(K / I).at[1, 4].set(1.0 / I)
    Ac = Ac.at[3, 0].set(K / J).at[3, 2].set(-K / J)
    Bc = jnp.zeros(NX, dtype=Ac.dtype).at[3].set(1.0 / J)
    aug = jnp.zeros((NX + 1, NX + 1), dtype=Ac.dtype).at[:NX, :NX].set(Ac).at[:NX, NX].set(Bc)
    E = jax.scipy.linalg.expm(aug * dt)
    return E[:NX, :NX], E[:NX, NX]


def solve_filter_riccati(A: Array, C: Array, Q: Array, R: Array,
                         iterations: int = DOUBLING_ITERATIONS) -> Array:
    """Prediction covariance P of the steady-state Kalman filter, the solution of

        P = A P A' - A P C' (C P C' + R)^-1 C P A' + Q,

    by the structure-preserving doubling algorithm (Chu, Fan, Lin and Wang 2004) on the dual
    control-form equation (transition F = A', input C'), with G = C' R^-1 C and H_0 = Q:

        W = I + G_k H_k,  F_k+1 = F_k W^-1 F_k,  G_k+1 = G_k + F_k W^-1 G_k F_k',
        H_k+1 = H_k + F_k' H_k W^-1 F_k,         H_k -> P.

    Needs R positive definite, (A, C) detectable and (A, Q^1/2) stabilisable."""
    eye = jnp.eye(A.shape[0], dtype=A.dtype)

    def body(_, carry):
        F, G, H = carry
        W = eye + G @ H
        WF = jnp.linalg.solve(W, F)
        G_new = G + F @ jnp.linalg.solve(W, G) @ F.T
        H_new = H + F.T @ H @ WF
        return F @ WF, 0.5 * (G_new + G_new.T), 0.5 * (H_new + H_new.T)

    _, _, P = jax.lax.fori_loop(0, iterations, body, (A.T, C.T @ jnp.linalg.solve(R, C), Q))
    return P


@eqx.filter_jit
def _filter_design(I: Array, J: Array, K: Array, q1_var: Array, q2_var: Array, tau_var: Array,
                   rate: Array, tn: Array, floor: Array, dt: float) -> tuple[Array, ...]:
    """Per joint (all (n,)): transition A, torque column B, gain L and prediction covariance P
    of the steady-state filter (``KalmanEstimator.build``), in one compiled program."""
    C = jnp.zeros((2, NX), dtype=I.dtype).at[0, 0].set(1.0).at[1, 2].set(1.0)

    def one(I_, J_, K_, r1, r2, tv, rate_, tn_, fl):
        A, B = joint_model(I_, J_, K_, dt)
        ed = jnp.zeros(NX, dtype=A.dtype).at[4].set(1.0)
        Q = ((tv + tn_**2) * jnp.outer(B, B) + rate_**2 * dt * jnp.outer(ed, ed))
        # the random walk's effect on the link within the sample (second order in dt)
        # is left out
        R = jnp.diag(jnp.stack([r1 + fl**2, r2 + fl**2]))
        P = solve_filter_riccati(A, C, Q, R)
        L = P @ C.T @ jnp.linalg.inv(C @ P @ C.T + R)
        return A, B, L, P

    return jax.vmap(one)(I, J, K, q1_var, q2_var, tau_var, rate, tn, floor)


class KalmanEstimator(eqx.Module):
    """Steady-state Kalman filter of q1', q2' per joint (module docstring); fields (n, ...).

    A (n, 5, 5) transition over one sample; B (n, 5) held rotor torque column; L (n, 5, 2)
    filter gain (estimate += L (y - C estimate), y = (q1, q2) measured); P (n, 5, 5) the
    steady prediction covariance (diagnostics); angles: whether the controller gets the
    filter's angles too (``KalmanTuning.angles``). Build with ``build``.
    """

    A: Float[Array, "n 5 5"]
    B: Float[Array, "n 5"]
    L: Float[Array, "n 5 2"]
    P: Float[Array, "n 5 5"]
    angles: bool = eqx.field(static=True, default=False)

    @classmethod
    def build(
        cls, model: FlexibleJointPlant, dt: float, *, q1_var: Array, q2_var: Array,
        tau_var: Array, tuning: KalmanTuning | None = None, q1_ref: Array | None = None,
    ) -> KalmanEstimator:
        """The filter for ``model`` (inertias from M(q1_ref), default q1 = 0; J, K) at period
        ``dt`` [s] with encoder variances ``q1_var``, ``q2_var`` [rad^2] (quantisation and
        noise; the tuning's floor is added here) and rotor-torque variance ``tau_var``
        [N^2 m^2] (the DAC's rounding; the tuning's torque noise is added here).

        Raises ``ValueError`` when a variance is negative, dt is not positive or the model is
        not in float64 (the encoder variances span 1e-14 to 1e-5 rad^2; the Riccati solution
        loses its meaning in float32).
        """
        tuning = KalmanTuning() if tuning is None else tuning
        if not dt > 0:
            raise ValueError(f"KalmanEstimator: dt must be > 0 s, got {dt}")
        check_nonnegative("KalmanEstimator", q1_var=q1_var, q2_var=q2_var, tau_var=tau_var)
        n = model.n
        q1_ref = jnp.zeros(n, model.K.dtype) if q1_ref is None else jnp.asarray(q1_ref)
        I = jnp.diagonal(model.links.mass_matrix(q1_ref))
        if I.dtype != jnp.float64 or model.K.dtype != jnp.float64:
            raise ValueError(
                f"KalmanEstimator: needs a float64 model, got {model.K.dtype}; turn on "
                "jax.config.update('jax_enable_x64', True) before building the plant")
        full = lambda v: jnp.broadcast_to(jnp.asarray(v, I.dtype), (n,))
        q1_var, q2_var, tau_var = full(q1_var), full(q2_var), full(tau_var)
        rate, tn, floor = (full(tuning.disturbance_rate), full(tuning.torque_noise),
                           full(tuning.angle_floor))
        A, B, L, P = _filter_design(I, model.J, model.K, q1_var, q2_var, tau_var, rate, tn,
                                    floor, float(dt))
        return cls(A=A, B=B, L=L, P=P, angles=tuning.angles)

    def init(self, q1: Array, q2: Array, dq1: Array | None = None,
             dq2: Array | None = None) -> EstimatorState:
        """Estimate at the first sample: the measured angles [rad], the given velocities [rad/s]
        (zero if not given), no disturbance."""
        q1 = jnp.asarray(q1, jnp.result_type(float))
        zero = jnp.zeros_like(q1)
        return EstimatorState(
            q1=q1, dq1=zero if dq1 is None else jnp.asarray(dq1, q1.dtype),
            q2=jnp.asarray(q2, q1.dtype), dq2=zero if dq2 is None else jnp.asarray(dq2, q1.dtype),
            d=zero)

    def update(self, prior: EstimatorState, q1: Array, q2: Array) -> EstimatorState:
        """Measurement update with the sensed angles q1, q2 [rad] of this sample."""
        x = prior.vector()
        innov = jnp.stack([q1 - x[:, 0], q2 - x[:, 2]], axis=-1)
        return EstimatorState.of(x + jnp.einsum("nij,nj->ni", self.L, innov))

    def predict(self, post: EstimatorState, tau: Array) -> EstimatorState:
        """Prediction to the next sample with the applied torque ``tau`` [N m] held over it."""
        x = post.vector()
        return EstimatorState.of(jnp.einsum("nij,nj->ni", self.A, x) + self.B * tau[:, None])

    def filter(self, q1: Float[Array, "N n"], q2: Float[Array, "N n"],
               tau: Float[Array, "N n"], dq1_0: Array | None = None,
               dq2_0: Array | None = None) -> EstimatorState:
        """Run the filter over recorded angles [rad] and applied torques [N m] (tau[k] held
        over [t_k, t_k+1]); the updated estimates at every sample, fields (N, n)."""

        def body(prior, inp):
            y1, y2, u = inp
            post = self.update(prior, y1, y2)
            return self.predict(post, u), post

        _, posts = jax.lax.scan(body, self.init(q1[0], q2[0], dq1_0, dq2_0), (q1, q2, tau))
        return posts


def kalman_for(sensing: Any, model: FlexibleJointPlant, dt: float,
               q1_ref: Array | None = None) -> KalmanEstimator:
    """The Kalman filter of a sensing (an ``AbstractSensing`` with velocity "kalman") for a
    controller's nominal ``model`` and period ``dt`` [s]: encoder variances r^2 / 12 +
    noise^2 [rad^2] from its resolutions and noise levels, rotor-torque variance lsb^2 / 12
    [N^2 m^2] from its DAC (lsb = 2 dac_range / 2^dac_bits), the rest from ``sensing.kalman``
    (defaults if None)."""
    q1_var = sensing.q1_resolution**2 / 12.0 + sensing.q1_noise**2
    q2_var = sensing.q2_resolution**2 / 12.0 + sensing.q2_noise**2
    if sensing.dac_bits:
        lsb = 2.0 * sensing.dac_range / 2**sensing.dac_bits
        tau_var = lsb**2 / 12.0
    else:
        tau_var = jnp.zeros(())
    return KalmanEstimator.build(model, dt, q1_var=q1_var, q2_var=q2_var, tau_var=tau_var,
                                 tuning=sensing.kalman, q1_ref=q1_ref)
