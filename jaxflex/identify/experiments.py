"""Identification experiments in simulation and the paper's two-step procedure (section 5).

- ``excitation_torque``: an open-loop torque with slow reversals and long low-speed dwell,
  the excitation that makes vs, sigma0, sigma1 identifiable (docs/spec.md section 9, "Identifiability");
- ``synthetic_log``: replay a torque through a plant and sense it (encoder quantisation and
  noise from ``jaxflex.sim.simulate.Sensing``) into a ``Log``;
- ``static_map_experiment``: constant-velocity runs (eq. 35 data): for each velocity a stiff
  PD loop drives the rigid model (eq. 37) along a ramp with a quantised encoder and a DAC;
  friction is the mean torque over the steady part, velocity the encoder slope;
- ``fit_static_map``: Fc, Fs, vs, sigma2 from (v, F) pairs (eq. 35), Levenberg-Marquardt;
- ``two_step``: the paper's procedure: static fit, then sigma0, sigma1 on the rigid model
  from an open-loop stick-slip log (eq. 36-39).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from jaxflex.fit import get_value, set_values
from jaxflex.identify.core import identify
from jaxflex.identify.result import IdentResult
from jaxflex.identify.static import STATIC_NAMES, StaticMap, fit_static_map
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.sensing import Sensing
from jaxflex.sim.step import ModelKind, replay, rigid_step


def excitation_torque(
    t_final: float = 6.0, dt: float = 1e-3, amplitude: float = 0.22, bias: float = 0.0,
    periods: Sequence[float] = (2.0, 0.9), n: int = 1,
) -> np.ndarray:
    """Open-loop torque [N m], shape (N, n): a slow sinusoid of period ``periods[0]`` [s] whose
    amplitude sweeps from 0.5 to 1 x ``amplitude``, plus a 25% component of period
    ``periods[1]``. With ``amplitude`` a little above Fs the link sticks and slips, dwells at low
    speed and reverses twice per period: the excitation vs, sigma0 and sigma1 need."""
    t = np.arange(int(round(t_final / dt))) * dt
    env = 0.5 + 0.5 * np.clip(t / (0.6 * t_final), 0.0, 1.0)
    u = amplitude * env * (np.sin(2 * np.pi * t / periods[0])
                           + 0.25 * np.sin(2 * np.pi * t / periods[1] + 0.7)) + bias
    return np.repeat(u[:, None], n, axis=1)


def synthetic_log(
    plant: FlexibleJointPlant, tau: np.ndarray, *, dt: float = 1e-3, substeps: int = 4,
    model: ModelKind = "flexible", sensing: Sensing | None = None,
    key: PRNGKeyArray | None = None, q1_0: float = 0.0,
) -> tuple[Log, object]:
    """Replay ``tau`` (N, n) [N m] through ``plant`` from rest at ``q1_0`` and sense the angles.

    Returns (log with t, tau, q1, q2 and exact v = q1', true states). ``sensing``: encoder
    quantisation and white noise (needs ``key``); None gives exact angles."""
    tau = jnp.asarray(tau, float)
    x0 = plant.init_state(q1=q1_0)
    xs, _ = eqx.filter_jit(lambda p, x, u: replay(model, p, x, u, dt, substeps))(plant, x0, tau)
    q1, q2 = np.asarray(xs.q1), np.asarray(xs.q2)
    if sensing is not None:
        k1, k2 = jax.random.split(key if key is not None else jax.random.PRNGKey(0))
        n1 = sensing.q1_noise * jax.random.normal(k1, q1.shape)
        n2 = sensing.q2_noise * jax.random.normal(k2, q2.shape)
        q1 = np.asarray(sensing.measure(jnp.asarray(q1), sensing.q1_resolution, n1))
        q2 = np.asarray(sensing.measure(jnp.asarray(q2), sensing.q2_resolution, n2))
    t = np.arange(tau.shape[0]) * dt
    log = Log.from_arrays(t=t, tau=np.asarray(tau), q1=q1, q2=q2, v=np.asarray(xs.dq1),
                          source="synthetic")
    return log, xs


def static_map_experiment(
    plant: FlexibleJointPlant, velocities: Sequence[float], *, sensing: Sensing | None = None,
    kp: float = 40.0, kd: float = 1.5, run_time: float = 3.0, dt: float = 1e-3,
    substeps: int = 4, key: PRNGKeyArray | None = None, joint: int = 0,
) -> StaticMap:
    """Constant-velocity runs on the rigid model (eq. 37) of ``plant`` (one joint).

    For each velocity v a PD loop at 1/``dt`` Hz with feedforward Jx*0 tracks the ramp
    q = v t from the sensed angle (``sensing``: quantisation, noise, DAC), velocity by a
    first difference of the sensed angle. Over the second half of the run the friction is
    the mean applied torque and the velocity is the encoder slope, as on a rig where the
    torque comes from the motor current. Runs are vmapped over the velocities.
    """
    sensing = Sensing() if sensing is None else sensing
    N = int(round(run_time / dt))
    vel = jnp.asarray(velocities, float)
    n = plant.n
    keys = jax.random.split(key if key is not None else jax.random.PRNGKey(0), len(velocities))

    def run(v, k):
        noise = sensing.q1_noise * jax.random.normal(k, (N, n))
        x0 = plant.init_state()
        q_prev0 = jnp.zeros(n)

        def body(carry, inp):
            x, q_prev = carry
            i, e = inp
            t = i * dt
            qm = sensing.measure(x.q1, sensing.q1_resolution, e)
            vm = (qm - q_prev) / dt
            u = kp * (v * t - qm) + kd * (v - vm)
            u = sensing.dac(u)
            x_new = rigid_step(plant, x, u, dt, substeps)
            return (x_new, qm), (u, qm)

        _, (u, qm) = jax.lax.scan(body, (x0, q_prev0), (jnp.arange(N), noise))
        h = N // 2
        F = jnp.mean(u[h:], axis=0)
        slope = (qm[-1] - qm[h]) / ((N - 1 - h) * dt)
        return slope[joint], F[joint]

    vs, Fs = eqx.filter_jit(jax.vmap(run))(vel, keys)
    return StaticMap(v=np.asarray(vs), F=np.asarray(Fs))


@dataclasses.dataclass
class TwoStepResult:
    """The paper's procedure: ``static`` name -> (value, stderr) for Fc, Fs, vs, sigma2;
    ``dynamic`` the rigid-model fit of sigma0, sigma1; ``params`` all six; ``wall_s``."""

    static: dict[str, tuple[float, float]]
    dynamic: IdentResult
    params: Params
    wall_s: float


def two_step(
    static: StaticMap, stick_slip: Log, init: Params, *, segment_length: int | None = None,
    substeps: int = 4, **identify_kw,
) -> TwoStepResult:
    """Section 5 of the paper on one joint: fit the static map (eq. 35), then sigma0, sigma1 by
    output error on the rigid model Jx x'' = u - F, Jx = I + J (eq. 36-39), from ``init``."""
    if init.n != 1:
        raise ValueError("two_step: the paper's procedure is per joint; pass 1-joint parameters")
    t0 = time.perf_counter()
    start = {k: init.friction[k][0] for k in STATIC_NAMES}
    st = fit_static_map(static, start)
    p1 = set_values(init, {k: [v[0]] for k, v in st.items()})
    dyn = identify(stick_slip, p1, ("sigma0", "sigma1"), model="rigid",
                   segment_length=segment_length, substeps=substeps, **identify_kw)
    params = dyn.params
    params.extra["stderr"].update({k: [v[1]] for k, v in st.items()})
    return TwoStepResult(static=st, dynamic=dyn, params=params, wall_s=time.perf_counter() - t0)


def perturb(params: Params, names: Sequence[str], factors: Sequence[float]) -> Params:
    """``params`` with each named parameter multiplied by its factor (keeps Fs >= Fc by
    raising Fs if needed)."""
    vals = {k: get_value(params, k) * f for k, f in zip(names, factors)}
    fc = vals.get("Fc", get_value(params, "Fc"))
    fs = vals.get("Fs", get_value(params, "Fs"))
    if np.any(fs < fc):
        vals["Fs"] = np.maximum(fs, 1.05 * fc)
    return set_values(params, vals)
