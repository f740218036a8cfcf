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

from jaxflex.fit import (
    CostBound,
    Problem,
    Solution,
    cost,
    dynamic_substeps,
    set_values,
)
from jaxflex.identify.discretisation import (
    BIAS_REL,
    BIAS_TOL,
    choose_substeps,
    rechoose_substeps,
    refine_fit,
)
from jaxflex.identify.links import structural_free
from jaxflex.identify.problem import (
    MODEL_CHOICES,
    choose_segment_length,
    default_free,
    exact_reading,
    gaussian_reading,
    make_problem,
    noise_statistics,
    reading_statistics,
    reading_units,
    segments_of,
    start_hints,
    with_named_effects,
    with_readings,
)
from jaxflex.identify.result import (
    IdentificationWarning,
    IdentResult,
    finish,
    is_settled,
    reason_of,
)
from jaxflex.identify.search import (
    REFIT_TOL,
    Search,
    best_at_final,
    compile_ahead,
    fix_unidentified,
    starts_of,
)
from jaxflex.identify.start import StartError, check_model, start_from_data
from jaxflex.identify.verdict import model_verdict
from jaxflex.io.progress import Progress, silent
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.state import PlantState
from jaxflex.core.validation import requires_float64
from jaxflex.sim.step import ModelKind, replay

#: identify's solver settings (``least_squares``): geodesic acceleration's bound on
#: 2 |a| / |v|, and the statistical stop (Gauss-Newton decrement, chi-square units)
GEODESIC: float = 0.3
DECREMENT_TOL: float = 1e-2
#: A start's solve that ends within this many standard deviations of the noise's own cost
#: (``noise_statistics``) ends the search: no other minimum can lie lower by what the data tell.
NOISE_BAND_Z: float = 4.0
#: ``identify``'s readings' models (``reading``).
READINGS: tuple[str, ...] = ("gaussian", "exact")

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
    rel_stderr_limit: float = 0.5, progress: Progress | None = None, static_start: bool = True,
    decrement_tol: float | None = DECREMENT_TOL, geodesic: float = GEODESIC,
    vs_restarts: Sequence[float] = (3.0, 1.0 / 3.0), data_start: bool = True,
    pin: Mapping[str, float | Sequence[float]] | None = None, reading: str = "exact",
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
            (``jaxflex.sim.step.MODEL_KINDS``), or "auto": the kind the encoders suggest
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
            noise can tell (``REFIT_TOL`` at the fit's residual scale); else it keeps its
            fitted value, marked as poorly determined.
        static_start: a start from the log's static friction map (``start_from_static_map``).
        vs_restarts: when no start reaches an adequate fit, the first start again with vs
            multiplied by these factors.
        data_start: also start from the log's inverse dynamics when ``init`` is given.
        pin: names (as ``free``) set to these values on the start and not fitted (a value
            or one per joint).
        reading: "exact" (default): a fit the noise explains, on a log whose encoders round
            coarser than their noise, is continued under the readings' exact likelihood
            (``exact_reading``: no pull to a count's centre where the angle dwells in one);
            such a log's fit runs in the exact likelihood's structure throughout
            (``gaussian_reading``), so both phases share one compiled solver. "gaussian":
            least squares throughout.
        progress: the reporter (``jaxflex.io.progress.Progress``) of each solver step (its
            number of the solve's ``max_steps``, and its cost) and each start's end (no
            total); None: silent.

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
    if reading not in READINGS:
        raise ValueError(f"identify: reading must be one of {READINGS}, got {reading!r}")
    if not (segment_length is None or segment_length == "auto" or (
            isinstance(segment_length, (int, np.integer))
            and not isinstance(segment_length, bool) and segment_length >= 2)):
        raise ValueError(f"identify: segment_length must be a number of samples (at least 2), "
                         f"None or 'auto', got {segment_length!r}")
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
    init = with_named_effects(init, free, None if data is None else data.params)
    # a coupled arm's fields beyond its base parameters: fixed before the fit, marked
    free, structural = structural_free(init, free)
    if segment_length == "auto":
        segment_length, segments = choose_segment_length(log, init, model)
    else:
        segments = {"mode": "given", **segments_of(log, segment_length)}
    prob, y0 = make_problem(
        log, init, free, model=model, segment_length=segment_length,
        substeps=dynamic_substeps(1) if auto else substeps,
        outputs=outputs, output_scale=output_scale, continuity_weight=continuity_weight,
    )
    # the readings' model, read off the log once; the search's readings Gaussian in the
    # exact likelihood's structure: both phases run the same compiled programs
    rounded = exact_reading(log, prob) if reading == "exact" else None
    if rounded is not None:
        prob = gaussian_reading(rounded)
    # the statistical stop at the fit's own residual scale: a step that would lower chi-square
    # by less than ``decrement_tol`` in units of the residual variance the fit leaves (the
    # noise's, or more for a model-limited fit: cost / noise cost), is below 0.1 of the
    # standard errors that residual gives; on a real rig's log the noise's own units would
    # run every solve to its step cap
    noise, spread = noise_statistics(log, prob)
    stop = (None if decrement_tol is None
            else CostBound(decrement_tol / noise, 0.0, (0.0, decrement_tol)))
    # the solver options every solve of this fit shares (they key its compiled program)
    options = dict(rtol=rtol, atol=atol, decrement_tol=stop, geodesic=geodesic)
    ahead = compile_ahead(prob, y0, options)
    # what the noise explains under the readings' exact likelihood (the same for every problem
    # of this log: its segments and readings), reckoned while the solver compiles
    rounded_noise = None if rounded is None else reading_statistics(rounded)[0]
    starts = starts_of(log, init, free, prob, y0, model, static_start, user_start, data)
    discretisation: dict[str, Any] = {"mode": "auto" if auto else "given"}
    if auto:
        prob, discretisation["first"] = choose_substeps(prob, starts[0][1])
    schedules = list(warm_start) if isinstance(warm_start, (list, tuple)) else [warm_start]
    if not schedules:
        raise ValueError("identify: warm_start needs at least one schedule (a factor or None)")
    if prob.segs.count == 1:  # one segment: nothing to loosen
        schedules = [None]
    good = accept_cost * noise
    band = noise * (1.0 + NOISE_BAND_Z * spread)
    search = Search(good, dict(options, progress=progress), progress or silent)
    t0 = time.perf_counter()
    best, best_factor = None, None

    def warmed(problem: Problem, y: Any, factor: float | None, label: str) -> Any:
        """``y`` after the first phase of the schedule ``factor``: at most ``warm_steps``
        steps with the continuity weight times ``factor`` (None, or one segment: ``y``)."""
        if factor is None or problem.segs.count == 1:
            return y
        loose = eqx.tree_at(lambda q: q.w_def, problem, problem.w_def * factor)
        return search.run(loose, y, {"warm": label, "warm_start": factor}, warm_steps,
                          full=False, scored=problem).y

    def solve_from(prob: Problem, origin: str, y_start: Any, factor: float | None,
                   ) -> Solution:
        """One start solved with ``prob``'s substeps after its warm-start schedule
        ``factor``; a solve that reaches the noise level still moving is let settle."""
        y = warmed(prob, y_start, factor, origin)
        label = {"start": origin, "warm_start": factor, "substeps": prob.n_substeps}
        sol = search.run(prob, y, label, max_steps)
        if sol.cost <= good and not sol.converged:
            more = search.run(prob, sol.y, {"start": f"{origin}, continued"}, max_steps)
            sol = dataclasses.replace(more, steps=sol.steps + more.steps,
                                      seconds=sol.seconds + more.seconds)
        return sol

    def search_starts(prob: Problem) -> tuple[Solution, tuple[str, Any, float | None]]:
        """Every start, the lowest first, solved with ``prob``'s substeps and the first
        warm-start schedule until one ends within the noise's own band (``NOISE_BAND_Z``):
        a start that settles only within ``accept_cost`` times the noise may sit in a
        minimum of its own and does not stop the others. Then, until one settles, the other
        schedules, the lowest start's first, and the vs restarts from the first start.
        Returns the lowest end point and the run that reached it (origin, start point,
        warm-start schedule)."""
        best, best_run = None, None
        ends = []
        for origin, y_start in ordered:
            run = (origin, y_start, schedules[0])
            sol = solve_from(prob, *run)
            ends.append((sol.cost, run))
            if best is None or sol.cost < best.cost:
                best, best_run = sol, run
            if is_settled(best, band):
                break
        for _, (origin, y_start, _f) in sorted(ends, key=lambda e: e[0]):
            if is_settled(best, good):
                break
            for factor in schedules[1:]:
                run = (origin, y_start, factor)
                sol = solve_from(prob, *run)
                if sol.cost < best.cost:
                    best, best_run = sol, run
                if is_settled(sol, good):
                    break
        if not is_settled(best, good) and "vs" in prob.space.names and vs_restarts:
            # The Stribeck velocity decides where in the velocity range the friction hump
            # lies; a fit whose vs starts on the wrong side of it lets Fs and sigma1 absorb
            # the hump and vs stops moving: the first start again (the static map's, which
            # placed vs from the log's own friction map, when there is one), vs on either side.
            origin, (th0, x0) = starts[0]
            phys = prob.space.physical_values(th0)
            for f in vs_restarts:
                run = (f"{origin}, vs x{f:g}",
                       (prob.space.theta_of({**phys, "vs": phys["vs"] * f}), x0), schedules[0])
                sol = solve_from(prob, *run)
                if sol.cost < best.cost:
                    best, best_run = sol, run
                if is_settled(sol, good):
                    break
        return best, best_run

    # the starts' order while the solver compiles (their replays compile the cost's program)
    ordered = sorted(starts, key=lambda s: cost(prob, s[1]))
    ahead.wait(0)
    best, best_run = search_starts(prob)
    if auto:
        # the substeps chosen at the first start judged again at the search's answer: a
        # coarse integrator's own error can make a minimum of its own, far from the start;
        # the run that found it is solved again from its start with the finer substeps (the
        # other end points are replayed and weighed with the final substeps at the end)
        finer, discretisation["at_first_answer"] = rechoose_substeps(prob, best, noise)
        if finer is not None:
            prob = finer
            best = solve_from(prob, *best_run)
    best_factor = best_run[2]
    ahead.join()
    first = finish(prob, init, best.y, steps=best.steps, converged=best.converged,
                   wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                   reason=reason_of(best, good), noise_cost=good, log=log, solution=best,
                   unidentified=structural)
    f_prob, f_sol, f_fixed, total = fix_unidentified(
        search, first, prob, best, init, y0, log, free, model=model,
        segment_length=segment_length, outputs=outputs, output_scale=output_scale,
        continuity_weight=continuity_weight, max_steps=max_steps, good=good,
        warmed=lambda p, y: warmed(p, y, best_factor, "refit"),
        noise=good / accept_cost, rel_stderr_limit=rel_stderr_limit)
    margin = REFIT_TOL * max(1.0, best.cost * accept_cost / good) if f_fixed else 0.0
    # the readings' exact likelihood: a fit at the noise level, on a log whose encoders'
    # counts exceed their noise, is continued under it from here on (a Gaussian residual
    # pulls the model to the centre of a count wherever the angle dwells in one)
    readings, q_prob = {"likelihood": "gaussian"}, None
    if f_sol.cost <= good and f_sol.converged and rounded is not None:
        q_prob = with_readings(f_prob, rounded)
    if q_prob is not None:
        q_sol = search.run(q_prob, f_sol.y, {"reading": "rounded",
                                             "substeps": q_prob.n_substeps}, max_steps,
                           full=False)
        if q_sol.converged and not q_sol.failed:
            readings = {"likelihood": "rounded",
                       "count": reading_units(q_prob, q_prob.quantum),
                       "noise": reading_units(q_prob, q_prob.read_noise),
                       "gaussian_cost": f_sol.cost}
            total += q_sol.steps
            good = accept_cost * rounded_noise
            # the search's problem under the same readings (its end points are weighed so)
            prob = with_readings(prob, rounded)
            f_prob, f_sol = q_prob, q_sol
        else:  # the Gaussian answer stands
            readings["rounded_failed"] = q_sol.reason
    # the integrator must not move the answer: refined at the solution, coarse to fine
    r_prob, r_sol, discretisation["checks"] = refine_fit(
        f_prob, f_sol, refine=auto,
        run=lambda p, y, label: search.run(p, y, label, max_steps, full=False))
    if r_prob is not f_prob:
        total += r_sol.steps - f_sol.steps
    # never worse than the best point a solve of the full problem reached, at this
    # discretisation: every end point replayed with the final substeps
    r_prob, r_sol, f_fixed, total = best_at_final(
        search, prob, r_prob, r_sol, f_fixed, total, max_steps, margin)
    discretisation.update(discretisation["checks"][-1])
    n_sub = r_prob.n_substeps
    res = finish(r_prob, init, r_sol.y, steps=total, converged=r_sol.converged,
                 wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                 reason=reason_of(r_sol, good), noise_cost=good, log=log,
                 unidentified={**structural, **(f_fixed or {})}, solution=r_sol)
    if f_fixed:
        res.rank, res.n_free, res.singular_values = first.rank, first.n_free, first.singular_values
        res.warnings = first.warnings + res.warnings
    verdict = model_verdict(r_prob, r_sol.y, res.cost, good / accept_cost, accept_cost)
    ident = res.params.extra["identification"]
    ident["model"] = verdict
    ident["solver"] = {"converged": r_sol.converged, "reason": r_sol.reason}
    ident["attempts"] = search.attempts
    ident["discretisation"] = discretisation
    ident["reading"] = readings
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
