"""Fitting one model on the workspace: the nominal parameters and training start states
(``fit_model``), the held-out start states with the parameters fixed (``fit_starts``,
``with_held_out``), polishing a fit (``settle``) and the base without an effect
(``without_effect``), the held-out errors, and the gap a correct model reaches on the log
(``gap_floor``). Every fit stops at the engine's statistical stop measured against its own
residual variance (``relative_stop``) or when it stops making progress (``progress_stop``).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import equinox as eqx
import jax
import numpy as np

from jaxflex.discover.candidates import CandidateFit, Model, Workspace, within_capacity
from jaxflex.fit import (
    CostBound,
    Padding,
    Problem,
    covariance,
    gap,
    least_squares,
    noise_level,
    params_of_plant,
    refined,
    simulated_outputs,
    trace_solver,
    white_noise_std,
)
from jaxflex.runtime.ahead import Ahead, all_side_by_side
from jaxflex.fit.residual_analysis import CONFIDENCE, analyse_segments
from jaxflex.fit.space import set_values
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.validation import to_device


#: Solver tolerances of the candidate fits (relative and absolute change of unknowns/cost).
_RTOL, _ATOL = 1e-7, 1e-10
#: The solver options of every fit (``fit_model``, ``screen`` and ``trace_fit`` share one
#: compiled loop; ``fit_starts``, the held-out start fits, has its own).
FIT_SOLVER: dict[str, Any] = dict(rtol=_RTOL, atol=_ATOL, scaling="marquardt")
#: Statistical stop of every fit (``relative_stop``): the step that remains is below
#: sqrt(DECREMENT) of the standard errors the fit reports.
DECREMENT = 0.01
#: Progress stop of every fit (``least_squares(stall=...)``, ``relative_stop``'s units): a fit
#: ends, not converged, when its last STALL_WINDOW steps lowered the residual by less than
#: STALL chi-square units. The fits of friction models creep (the decrement can stay far
#: above the statistical stop while many steps gain a fraction of a unit together), and AIC
#: and BIC resolve differences of one unit.
STALL_WINDOW, STALL = 10, 0.1


def relative_stop(n_res: int, inflation: float = 1.0,
                  fraction: float = DECREMENT) -> CostBound:
    """The engine's statistical stop (``least_squares(decrement_tol=...)``) for a fit whose
    residuals are not in noise units: the Gauss-Newton decrement measured against the residual
    variance the fit itself estimates, 2 cost / ``n_res``, times the ``inflation`` its standard
    errors carry (the residual autocorrelation time). A fit stops when a full Gauss-Newton step
    would move every combination of the unknowns by less than sqrt(``fraction``) of its
    reported standard error: further steps change nothing the workflow can resolve, and the
    tolerances on the unknowns alone are rarely met within a fit's step cap."""
    return CostBound(fraction * inflation * 2.0 / n_res)


def progress_stop(n_res: int, inflation: float, max_steps: int,
                  catch_up: float | None = None) -> CostBound:
    """The progress stop of a fit (``least_squares(stall=...)``, over STALL_WINDOW steps):
    STALL chi-square units (``relative_stop``), or, with ``catch_up`` (the residual sum of
    squares of a fit this one competes with), the larger of that and the share
    STALL_WINDOW / ``max_steps`` of the distance still to go, (2 cost - catch_up): a solve
    that gains less cannot reach the other within its steps at its current rate."""
    bound = relative_stop(n_res, inflation, STALL)
    if catch_up is None or not math.isfinite(catch_up):
        return bound
    share = STALL_WINDOW / max_steps
    return dataclasses.replace(bound, other=(2.0 * share, -share * catch_up))


def start_residuals(y: tuple[dict[str, jax.Array], jax.Array],
                    args: tuple[Problem, dict[str, jax.Array]]) -> jax.Array:
    """Residuals of the free-start problem ``args[0]`` at fixed parameters ``args[1]`` as a
    function of the segment start states alone: ``y`` = (no shared unknowns ``{}``, start
    states (S, n_state, n)), the multiple-shooting layout with no parameter block, so that the
    engine's structured solve applies (``structure="shooting"``)."""
    prob, theta = args
    return prob.residuals((theta, y[1]))


def fit_starts(prob: Problem, theta: dict[str, jax.Array], x0s: jax.Array, *,
               max_steps: int = 20) -> jax.Array:
    """The start states (S, n_state, n) that replay each segment of ``prob`` best with the
    parameters ``theta`` held fixed (the engine's Levenberg-Marquardt from ``x0s``): how the
    held-out segments are started, so that their gap measures the model and not an estimate
    of the start (no parameter sees the held-out data). Each segment's rows depend on its own
    start only: the structured solve takes 2 n_state Jacobian-vector products per step where
    the dense Jacobian takes S n_state, with the same starts to rounding."""
    # in the bucket of segment slots (``jaxflex.fit.Padding``): held-out parts of logs of
    # other lengths share the compiled step; the stop counts the data's residuals only
    pad = Padding.of(prob, x0s)
    run, x_in = (prob, x0s) if pad is None else (prob.padded(pad.slots),
                                                  pad.unknowns(({}, x0s))[1])
    sol = least_squares((run, theta), ({}, x_in), fn=start_residuals, max_steps=max_steps,
                        structure="shooting" if prob.segs.count > 1 else "dense",
                        decrement_tol=relative_stop(prob.n_out),
                        stall=(STALL_WINDOW, relative_stop(prob.n_out, fraction=STALL)),
                        **FIT_SOLVER)
    return sol.y[1] if pad is None else pad.unknowns_back(sol.y)[1]


def _fit_start(ws: Workspace, model: Model, starts: tuple[jax.Array, jax.Array] | None,
               ) -> tuple[Problem, Problem, dict[str, jax.Array], jax.Array, jax.Array]:
    """``fit_model``'s training and held-out problems of ``model``, its start coordinates and
    the first guesses of the training and held-out start states (``starts``, default the
    workspace's estimates), brought within the friction's capacity."""
    train, test, theta0 = ws.for_model(model)
    plant0 = train.space.plant(theta0)
    x_train, x_test = (within_capacity(x, plant0) for x in
                       (starts if starts is not None else (train.segs.x0, test.segs.x0)))
    return train, test, theta0, x_train, x_test


def trace_fit(ws: Workspace, model: Model) -> bool:
    """Trace and keep the compiled loop of ``fit_model(ws, model)`` without compiling it
    (``jaxflex.fit.trace_solver``). ``discover`` calls it before the background work starts
    (``made_ahead``): tracing holds Python's interpreter lock, so traces made side by side
    each take about twice as long. Every model of the workspace shares the loop. True when a kept program
    now serves the fits (False: the trace cache is off)."""
    train, _, theta0, x_train, _ = _fit_start(ws, model, None)
    return trace_solver(train, (theta0, x_train), **FIT_SOLVER)


def check_bounded(space: Any, theta: Any) -> None:
    """Refuse a fit that ran a fitted parameter of ``space`` to a non-finite value at the
    unknowns ``theta`` (an inertia grown until the replay no longer feels it: the residual
    stays finite along such a direction, its Jacobian and covariance do not).

    **Raises:** ``FloatingPointError`` naming the parameters and their values (a candidate's
    own failure, ``candidate_error``)."""
    phys = space.physical_values(theta)
    runaway = {k: float(np.ravel(phys[k])[0]) for k in space.fitted_names()
               if not np.all(np.isfinite(np.asarray(phys[k])))}
    if runaway:
        raise FloatingPointError(
            "the fit ran " + ", ".join(f"{k} to {v}" for k, v in runaway.items())
            + ": the log does not bound it from this start (the model does not describe the "
            "log, or the start is far from where it does)")


def fit_model(ws: Workspace, model: Model, *, max_steps: int = 15, tau_int: float = 1.0,
              starts: tuple[jax.Array, jax.Array] | None = None,
              held_out: bool = True, catch_up: float | None = None) -> CandidateFit:
    """Refit ``model`` on the training segments with the engine, every segment's start state
    fitted with the parameters; then fit the held-out segments' start states with the
    parameters fixed (``fit_starts``) and take the held-out gap. ``starts``: first guesses of
    the (training, held-out) start states (default: the workspace's estimates from the log),
    their start loads brought within the friction's capacity (``within_capacity``).
    Standard errors are inflated by the residual autocorrelation time ``tau_int``
    (samples). ``held_out`` False: the held-out part is left for later (``with_held_out``):
    the held-out starts are the first guesses and the held-out gap is NaN. ``catch_up``: the
    training residual sum of squares of a fit this one competes with (``settle``'s fresh
    solve): the solve also ends, not converged, once its last STALL_WINDOW steps gained less
    than that many steps' share of what it still lacks to reach it (at that rate it would
    not catch up within ``max_steps``).

    **Raises:** ``FloatingPointError`` when the solve runs a fitted parameter to a non-finite
    value (``check_bounded``)."""
    t0 = time.perf_counter()
    train, test, theta0, x_train, x_test = _fit_start(ws, model, starts)
    sol = least_squares(train, (theta0, x_train), max_steps=max_steps,
                        decrement_tol=relative_stop(train.n_out, tau_int),
                        stall=(STALL_WINDOW, progress_stop(train.n_out, tau_int, max_steps,
                                                           catch_up)), **FIT_SOLVER)
    theta, x_train = sol.y
    space = train.space
    phys = space.physical_values(theta)
    fitted = space.fitted_names()
    check_bounded(space, theta)
    cov = covariance(train, sol.y, inflation=tau_int, solution=sol)
    if held_out:
        x_test = fit_starts(test, theta, x_test)
    values = {k: float(np.ravel(phys[k])[0]) for k in fitted}
    stderr = {k: float(np.ravel(cov["stderr"][k])[0]) for k in fitted}
    plant = space.plant(theta)
    params = params_of_plant(plant, model.params)
    act = {e.name: e for e in plant.effects if e.name in model.active}
    effects = [act[e.name].inner for e in model.effects]
    params.effects = {e.name: e.params() for e in effects}
    fitted_model = Model(params, effects, model.starts)
    return CandidateFit(
        model=fitted_model, theta=theta, starts=x_train, test_starts=x_test, values=values,
        stderr=stderr, rss=cov["rss"], n_res=cov["n_res"], n_par=cov["n_free"],
        gap_train=float(gap(train, sol.y)),
        gap_test=float(gap(test, (theta, x_test))) if held_out else math.nan,
        steps=sol.steps, converged=sol.converged, seconds=time.perf_counter() - t0,
    )


def with_held_out(ws: Workspace, fit: CandidateFit) -> CandidateFit:
    """``fit`` with its held-out part (``fit_model``'s ``held_out``): the held-out segments'
    start states fitted with the parameters fixed (``held_out_starts``, from its held-out
    starts and from the log's estimates), and the gap."""
    if math.isfinite(fit.gap_test):
        return fit
    t0 = time.perf_counter()
    _, test, _ = ws.for_model(fit.model)
    theta = ws.theta_of(fit)
    x_test = held_out_starts(test, theta, fit.test_starts)
    return dataclasses.replace(fit, theta=theta, test_starts=x_test,
                               gap_test=float(gap(test, (theta, x_test))),
                               seconds=fit.seconds + time.perf_counter() - t0)


def held_out_starts(prob: Problem, theta: dict[str, jax.Array], carried: jax.Array, *,
                    max_steps: int = 40) -> jax.Array:
    """Start states (S, n_state, n) of the held-out problem ``prob`` at fixed parameters
    ``theta`` (``fit_starts``) from two first guesses, each segment keeping the start that
    replays it better (the segments are independent at fixed parameters): ``carried``, the
    starts of an earlier solve, and the log's estimates (``prob.segs.x0``), both brought within
    the friction's capacity. Carried starts fitted under other parameters can lie far from
    this model's (after a refit that moved the friction far, the carried starts need twice
    the steps the log's estimates need to reach the same held-out gap). ``max_steps``: twice
    fit_starts' default, since the solves this replaces each continued the held-out start fit
    of the one before (the statistical stop ends it sooner where it can)."""
    plant = prob.space.plant(theta)
    tries = all_side_by_side(lambda first: fit_starts(prob, theta, within_capacity(first, plant),
                                                      max_steps=max_steps),
                             (carried, prob.segs.x0))
    y = np.asarray(prob.segs.y_meas)
    err = np.stack([np.sum((np.asarray(simulated_outputs(prob, (theta, x))) - y) ** 2,
                           axis=(1, 2)) for x in tries])
    pick = np.argmin(np.where(np.isfinite(err), err, np.inf), axis=0)
    return to_device(np.stack([np.asarray(x) for x in tries])[pick, np.arange(pick.size)])


def made_ahead(ws: Workspace, nominal: Params) -> Ahead:
    """The programs of the held-out part (``fit_starts``' solver, the replay that gives the
    gap, ``gap_floor``'s finer replay) and of the training replay, made in a background
    thread (``jaxflex.runtime.ahead``) from the nominal model's start coordinates while the
    calling thread fits the nominal model: every model of the workspace shares them, and
    reading them from the cache no longer holds up the main thread."""
    train, test, theta = ws.for_model(Model(nominal, []))

    def held_out() -> None:
        x = within_capacity(test.segs.x0, test.space.plant(theta))
        fit_starts(test, theta, x, max_steps=1)
        gap(test, (theta, x))
        simulated_outputs(finer(test), (theta, x))

    def training() -> None:
        gap(train, (theta, train.segs.x0))

    return Ahead([held_out, training])


def settle(ws: Workspace, fit: CandidateFit, *, max_steps: int, tau_int: float = 1.0,
           rounds: int = 3, tol: float = 1e-3, probe: int | None = None,
           fresh: bool = True) -> CandidateFit:
    """``fit`` solved again from its own start states, their loads brought back within the
    friction's capacity (``within_capacity``), until the training residual falls by less than
    ``tol`` (relative) or ``rounds`` solves: the base every candidate is compared with. A
    solve's long steps push some start loads past the capacity, where the clip has no slope
    and they stop moving; every candidate fit starts with them brought back, so against an
    unsettled base every candidate gains, and the one named can be a negligible effect.

    The first solve continues ``fit``; each further one confirms it: it first runs ``probe``
    steps (default a quarter of ``max_steps``) and goes on to the full solve only when those
    already lower the residual by more than ``tol`` (a full confirming solve usually
    changes the residual by far less than it costs)."""
    probe = max(1, max_steps // 4) if probe is None else probe

    def solve(fit: CandidateFit, steps: int, starts: tuple[jax.Array, jax.Array],
              catch_up: float | None = None) -> CandidateFit:
        # the held-out part only for the fit kept (one held-out start fit, not one a solve)
        return fit_model(ws, fit.model, max_steps=steps, tau_int=tau_int, starts=starts,
                         held_out=False, catch_up=catch_up)

    def confirmed(fit: CandidateFit) -> CandidateFit:
        for _ in range(1, rounds):
            nxt = solve(fit, probe, (fit.starts, fit.test_starts))
            if nxt.steps >= probe and nxt.rss < fit.rss * (1.0 - tol):
                # the probe still gains: the full confirming solve, on from where it got
                more = solve(nxt, max_steps, (nxt.starts, nxt.test_starts))
                nxt = dataclasses.replace(more, steps=nxt.steps + more.steps,
                                          seconds=nxt.seconds + more.seconds) \
                    if more.rss < nxt.rss else nxt
            done = not nxt.rss < fit.rss * (1.0 - tol)
            fit = nxt if nxt.rss < fit.rss else fit
            if done:
                break
        return fit

    first = solve(fit, max_steps, (fit.starts, fit.test_starts))
    settled = not first.rss < fit.rss * (1.0 - tol)
    fit = first if first.rss < fit.rss else fit
    if not settled:
        fit = confirmed(fit)
    if not fresh:
        return with_held_out(ws, fit)
    # the base gets the second first guess every candidate gets (``discover``): the log's
    # start estimates instead of its own fitted starts, which can hold the shared parameters
    # in a valley a candidate's fit from the estimates leaves (a base polished from a refit
    # whose Fs rode its bound can more than halve its own residual from the estimates, and
    # every candidate would otherwise seem significant against it). It starts from the
    # confirmed fit, after the confirming solves: started beside them from the first solve's,
    # it can leave a worse base.
    # And a static friction pinned where its coordinates have no slope stays there in every
    # solve, also once the effect it stood in for is in the model: once more from the
    # nominal friction (``released``). Not for the nominal model itself, whose friction
    # stands in for what it misses (a solve from the nominal friction comes back to the same
    # residual). Side by side with the solve from the estimates, on the core
    # the settle leaves idle, and used only when that one does not lower the residual: the
    # result of solving it after that one
    free = released(ws, fit) if fit.model.effects else None
    tries = [(fit, (ws.train.segs.x0, fit.test_starts))]
    if free is not None:
        tries.append((dataclasses.replace(fit, model=free), (fit.starts, fit.test_starts)))
    for again in all_side_by_side(lambda t: solve(t[0], max_steps, t[1], catch_up=fit.rss),
                                  tries):
        if again.rss < fit.rss * (1.0 - tol):
            return settle(ws, again, max_steps=max_steps, tau_int=tau_int, rounds=rounds,
                          tol=tol, probe=probe, fresh=False)
    return with_held_out(ws, fit)


#: ``released``: a static friction is pinned when Fs - Fc or Fc is within PINNED of the
#: space's cap on them (``ParamSpace.friction_cap``: the sigmoid's slope is then below 2% of
#: the level), or Fc below PINNED_FC of Fs (Fc = exp(u): its Jacobian column is Fc itself).
PINNED: float = 0.02
PINNED_FC: float = 1e-6


def released(ws: Workspace, fit: CandidateFit) -> Model | None:
    """``fit``'s model with its Coulomb and static friction set back to the workspace's
    nominal values when the fit left them pinned (``PINNED``): Fs - Fc at the cap of the
    largest logged torque, or Fc at zero. There the coordinates have no slope, so no solve
    moves them back, whatever the data say once a missing effect is in the model. None when
    neither is pinned or friction is not fitted. Without it, a nominal refit that raised Fs
    to its cap with Fc at zero keeps the polish of a later model there, or lets it leave by
    the chance of rounding."""
    v = fit.values
    if "Fc" not in v or "Fs" not in v:
        return None
    fc, fs = v["Fc"], v["Fs"]
    cap = float(np.ravel(ws.space.friction_cap)[0])
    at_cap = math.isfinite(cap) and max(fs - fc, fc) > (1.0 - PINNED) * cap
    if not (at_cap or fc < PINNED_FC * fs):
        return None
    nominal = ws.space.base.friction
    params = set_values(fit.model.params, {"Fc": np.asarray(nominal.Fc, float),
                                           "Fs": np.asarray(nominal.Fs, float)})
    return dataclasses.replace(fit.model, params=params)


def without_effect(ws: Workspace, fit: CandidateFit, name: str, *, max_steps: int,
                   tau_int: float = 1.0) -> CandidateFit:
    """``fit``'s model without effect ``name``, refitted from ``fit``'s values of the shared
    parameters and its start states (training segments only; the held-out part is left for
    ``with_held_out``): the base against which ``name`` must still be significant once it is
    added (``discover``). One solve, not settled: its residual can only be above the reduced
    model's optimum, so the test errs toward keeping the effect."""
    m = fit.model
    reduced = Model(m.params, [e for e in m.effects if e.name != name], m.starts)
    return fit_model(ws, reduced, max_steps=max_steps, tau_int=tau_int,
                     starts=(fit.starts, fit.test_starts), held_out=False)


def held_out_mse(ws: Workspace, fit: CandidateFit) -> np.ndarray:
    """Mean squared error [rad^2] of a fitted model's replay per held-out segment and output
    (S, C): (q1, q2), or q1 alone (``replayed_outputs``)."""
    y_meas = np.asarray(ws.test.segs.y_meas)  # the held-out measurements, any model
    return np.mean((held_out_traces(ws, fit) - y_meas) ** 2, axis=1)


def segment_errors(ws: Workspace, fit: CandidateFit) -> np.ndarray:
    """RMS error [rad] of a fitted model's replay per held-out segment (S,), q1 and q2
    together: the held-out evidence, segment by segment, for comparing two models on the
    same segments (``paired_p_value``)."""
    return np.sqrt(np.mean(held_out_mse(ws, fit), axis=1))


def held_out_traces(ws: Workspace, fit: CandidateFit) -> np.ndarray:
    """Simulated outputs (S, L, C) = (q1, q2), or q1 alone, [rad] of a fitted model on the held-out
    segments (for plots)."""
    _, test, _ = ws.for_model(fit.model)
    return np.asarray(simulated_outputs(test, (ws.theta_of(fit), fit.test_starts)))


def residual_analysis(ws: Workspace, fit: CandidateFit,
                      lags: int = 25) -> dict[str, Any]:
    """MATLAB ``resid`` of a fitted model on the held-out segments: per output (q1, q2) the
    autocorrelation of the residual (measured - simulated [rad]) and its cross-correlation
    with the logged torque, each with its 99% band, and the Ljung-Box whiteness test
    (``jaxflex.fit.residual_analysis.analyse_segments``: the lagged products pooled within
    the segments, each replayed from its own fitted start).

    **Arguments:**

    - `ws`: the workspace of the run.
    - `fit`: the fitted model (its held-out starts fitted).
    - `lags`: the largest lag [samples] (at most a segment's half less one; MATLAB's
      ``resid``: 25).

    **Returns:**

    ``{"part", "input", "residual", "lags", "confidence", "channels": {"q1": summary,
    "q2": summary}}``, each summary ``ResidualAnalysis.summary`` (curves included)."""
    _, test, _ = ws.for_model(fit.model)
    sim = np.asarray(simulated_outputs(test, (ws.theta_of(fit), fit.test_starts)))
    meas = np.asarray(test.segs.y_meas)
    u = np.asarray(test.segs.tau)[..., 0]
    if test.segs.active is not None:  # padding slots hold no data
        keep = np.asarray(test.segs.active, bool)
        sim, meas, u = sim[keep], meas[keep], u[keep]
    lags = max(1, min(lags, test.segs.length // 2 - 1))
    channels = {name: analyse_segments(meas[..., c] - sim[..., c], u, lags=lags).summary()
                for c, name in enumerate(test.outputs)}
    return {"part": "held-out segments", "input": "tau [N m]",
            "residual": "measured - simulated [rad]", "lags": lags,
            "confidence": CONFIDENCE, "channels": channels}


def gap_floor(log: Log, ws: Workspace, fit: CandidateFit, *, draws: int = 3,
              seed: int = 0) -> dict[str, Any]:
    """The held-out gap a *correct* model reaches on this log (parametric bootstrap).

    The fitted model ``fit`` stands in for the truth: it is replayed over the held-out
    segments from its fitted held-out start states with 4 x the workflow's substeps; the
    synthetic angles get the log's white noise (``white_noise_std`` less the quantisation)
    and are quantised to the log's encoder steps; then the workflow's own held-out steps
    follow on the synthetic data: start states fitted (``fit_starts``) from the starts that
    made them, open-loop replay with the workflow's substeps, and the gap. So the floor holds
    what noise, quantisation, the fitted starts and the replay's integration error cost a
    correct model on this log, and not the model's own errors, nor a start fit that stopped
    on its way from a far first guess (a floor from the log's own start estimates can exceed a
    correct model's final gap; the held-out part of a fit has its own second guess,
    ``held_out_starts``).

    Returns ``floor`` (mean over ``draws``), ``floor_sd`` (their spread), ``noise_std`` and
    ``step`` [rad] per output (q1, q2; q1 alone on a one-encoder log), ``segments`` used."""
    _, test, _ = ws.for_model(fit.model)
    th = ws.theta_of(fit)
    chans = [np.asarray(getattr(log, name), float)[:, 0] for name in test.outputs]
    steps = [noise_level(c)["step"] for c in chans]
    sig = [math.sqrt(max(white_noise_std(c) ** 2 - st**2 / 12.0, 0.0))
           for c, st in zip(chans, steps)]
    fine = finer(test)
    y_true = np.asarray(simulated_outputs(fine, (th, fit.test_starts)))  # (S, L, 2)
    x_true = within_capacity(fit.test_starts, test.space.plant(th))
    rng = np.random.default_rng(seed)
    synthetic = []
    for _ in range(draws):
        y = y_true + rng.normal(size=y_true.shape) * np.asarray(sig)
        for k, st in enumerate(steps):
            if st > 0:
                y[..., k] = np.round(y[..., k] / st) * st
        synthetic.append(eqx.tree_at(lambda p: p.segs.y_meas, test, to_device(y)))

    def draw_gap(rep: Problem) -> float:
        return float(gap(rep, (th, fit_starts(rep, th, x_true))))

    gaps = all_side_by_side(draw_gap, synthetic)  # the draws side by side
    return {"floor": float(np.mean(gaps)), "floor_sd": float(np.std(gaps)), "noise_std": sig,
            "step": steps, "segments": int(test.segs.count), "draws": draws}


def finer(prob: Problem) -> Problem:
    """``prob`` replayed with 4 x its substeps (``gap_floor``'s synthetic truth), as a traced
    loop count (``jaxflex.fit.refined``'s ``traced``): one copy of the substep in the program
    instead of four unrolled ones, for a replay that runs once per run: a program a third
    the size, the same floor."""
    return refined(prob, 4, traced=True)
