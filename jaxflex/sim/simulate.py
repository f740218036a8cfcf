"""Closed-loop simulation: a continuous reference (diffrax) and a sampled-data loop (lax.scan).

Sampled-data loop (as on the rig): at each sample t_k = k dt the controller reads the sensed
angles, computes tau_k, which is held (zero-order hold, optionally DAC-quantised) while the
plant is integrated over [t_k, t_k + dt] in ``substeps`` steps.

Plant integrator (``integrator="split"``, the default): Strang splitting per substep h,
z-half-step / mechanics RK4 step / z-half-step. The LuGre bristle state z is advanced exactly
with the link velocity frozen (eq. 5 is linear in z at fixed v), so the stiff rate
sigma0 |v| / g(v) never limits the step (docs/spec.md section 9); the mechanical part has no such
stiffness. The scheme is second order in h; ``tests/test_simulate.py`` shows convergence to a
diffrax solution of the same sampled-data loop (``integrator="diffrax"``, Kvaerno5 per sample
interval, which restarts at every jump of the held torque).

Everything is a pure function of the plant and controller modules, so ``jit``, ``vmap`` and
``grad`` reach every parameter. ``save=False`` keeps only running metrics (for large sweeps).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from jaxflex.core.controller import AbstractTrackingLaw, ControllerState, LawOutput
from jaxflex.core.estimator import KalmanEstimator, kalman_for
from jaxflex.core.sensing import AbstractSensing, Sensing
from jaxflex.core.plant import FlexibleJointPlant, PlantState
from jaxflex.sim.step import plant_step, plant_step_diffrax
from jaxflex.core.trajectory import Taylor

if TYPE_CHECKING:  # diffrax is imported where it is used: importing it takes 0.25 s
    import diffrax

_tmap = jax.tree_util.tree_map
#: Reference derivatives the sampled-data loop hands the controller (q2d'' needs the 4th).
REFERENCE_ORDER = 4


class Metrics(eqx.Module):
    """Running tracking metrics of one closed-loop run (reduced inside the loop).

    All (n,) except ``count``, ``diverged`` and ``diverged_at``: sum of squared link error
    [rad^2], max |e1| [rad], sum of squared torque [N^2 m^2], samples at the torque limit,
    sample count; ``diverged``: the run is lost, i.e. the state became non-finite or beyond
    1e3 rad or rad/s (the state is then held), or the link error left the band
    |e1| <= LOST_FACTOR (A + LOST_FLOOR) around a reference of half-range A [rad] (see
    ``lost_band``); ``diverged_at``: the first sample where that happened (-1: never).
    """

    sum_e2: Array
    max_e: Array
    sum_tau2: Array
    sat_count: Array
    count: Array
    diverged: Array
    diverged_at: Array

    @property
    def rms_error(self) -> Array:
        """RMS link tracking error [rad]."""
        return jnp.sqrt(self.sum_e2 / self.count)

    @property
    def max_error(self) -> Array:
        """Max absolute link tracking error [rad]."""
        return self.max_e

    @property
    def tau_rms(self) -> Array:
        """RMS motor torque [N m]."""
        return jnp.sqrt(self.sum_tau2 / self.count)

    @property
    def saturation_fraction(self) -> Array:
        """Fraction of samples with the torque at its limit."""
        return self.sat_count / self.count


class SimResult(eqx.Module):
    """Closed-loop trajectories at the controller samples, shape (N, n) (None if not saved).

    t [s]; q1, q2 [rad]; dq1, dq2 [rad/s]; z, z_hat [rad]; tau [N m] applied over the sample;
    F [N m] true friction; F_hat [N m] estimated; q1d [rad] reference; e1 [rad] = q1 - q1d;
    q1_meas, q2_meas [rad] sensed angles; dq1_hat, dq2_hat [rad/s] the velocities the
    controller used (exact, filtered or Kalman, per ``Sensing.velocity``). ``metrics`` is
    always present.
    """

    metrics: Metrics
    t: Array | None = None
    q1: Array | None = None
    dq1: Array | None = None
    q2: Array | None = None
    dq2: Array | None = None
    z: Array | None = None
    z_hat: Array | None = None
    tau: Array | None = None
    F: Array | None = None
    F_hat: Array | None = None
    q1d: Array | None = None
    e1: Array | None = None
    q1_meas: Array | None = None
    q2_meas: Array | None = None
    dq1_hat: Array | None = None
    dq2_hat: Array | None = None


def loop_estimator(controller: AbstractTrackingLaw, sensing: AbstractSensing
                   ) -> KalmanEstimator | None:
    """The Kalman filter the sampled-data loop runs for ``sensing`` (velocity "kalman"), built
    from the controller's nominal model and period with the encoder and DAC noise of the
    sensing (``jaxflex.core.estimator.kalman_for``), the arm's inertia taken at the reference's
    start pose; None for the other velocity sources."""
    if sensing.velocity != "kalman":
        return None
    q1_ref = controller.trajectory.position(jnp.asarray(0.0, jnp.result_type(float)))
    return kalman_for(sensing, controller.model, controller.dt, q1_ref=q1_ref)


def init_controller(
    controller: AbstractTrackingLaw, estimator: KalmanEstimator | None, t0: ArrayLike,
    q1: Array, q2: Array, dq1: Array, dq2: Array,
) -> ControllerState:
    """``controller.init`` at sensed angles q1, q2 [rad] and velocities dq1, dq2 [rad/s], with
    the estimator (if any) started there too (its state in ``ControllerState.estimator``)."""
    c0 = controller.init(t0, q1, q2, dq1, dq2)
    if estimator is None:
        return c0
    return dataclasses.replace(c0, estimator=estimator.init(c0.q1_prev, c0.q2_prev, dq1, dq2))


def controller_sample(
    controller: AbstractTrackingLaw, sensing: AbstractSensing, estimator: KalmanEstimator | None,
    c: ControllerState, t: Array, q1m: Array, q2m: Array, dq1: Array, dq2: Array,
) -> tuple[ControllerState, LawOutput, Array]:
    """One controller sample of the loop at time t [s] from the sensed angles q1m, q2m [rad]:
    the velocities per ``sensing.velocity`` ("exact": the true dq1, dq2 [rad/s] given here;
    "filtered": the controller's dirty derivative; "kalman": ``estimator``'s measurement
    update, then its prediction with the applied torque), the law (eq. 9-22) and the DAC.
    Returns the next controller state, the law's output and the applied torque [N m]."""
    if estimator is not None:
        post = estimator.update(c.estimator, q1m, q2m)
        if estimator.angles:
            q1m, q2m = post.q1, post.q2
        c_new, out = controller.step(c, t, q1m, q2m, post.dq1, post.dq2)
        tau = sensing.dac(out.tau)
        return dataclasses.replace(c_new, estimator=estimator.predict(post, tau)), out, tau
    if sensing.velocity == "exact":
        c_new, out = controller.step(c, t, q1m, q2m, dq1, dq2)
    else:
        c_new, out = controller.step(c, t, q1m, q2m)
    return c_new, out, sensing.dac(out.tau)


def _noise(key, shape, std):
    if key is None:
        return jnp.zeros(shape)
    return std * jax.random.normal(key, shape)


LOST_FACTOR: float = 2.0
"""A run is lost when |e1| exceeds LOST_FACTOR times (the reference's half-range + LOST_FLOOR)."""
LOST_FLOOR: float = 0.01
"""[rad] added to the reference's half-range so that a reference at rest has a band too."""


def lost_band(q1d: Float[Array, "N n"]) -> Float[Array, " n"]:
    """The link-error band [rad] outside which a run is lost: LOST_FACTOR (A + LOST_FLOOR),
    A = (max q1d - min q1d) / 2 the reference's half-range [rad] over the run, per joint.
    An error of twice the motion itself means the loop no longer follows the reference
    (a tracking loop that works keeps |e1| well below A)."""
    half = 0.5 * (jnp.max(q1d, axis=0) - jnp.min(q1d, axis=0))
    return LOST_FACTOR * (half + LOST_FLOOR)


def _blown(x: PlantState, bound: float = 1e3) -> Array:
    v = jnp.stack([x.q1, x.dq1, x.q2, x.dq2])
    return jnp.logical_not(jnp.all(jnp.isfinite(v) & (jnp.abs(v) < bound)))


def simulate_sampled(
    plant: FlexibleJointPlant,
    controller: AbstractTrackingLaw,
    t_final: float,
    *,
    x0: PlantState | None = None,
    substeps: int = 10,
    sensing: AbstractSensing | None = None,
    key: PRNGKeyArray | None = None,
    save: bool = True,
    integrator: Literal["split", "diffrax"] = "split",
    unroll_substeps: bool | int = 2,
    unroll: int = 1,
) -> SimResult:
    """Sampled-data closed loop for ``t_final`` seconds at the controller period ``dt``.

    ``plant`` is the true plant, ``controller`` carries its own nominal model. ``x0`` defaults
    to rest at q1d(0). ``substeps`` plant steps per sample. ``sensing`` adds encoder
    quantisation, noise (with ``key``), filtered or Kalman-estimated velocities (the filter's
    state rides in the controller state) and DAC quantisation. A run that
    blows up is flagged in ``metrics.diverged`` and its state frozen, never an exception.
    ``unroll_substeps``: the plant's substep loop (``jaxflex.sim.step.model_step``): True
    unrolled, False rolled, an int k: k substeps per trip of the loop (default 2); same
    numbers, another speed. Unrolled pays under ``vmap`` on a CPU (the sweep engine decides
    per control law); two per trip is the default for one run (as fast as a plain
    ``lax.scan`` of the same loop, ``studies/bench_simulate.py --part single``); through a
    gradient pass False (``jaxflex.tune`` does). ``unroll``: samples per trip of the time loop
    (``lax.scan``'s ``unroll``); same numbers. More than one pays on a GPU, where each trip
    of a loop costs a round trip to the host (``jaxflex.sweep.engine.loop_unrolls``).
    Pure and jit/vmap/grad friendly; wrap in ``eqx.filter_jit`` at the call site.
    """
    if substeps < 1:
        raise ValueError(f"simulate_sampled: substeps must be >= 1, got {substeps}")
    if unroll < 1:
        raise ValueError(f"simulate_sampled: unroll must be >= 1, got {unroll}")
    if not t_final > 0:
        raise ValueError(f"simulate_sampled: t_final must be > 0 s, got {t_final}")
    if integrator not in ("split", "diffrax"):
        raise ValueError(f"simulate_sampled: integrator must be 'split' or 'diffrax', got {integrator!r}")
    if controller.model.n != plant.n:
        raise ValueError(
            f"simulate_sampled: controller is for {controller.model.n} joint(s), plant has {plant.n}"
        )
    sensing = Sensing() if sensing is None else sensing
    dt = controller.dt
    N = int(round(t_final / dt))
    n = plant.n
    ts = jnp.arange(N) * dt
    if x0 is None:
        x0 = plant.init_state(q1=controller.trajectory.position(jnp.asarray(0.0)))
    if key is not None:
        k1, k2 = jax.random.split(key)
        n1 = _noise(k1, (N, n), sensing.q1_noise)
        n2 = _noise(k2, (N, n), sensing.q2_noise)
    else:
        n1 = n2 = jnp.zeros((N, n))
    estimator = loop_estimator(controller, sensing)
    c0 = init_controller(
        controller, estimator, 0.0, sensing.measure(x0.q1, sensing.q1_resolution, n1[0]),
        sensing.measure(x0.q2, sensing.q2_resolution, n2[0]),
        x0.dq1, x0.dq2,
    )
    zero = jnp.zeros(n)
    m0 = Metrics(zero, zero, zero, zero, jnp.zeros(()), jnp.zeros((), bool),
                 -jnp.ones((), jnp.int32))
    band = lost_band(jax.vmap(controller.trajectory.position)(ts))

    # The reference's derivatives ride in the carry, one sample ahead: each sample evaluates
    # them once for the next, and the controller reads them through a Taylor reference at
    # the sample time (exactly the same values; otherwise XLA repeats a sinusoid's sine and
    # cosine in every kernel that uses a derivative)
    def reference(t):
        return controller.trajectory.derivatives(t, order=REFERENCE_ORDER)

    def body(carry, inp):
        x, c, m, ref = carry
        t, t_next, e1n, e2n = inp
        ctl = eqx.tree_at(lambda k: k.trajectory, controller, Taylor(ref, t))
        q1m = sensing.measure(x.q1, sensing.q1_resolution, e1n)
        q2m = sensing.measure(x.q2, sensing.q2_resolution, e2n)
        c_new, out, tau = controller_sample(ctl, sensing, estimator, c, t, q1m, q2m,
                                            x.dq1, x.dq2)
        if integrator == "split":
            x_new = plant_step(plant, x, tau, dt, substeps, unroll_substeps)
        else:
            x_new = plant_step_diffrax(plant, x, tau, dt)
        blown = _blown(x_new)
        x_new = _tmap(lambda a, b: jnp.where(blown, a, b), x, x_new)  # hold the last finite state
        e = x.q1 - ref[0]
        bad = blown | jnp.any(jnp.abs(e) > band) | m.diverged
        sat = jnp.abs(out.tau) >= controller.tau_max
        m_new = Metrics(
            sum_e2=m.sum_e2 + e**2, max_e=jnp.maximum(m.max_e, jnp.abs(e)),
            sum_tau2=m.sum_tau2 + tau**2, sat_count=m.sat_count + sat, count=m.count + 1,
            diverged=bad,
            diverged_at=jnp.where(bad & ~m.diverged, m.count.astype(jnp.int32), m.diverged_at),
        )
        rec = None
        if save:
            F = plant.friction_torque(x)
            rec = (x, c.z_hat, tau, F, out.F_hat, e, q1m, q2m, c_new.dq1, c_new.dq2)
        return (x_new, c_new, m_new, reference(t_next)), rec

    ts_next = jnp.arange(1, N + 1) * dt
    (_, _, m, _), rec = jax.lax.scan(body, (x0, c0, m0, reference(ts[0])), (ts, ts_next, n1, n2),
                                     unroll=unroll)
    if not save:
        return SimResult(metrics=m)
    xs, zh, tau, F, F_hat, e, q1m, q2m, v1, v2 = rec
    return SimResult(
        metrics=m, t=ts, q1=xs.q1, dq1=xs.dq1, q2=xs.q2, dq2=xs.dq2, z=xs.z, z_hat=zh,
        tau=tau, F=F, F_hat=F_hat, q1d=xs.q1 - e, e1=e, q1_meas=q1m, q2_meas=q2m,
        dq1_hat=v1, dq2_hat=v2,
    )


class ContinuousResult(eqx.Module):
    """Continuous closed loop sampled at ``t`` (N,); arrays (N, n); ``stats`` from diffrax."""

    t: Array
    q1: Array
    dq1: Array
    q2: Array
    dq2: Array
    z: Array
    z_hat: Array
    tau: Array
    e1: Array
    stats: dict


def simulate_continuous(
    plant: FlexibleJointPlant,
    controller: AbstractTrackingLaw,
    t_final: float,
    *,
    x0: PlantState | None = None,
    save_dt: float = 1e-3,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    solver: diffrax.AbstractSolver | None = None,
    max_steps: int = 2_000_000,
) -> ContinuousResult:
    """Continuous closed loop (controller in continuous time, exact velocities), solved with
    an adaptive diffrax solver (default Kvaerno5, stiff-capable, PID step control). The
    accurate reference for the sampled-data loop as dt -> 0. Outputs every ``save_dt`` s.
    """
    if not t_final > 0:
        raise ValueError(f"simulate_continuous: t_final must be > 0 s, got {t_final}")
    import diffrax

    if x0 is None:
        x0 = plant.init_state(q1=controller.trajectory.position(jnp.asarray(0.0)))
    y0 = (x0, jnp.zeros(plant.n, dtype=x0.q1.dtype))

    def law(t, y):
        x, zh = y
        return controller.continuous(t, x.q1, x.dq1, x.q2, x.dq2, zh)

    def vf(t, y, args):
        x, _ = y
        out = law(t, y)
        return plant.vector_field(x, out.tau), out.z_hat_dot

    n_save = int(round(t_final / save_dt)) + 1
    ts = jnp.linspace(0.0, t_final, n_save)
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf), solver if solver is not None else diffrax.Kvaerno5(),
        0.0, t_final, save_dt / 10, y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
    )
    xs, zh = sol.ys
    tau = jax.vmap(lambda t, x, z: law(t, (x, z)).tau)(ts, xs, zh)
    q1d = jax.vmap(controller.trajectory.position)(ts)
    return ContinuousResult(
        t=ts, q1=xs.q1, dq1=xs.dq1, q2=xs.q2, dq2=xs.dq2, z=xs.z, z_hat=zh, tau=tau,
        e1=xs.q1 - q1d, stats=dict(sol.stats),
    )


def tracking_summary(e1: ArrayLike, tau: ArrayLike) -> dict[str, float | list[float]]:
    """RMS and max link error [rad] and torque RMS [N m] of saved trajectories (host side)."""
    e1, tau = np.asarray(e1), np.asarray(tau)
    f = lambda a: float(a[0]) if a.size == 1 else a.tolist()
    return {
        "rms_error": f(np.sqrt(np.mean(e1**2, axis=0))),
        "max_error": f(np.max(np.abs(e1), axis=0)),
        "tau_rms": f(np.sqrt(np.mean(tau**2, axis=0))),
    }
