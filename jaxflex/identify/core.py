"""Joint identification from one log by gradient through the simulator (docs/spec.md
section 5): a thin workflow on the fitting engine ``jaxflex.fit``.

Output-error least squares with multiple shooting and free segment start states
(``jaxflex.fit.Problem``): residuals are the output errors ``w_y (y_sim - y_meas)`` with
``y = q1`` (and ``q2`` for the flexible model) and the continuity defects between segments,
``w_y`` the inverse of the encoder-noise level estimated from the log, so a cost of about
``n_out / 2`` (``noise_cost``, less with a finer second encoder) is what noise explains. Physical constraints hold by reparametrisation
(``jaxflex.fit.ParamSpace``); the solver is the engine's Levenberg-Marquardt
(``jaxflex.fit.least_squares``); standard errors come from the engine's covariance with the
nuisance start states included. Several starts (the user's, the log's static map, the log's
inverse dynamics, ``jaxflex.identify.start``) and continuation schedules guard against local
minima; the answer is the best point any solve reached, with a two-part verdict
(``jaxflex.identify.verdict``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.fit import (
    CostBound,
    ParamSpace,
    Problem,
    Solution,
    cost,
    covariance,
    discretisation_bias,
    dynamic_substeps,
    get_value,
    least_squares,
    make_segments,
    noise_level,
    output_columns,
    refined,
    remaining_step,
    segment_robust_covariance,
    set_values,
    simulated_outputs,
    step_doubling_error,
    trace_solver,
)
from jaxflex.fit.ahead import Ahead
from jaxflex.identify.start import DataStart, StartError, check_model, start_from_data
from jaxflex.identify.static import start_from_static_map
from jaxflex.identify.verdict import model_verdict
from jaxflex.logs import Log
from jaxflex.params import Params
from jaxflex.state import PlantState
from jaxflex.validation import requires_float64, to_device
from jaxflex.step import MODEL_KINDS, ModelKind, replay

DEFAULT_FREE: tuple[str, ...] = ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")
#: identify's solver settings (``least_squares``): geodesic acceleration's bound on
#: 2 |a| / |v|, and the statistical stop (Gauss-Newton decrement, chi-square units)
GEODESIC: float = 0.3
DECREMENT_TOL: float = 1e-2
#: Automatic substeps (``choose_substeps``, ``identify(substeps="auto")``): the first choice
#: keeps the replay's step-doubling error below OUTPUT_TOL of the noise (weighted RMS: the
#: cost is then inflated by at most a quarter of what the noise explains, so the judgements
#: "settled" and "identifiable" still hold at that level); the fit is then refined until the
#: integrator moves no fitted parameter by more than BIAS_TOL standard errors
#: (``jaxflex.fit.discretisation_bias``), at most MAX_SUBSTEPS. Measured on the 3 s
#: closed-loop logs of seeds 7-14 (20-bit encoder, 50% off): a first choice at 2 noise units
#: (1 substep) left seed 8 unconverged; 0.5 and 0.1 converged the same seven (13 fails either
#: way), every one within 0.8% and within 0.33 standard errors of the integrator.
OUTPUT_TOL: float = 0.5
BIAS_TOL: float = 0.5
#: ``refine_fit`` also refines while the integrator moves a fitted parameter by more than
#: this share of its value: the standard errors of a model-limited fit are inflated by its
#: residual and alone would let a coarse integrator bias the answer.
BIAS_REL: float = 5e-3
MAX_SUBSTEPS: int = 32
#: Automatic segment length (``choose_segment_length``, ``identify(segment_length="auto")``):
#: SEGMENT_TIME_CONSTANTS mechanical time constants of the start model (inertia over viscous
#: friction of what the replay simulates), within [SEGMENT_MIN_S, SEGMENT_MAX_S] seconds, on
#: a grid of SEGMENT_GRID x 2^k samples (so that logs and starts share compiled programs).
SEGMENT_TIME_CONSTANTS: float = 2.0
SEGMENT_MIN_S: float = 0.1
SEGMENT_MAX_S: float = 2.0
SEGMENT_GRID: int = 125
#: ``refine_fit``: the most the substeps grow in one refinement.
REFINE_MOST: int = 8


class IdentificationWarning(UserWarning):
    """Raised (as a warning) for parameters the data cannot identify."""


@dataclasses.dataclass
class IdentResult:
    """Outcome of ``identify``.

    params: identified ``Params`` (standard errors under ``extra["stderr"]``);
    stderr, rel_stderr: dict name -> list per joint (physical units; relative = stderr/|value|),
    segment-robust (``jaxflex.fit.segment_robust_covariance``: they hold for residuals
    correlated in time, a model's mismatch on a real log) where the log has the segments for
    it, as is the posterior in the file (``identification.stderr_kind`` says which);
    cost: final 0.5 sum r^2 (output and continuity residuals, in the weighted units);
    rms: RMS output residual [rad]; rank, n_free: numerical rank of the Jacobian over all
    unknowns and their number; singular_values of the column-scaled Jacobian; unidentifiable:
    names the data cannot identify, marked ``"identified": false`` with the reason in the
    file (those fixed at their start values, or kept at their fitted values where fixing
    them costs what the data can see); warnings: messages; steps: solver steps;
    converged: the solver reached a stationary point (its tolerance or statistical stop);
    model: the model's half of the verdict (``jaxflex.identify.verdict.model_verdict``:
    "adequate" when the measurement noise explains the cost, else "model-limited" with the
    residual's size, colour and where it sits); reason: both halves in words; noise_cost:
    accept_cost x what the noise explains; wall_s: solve time [s]; problem: the ``Problem``
    (for re-simulation and benchmarks); solution: the solver's final unknowns (theta and
    segment states); attempts: every solve, with its final cost and how it ended; why: per
    unidentifiable name, the reason; discretisation: the substeps used and how far they move
    the fitted parameters (``refine_fit``); segments: the multiple-shooting segments (their
    length, how it was chosen). rank, n_free, singular_values describe the fit with every
    free parameter (before any was fixed).
    """

    params: Params
    stderr: dict[str, list[float]]
    rel_stderr: dict[str, list[float]]
    cost: float
    rms: float
    rank: int
    n_free: int
    singular_values: list[float]
    unidentifiable: list[str]
    warnings: list[str]
    steps: int
    converged: bool
    wall_s: float
    problem: Problem
    solution: Any
    attempts: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    reason: str = ""
    noise_cost: float = math.nan
    why: dict[str, str] = dataclasses.field(default_factory=dict)
    discretisation: dict[str, Any] = dataclasses.field(default_factory=dict)
    segments: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: relative standard errors of white residuals (the information in the data), on which
    #: identifiability is judged and the least determined parameter chosen
    information_rel_stderr: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    model: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def adequate(self) -> bool:
        """Whether the model explains the log to its noise level (``model["verdict"]``)."""
        return self.model.get("verdict") == "adequate"

    def table(self) -> str:
        """A short text table: name, value, standard error, relative standard error (or
        "unidentified", with the value kept at its initial guess)."""
        rows = [f"{'param':<24}{'value':>14}{'stderr':>12}{'rel':>12}"]
        for name in self.stderr:
            vals = get_value(self.params, name).tolist()
            for j, v in enumerate(vals):
                label = name if len(vals) == 1 else f"{name}[{j}]"
                if name in self.unidentifiable:
                    rows.append(f"{label:<24}{v:>14.6g}{'-':>12}{'unidentified':>12}")
                    continue
                se, rel = self.stderr[name][j], self.rel_stderr[name][j]
                rel_s = f"{100 * rel:.2f}%" if rel <= 10 else "> 1e3 %"
                rows.append(f"{label:<24}{v:>14.6g}{se:>12.3g}{rel_s:>12}")
        rows.append(f"RMS output residual {self.rms:.3g}; cost {self.cost:.4g} (noise explains "
                    f"<= {self.noise_cost:.4g}); Jacobian rank {self.rank}/{self.n_free}; "
                    f"{self.steps} steps; converged: {self.converged} ({self.reason})")
        kind = self.params.extra.get("identification", {}).get("stderr_kind")
        if kind:
            rows.append(f"standard errors: {kind}; identifiability judged on the "
                        "white-residual information")
        d = self.discretisation
        if d.get("substeps"):
            rows.append(f"integrator: {d['substeps']} substeps per sample ({d['mode']}); it moves "
                        f"the fitted parameters by at most {d['bias_se']:.2g} standard errors")
        g = self.segments
        if g.get("samples"):
            rows.append(f"segments: {g['segments']} of {g['samples']} samples "
                        f"({g['seconds']:.3g} s, {g['mode']})")
        if self.unidentifiable:
            rows.append(f"unidentified (kept at their initial values): {self.unidentifiable}")
        return "\n".join(rows)


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
    explains on every joint). ``continuity_weight`` scales the defects.
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
    # no friction level above the largest torque the log applies (``ParamSpace.friction_cap``)
    top = float(np.max(np.abs(np.asarray(log.tau, float))))
    if math.isfinite(top) and top > 0:
        space = eqx.tree_at(lambda s: s.friction_cap, space, to_device(top))
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
                         friction=plant.friction)
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
                   outputs=outputs, free_starts=True)
    return prob, prob.y0()


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


def _with_named_effects(init: Params, free: Sequence[str], data: Params | None) -> Params:
    """``init`` with every effect that ``free`` names ("<effect>.<param>") and ``init`` lacks,
    started from the data's start where it has the effect, else from the effect's
    ``typical`` instance (a torque offset from zero)."""
    from jaxflex.effects import EFFECTS

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
    (a decimated log, milliseconds). Empty when the two agree within a factor of 3."""
    hints = []
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


#: A model-limited solve that ends at its step cap is converged when a full Gauss-Newton step
#: would move no parameter by more than this many of its reported standard errors.
REMAINING_TOL: float = 0.1


class _Search:
    """Every solve of one identification: the attempts written to the file and the end
    points of the full problem's solves, from which the best is taken at the end."""

    def __init__(self, good: float, solve: dict[str, Any], progress: bool | int):
        self.good, self.solve, self.progress = good, solve, progress
        self.attempts: list[dict[str, Any]] = []
        self.ends: list[tuple[int, Any]] = []  # (attempt index, y) of the full problem

    def run(self, prob: Problem, y: Any, label: dict[str, Any], max_steps: int,
            full: bool = True) -> Solution:
        """One ``least_squares`` solve, recorded; a Ctrl-C inside it ends the whole
        identification (``KeyboardInterrupt``)."""
        sol = least_squares(prob, y, max_steps=max_steps, **self.solve)
        if sol.interrupted:
            raise KeyboardInterrupt
        if "warm" not in label and not sol.converged and sol.cost > self.good and (
                sol.normal is not None):
            # a model-limited fit creeping down a valley: converged when the step that
            # remains is small against the standard errors it reports (segment-robust)
            rem = remaining_step(prob, sol)
            if rem <= REMAINING_TOL:
                sol = dataclasses.replace(sol, converged=True, reason=(
                    f"statistical stop at the reported (segment-robust) standard errors: a "
                    f"full Gauss-Newton step would move no parameter by more than {rem:.2g} "
                    f"of them ({sol.reason})"))
        self.attempts.append({**label, "cost": sol.cost, "steps": sol.steps,
                              "converged": sol.converged, "reason": sol.reason})
        if full:
            self.ends.append((len(self.attempts) - 1, sol.y))
        if self.progress and "start" in label:
            print(f"  [identify] {label['start']}: cost {sol.cost:.6e} (noise explains <= "
                  f"{self.good:.3e}); {sol.reason}")
        return sol


@requires_float64
def identify(
    log: Log, init: Params | None = None, free: Sequence[str] | None = None, *,
    model: ModelKind | str = "flexible", segment_length: int | str | None = "auto",
    substeps: int | str = "auto",
    outputs: Sequence[str] | None = None, output_scale: float | Sequence[float] | None = None,
    continuity_weight: float = 10.0,
    warm_start: float | None | Sequence[float | None] = (1e-3, 1e-2, None),
    warm_steps: int = 40, accept_cost: float = 4.0,
    rtol: float = 1e-10, atol: float = 1e-10, max_steps: int = 200,
    rel_stderr_limit: float = 0.5, progress: bool | int = False, static_start: bool = True,
    decrement_tol: float | None = DECREMENT_TOL, geodesic: float = GEODESIC,
    vs_restarts: Sequence[float] = (3.0, 1.0 / 3.0), data_start: bool = True,
    pin: Mapping[str, float | Sequence[float]] | None = None,
) -> IdentResult:
    """Identify the ``free`` parameters from ``log`` (docs/spec.md section 5).

    Arguments:
        log: the log (docs/spec.md section 6).
        init: the start parameter set; None: the log's own (``start_from_data``, linear
            least squares on the inverse dynamics), every parameter included.
        free: the fitted names (``jaxflex.fit.ParamSpace``); None: ``default_free``. A name
            "<effect>.<param>" of an effect ``init`` lacks adds the effect, started from the
            data's estimate (a torque offset) or the effect's typical value.
        model: "flexible" (eq. 3), "rigid" (eq. 37, Jx = I + J), "rotor", "link"
            (``jaxflex.step.MODEL_KINDS``), or "auto": the kind the encoders suggest
            (``suggest_model``: one encoder, q1 = q2, is rigid).
        segment_length: samples per multiple-shooting segment (None: single shooting), or
            "auto": two mechanical time constants of the start model
            (``choose_segment_length``).
        substeps: integrator substeps per sample, or "auto": the fewest whose replay error at
            the start is below ``OUTPUT_TOL`` of the noise (``choose_substeps``), then refined
            at the solution until its own finer replay moves no fitted parameter by more than
            ``BIAS_TOL`` standard errors nor ``BIAS_REL`` of its value (``refine_fit``).
        warm_start, warm_steps: continuation schedules: the first ``warm_steps`` steps with
            the continuity weight times each factor (None: none), tried in turn.
        accept_cost: the model is adequate when the cost is at most this times what the
            noise explains (``noise_cost``).
        rtol, atol, max_steps, decrement_tol, geodesic: the solver's
            (``jaxflex.fit.least_squares``).
        rel_stderr_limit: a parameter above this relative standard error (white residuals),
            or in a null direction, is fixed at its start if that costs no more than the
            noise can tell (``_REFIT_TOL`` at the fit's residual scale); else it keeps its
            fitted value, marked as poorly determined.
        static_start: a start from the log's static friction map (``start_from_static_map``).
        vs_restarts: when no start reaches an adequate fit, the first start again with vs
            multiplied by these factors.
        data_start: also start from the log's inverse dynamics when ``init`` is given.
        pin: names (as ``free``) set to these values on the start and not fitted (a value
            or one per joint).
        progress: print the cost every ``progress`` steps (True: every step).

    Returns:
        An ``IdentResult`` whose file records every attempt's cost and how it ended
        (``identification.attempts``), the two-part verdict (``converged``: the solver reached
        a stationary point; ``identification.model``: adequate or model-limited, from
        ``model_verdict``). The answer is never worse than the best point any solve of the
        full problem reached, judged at the final discretisation.

    Raises:
        ValueError: a bad model, column, parameter, segment length, a log whose single
            encoder is asked to be flexible, or (``init`` None) a log whose inverse dynamics
            give no physical start.
        KeyboardInterrupt: on Ctrl-C, from within the solve that was running.
    """
    auto = substeps == "auto"
    if not auto and not (isinstance(substeps, int) and substeps >= 1):
        raise ValueError(f"identify: substeps must be a positive integer or 'auto', "
                         f"got {substeps!r}")
    if model not in MODEL_CHOICES:
        raise ValueError(f"identify: model must be one of {MODEL_CHOICES}, got {model!r}")
    model, why_kind = check_model(log, model)
    data, data_note = None, ""
    if init is None or data_start:
        try:
            data = start_from_data(log, model)
        except StartError as e:
            if init is None:
                raise ValueError(f"identify: no start from the data: {e}; give a start "
                                 "(--params)") from None
            data_note = str(e)
    hints = start_hints(data, init) if (data is not None and init is not None) else []
    for h in hints:
        warnings.warn(h, IdentificationWarning, stacklevel=3)
    user_start = init is not None
    init = data.params if init is None else init
    if free is None:
        free = default_free(model, init, from_data=not user_start, data_offset=(
            data is not None and "torque_offset" in data.params.effects))
    free = list(free)
    if pin:
        init = set_values(init, {k: np.broadcast_to(np.asarray(v, float), (init.n,))
                                 for k, v in pin.items()})
        free = [k for k in free if k not in pin]
    init = _with_named_effects(init, free, None if data is None else data.params)
    if isinstance(segment_length, str):
        if segment_length != "auto":
            raise ValueError(f"identify: segment_length must be a number of samples, None or "
                             f"'auto', got {segment_length!r}")
        segment_length, segments = choose_segment_length(log, init, model)
    else:
        segments = {"mode": "given", **_segments_of(log, segment_length)}
    prob, y0 = make_problem(
        log, init, free, model=model, segment_length=segment_length,
        substeps=dynamic_substeps(1) if auto else substeps,
        outputs=outputs, output_scale=output_scale, continuity_weight=continuity_weight,
    )
    # the statistical stop at the fit's own residual scale: a step that would lower chi-square
    # by less than ``decrement_tol`` in units of the residual variance the fit leaves (the
    # noise's, or more for a model-limited fit: cost / noise cost), is below 0.1 of the
    # standard errors that residual gives; on a real rig's log the noise's own units would
    # run every solve to its step cap
    noise = noise_cost(log, prob)
    stop = (None if decrement_tol is None
            else CostBound(decrement_tol / noise, 0.0, (0.0, decrement_tol)))
    # the solver options every solve of this fit shares (they key its compiled program)
    options = dict(rtol=rtol, atol=atol, decrement_tol=stop, geodesic=geodesic)
    ahead = compile_ahead(prob, y0, options)
    starts = _starts(log, init, free, prob, y0, model, static_start, user_start, data)
    discretisation: dict[str, Any] = {"mode": "auto" if auto else "given"}
    if auto:
        prob, discretisation["first"] = choose_substeps(prob, starts[0][1])
    every = int(progress)
    say = None
    if progress:
        say = lambda k, c: print(f"  [identify] step {k:4d}  cost {c:.6e}") if k % every == 0 else None
    schedules = list(warm_start) if isinstance(warm_start, (list, tuple)) else [warm_start]
    if not schedules:
        raise ValueError("identify: warm_start needs at least one schedule (a factor or None)")
    if prob.segs.count == 1:  # one segment: nothing to loosen
        schedules = [None]
    good = accept_cost * noise
    search = _Search(good, dict(options, progress=say), progress)
    t0 = time.perf_counter()
    best, best_factor = None, None

    def warmed(problem: Problem, y: Any, factor: float | None, label: str) -> Any:
        """``y`` after the first phase of the schedule ``factor``: at most ``warm_steps``
        steps with the continuity weight times ``factor`` (None, or one segment: ``y``)."""
        if factor is None or problem.segs.count == 1:
            return y
        loose = eqx.tree_at(lambda q: q.w_def, problem, problem.w_def * factor)
        return search.run(loose, y, {"warm": label, "warm_start": factor}, warm_steps,
                          full=False).y

    ahead.wait(0)
    for origin, y_start in starts:
        for factor in schedules:
            y = warmed(prob, y_start, factor, origin)
            label = {"start": origin, "warm_start": factor}
            sol = search.run(prob, y, label, max_steps)
            if sol.cost <= good and not sol.converged:
                # at the noise level but still moving: let it settle before judging
                more = search.run(prob, sol.y, {"start": f"{origin}, continued"}, max_steps)
                sol = dataclasses.replace(more, steps=sol.steps + more.steps,
                                          seconds=sol.seconds + more.seconds)
            if best is None or sol.cost < best.cost:
                best, best_factor = sol, factor
            if _settled(sol, good):
                break
        if _settled(best, good):
            break
    if not _settled(best, good) and "vs" in prob.space.names and vs_restarts:
        # The Stribeck velocity decides where in the velocity range the friction hump lies;
        # a fit whose vs starts on the wrong side of it lets Fs and sigma1 absorb the hump
        # and vs stops moving: the first start again, vs on either side.
        origin, (th0, x0) = starts[0]
        phys = prob.space.physical_values(th0)
        for f in vs_restarts:
            th = prob.space.theta_of({**phys, "vs": phys["vs"] * f})
            y = warmed(prob, (th, x0), schedules[0], f"{origin}, vs x{f:g}")
            label = {"start": f"{origin}, vs x{f:g}", "warm_start": schedules[0]}
            sol = search.run(prob, y, label, max_steps)
            if sol.cost < best.cost:
                best, best_factor = sol, schedules[0]
            if _settled(sol, good):
                break
    ahead.join()
    first = finish(prob, init, best.y, steps=best.steps, converged=best.converged,
                   wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                   reason=_reason(best, good), noise_cost=good, log=log, solution=best)
    f_prob, f_sol, f_fixed, total = _fix_unidentified(
        search, first, prob, best, init, y0, log, free, model=model,
        segment_length=segment_length, outputs=outputs, output_scale=output_scale,
        continuity_weight=continuity_weight, max_steps=max_steps, good=good,
        warmed=lambda p, y: warmed(p, y, best_factor, "refit"),
        noise=good / accept_cost, rel_stderr_limit=rel_stderr_limit)
    # the integrator must not move the answer: refined at the solution, coarse to fine
    r_prob, r_sol, discretisation["checks"] = refine_fit(
        f_prob, f_sol, refine=auto, solve=dict(search.solve, max_steps=max_steps),
        attempts=search.attempts)
    if r_prob is not f_prob:
        total += r_sol.steps - f_sol.steps
    # never worse than the best point a solve of the full problem reached, at this
    # discretisation: every end point replayed with the final substeps
    margin = _REFIT_TOL * max(1.0, best.cost * accept_cost / good) if f_fixed else 0.0
    r_prob, r_sol, f_fixed, total = _best_at_final(
        search, prob, r_prob, r_sol, f_fixed, total, max_steps, margin)
    discretisation.update(discretisation["checks"][-1])
    n_sub = r_prob.n_substeps
    res = finish(r_prob, init, r_sol.y, steps=total, converged=r_sol.converged,
                 wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                 reason=_reason(r_sol, good), noise_cost=good, log=log,
                 unidentified=f_fixed, solution=r_sol)
    if f_fixed:
        res.rank, res.n_free, res.singular_values = first.rank, first.n_free, first.singular_values
        res.warnings = first.warnings + res.warnings
    verdict = model_verdict(r_prob, r_sol.y, res.cost, good / accept_cost, accept_cost)
    ident = res.params.extra["identification"]
    ident["model"] = verdict
    ident["solver"] = {"converged": r_sol.converged, "reason": r_sol.reason}
    ident["attempts"] = search.attempts
    ident["discretisation"] = discretisation
    ident["segments"] = segments
    ident["start"] = {"kind": model, "kind_reason": why_kind,
                      "user": user_start, "hints": hints,
                      **({"data": data.fits} if data is not None else {}),
                      **({"data_refused": data_note} if data_note else {})}
    res.model = verdict
    res.attempts = search.attempts
    res.discretisation = discretisation
    res.segments = segments
    res.warnings = hints + res.warnings
    d = discretisation
    if not (d["bias_se"] <= BIAS_TOL and d.get("bias_rel", 0.0) <= BIAS_REL) and math.isfinite(
            d["bias_se"]):
        msg = (f"the integrator ({n_sub} substeps per sample) moves a fitted parameter by "
               f"{d['bias_se']:.3g} standard errors and {100 * d.get('bias_rel', 0.0):.3g}% "
               f"(> {BIAS_TOL} and {100 * BIAS_REL:g}%): use more substeps (or "
               "substeps='auto')")
        res.warnings.append(msg)
        warnings.warn(msg, IdentificationWarning, stacklevel=2)
    return res


def _starts(log: Log, init: Params, free: Sequence[str], prob: Problem, y0: Any,
            model: str, static_start: bool, user_start: bool, data: DataStart | None,
            ) -> list[tuple[str, Any]]:
    """The starts, in the order they are tried: the log's static map over the start, the
    user's start, the log's inverse dynamics (each once: the data start is the start when
    the user gave none)."""
    starts: list[tuple[str, Any]] = []
    static = (start_from_static_map(log, init, free)
              if (static_start and model in ("flexible", "link")) else None)
    if static:
        th = prob.space.theta_of({**{k: get_value(init, k) for k in prob.space.names},
                                  **static})
        starts.append(("static map of the log", (th, y0[1])))
    starts.append(("user" if user_start else "inverse dynamics of the log", y0))
    if user_start and data is not None:
        vals = {}
        for k in prob.space.names:
            try:
                vals[k] = get_value(data.params, k)
            except (KeyError, ValueError):
                vals[k] = get_value(init, k)
        th = prob.space.theta_of(vals)
        starts.append(("inverse dynamics of the log", (th, y0[1])))
    return starts


#: A parameter the data cannot determine is fixed at its start only when that raises the
#: cost by at most this many units of 0.5 chi-square at the fit's own residual scale
#: (cost / noise cost, at least 1): a fixing the data can see is not made.
_REFIT_TOL: float = 2.0


def _fix_unidentified(search: _Search, res: IdentResult, prob: Problem, best: Solution,
                      init: Params, y0: Any, log: Log, free: Sequence[str], *,
                      model: str, segment_length: int | None, outputs: Any, output_scale: Any,
                      continuity_weight: float, max_steps: int, good: float, warmed: Any,
                      noise: float, rel_stderr_limit: float,
                      ) -> tuple[Problem, Solution, dict[str, str] | None, int]:
    """Fix what the data cannot determine at its start value and refit the rest, one
    parameter at a time (the least determined first: the largest relative standard error,
    then the names of a null direction, never Fs before Fc), each refit from the values
    fitted so far and from the user's start. The refits are kept when the last one's cost is
    within ``_REFIT_TOL`` of the free fit's (at the fit's residual scale), and then released
    once from their point; otherwise the free fit is the answer, its poorly determined
    parameters marked at their fitted values. Returns the answer's problem, solution, the
    names fixed (with why; None: none) and the steps taken."""
    fixed_why: dict[str, str] = {}
    cur, sol_cur, total = prob, best, best.steps
    for _ in range(len(prob.space.names)):
        own = [k for k in res.unidentifiable if k in cur.space.names
               and not res.why.get(k, "").startswith("kept at its initial value with")]
        if not own:
            break
        worst = max(own, key=lambda k: (k != "Fs" or len(own) == 1,  # fixing Fs caps Fc
                                        "null direction" not in res.why.get(k, ""),
                                        max(res.information_rel_stderr.get(k, [0.0]))))
        keep = [k for k in cur.space.names if k != worst]
        if not keep:
            break
        fixed_why[worst] = res.why[worst]
        sub, _ = make_problem(log, init, keep, model=model, segment_length=segment_length,
                              substeps=prob.substeps, outputs=outputs,
                              output_scale=output_scale, continuity_weight=continuity_weight)

        def kept(space: Any, y: Any) -> Any:
            """``y`` in the refit's coordinates: the physical values of the names kept (an
            ordered Fs is built on Fc, so with Fc fixed the same coordinate is another Fs)."""
            phys = space.physical_values(y[0])
            return sub.space.theta_of({k: phys[k] for k in keep}), y[1]

        sol = None
        for label, start_of in (("fitted", lambda: kept(cur.space, sol_cur.y)),
                                ("user", lambda: warmed(sub, kept(prob.space, y0)))):
            s_ = search.run(sub, start_of(), {"refit_without": list(fixed_why),
                                              "start": label}, max_steps, full=False)
            total += s_.steps
            if sol is None or s_.cost < sol.cost:
                sol = s_
            if _settled(sol, good):
                break
        res = finish(sub, init, sol.y, steps=total, converged=sol.converged, wall_s=0.0,
                     rel_stderr_limit=rel_stderr_limit, noise_cost=good, log=log,
                     unidentified=dict(fixed_why), solution=sol)
        cur, sol_cur = sub, sol
    if not fixed_why:
        return prob, best, None, total
    scale = max(1.0, best.cost / noise)
    if sol_cur.cost > best.cost + _REFIT_TOL * scale:
        # fixing them costs what the data can see: they are determined, if poorly; the free
        # fit is the answer, with them marked (``finish``'s ``poorly``)
        search.attempts.append({"refits_rejected": list(fixed_why),
                                "cost_increase": sol_cur.cost - best.cost,
                                "tolerance": _REFIT_TOL * scale})
        return prob, best, None, total
    # judged unidentifiable at the first fit's point, which may be a local minimum: from the
    # refit's lower point, free them again; kept if then every parameter is determined
    # in physical values: an ordered pair's coordinates differ between the two spaces
    phys = cur.space.physical_values(sol_cur.y[0])
    th = prob.space.theta_of({k: phys[k] if k in phys else get_value(init, k)
                              for k in prob.space.names})
    full = search.run(prob, (th, sol_cur.y[1]), {"released": list(fixed_why),
                                                 "start": "refit"}, max_steps)
    total += full.steps
    if full.cost < sol_cur.cost:
        again = finish(prob, init, full.y, steps=total, converged=full.converged, wall_s=0.0,
                       rel_stderr_limit=rel_stderr_limit, noise_cost=good, log=log,
                       solution=full)
        if not again.unidentifiable:
            return prob, full, None, total
    return cur, sol_cur, dict(fixed_why), total


def _best_at_final(search: _Search, prob: Problem, r_prob: Problem, r_sol: Solution,
                   fixed: dict[str, str] | None, total: int, max_steps: int, margin: float,
                   ) -> tuple[Problem, Solution, dict[str, str] | None, int]:
    """The answer, or the best end point of the full problem's solves if one is lower at the
    answer's discretisation (every end point replayed with its substeps; recorded as
    ``cost_final`` in the attempts), continued there. A fit with fixed parameters (the same
    residual, fewer unknowns) gives way only to a point lower by more than ``margin``, the
    cost its fixing was allowed."""
    final = dataclasses.replace(prob, substeps=r_prob.substeps)
    costs = []
    for i, y in search.ends:
        c = cost(final, y)
        search.attempts[i]["cost_final"] = c
        costs.append((c, i, y))
    if not costs:
        return r_prob, r_sol, fixed, total
    c_best, i_best, y_best = min(costs, key=lambda t: t[0])
    if not c_best < r_sol.cost - margin:
        return r_prob, r_sol, fixed, total
    again = search.run(final, y_best, {"start": f"best end point (attempt {i_best})",
                                       "substeps": final.n_substeps}, max_steps)
    total += again.steps
    if again.cost < r_sol.cost - margin:
        return final, again, None, total
    return r_prob, r_sol, fixed, total


def compile_ahead(prob: Problem, y0: Any, solve: dict[str, Any]) -> Ahead:
    """The compiled programs of ``prob``'s fit (its solver, then its covariance and
    discretisation check), made in a background thread (``jaxflex.fit.ahead``) while
    ``identify`` does the work that comes before them: the static map's own fit and the
    choice of substeps. On the two cores of the project's machine the two compilations
    overlap; the solver is the same program at every level of substeps
    (``dynamic_substeps``) and every warm-start weight, so the one made here serves them all.
    The thread runs one solver step from ``y0`` and discards it. ``solve``: the
    ``least_squares`` options of the real solves that key their program (tolerances,
    geodesic); ``wait(0)`` before the first solve, ``join`` before the covariance, so that no
    program is compiled twice at once."""
    made: dict[str, Solution] = {}
    # the solver's trace holds the interpreter: made here, alone, before the thread starts
    # (traced by turns with the static map's fit, it finished 0.6 s later and its
    # compilation with it)
    trace_solver(prob, y0, **solve)

    def solver() -> None:
        made["solution"] = least_squares(prob, y0, max_steps=1, **solve)

    def checks() -> None:
        sol = made.get("solution")
        if sol is not None and sol.normal is not None:
            covariance(prob, sol.y, solution=sol)
            discretisation_bias(prob, sol)

    return Ahead([solver, checks])


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
    the log (None: one segment, single shooting). On the paper's plant 50% off (tau 0.28 s)
    it gives 500 samples at 1 kHz, on EMPS from the study's start (60 kg, 100 N s/m) 1000;
    there the fit (2 substeps) with 250 / 500 / 1000 / 2000 samples gave closed-loop force
    errors of 4.6-6.0% (DATA_EMPS), and on generated logs the answer does not depend on the
    length (the continuity defects join the segments). Returns (length, record) with the record for
    the result file: mode, samples, seconds, the time constants and the rule."""
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
    span = float(np.clip(SEGMENT_TIME_CONSTANTS * np.min(tau), SEGMENT_MIN_S, SEGMENT_MAX_S))
    k_lo, k_hi = (math.ceil(math.log2(SEGMENT_MIN_S / log.dt / SEGMENT_GRID)),
                  math.floor(math.log2(SEGMENT_MAX_S / log.dt / SEGMENT_GRID)))
    k = round(math.log2(span / log.dt / SEGMENT_GRID))
    k = min(max(k, k_lo), k_hi) if k_lo <= k_hi else k
    L = max(int(SEGMENT_GRID * 2.0 ** k), 2)
    record = {"mode": "auto", "time_constants_s": [float(t) for t in tau],
              "rule": f"{SEGMENT_TIME_CONSTANTS:g} x the smallest time constant (inertia / "
                      f"sigma2 of the start model), within [{SEGMENT_MIN_S:g}, "
                      f"{SEGMENT_MAX_S:g}] s, on the grid {SEGMENT_GRID} x 2^k samples"}
    length = None if L >= log.N else L
    return length, {**record, **_segments_of(log, length)}


def _relative(stderr: dict[str, Any], phys: dict[str, Any]) -> dict[str, list[float]]:
    """Relative standard errors stderr / |value| per name (lists per joint)."""
    return {k: (np.asarray(stderr[k]) / np.maximum(np.abs(phys[k]), 1e-300)).tolist()
            for k in phys}


def _segments_of(log: Log, length: int | None) -> dict[str, Any]:
    """The record of ``log``'s multiple-shooting segments of ``length`` samples (None: one
    segment, the whole log): samples, seconds, segments."""
    L = length or log.N
    return {"samples": L, "seconds": L * log.dt, "segments": log.N // L}


def choose_substeps(prob: Problem, y: Any, *, tol: float = OUTPUT_TOL,
                    most: int = MAX_SUBSTEPS) -> tuple[Problem, dict[str, Any]]:
    """The first choice of substeps for ``prob`` at the unknowns ``y``: starting from the
    problem's own, doubled until the replay's step-doubling error
    (``jaxflex.fit.integration_error``, weighted RMS: units of the log's noise) is at most
    ``tol``, or ``most``. Set by the log (sample time, its noise), the model's stiffness
    (sigma0 |v| / g(v) h of the LuGre state, the spring's and bristles' modes) and the
    excitation, as the replay of this log sees them. Returns the problem with that many
    substeps and the errors measured (substeps -> error). Each level's finer replay is the
    next level's coarse one (one replay per level)."""
    errors = {}
    coarse = simulated_outputs(prob, y)
    while True:
        fine = simulated_outputs(refined(prob), y)
        err = step_doubling_error(prob, coarse, fine)
        errors[prob.n_substeps] = err
        if err <= tol or prob.n_substeps * 2 > most:
            return prob, {"substeps": prob.n_substeps, "output_error": errors}
        prob, coarse = refined(prob), fine


def relative_shift(prob: Problem, y: Any, shift_theta: dict[str, float]) -> float:
    """The largest relative change |dp| / |p| of a fitted physical parameter when its
    coordinates move by ``shift_theta`` ("name[j]" -> engine-coordinate shift, as
    ``discretisation_bias`` gives it)."""
    theta = prob.split(y)[0]
    moved = {k: np.array(v, float) for k, v in theta.items()}
    for label, d in shift_theta.items():
        k, _, j = label.partition("[")
        moved[k].reshape(-1)[int(j.rstrip("]"))] += d
    p0 = prob.space.physical_values(theta)
    p1 = prob.space.physical_values({k: to_device(v) for k, v in moved.items()})
    rel = [float(np.max(np.abs(np.asarray(p1[k]) - np.asarray(p0[k]))
                        / np.maximum(np.abs(np.asarray(p0[k])), 1e-12))) for k in p0]
    return max(rel) if rel else 0.0


def refine_fit(prob: Problem, sol: Solution, *, refine: bool, solve: dict[str, Any],
               tol: float = BIAS_TOL, rel_tol: float = BIAS_REL, most: int = MAX_SUBSTEPS,
               attempts: list[dict[str, Any]] | None = None,
               ) -> tuple[Problem, Solution, list[dict[str, Any]]]:
    """Check how far the integrator moves the fitted parameters of ``sol`` and, with
    ``refine``, continue the fit with more substeps until it does not.

    The shift is the Gauss-Newton step the solution's own finer replay induces
    (``jaxflex.fit.discretisation_bias``), judged twice: in standard errors (``bias_se`` at
    most ``tol``) and against the parameters' values (``bias_rel`` at most ``rel_tol``, over
    the parameters it moves by a tenth of a standard error or more). A
    model-limited fit's standard errors are inflated by its residual, and a coarse
    integrator's own error can be that residual; the relative shift holds either way. The fit
    is refined while either fails. Each refinement multiplies the substeps by 2^k (a first-order
    fall of the shift, at most ``REFINE_MOST`` x) and continues from the solution, so most
    steps use the cheap replay; with ``make_problem``'s traced substep count every level runs
    the same compiled solver.

    Arguments:
        prob, sol: the problem and its ``least_squares`` solution.
        refine: continue the fit with more substeps (else only check).
        solve: ``least_squares`` options.
        tol, rel_tol: the bounds on the shift (standard errors; share of the value).
        most: the most substeps.
        attempts: a list the continuations are recorded in.

    Returns:
        The final problem, solution, and every check (``discretisation_bias``'s numbers
        with ``bias_rel``).
    """
    checks = []
    while True:
        if sol.normal is None:  # no step was taken: nothing to judge
            checks.append({"substeps": prob.n_substeps, "bias_se": math.nan, "bias_rel": math.nan,
                           "bias_mahalanobis": math.nan, "output_error": math.nan})
            return prob, sol, checks
        chk = discretisation_bias(prob, sol)
        finite = all(math.isfinite(v) for v in chk["shift_theta"].values())
        # the relative shift of the parameters it moves by a tenth of a standard error or
        # more (a shift far inside a poorly determined parameter's error is no bias)
        seen = {k: v for k, v in chk["shift_theta"].items()
                if abs(v) >= 0.1 * chk["stderr_theta"][k]}
        chk["bias_rel"] = relative_shift(prob, sol.y, seen) if finite else math.inf
        checks.append(chk)
        settled = chk["bias_se"] <= tol and chk["bias_rel"] <= rel_tol
        if not refine or settled or prob.n_substeps * 2 > most:
            return prob, sol, checks
        need = max(chk["bias_se"] / tol, chk["bias_rel"] / rel_tol, 2.0)
        factor = 2 ** max(1, math.ceil(math.log2(min(need, 1e6))))
        factor = max(2, min(factor, REFINE_MOST, most // prob.n_substeps))
        finer = refined(prob, factor)
        more = least_squares(finer, sol.y, **solve)
        if more.interrupted:
            raise KeyboardInterrupt
        if attempts is not None:
            attempts.append({"refined_substeps": finer.n_substeps, "cost": more.cost,
                             "steps": more.steps, "converged": more.converged,
                             "reason": more.reason})
        prob = finer
        sol = dataclasses.replace(more, steps=sol.steps + more.steps,
                                  seconds=sol.seconds + more.seconds)


def noise_cost(log: Log, prob: Problem) -> float:
    """The cost 0.5 ||r||^2 that measurement noise alone gives ``prob`` (a ``make_problem``
    problem of ``log``), in its weighted units: 0.5 sum over the output columns (channel,
    joint) of samples x (sigma w)^2, sigma the column's own noise (``noise_level``, at least
    1e-6 rad, the floor of ``make_problem``'s scale) and w its weight. About n_out / 2 when
    every channel is as noisy as the one that set the scale; less for a finer second encoder
    (a 20-bit link encoder with the motor's far finer one: about n_out / 4)."""
    N = int(prob.segs.y_meas.shape[0] * prob.segs.y_meas.shape[1])
    w = np.asarray(prob.w_y, float).reshape(-1)
    sig = [max(noise_level(np.asarray(getattr(log, c), float).reshape(log.N, log.n)[:, j])
               ["total_std"], 1e-6) for c in prob.outputs for j in range(log.n)]
    w = np.broadcast_to(w, (len(sig),))
    return 0.5 * N * float(np.sum((np.asarray(sig) * w) ** 2))


def _settled(sol: Any, good: float) -> bool:
    """Converged: the cost is explained by the noise and the solver met its tolerance."""
    return sol.cost <= good and sol.converged


def _reason(sol: Any, good: float) -> str:
    """Both halves of the verdict in words: the solver's, then the model's."""
    if _settled(sol, good):
        return "cost explained by noise"
    if sol.cost <= good:
        return f"cost explained by noise but the solver did not settle ({sol.reason})"
    model = (f"cost {sol.cost:.4g} is above what the measurement noise explains ({good:.4g}): "
             "model-limited (a model that lacks something, or a local minimum)")
    if sol.converged:
        return f"converged ({sol.reason}); {model}"
    return f"not converged ({sol.reason}); {model}"


def finish(
    prob: Problem, init: Params, y: Any, *, steps: int, converged: bool, wall_s: float,
    rel_stderr_limit: float = 0.5, reason: str = "", noise_cost: float = math.nan,
    log: Log | None = None, unidentified: dict[str, str] | None = None,
    solution: Solution | None = None,
) -> IdentResult:
    """Build an ``IdentResult`` from a solution ``y`` of ``prob`` (also used by the scipy
    benchmark so that both solvers are judged alike).

    A free parameter is unidentifiable when it lies in a numerically null direction of the
    Jacobian, its relative standard error exceeds ``rel_stderr_limit``, or (Fs, Fc) it exceeds
    the largest torque in ``log``; ``unidentified`` names parameters already fixed at their
    initial values, with the reason. ``solution``: the ``jaxflex.fit.Solution`` that ended at
    ``y``, whose normal equations the covariance then reuses."""
    theta, _ = prob.split(y)
    phys = prob.space.physical_values(theta)
    cov = covariance(prob, y, solution=solution)
    # identifiability is judged on the information in the data (white residuals); the
    # standard errors reported and the posterior hold for correlated residuals too
    robust = (segment_robust_covariance(prob, solution)
              if solution is not None and solution.y is y else None)
    shown = cov if robust is None else robust
    se = {k: shown["stderr"][k].tolist() for k in phys}
    information = _relative(cov["stderr"], phys)
    msgs, bad = [], list(cov["null_names"])
    why = {k: "numerically null direction of the Jacobian (the data cannot separate it)"
           for k in bad}
    for k in phys:
        if max(information[k]) > rel_stderr_limit and k not in bad:
            bad.append(k)
            why[k] = (f"relative standard error {100 * max(information[k]):.3g}% > "
                      f"{100 * rel_stderr_limit:g}% (white residuals)")
    if log is not None and log.tau is not None:
        top = float(np.max(np.abs(log.tau)))
        for k in ("Fs", "Fc"):
            if k in phys and float(np.max(phys[k])) > top and k not in bad:
                bad.append(k)
                why[k] = (f"{k} = {float(np.max(phys[k])):.4g} exceeds the largest logged torque "
                          f"{top:.4g}: the log never breaks away")
    if cov["null_names"]:
        msgs.append(
            f"Jacobian rank {cov['rank']} < {cov['n_free']} unknowns: the data cannot separate "
            f"{cov['null_names']}"
        )
    huge = [k for k in bad if k not in cov["null_names"]]
    if huge:
        msgs.append(
            "relative standard error above "
            f"{100 * rel_stderr_limit:g}% for {huge}: not identifiable from this log "
            "(vs, sigma0, sigma1 need low-speed dwell and frequent reversals)"
        )
    for m in msgs:
        warnings.warn(m, IdentificationWarning, stacklevel=4)
    cost = 0.5 * (cov["rss"] + cov["defects_ss"])
    ys = simulated_outputs(prob, y)
    rms = float(np.sqrt(np.mean((np.asarray(ys) - np.asarray(prob.segs.y_meas)) ** 2)))
    if not converged and reason:
        msgs.append(f"not converged: {reason}")
    for a, b in (("Fc", "Fs"), ("Fs", "Fc")):  # an ordered pair is kept or fitted together
        if a in bad and b in phys and b not in bad:
            bad.append(b)
            why[b] = f"kept at its initial value with {a} (Fs >= Fc): {why[a]}"
    fixed = dict(unidentified or {})
    for k, w in fixed.items():
        if k not in bad:
            bad.append(k)
            why[k] = w
    # every fitted name keeps its fitted value (those the data cannot determine are marked):
    # the file holds the point the fit reached, whose cost it reports
    out = set_values(init, phys)
    out.extra = dict(out.extra)
    out.extra["stderr"] = {k: se[k] for k in phys}
    marks = {k: {"identified": k not in bad, **({"reason": why[k]} if k in bad else {})}
             for k in list(phys) + list(fixed)}
    out.extra["identification"] = {
        "free": list(prob.space.names) + list(fixed), "model": prob.kind, "cost": cost,
        "noise_cost": noise_cost, "rms_residual": rms, "jacobian_rank": cov["rank"],
        "unknowns": cov["n_free"], "steps": steps, "converged": converged,
        "reason": reason or ("cost explained by noise" if converged else "not converged"),
        "unidentifiable": bad, "parameters": marks,
    }
    out.extra["identification"]["stderr_kind"] = (
        f"segment-robust ({robust['clusters']} segments as clusters)" if robust is not None
        else "white residuals")
    out.extra["identification"]["covariance"] = posterior_record(prob, theta, shown, bad)
    rel = _relative(se, phys)
    for k in fixed:
        se[k] = [math.nan] * len(get_value(init, k))
        rel[k] = [math.inf] * len(get_value(init, k))
    res = IdentResult(
        params=out, stderr=se, rel_stderr=rel, cost=cost, rms=rms, rank=cov["rank"],
        n_free=cov["n_free"], singular_values=cov["singular_values"], unidentifiable=bad,
        warnings=msgs, steps=steps, converged=converged, wall_s=wall_s, problem=prob,
        solution=y, reason=out.extra["identification"]["reason"], noise_cost=noise_cost, why=why,
        information_rel_stderr=information,
    )
    return res


def posterior_record(prob: Problem, theta: dict[str, Any], cov: dict[str, Any],
                     exclude: Sequence[str] = ()) -> dict[str, Any]:
    """The identification's Gaussian posterior in the unconstrained coordinates theta
    (``jaxflex.fit.space``), for the file: ``parameters`` (names in the space's order, those
    in ``exclude`` left out: their rows are dropped, i.e. marginalised), ``labels`` (one per
    flattened entry, "name[j]"), ``theta`` (the estimate) and ``matrix`` (its covariance).
    ``jaxflex.robust.Posterior`` draws from it; every draw maps to physical values that keep
    the constraints (positivity, Fs >= Fc)."""
    fitted = prob.space.fitted_flat()
    # flattened entries in ravel_pytree's order (sorted names, then joints), as fitted_flat
    entries = [(k, j) for k in sorted(theta) for j in range(np.size(theta[k]))]
    flat = np.concatenate([np.ravel(np.asarray(theta[k], float)) for k in sorted(theta)])
    keep = [i for i, (k, _) in enumerate(entries) if fitted[i] and k not in exclude]
    kept = {entries[i][0] for i in keep}
    params = [k for k in prob.space.names if k in kept]
    C = np.asarray(cov["cov_theta"])[np.ix_(keep, keep)]
    return {
        "space": "theta", "parameters": params,
        "labels": [f"{entries[i][0]}[{entries[i][1]}]" for i in keep],
        "theta": [float(flat[i]) for i in keep], "matrix": C.tolist(),
    }


def simulate_log(
    params: Params, log: Log, *, model: ModelKind = "flexible", substeps: int = 4,
    x0: PlantState | None = None,
) -> PlantState:
    """Open-loop replay of the whole log's torque through ``params``' model (single shooting
    from rest at the first logged angles unless ``x0`` is given). States (N, n) per field."""
    plant = params.to_plant()
    if x0 is None:
        q2 = log.q2[0] if (log.q2 is not None and model == "flexible") else log.q1[0]
        x0 = plant.init_state(q1=log.q1[0], q2=q2)
    fn = eqx.filter_jit(lambda p, x, u: replay(model, p, x, u, log.dt, substeps)[0])
    return fn(plant, x0, jnp.asarray(log.tau))
