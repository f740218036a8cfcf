"""The closed-loop part of validation: a declared loop replayed against the log in the
benchmark metric ``100 ||y - y_sim|| / ||y||`` [%] beside its noise floor
(``closed_loop_errors``, ``closed_loop_noise_floor``), the loop's parameters fitted to the
log (``closed_loop_fit``) and the rigid inverse-dynamics torque fit of the EMPS benchmark
(``rigid_torque_fit``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.fit import (
    ParamSpace,
    savgol,
)
from jaxflex.core.controller import AbstractControlLaw
from jaxflex.fit.inverse import RIGID_TERMS, linear_fit, rigid_regressors
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.validate.loops import (
    check_loop_kind,
    loop_controller,
    loop_start,
    need_float64,
    sampled_loop,
    simulate_loop,
)
from jaxflex.validate.replay import noise_std


def benchmark_derivative(q: np.ndarray, dt: float) -> np.ndarray:
    """Velocity of a measured position as the EMPS benchmark computes it: 4th-order 100 Hz
    (or 0.4 x Nyquist, whichever is lower) Butterworth filtfilt, then central differences."""
    from scipy.signal import butter, filtfilt

    b, a = butter(4, min(100.0 / (0.5 / dt), 0.4))
    return np.gradient(filtfilt(b, a, q), dt)


def _rigid_regressors(log: Log, joint: int, window: int) -> np.ndarray:
    if not 0 <= joint < log.n:
        raise ValueError(f"rigid torque model: joint {joint} not in a {log.n}-joint log")
    q = (log.q2 if log.q2 is not None else log.q1)[:, joint]
    return rigid_regressors(savgol(q, log.dt, 1, window), savgol(q, log.dt, 2, window))


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
    fit = linear_fit(_rigid_regressors(log, joint, window), log.tau[:, joint])
    return dict(zip(RIGID_TERMS, map(float, fit.x)))


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
    declared loop's sampled law (holding the reference and disturbance), the reference (N, 1)
    (its first sample starts the plant), the measured position
    and torque, the weights of the two outputs and the simulation settings."""

    space: ParamSpace
    law: AbstractControlLaw
    r: jax.Array
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
    q_sim, tau_sim = sampled_loop(plant, data.kind, data.law, loop_start(plant, data.r[0]),
                                  data.dt, data.substeps, data.r.shape[0])
    q_sim, tau_sim = q_sim[:, 0], tau_sim[:, 0]
    k = data.drop
    return jnp.concatenate([(data.q[k:] - q_sim[k:]) * data.w[0],
                            (data.tau[k:] - tau_sim[k:]) * data.w[1]])


#: ``closed_loop_fit``'s standard errors: consecutive blocks of the log taken as independent
#: clusters (EMPS: 20 blocks of 1.2 s; its closed-loop errors are correlated over ~0.4 s)
ROBUST_BLOCKS: int = 20


@dataclasses.dataclass(frozen=True)
class ClosedLoopFitResult:
    """Result of ``closed_loop_fit``.

    **Fields:**

    - ``params``: the refined ``Params``.
    - ``stderr``: name -> physical standard error (the parameter's units): cluster-robust
      over ``ROBUST_BLOCKS`` consecutive blocks of the log
      (``jaxflex.fit.cluster_robust_covariance``), since a closed loop's errors are
      correlated over hundreds of samples; the white-residual ones where there are too few
      blocks for the parameters.
    - ``stderr_kind``: which of the two.
    - ``converged``, ``steps``, ``reason``: the engine's verdict, step count and why it
      stopped.
    - ``cost_start``, ``cost``: 0.5 ||r||^2 of the weighted errors (dimensionless) at the
      start (1 by the weighting) and at the end.
    """

    params: Params
    stderr: dict[str, list[float]]
    stderr_kind: str
    converged: bool
    steps: int
    cost_start: float
    cost: float
    reason: str

    def to_dict(self) -> dict[str, Any]:
        """The fields as a dict (``params`` stays a ``Params``)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


def closed_loop_fit(
    params: Params, log: Log, free: list[str], *, kind: str = "rigid",
    disturbance: np.ndarray | None = None, substeps: int = 2, drop: int = 49,
    max_steps: int = 100, rtol: float = 1e-8, atol: float = 1e-8,
) -> ClosedLoopFitResult:
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

    Returns a ``ClosedLoopFitResult``. Raises ``ValueError`` when the parameters declare no
    controller, the log has no reference, or ``free`` names an unknown parameter.
    """
    from jaxflex.fit import cluster_robust_covariance, covariance, least_squares, set_values

    need_float64("closed_loop_fit")
    ctrl = loop_controller(params)
    if ctrl is None:
        raise ValueError("closed_loop_fit: the parameters declare no controller "
                         "('loop_controller' section)")
    if log.q1d is None:
        raise ValueError("closed_loop_fit: the log has no reference q1d")
    check_loop_kind(kind)
    if not free:
        raise ValueError("closed_loop_fit: no parameter to fit")
    plant = params.to_plant()
    space = ParamSpace.build(plant, list(free))
    r = jnp.asarray(log.q1d[:, :1], float)
    d = None if disturbance is None else jnp.asarray(disturbance, float).reshape(-1, 1)
    q, tau = jnp.asarray(log.q1[:, 0], float), jnp.asarray(log.tau[:, 0], float)
    data = ClosedLoopFit(space=space, law=ctrl.law(params, r, float(log.dt), d), r=r, q=q,
                         tau=tau, w=jnp.ones(2),
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
    return ClosedLoopFitResult(
        params=set_values(params, phys),
        stderr={k: np.asarray(v).tolist() for k, v in cov["stderr"].items()},
        stderr_kind=kind_se, converged=bool(sol.converged), steps=int(sol.steps),
        cost_start=1.0, cost=float(sol.cost), reason=sol.reason)


