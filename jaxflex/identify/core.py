"""Joint identification from one log by gradient through the simulator (docs/spec.md
section 5): a thin workflow on the fitting engine ``jaxflex.fit``.

Output-error least squares with multiple shooting and free segment start states
(``jaxflex.fit.Problem``): residuals are the output errors ``w_y (y_sim - y_meas)`` with
``y = q1`` (and ``q2`` for the flexible model) and the continuity defects between segments,
``w_y`` the inverse of the encoder-noise level estimated from the log, so a cost of about
``n_out / 2`` (``noise_cost``, less with a finer second encoder) is what noise explains. Physical constraints hold by reparametrisation
(``jaxflex.fit.ParamSpace``); the solver is the engine's Levenberg-Marquardt
(``jaxflex.fit.least_squares``); standard errors come from the engine's covariance with the
nuisance start states included. A portfolio of continuation schedules guards against local
minima (``identify``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.fit import (
    ParamSpace,
    Problem,
    Solution,
    covariance,
    discretisation_bias,
    dynamic_substeps,
    get_value,
    least_squares,
    make_segments,
    noise_level,
    output_columns,
    refined,
    segment_robust_covariance,
    set_values,
    simulated_outputs,
    step_doubling_error,
    trace_solver,
)
from jaxflex.fit.ahead import Ahead
from jaxflex.identify.static import start_from_static_map
from jaxflex.logs import Log
from jaxflex.params import Params
from jaxflex.state import PlantState
from jaxflex.validation import requires_float64
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
    names the data cannot identify (they keep their initial values in ``params`` and are
    marked ``"identified": false`` with the reason in the file); warnings: messages; steps:
    solver steps; converged: the final cost is explained by the measurement noise (0.5 ||r||^2
    <= accept_cost x ``noise_cost``, what the noise estimated from the log explains) and
    the solver met its tolerance;
    reason: why not, or "cost explained by noise"; noise_cost: that bound; wall_s: solve time
    [s]; problem: the ``Problem`` (for re-simulation and benchmarks); solution: the solver's
    final unknowns (theta and segment states); attempts: the continuation schedules tried, with
    their final costs; why: per unidentifiable name, the reason; discretisation: the
    substeps used and how far they move the fitted parameters (``refine_fit``); segments: the
    multiple-shooting segments (their length, how it was chosen). rank, n_free,
    singular_values describe the fit with every free parameter (before the unidentifiable
    ones were fixed).
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


@requires_float64
def identify(
    log: Log, init: Params, free: Sequence[str] = DEFAULT_FREE, *,
    model: ModelKind = "flexible", segment_length: int | str | None = "auto",
    substeps: int | str = "auto",
    outputs: Sequence[str] | None = None, output_scale: float | Sequence[float] | None = None,
    continuity_weight: float = 10.0,
    warm_start: float | None | Sequence[float | None] = (1e-3, 1e-2, None),
    warm_steps: int = 40, accept_cost: float = 4.0,
    rtol: float = 1e-10, atol: float = 1e-10, max_steps: int = 200,
    rel_stderr_limit: float = 0.5, progress: bool | int = False, static_start: bool = True,
    decrement_tol: float | None = DECREMENT_TOL, geodesic: float = GEODESIC,
    vs_restarts: Sequence[float] = (3.0, 1.0 / 3.0),
) -> IdentResult:
    """Identify the ``free`` parameters of ``init`` from ``log`` (docs/spec.md section 5).

    ``model``: "flexible" (eq. 3) or "rigid" (eq. 37, Jx = I + J). ``segment_length``:
    samples per multiple-shooting segment (None: single shooting), or "auto" (default): two
    mechanical time constants of the start model on a grid of lengths
    (``choose_segment_length``; recorded under ``extra["identification"]["segments"]``);
    ``substeps``: integrator
    substeps per sample, or "auto": chosen from the log and the model (``choose_substeps``:
    the fewest whose replay error is below ``OUTPUT_TOL`` of the noise at the start), then,
    coarse to fine, doubled and the fit continued from its own solution until the
    discretisation moves no fitted parameter by more than ``BIAS_TOL`` standard errors
    (``jaxflex.fit.discretisation_bias``, at most ``MAX_SUBSTEPS``). With a number the check
    is still made and reported (``extra["identification"]["discretisation"]``; a warning when
    it fails). ``rtol``/``atol``: Levenberg-Marquardt termination; ``max_steps``:
    iteration cap; ``accept_cost``: the factor on ``noise_cost`` below which the cost counts as
    explained by the noise; ``decrement_tol``: the solver's statistical stop (``least_squares``): the
    residuals are in units of the log's noise, so a point from which a full Gauss-Newton step
    would lower chi-square by less than this is as settled as the data can tell (default 1e-2:
    the remaining step is below 0.1 standard errors; None: the tolerances alone);
    ``geodesic``: the solver's geodesic acceleration (``least_squares``; 0: off), which takes
    LuGre's curved Fs-vs-sigma valley in a few steps where plain Levenberg-Marquardt creeps
    along it for hundreds. A parameter whose relative standard error exceeds ``rel_stderr_limit``, or
    that lies in a numerically null direction of the Jacobian, is named in an
    ``IdentificationWarning`` and in ``IdentResult.unidentifiable``. ``progress``: print the
    cost every ``progress`` steps (True: every step).
    ``warm_start``: with several segments, first solve for at most ``warm_steps`` steps with
    the continuity weight multiplied by this factor (segments nearly independent, a far less
    nonconvex problem), then tighten to the full weight (a continuation; None: off). A
    sequence of factors is a portfolio of such schedules, tried in order from the same start
    until one ends with a cost the noise explains (0.5 ||r||^2 <= ``accept_cost`` x
    ``noise_cost``, what the noise estimated from each channel of the log gives); otherwise the
    lowest cost wins. The default tries 1e-2 before the plain schedule: on the 3 s closed-loop
    logs of datagen seeds 7-14 both orders converge the same eight, but on seed 7 the plain
    schedule first runs its 200 steps into a local minimum.
    All stages share one compilation (the engine's solver loops on the host).
    ``static_start``: for the flexible and link models (both encoders), a first start takes
    the free static parameters (Fc, Fs, vs, sigma2) from a fit of eq. 35 to the friction the
    log shows by inverse dynamics (``start_from_static_map``), where that fit determines them,
    joint by joint (each joint's map from its own inverse dynamics; a joint whose map fixes
    nothing keeps its values in ``init``); the user's ``init`` is the second start, tried
    when the first does not reach the noise level (a portfolio of starts x schedules,
    stopping at the first success). ``vs_restarts``: when every start and schedule ends in
    a local minimum (the cost above what the noise explains), the first start is tried again
    with vs multiplied by each of these factors in turn (a multi-start in the Stribeck
    velocity, which decides where the friction hump lies; () turns it off).
    Parameters the data cannot determine keep their initial values and are marked (see
    ``finish``); a converged fit is then repeated without them.
    """
    auto = substeps == "auto"
    if not auto and not (isinstance(substeps, int) and substeps >= 1):
        raise ValueError(f"identify: substeps must be a positive integer or 'auto', "
                         f"got {substeps!r}")
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
    # the solver options every solve of this fit shares (they key its compiled program)
    options = dict(rtol=rtol, atol=atol, decrement_tol=decrement_tol, geodesic=geodesic)
    ahead = compile_ahead(prob, y0, options)
    start = (start_from_static_map(log, init, free)
             if (static_start and model in ("flexible", "link")) else None)
    starts = [("user", y0)]
    if start:
        th = prob.space.theta_of({**{k: get_value(init, k) for k in prob.space.names}, **start})
        starts.insert(0, ("static map of the log", (th, y0[1])))
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
    good = accept_cost * noise_cost(log, prob)
    solve = dict(options, progress=say)
    t0 = time.perf_counter()
    best, best_factor = None, None
    attempts = []

    def warmed(problem: Problem, y: Any, factor: float | None) -> Any:
        """``y`` after the first phase of the schedule ``factor``: at most ``warm_steps``
        steps with the continuity weight times ``factor`` (None, or one segment: ``y``)."""
        if factor is None or problem.segs.count == 1:
            return y
        loose = eqx.tree_at(lambda q: q.w_def, problem, problem.w_def * factor)
        return least_squares(loose, y, max_steps=warm_steps, **solve).y

    ahead.wait(0)
    for origin, y_start in starts:
        for factor in schedules:
            y = warmed(prob, y_start, factor)
            sol = least_squares(prob, y, max_steps=max_steps, **solve)
            if sol.cost <= good and not sol.converged:
                # at the noise level but still moving: let it settle before judging
                more = least_squares(prob, sol.y, max_steps=max_steps, **solve)
                sol = dataclasses.replace(more, steps=sol.steps + more.steps,
                                          seconds=sol.seconds + more.seconds)
            attempts.append({"start": origin, "warm_start": factor, "cost": sol.cost,
                             "steps": sol.steps, "reason": sol.reason})
            if progress:
                print(f"  [identify] start {origin}, warm_start={factor}: cost {sol.cost:.6e}"
                      f" (noise explains <= {good:.3e}); {sol.reason}")
            if best is None or sol.cost < best.cost:
                best, best_factor = sol, factor
            if _settled(sol, good):
                break
        if _settled(best, good):
            break
    if not _settled(best, good) and "vs" in prob.space.names and vs_restarts:
        # Every start and schedule ended in a local minimum. The Stribeck velocity decides
        # where in the velocity range the friction hump lies; a fit whose vs starts on the
        # wrong side of the hump lets Fs and sigma1 absorb it and vs stops moving (the 3 s
        # closed-loop log of seed 13: vs 50% low from every start, cost 500x the noise; from
        # vs x2 or x3 it converges within 0.2%). Multi-start in vs, geometrically, from the
        # first start with the first schedule; the first that settles, else the lowest, wins.
        origin, (th0, x0) = starts[0]
        phys = prob.space.physical_values(th0)
        for f in vs_restarts:
            th = prob.space.theta_of({**phys, "vs": phys["vs"] * f})
            y = warmed(prob, (th, x0), schedules[0])
            sol = least_squares(prob, y, max_steps=max_steps, **solve)
            attempts.append({"start": f"{origin}, vs x{f:g}", "warm_start": schedules[0],
                             "cost": sol.cost, "steps": sol.steps, "reason": sol.reason})
            if progress:
                print(f"  [identify] restart vs x{f:g}: cost {sol.cost:.6e}; {sol.reason}")
            if sol.cost < best.cost:
                best, best_factor = sol, schedules[0]
            if _settled(sol, good):
                break
    ahead.join()
    res = finish(prob, init, best.y, steps=best.steps, converged=_settled(best, good),
                 wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                 reason=_reason(best, good), noise_cost=good, log=log, solution=best)
    res.attempts = attempts
    if start:
        attempts.insert(0, {"static_start": {k: [float(x) for x in v] for k, v in start.items()}})
    # Fix what the data cannot determine at its initial value and refit the rest, so that the
    # identified values neither absorb a meaningless direction nor are reported beside a
    # parameter reset after the fit (converged or not: a reset value and the values fitted
    # with the discarded one do not belong together). One parameter at a time, the least
    # determined first: the largest relative standard error, then the names of a null
    # direction, never one marked only because its Fs/Fc partner is; until the rest are all
    # determined. A null direction names every parameter with weight in it, also a
    # well-determined one whose column a poorly determined partner copies: on EMPS (rigid,
    # segments of 1000) the first fit ends with vs = 157 m/s, far above the log's speeds, so
    # the Stribeck hump is a level shift and Fc, Fs share a null direction although the
    # friction level is the log's best-determined quantity; fixing Fc first (the order before)
    # left a refit that could not recover and a report with Fc at its start, 10 N against the
    # 20 N the log shows (force error 19% instead of 5%). vs, its relative standard error
    # 1e14%, is the one to fix.
    first, fixed_why, cur, y_cur, total = res, {}, prob, best.y, best.steps
    final = (prob, best, None)  # the problem, solution and fixed names behind ``res``
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
                              output_scale=output_scale,
                              continuity_weight=continuity_weight)
        # from the values fitted so far and from the user's start with the winning schedule
        # (those fitted together with the parameter now fixed may sit far from where the
        # better-posed problem goes); the second start is only prepared if it is tried
        def kept(space: Any, y: Any) -> Any:
            """``y`` (unknowns of the problem whose space is ``space``) in the refit's
            coordinates: the physical values of the names kept (not their coordinates: an
            ordered Fs is built on Fc, so with Fc fixed the same coordinate is another Fs)."""
            phys = space.physical_values(y[0])
            return sub.space.theta_of({k: phys[k] for k in keep}), y[1]

        sol = None
        for label, start_of in (("fitted", lambda: kept(cur.space, y_cur)),
                                ("user", lambda: warmed(sub, kept(prob.space, y0), best_factor))):
            s_ = least_squares(sub, start_of(), max_steps=max_steps, **solve)
            total += s_.steps
            attempts.append({"refit_without": list(fixed_why), "start": label,
                             "cost": s_.cost, "steps": s_.steps, "reason": s_.reason})
            if sol is None or s_.cost < sol.cost:
                sol = s_
            if _settled(sol, good):
                break
        # The refit is the answer even when its cost is above the free fit's: that fit is not
        # what would be reported (its unidentified parameters reset to their initial values,
        # beside values fitted with them: a set no fit produced), the refit's values are fitted
        # together. (Before, a refit above the free fit's cost was
        # dropped for the free fit's reset set: on EMPS with segments of 250 the refit reached
        # 3.06e10, the free fit 3.03e10 with Fs = 3e20 N and vs = 0, and the set reported, Fc
        # and Fs at their starts, had a closed-loop force error of 21% instead of 5%.)
        res = finish(sub, init, sol.y, steps=total, converged=_settled(sol, good),
                     wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                     reason=_reason(sol, good), noise_cost=good, log=log,
                     unidentified=dict(fixed_why), solution=sol)
        cur, y_cur = sub, sol.y
        final = (sub, sol, dict(fixed_why))
    if fixed_why and cur is not prob:
        # the parameters were judged unidentifiable at the first fit's point, which may be a
        # local minimum (a 3 s log: vs "unidentifiable" at a cost 20x the optimum's, fixed
        # 50% off, Fs then fitted 46% off to make up for it). From the refit's lower point,
        # free them again: if every parameter is then determined at a lower cost, that fit
        # is the answer
        th = {k: (y_cur[0][k] if k in y_cur[0] else y0[0][k]) for k in prob.space.names}
        full = least_squares(prob, (th, y_cur[1]), max_steps=max_steps, **solve)
        total += full.steps
        attempts.append({"released": list(fixed_why), "start": "refit", "cost": full.cost,
                         "steps": full.steps, "reason": full.reason})
        if full.cost < final[1].cost:  # the last refit's cost
            again = finish(prob, init, full.y, steps=total, converged=_settled(full, good),
                           wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                           reason=_reason(full, good), noise_cost=good, log=log,
                           solution=full)
            if not again.unidentifiable:
                res = first = again
                final = (prob, full, None)
    # coarse to fine: the integrator must not move the fitted parameters (``refine_fit``);
    # with substeps="auto" the answer is refined from its own solution until it does not
    f_prob, f_sol, f_fixed = final
    r_prob, r_sol, discretisation["checks"] = refine_fit(
        f_prob, f_sol, refine=auto, solve=dict(solve, max_steps=max_steps), attempts=attempts)
    discretisation.update(discretisation["checks"][-1])
    substeps = r_prob.n_substeps
    if r_prob is not f_prob:
        total += r_sol.steps - f_sol.steps
        again = finish(r_prob, init, r_sol.y, steps=total, converged=_settled(r_sol, good),
                       wall_s=time.perf_counter() - t0, rel_stderr_limit=rel_stderr_limit,
                       reason=_reason(r_sol, good), noise_cost=good, log=log,
                       unidentified=f_fixed, solution=r_sol)
        if res is first:
            first = again
        res = again
    if res is not first:
        res.rank, res.n_free, res.singular_values = first.rank, first.n_free, first.singular_values
        res.warnings = first.warnings + res.warnings
    res.attempts = attempts
    res.params.extra["identification"]["attempts"] = attempts
    res.params.extra["identification"]["discretisation"] = discretisation
    res.params.extra["identification"]["segments"] = segments
    res.discretisation = discretisation
    res.segments = segments
    if not discretisation["bias_se"] <= BIAS_TOL and math.isfinite(discretisation["bias_se"]):
        msg = (f"the integrator ({substeps} substeps per sample) moves a fitted parameter by "
               f"{discretisation['bias_se']:.3g} standard errors (> {BIAS_TOL}): use more "
               f"substeps (or substeps='auto')")
        res.warnings.append(msg)
        warnings.warn(msg, IdentificationWarning, stacklevel=2)
    return res


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


def refine_fit(prob: Problem, sol: Solution, *, refine: bool, solve: dict[str, Any],
               tol: float = BIAS_TOL, most: int = MAX_SUBSTEPS,
               attempts: list[dict[str, Any]] | None = None,
               ) -> tuple[Problem, Solution, list[dict[str, Any]]]:
    """Check how far the integrator moves the fitted parameters of ``sol`` (``prob``'s
    solution; ``jaxflex.fit.discretisation_bias``, in standard errors) and, with ``refine``,
    continue the fit from its own solution with more substeps until the shift is at most
    ``tol`` (or ``most`` substeps): a continuation from coarse to fine, so that most steps are
    taken with the cheap replay. Each refinement multiplies the substeps by 2^k, k from a
    first-order fall of the shift (b / tol times smaller steps; at most REFINE_MOST x per
    refinement, each then checked again), and continues the fit from its solution (on a log
    the noise explains, in 2-3 steps: the shift is a Gauss-Newton correction; a fit the model
    cannot bring to the noise, e.g. real data, runs on to its step cap at the finer level,
    and a capped continuation of 20 steps left an EMPS fit 400x above the coarse cost). On
    the generated logs the shift fell 6x from 4 to 16 substeps, not the 16x of a second-order
    scheme (logs made by a 10-substep simulator); on EMPS it fell from 11.6 to 0.0005
    standard errors from 4 to 32.
    With ``make_problem``'s traced substep count (``jaxflex.fit.dynamic_substeps``) every
    level runs the same compiled solver. ``solve``: ``least_squares`` options.
    Returns the final problem, solution and every check."""
    checks = []
    while True:
        if sol.normal is None:  # no step was taken: nothing to judge
            checks.append({"substeps": prob.n_substeps, "bias_se": math.nan,
                           "bias_mahalanobis": math.nan, "output_error": math.nan})
            return prob, sol, checks
        chk = discretisation_bias(prob, sol)
        checks.append(chk)
        if not refine or not chk["bias_se"] > tol or prob.n_substeps * 2 > most:
            return prob, sol, checks
        factor = 2 ** max(1, math.ceil(math.log2(min(chk["bias_se"] / tol, 1e6))))
        factor = max(2, min(factor, REFINE_MOST, most // prob.n_substeps))
        prob = refined(prob, factor)
        more = least_squares(prob, sol.y, **solve)
        if attempts is not None:
            attempts.append({"refined_substeps": prob.n_substeps, "cost": more.cost,
                             "steps": more.steps, "reason": more.reason})
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
    if _settled(sol, good):
        return "cost explained by noise"
    if sol.cost <= good:
        return f"cost explained by noise but the solver did not settle ({sol.reason})"
    return (f"cost {sol.cost:.4g} is above what the measurement noise explains ({good:.4g}): "
            f"a local minimum or a model that lacks something; solver: {sol.reason}")


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
    out = set_values(init, {k: v for k, v in phys.items() if k not in bad})
    out.extra = dict(out.extra)
    out.extra["stderr"] = {k: se[k] for k in phys if k not in bad}
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
