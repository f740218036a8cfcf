"""The identification problem of a log: its residual (``make_problem``), the default free
set, the automatic segment length, the cost the noise explains and the hints a start gives.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.fit import (
    ParamSpace,
    Problem,
    make_segments,
    noise_level,
    output_columns,
)
from jaxflex.fit.readings import READING_GAUSS, quantised_residual
from jaxflex.fit.signal import savgol, savgol_coeffs, savgol_window
from jaxflex.identify.start import DataStart
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.validation import to_device
from jaxflex.sim.step import MODEL_KINDS, ModelKind

DEFAULT_FREE: tuple[str, ...] = ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")
#: The friction levels Fc and Fs - Fc of a fit stay below this many times the largest torque
#: the log applies (``ParamSpace.friction_cap``): a level the actuator could never break is not
#: one the log can show, and a fit that misses an effect could otherwise raise it without
#: bound (the bristles then act as a spring to ground). Far above the cap's own scale the map
#: is exp(u) to within a tenth, so the levels a log does show are fitted as without it.
FRICTION_CAP_FACTOR: float = 10.0
#: Automatic segment length (``choose_segment_length``, ``identify(segment_length="auto")``):
#: SEGMENT_TIME_CONSTANTS mechanical time constants of the start model (inertia over viscous
#: friction of what the replay simulates), within [SEGMENT_MIN_S, SEGMENT_MAX_S] seconds, on
#: a grid of SEGMENT_GRID x 2^k samples (so that logs and starts share compiled programs), and
#: at most SEGMENT_REVERSALS x the log's mean interval between velocity reversals
#: (``reversal_interval``; a reversal counts once the velocity crosses the largest value its
#: noise reaches, plus REVERSAL_MARGIN of its standard deviation, on the other side of zero).
SEGMENT_TIME_CONSTANTS: float = 2.0
SEGMENT_REVERSALS: float = 1.0
REVERSAL_MARGIN: float = 1.0
SEGMENT_MIN_S: float = 0.1
SEGMENT_MAX_S: float = 2.0
SEGMENT_GRID: int = 125
#: The readings' model (``reading_model``, ``exact_reading``): the white noise before an
#: encoder's rounding is at least READ_NOISE_FLOOR of a count, and the exact likelihood
#: replaces the Gaussian where a count is at least QUANTISED_RATIO times that noise.
READ_NOISE_FLOOR: float = 1.0 / 32.0
QUANTISED_RATIO: float = 2.0

def make_problem(
    log: Log, init: Params, free: Sequence[str] = DEFAULT_FREE, *, model: ModelKind = "flexible",
    segment_length: int | None = None, substeps: int | Array = 4,
    outputs: Sequence[str] | None = None,
    output_scale: float | Sequence[float] | None = None, continuity_weight: float = 10.0,
) -> tuple[Problem, tuple[dict[str, Any], Any]]:
    """The identification problem of a log and its starting point (module docstring).

    ``segment_length`` samples per shooting segment (default: the whole log, single
    shooting); a tail shorter than one segment is dropped. ``substeps``: integrator substeps
    per sample, an int (compiled in) or ``jaxflex.fit.dynamic_substeps(n)`` (a traced count:
    problems of every count share the compiled programs; ``identify``'s automatic choice).
    ``outputs``: measured channels fitted, default ("q1", "q2") for the flexible model when
    the log has q2, else ("q1",).
    ``output_scale`` [rad]: one value or one per joint; joint j's residuals (its outputs and
    its continuity defects) are divided by its value (default: each joint's encoder-noise level
    estimated from its own first output channel, at least 1e-6 rad, so that a joint that moves
    little weighs as much as one that moves a lot and a cost of about n_out / 2 is what noise
    explains on every joint). ``continuity_weight`` scales the defects. The output residual
    is Gaussian (``exact_reading`` gives the readings' exact likelihood).
    Raises ``ValueError`` naming a bad model, column, parameter or segment length.
    """
    if model not in MODEL_KINDS:
        raise ValueError(f"identify: model must be one of {MODEL_KINDS}, got {model!r}")
    if log.tau is None or log.q1 is None:
        raise ValueError("identify: the log needs columns tau and q1")
    if log.n != init.n:
        raise ValueError(f"identify: log has {log.n} joint(s), parameters have {init.n}")
    if not int(substeps) >= 1:
        raise ValueError(f"identify: substeps must be >= 1, got {substeps}")
    N = log.N
    L = N if segment_length is None else int(segment_length)
    if not 2 <= L <= N:
        raise ValueError(f"identify: segment_length must be in [2, {N}], got {segment_length}")
    plant = init.to_plant()
    space = ParamSpace.build(plant, free)
    # no friction level the log could never show (``ParamSpace.friction_cap``)
    top = float(np.max(np.abs(np.asarray(log.tau, float))))
    if math.isfinite(top) and top > 0:
        space = eqx.tree_at(lambda s: s.friction_cap, space,
                            to_device(FRICTION_CAP_FACTOR * top))
    outputs = output_columns(log, model, outputs)
    n = log.n
    if output_scale is None:  # each joint's own noise level: joints may move very differently
        meas = np.asarray(getattr(log, outputs[0]), float).reshape(N, n)
        output_scale = [noise_level(meas[:, j])["total_std"] for j in range(n)]
    scale = np.broadcast_to(np.asarray(output_scale, float), (n,))
    if not np.all(np.isfinite(scale) & (scale > 0)):
        raise ValueError(f"identify: output_scale must be positive, got {output_scale}")
    scale = np.maximum(scale, 1e-6)
    segs = make_segments(log, kind=model, outputs=outputs, length=L,
                         friction=plant.lugre)
    dt = log.dt
    if model == "rigid":
        w_def = np.array([1.0, L * dt / 2, 1.0])
    elif model == "rotor":  # the link motion is measured, not simulated: only q2, q2' join
        w_def = np.array([0.0, 0.0, 1.0, L * dt / 2, 0.0])
    elif model == "link":  # the rotor motion is measured, not simulated: q1, q1', z join
        w_def = np.array([1.0, L * dt / 2, 0.0, 0.0, 1.0])
    else:
        w_def = np.array([1.0, L * dt / 2, 1.0, L * dt / 2, 1.0])
    # defects of joint j in units of joint j's noise, as its outputs: (n_state, n)
    w_def = w_def[:, None] * continuity_weight * math.sqrt(L) / scale[None, :]
    # output columns are (channel, joint): ``outputs`` in order, each with n joints
    w_y = np.tile(1.0 / scale, len(outputs))
    prob = Problem(space=space, segs=segs, w_y=jnp.asarray(w_y),
                   w_def=jnp.asarray(w_def), dt=dt, kind=model, substeps=substeps,
                   outputs=outputs, free_starts=True,
                   rolled_stages=True)  # a smaller program: faster to compile and to run
    return prob, prob.y0()


def reading_model(log: Log, prob: Problem) -> tuple[np.ndarray, np.ndarray]:
    """The readings of ``prob``'s output columns (channel-major) as ``log`` shows them: each
    encoder's count and the white noise before its rounding, both in ``prob``'s weighted
    units (``w_y``). The count is ``noise_level``'s step where every reading lies on its grid
    (``on_grid``; else 0: no rounding); the noise is the log's white noise
    beyond the rounding's (``total_std^2 - step^2 / 12``), at least ``READ_NOISE_FLOOR`` of a
    count (the replay is no more exact than that)."""
    cols = [np.asarray(getattr(log, c), float).reshape(log.N, log.n)[:, j]
            for c in prob.outputs for j in range(log.n)]
    levels = [noise_level(c) for c in cols]
    # a count only where the readings lie on its grid (a float log's smallest increment is none)
    step = np.array([v["step"] if on_grid(c, v["step"]) else 0.0
                     for c, v in zip(cols, levels)])
    total = np.array([v["total_std"] for v in levels])
    noise = np.maximum(np.sqrt(np.maximum(total**2 - step**2 / 12.0, 0.0)),
                       READ_NOISE_FLOOR * step)
    w = np.broadcast_to(np.asarray(prob.w_y, float).reshape(-1), step.shape)
    return step * w, np.maximum(noise, 1e-300) * w


def on_grid(q: np.ndarray, step: float, tol: float = 1e-3) -> bool:
    """Whether the readings ``q`` all lie on a grid of ``step`` (to ``tol`` of a step)."""
    if not step > 0:
        return False
    k = (q - q[0]) / step
    return bool(np.max(np.abs(k - np.round(k))) <= tol)


def exact_reading(log: Log, prob: Problem) -> Problem | None:
    """``prob`` with its readings' exact likelihood (``reading_model``,
    ``jaxflex.fit.readings.quantised_residual``), or None where no output column's count is at least
    ``QUANTISED_RATIO`` times its noise (a finer count is the Gaussian's variance)."""
    quantum, noise = reading_model(log, prob)
    if not np.any(quantum >= QUANTISED_RATIO * noise):
        return None
    return dataclasses.replace(prob, quantum=jnp.asarray(quantum),
                               read_noise=jnp.asarray(noise))


def with_readings(prob: Problem, source: Problem) -> Problem:
    """``prob`` with ``source``'s readings' model (``exact_reading``'s ``quantum`` and
    ``read_noise``, weighted units: the two problems share their output weights)."""
    return dataclasses.replace(prob, quantum=source.quantum, read_noise=source.read_noise)


def gaussian_reading(prob: Problem) -> Problem:
    """``prob`` (one with the readings' model, ``exact_reading``) with Gaussian readings of
    its own weighted noise: the least-squares residual, in the exact likelihood's structure
    (the two share compiled programs)."""
    return dataclasses.replace(prob, quantum=jnp.zeros_like(prob.quantum),
                               read_noise=jnp.ones_like(prob.read_noise))


def reading_units(prob: Problem, values: Array) -> list[float]:
    """Per output column, ``values`` in the problem's weighted units back in rad."""
    w = np.broadcast_to(np.asarray(prob.w_y, float).reshape(-1), np.shape(values))
    return [float(v) for v in np.asarray(values, float) / w]


@jax.jit
def _residual_on_host(e: Array, quantum: Array) -> Array:
    """``quantised_residual`` compiled once (the quadrature's grid)."""
    return quantised_residual(e, quantum)


def reading_statistics(prob: Problem) -> tuple[float, float]:
    """``noise_statistics`` for a problem with the readings' exact likelihood
    (``exact_reading``): the expected cost 0.5 ||r||^2 of its output residuals and that
    cost's relative standard deviation, where every model angle is the truth and the reading
    the truth plus the noise, rounded; by quadrature of each column's residual over the
    reading error's density (Phi(h - e) - Phi(-h - e)) / 2h, noise units, h half a count)."""
    from scipy.special import ndtr  # scipy: loaded here

    L = int(prob.segs.y_meas.shape[0] * prob.segs.y_meas.shape[1])
    q = np.asarray(prob.quantum, float) / np.asarray(prob.read_noise, float)
    means, variances = [], []
    for qc in np.atleast_1d(q):
        h = 0.5 * qc
        e = np.linspace(-h - 12.0, h + 12.0, 4001)
        if h <= READING_GAUSS:  # no grid: the unit normal
            dens = np.exp(-0.5 * e**2) / math.sqrt(2 * math.pi)
        else:
            dens = (ndtr(h - e) - ndtr(-h - e)) / (2 * h)
        dens = dens / np.trapezoid(dens, e)
        f = 0.5 * np.asarray(_residual_on_host(e, qc))**2
        m = float(np.trapezoid(f * dens, e))
        means.append(m)
        variances.append(float(np.trapezoid(f**2 * dens, e)) - m**2)
    total = L * float(np.sum(means))
    return total, math.sqrt(L * max(float(np.sum(variances)), 0.0)) / total


#: The model kinds ``identify`` takes, and "auto": the kind the log's encoders suggest.
MODEL_CHOICES: tuple[str, ...] = (*MODEL_KINDS, "auto")
#: Inertia ratios (the log's inverse dynamics against the user's start) that point to a unit
#: or rate mistake: degrees instead of radians (180 / pi) and a time axis off by an integer.
_DEGREES = 180.0 / math.pi


def default_free(model: ModelKind, params: Params, *, from_data: bool,
                 data_offset: bool = False) -> list[str]:
    """The parameters ``identify`` fits when none are named.

    Arguments:
        model: the model kind.
        params: the start.
        from_data: the start is the log's own (``start_from_data``): its inertia (I; J and K
            for the flexible model) is fitted too.
        data_offset: the log's inverse dynamics show a torque offset.

    Returns:
        The six LuGre parameters, the inertia when ``from_data``, and the torque offset
        where ``params`` has a ``torque_offset`` effect or ``data_offset``.
    """
    free = list(DEFAULT_FREE)
    if from_data:
        free += {"rigid": ["I"], "flexible": ["I", "J", "K"], "rotor": ["J", "K"],
                 "link": ["I", "K"]}[model]
    if data_offset or "torque_offset" in params.effects:
        free.append("torque_offset.offset")
    return free


def with_named_effects(init: Params, free: Sequence[str], data: Params | None) -> Params:
    """``init`` with every effect that ``free`` names ("<effect>.<param>") and ``init`` lacks,
    started from the data's start where it has the effect, else from the effect's
    ``typical`` instance (a torque offset from zero)."""
    from jaxflex.core.effects import EFFECTS

    missing = [k.partition(".")[0] for k in free if "." in k]
    missing = [e for e in dict.fromkeys(missing) if e not in init.effects and e in EFFECTS]
    if not missing:
        return init
    effects = dict(init.effects)
    for name in missing:
        if data is not None and name in data.effects:
            effects[name] = data.effects[name]
        else:
            inst = EFFECTS[name].typical(init.n)
            effects[name] = {f.name: np.asarray(getattr(inst, f.name), float).tolist()
                             for f in dataclasses.fields(inst)
                             if not f.metadata.get("static", False)}
    return dataclasses.replace(init, effects=effects)


def start_hints(data: DataStart, init: Params) -> list[str]:
    """Hints for the common log mistakes, from the log's inverse-dynamics inertia against the
    user's start (before any fit): angles in degrees, a time axis off by an integer factor
    (a decimated log, milliseconds). Empty when the two agree within a factor of 3, and for
    a coupled arm (a ``links`` model: the log's per-joint inertia is no field of it)."""
    hints = []
    if init.links is not None:
        return hints
    for j, f in enumerate(data.fits):
        ratio = f["Jx"][0] / float(init.plant["I"][j] + init.plant["J"][j])
        if 1 / 3 <= ratio <= 3:
            continue
        what = f"joint {j}: the log's inverse dynamics give an inertia {ratio:.3g} x the start's"
        if abs(math.log(ratio * _DEGREES)) < math.log(2):
            hints.append(f"{what}: are the angles in degrees? (map them with ':deg')")
        elif ratio > 1 and abs(round(ratio ** 0.5) - ratio ** 0.5) < 0.15:
            # a time axis r x too long makes accelerations r^2 x too small
            hints.append(f"{what}: is the time axis {round(ratio ** 0.5)} x too long "
                         "(a decimated log, a wrong rate)?")
        elif ratio < 1 and abs(round(ratio ** -0.5) - ratio ** -0.5) < 0.15:
            hints.append(f"{what}: is the time axis {round(ratio ** -0.5)} x too short "
                         "(a decimated log, a wrong rate)?")
        else:
            hints.append(f"{what}: check the torque's units and gear ratio")
    return hints


def choose_segment_length(log: Log, init: Params, model: ModelKind = "flexible",
                          ) -> tuple[int | None, dict[str, Any]]:
    """Samples per multiple-shooting segment for ``identify`` on ``log`` from ``init``
    (``segment_length="auto"``): SEGMENT_TIME_CONSTANTS mechanical time constants

        tau_j = inertia_j / sigma2_j  [s]

    of the start model, the smallest over the joints. The inertia is what the replay moves:
    M(q)_jj + J_j at the log's first link angles for the flexible model (at low frequency
    link and rotor move together) and the rigid one (Jx, eq. 37), M(q)_jj for the link
    subsystem, J_j for the rotor subsystem (no plant damping acts there: tau is infinite).
    Why this length: under a force error dF the replay's velocity error settles to dF /
    sigma2 with time constant tau, so within about two time constants a segment has seen the
    inertial and the viscous response (86% of it); beyond that its position error only grows
    linearly (drift), which on a real rig is unmodelled force, and no new information on the
    parameters comes in. The length is clipped to [SEGMENT_MIN_S, SEGMENT_MAX_S] (sigma2 = 0:
    the longest), put on the grid SEGMENT_GRID x 2^k samples (nearest in ratio) and at most
    the log (None: one segment, single shooting). Where the time constants decide, the
    answer depends little on the length: the continuity defects join the segments. A segment
    also spans at most SEGMENT_REVERSALS of the log's mean intervals between velocity
    reversals (``reversal_interval``, of the simulated coordinate: q2 for the rotor
    subsystem, else q1; the smallest over the joints): each reversal is a stick-slip
    transition whose timing hangs on every friction parameter, and a replay that chains
    several of them makes a cost with minima of its own between the starts and the answer.
    Returns (length, record) with the record for the result file: mode, samples, seconds, the
    time constants, the reversal interval and the rule."""
    if model not in MODEL_KINDS:
        raise ValueError(f"identify: model must be one of {MODEL_KINDS}, got {model!r}")
    if log.q1 is None or log.N < 2:
        raise ValueError("identify: the log needs a column q1 with at least 2 samples")
    plant = init.to_plant()
    q0 = np.asarray(log.q1, float).reshape(log.N, -1)[0]
    M = np.diag(np.asarray(plant.links.mass_matrix(jnp.asarray(q0)), float))
    J = np.asarray(plant.J, float)
    inertia = {"flexible": M + J, "rigid": M + J, "link": M, "rotor": J}[model]
    sigma2 = (np.asarray(plant.friction.sigma2, float) if plant.friction is not None
              and model != "rotor" else np.zeros_like(inertia))
    with np.errstate(divide="ignore"):
        tau = np.where(sigma2 > 0, inertia / np.maximum(sigma2, 1e-300), np.inf)
    column = log.q2 if (model == "rotor" and log.q2 is not None) else log.q1
    between = reversal_interval(np.asarray(column, float).reshape(log.N, -1), log.dt)
    span = float(np.clip(min(SEGMENT_TIME_CONSTANTS * np.min(tau), SEGMENT_REVERSALS * between),
                         SEGMENT_MIN_S, SEGMENT_MAX_S))
    k_lo, k_hi = (math.ceil(math.log2(SEGMENT_MIN_S / log.dt / SEGMENT_GRID)),
                  math.floor(math.log2(SEGMENT_MAX_S / log.dt / SEGMENT_GRID)))
    k = round(math.log2(span / log.dt / SEGMENT_GRID))
    k = min(max(k, k_lo), k_hi) if k_lo <= k_hi else k
    L = max(int(SEGMENT_GRID * 2.0 ** k), 2)
    record = {"mode": "auto", "time_constants_s": [float(t) for t in tau],
              "reversal_interval_s": between,
              "rule": f"{SEGMENT_TIME_CONSTANTS:g} x the smallest time constant (inertia / "
                      f"sigma2 of the start model), at most {SEGMENT_REVERSALS:g} x the mean "
                      f"interval between velocity reversals, within [{SEGMENT_MIN_S:g}, "
                      f"{SEGMENT_MAX_S:g}] s, on the grid {SEGMENT_GRID} x 2^k samples"}
    length = None if L >= log.N else L
    return length, {**record, **segments_of(log, length)}


def reversal_interval(q: np.ndarray, dt: float) -> float:
    """Mean interval [s] between velocity reversals of the angles ``q`` (N, n) [rad] sampled
    every ``dt`` [s], the smallest over the joints (inf where a joint never reverses). The
    velocity is ``savgol``'s derivative; a reversal counts once the velocity crosses, on the
    other side of zero, the largest value its own noise reaches in the log (the angle's noise,
    ``noise_level``, through the derivative's weights, times the extreme of as many independent
    draws as the log has windows, plus ``REVERSAL_MARGIN``), so the encoder's noise and
    quantisation at rest count none."""
    n = q.shape[0]
    window, order = savgol_window(31, n), 3
    v = savgol(q, dt, deriv=1, window=window, order=order)
    gain = float(np.linalg.norm(savgol_coeffs(window, order, 1, dt)))  # the same weights
    # the largest of n / window independent normal draws is about sqrt(2 ln(n / window))
    z = math.sqrt(2.0 * math.log(max(n / window, 2.0))) + REVERSAL_MARGIN
    out = math.inf
    for j in range(v.shape[1]):
        level = z * gain * noise_level(q[:, j])["total_std"]
        side = np.sign(v[:, j]) * (np.abs(v[:, j]) > level)
        side = side[side != 0]
        count = int(np.sum(side[1:] != side[:-1]))
        if count:
            out = min(out, v.shape[0] * dt / count)
    return out


def segments_of(log: Log, length: int | None) -> dict[str, Any]:
    """The record of ``log``'s multiple-shooting segments of ``length`` samples (None: one
    segment, the whole log): samples, seconds, segments."""
    L = length or log.N
    return {"samples": L, "seconds": L * log.dt, "segments": log.N // L}


def noise_statistics(log: Log, prob: Problem) -> tuple[float, float]:
    """The cost 0.5 ||r||^2 that white Gaussian measurement noise alone gives ``prob`` (a
    ``make_problem`` problem of ``log``), in its weighted units, and that cost's relative
    standard deviation.

    The cost is 0.5 sum over the output columns (channel, joint) of L samples x a, a =
    (sigma w)^2, sigma the column's own noise (``noise_level``, at least 1e-6 rad, the floor
    of ``make_problem``'s scale) and w its weight: about n_out / 2 when every channel is as
    noisy as the one that set the scale; less for a finer second encoder (a 20-bit link
    encoder with the motor's far finer one: about n_out / 4). Each residual's 0.5 e^2 has
    variance 0.5 a^2, so the spread is sqrt(2 / L) sqrt(sum a^2) / sum a (sqrt(2 / n_out)
    when every column is alike)."""
    L = int(prob.segs.y_meas.shape[0] * prob.segs.y_meas.shape[1])
    w = np.asarray(prob.w_y, float).reshape(-1)
    sig = [max(noise_level(np.asarray(getattr(log, c), float).reshape(log.N, log.n)[:, j])
               ["total_std"], 1e-6) for c in prob.outputs for j in range(log.n)]
    a = (np.asarray(sig) * np.broadcast_to(w, (len(sig),))) ** 2
    total = float(np.sum(a))
    return 0.5 * L * total, math.sqrt(2.0 / L) * math.sqrt(float(np.sum(a ** 2))) / total


def noise_cost(log: Log, prob: Problem) -> float:
    """The cost 0.5 ||r||^2 that measurement noise alone gives ``prob`` (``noise_statistics``,
    its first part)."""
    return noise_statistics(log, prob)[0]
