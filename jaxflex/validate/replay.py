"""The open-loop part of validation: the torque the model predicts from the measured motion
(``torque_prediction``), the segment replay gap (``segment_gap``), what the log's noise alone
gives each (``torque_noise_floor``, ``segment_gap_floor``) and the segment replay's residual
analysis (``replay_residual_analysis``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.fit import (
    ParamSpace,
    Problem,
    gap,
    make_segments,
    noise_level,
    output_columns,
    savgol,
    savgol_coeffs,
    simulated_outputs,
)
from jaxflex.fit.inverse import Motion, measured_motion, model_residuals
from jaxflex.fit.residual_analysis import CONFIDENCE, analyse_segments
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.validate.loops import need_float64


def predicted_torque(plant: FlexibleJointPlant, kind: str, motion: Motion) -> jax.Array:
    """Torque [N m] (N, n) the model needs for a measured ``motion``
    (``jaxflex.fit.inverse.measured_motion``): the logged torque plus the rotor line's
    residual, both lines' for the rigid kind, whose one body carries both
    (``jaxflex.fit.inverse.model_residuals``, eq. 2-3); traceable in the plant."""
    r_link, r_rotor = model_residuals(plant, kind, motion)
    return jnp.asarray(motion.tau) + (r_link + r_rotor if kind == "rigid" else r_rotor)


def torque_prediction(params: Params, log: Log, *, kind: str = "flexible",
                      window: int = 31) -> np.ndarray:
    """Torque [N m] the model needs for the measured motion of ``log`` (module docstring),
    (N, n)."""
    need_float64("torque_prediction")
    motion = measured_motion(log, window, kind=kind)
    return np.asarray(eqx.filter_jit(predicted_torque)(params.to_plant(), kind, motion))


def _replay_problem(params: Params, log: Log, kind: str, length: int | None,
                    substeps: int) -> tuple[Problem, Any]:
    """``segment_gap``'s problem (segments of ``length`` samples, default 0.5 s and at least
    20, started from the measured state) and its coordinates (the parameters as given)."""
    plant = params.to_plant()
    L = min(log.N, length or max(20, int(round(0.5 / log.dt))))
    outputs = output_columns(log, kind, None)
    segs = make_segments(log, kind=kind, outputs=outputs, length=L,
                         friction=plant.lugre)
    space = ParamSpace.build(plant, ["J"])  # evaluated at the base values: nothing is fitted
    n_state = segs.x0.shape[1]
    prob = Problem(space=space, segs=segs, w_y=jnp.asarray(1.0), w_def=jnp.zeros(n_state),
                   dt=log.dt, kind=kind, substeps=substeps, outputs=outputs, free_starts=False)
    return prob, space.theta0()


def segment_gap(params: Params, log: Log, *, kind: str = "flexible", length: int | None = None,
                substeps: int = 4) -> float:
    """Open-loop segment replay gap of ``params`` on ``log`` (module docstring): segments of
    ``length`` samples (default: 0.5 s, at least 20 samples) started from the measured state."""
    need_float64("segment_gap")
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
    need_float64("segment_gap_floor")
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
    - `kind`: the model structure (``jaxflex.sim.step.MODEL_KINDS``).
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
    need_float64("replay_residual_analysis")
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


