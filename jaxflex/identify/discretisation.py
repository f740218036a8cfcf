"""The integrator's substeps of an identification: chosen at the start by step doubling
(``choose_substeps``) and refined at the solution until its own finer replay moves no fitted
parameter (``refine_fit``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from jaxflex.fit import (
    SCHEME_ORDER,
    Problem,
    ReplayError,
    Solution,
    cost,
    discretisation_bias,
    induced_point,
    refined,
    replay_error,
    residual_cost,
    simulated_outputs,
    step_doubling_error,
)
from jaxflex.core.validation import to_device

#: Automatic substeps (``choose_substeps``, ``identify(substeps="auto")``): the first choice
#: keeps the replay's step-doubling error below OUTPUT_TOL of the noise (weighted RMS: the
#: cost is then inflated by at most a quarter of what the noise explains, so the judgements
#: "settled" and "identifiable" still hold at that level); the fit is then refined until the
#: integrator moves no fitted parameter by more than BIAS_TOL standard errors
#: (``jaxflex.fit.discretisation_bias``), at most MAX_SUBSTEPS.
OUTPUT_TOL: float = 0.5
BIAS_TOL: float = 0.5
#: ``refine_fit`` also refines while the integrator moves a fitted parameter by more than
#: this share of its value: the standard errors of a model-limited fit are inflated by its
#: residual and alone would let a coarse integrator bias the answer.
BIAS_REL: float = 5e-3
MAX_SUBSTEPS: int = 32
#: ``refine_fit``: the most the substeps grow in one refinement.
REFINE_MOST: int = 8


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


#: ``rechoose_substeps``: the search's answer is an artefact of the integrator where its
#: replay's own error exceeds the residual the fit leaves there (this share of it).
ARTEFACT_TOL: float = 1.0


def rechoose_substeps(prob: Problem, sol: Solution, noise: float, *,
                      tol: float = ARTEFACT_TOL, most: int = MAX_SUBSTEPS,
                      ) -> tuple[Problem | None, dict[str, Any]]:
    """The substeps judged again at a search's answer ``sol`` of ``prob``: its replay's
    step-doubling error against the residual the fit leaves there (``tol`` times the larger
    of the noise and the fit's RMS residual, ``sqrt(cost / noise)`` in noise units), as
    ``choose_substeps`` measures it from ``prob``'s level. An error above that residual
    makes the answer a minimum of the integrator rather than of the data; one inside a
    model-limited residual is left to ``refine_fit``, which continues the fit. ``noise``: the cost the
    measurement noise alone gives (``noise_cost``). Returns the finer problem, or None where
    ``prob``'s substeps hold at the answer, and the errors measured."""
    scale = max(1.0, math.sqrt(max(float(sol.cost), 0.0) / noise))
    finer, info = choose_substeps(prob, sol.y, tol=tol * scale, most=most)
    info["tolerance"] = tol * scale
    return (finer if finer.n_substeps > prob.n_substeps else None), info


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


def refined_start(finer: Problem, sol: Solution, error: ReplayError, factor: int) -> Any:
    """Where the fit with ``factor`` x the substeps starts: ``sol``'s unknowns moved by the
    share 1 - factor^-p of the first-order move its replay's error induces
    (``jaxflex.fit.induced_point``; the finer replay keeps factor^-p of the error), where the
    replays are in the scheme's asymptotic range (their order at least ``SCHEME_ORDER``: a
    lower one makes the extrapolated error, and the move, a guess that can carry the fit to
    another minimum) and that point costs less than ``sol``'s own with the finer substeps
    (read off the error's own replays where it made one with them); else ``sol.y``.
    ``error``: ``sol``'s ``replay_error``."""
    if error.blown or error.order < SCHEME_ORDER:
        return sol.y
    moved = induced_point(finer, sol, error.e, 1.0 - float(factor) ** -error.order)
    if moved is None:
        return sol.y
    made = error.replays.get(finer.n_substeps)
    here = cost(finer, sol.y) if made is None else residual_cost(made)
    return moved if cost(finer, moved) < here else sol.y


def refine_fit(prob: Problem, sol: Solution, *, refine: bool,
               run: Callable[[Problem, Any, dict[str, Any]], Solution],
               tol: float = BIAS_TOL, rel_tol: float = BIAS_REL, most: int = MAX_SUBSTEPS,
               ) -> tuple[Problem, Solution, list[dict[str, Any]]]:
    """Check how far the integrator moves the fitted parameters of ``sol`` and, with
    ``refine``, continue the fit with more substeps until it does not.

    The shift is the Gauss-Newton step the solution's own finer replay induces
    (``jaxflex.fit.discretisation_bias``), judged twice: in standard errors (``bias_se`` at
    most ``tol``) and against the parameters' values (``bias_rel`` at most ``rel_tol``, over
    the parameters it moves by a tenth of a standard error or more). A
    model-limited fit's standard errors are inflated by its residual, and a coarse
    integrator's own error can be that residual; the relative shift holds either way. The fit
    is refined while either fails. Each refinement multiplies the substeps by 2^k, the shift
    falling by 2^(k p) with the order p the check measured (at most ``REFINE_MOST`` x), and
    continues from the solution moved by the shift the check predicts (``refined_start``),
    so most
    steps use the cheap replay; with ``make_problem``'s traced substep count every level runs
    the same compiled solver.

    Arguments:
        prob, sol: the problem and its ``least_squares`` solution.
        refine: continue the fit with more substeps (else only check).
        run: the solve that continues it, ``run(problem, y, label)`` (identify's
            ``Search.run``: the same stops and record as every other solve of the fit;
            ``label`` names the substeps).
        tol, rel_tol: the bounds on the shift (standard errors; share of the value).
        most: the most substeps.

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
        # an order a coarser check saw at the scheme's own serves the finer ones (one replay
        # fewer each); below it the steps were still in the pre-asymptotic range, where the
        # finer check measures afresh (a low order overstates the error there)
        seen = checks[-1]["order"] if checks else 0.0
        error = replay_error(prob, sol, order=seen if seen >= SCHEME_ORDER else None)
        chk = discretisation_bias(prob, sol, error=error)
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
        # the shift falls by 2^p per halving of the step, p the order the replays show
        need = max(chk["bias_se"] / tol, chk["bias_rel"] / rel_tol, 2.0)
        factor = 2 ** max(1, math.ceil(math.log2(min(need, 1e6)) / chk["order"]))
        factor = max(2, min(factor, REFINE_MOST, most // prob.n_substeps))
        finer = refined(prob, factor)
        more = run(finer, refined_start(finer, sol, error, factor),
                   {"refined_substeps": finer.n_substeps})
        if more.failed:  # the finer fit broke down: the coarser answer stands, judged as is
            checks[-1]["refinement_failed"] = finer.n_substeps
            return prob, sol, checks
        prob = finer
        sol = dataclasses.replace(more, steps=sol.steps + more.steps,
                                  seconds=sol.seconds + more.seconds)
