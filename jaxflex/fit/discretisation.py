"""How far the integrator's discretisation moves a fit: the replay's error by step doubling
(``integration_error``) and the shift of the fitted parameters it induces, in their standard
errors, with the order the replays show (``discretisation_bias``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import jax
import numpy as np

from jaxflex.fit.problem import BLOWN_RESIDUAL, Problem, dynamic_substeps
from jaxflex.fit.replay import residuals, simulated_outputs
from jaxflex.fit.solve import Solution
from jaxflex.fit.uncertainty import induced_shift


#: Error bound factor of a step-doubling estimate whose order is not measured: the error of
#: the coarse replay is at most RICHARDSON x (coarse - fine) for a scheme of order >= 1
#: (e_h = C h^p gives e_h = (y_h - y_h/2) / (1 - 2^-p): 2 for p = 1, 4/3 for p = 2). The
#: Strang-split step is second order only once sigma0 |v| / g(v) h is small; on the paper's
#: plant at 1 kHz the differences 1->2, 2->4, 4->8 substeps fall by 1.6x then 4x, so the
#: first-order bound is the one that holds at coarse steps.
RICHARDSON = 2.0
#: The bounds of the order ``observed_order`` reads off three replays (1: the first-order
#: bound, where the differences do not fall as a power of the step).
ORDER_RANGE: tuple[float, float] = (1.0, 4.0)
#: The replay's order as its step falls (the Strang-split step of ``jaxflex.sim.step``).
SCHEME_ORDER: float = 2.0


def refined(prob: Problem, factor: int = 2, traced: bool = False) -> Problem:
    """``prob`` with ``factor`` x its integrator substeps (the same data and unknowns): a
    Python int if ``prob``'s is one, else a traced count (``dynamic_substeps``); ``traced``:
    a traced count in any case (a loop in the program instead of unrolled substeps)."""
    n = prob.n_substeps * int(factor)
    return dataclasses.replace(
        prob, substeps=n if isinstance(prob.substeps, int) and not traced
        else dynamic_substeps(n))


def integration_error(prob: Problem, y: Any) -> float:
    """RMS integration error of ``prob``'s output replay at ``y``, in the problem's weighted
    units (``w_y``; for identification, units of the log's noise), by step doubling: RICHARDSON
    x RMS of the weighted difference between the replay with the problem's substeps and with
    twice as many. Compiles the finer replay once per problem shape."""
    return step_doubling_error(prob, simulated_outputs(prob, y),
                               simulated_outputs(refined(prob), y))


def step_doubling_error(prob: Problem, coarse: jax.Array, fine: jax.Array) -> float:
    """``integration_error`` from replays already made: ``coarse``, ``prob``'s outputs
    (``simulated_outputs``) with its substeps, and ``fine``, with twice as many; inf if
    either is not finite."""
    d = np.asarray(prob.w_y) * (np.asarray(fine) - np.asarray(coarse))  # on the host
    return RICHARDSON * float(np.sqrt(np.mean(d**2))) if np.all(np.isfinite(d)) else math.inf


def observed_order(coarse: np.ndarray, fine: np.ndarray, finer: np.ndarray) -> float:
    """The integrator's order as three replays with h, h/2 and h/4 show it:
    log2(|coarse - fine| / |fine - finer|) (the differences of a scheme of order p fall by
    2^p per halving), within ``ORDER_RANGE``; its lower bound where either difference is not
    finite or the finer one vanishes only because both do."""
    d1 = float(np.linalg.norm(np.asarray(fine) - np.asarray(coarse)))
    d2 = float(np.linalg.norm(np.asarray(finer) - np.asarray(fine)))
    lo, hi = ORDER_RANGE
    if not (math.isfinite(d1) and math.isfinite(d2)) or d1 == 0.0:
        return lo
    return hi if d2 == 0.0 else min(max(math.log2(d1 / d2), lo), hi)


class ReplayError(NamedTuple):
    """The integration error of a solution's residuals (``replay_error``): ``e``, the exact
    replay's residuals minus the solution's (rows as the problem's residual, estimated),
    ``order``, the p it was extrapolated with, ``blown``: a replay blew up (``e`` not
    meaningful), and ``replays``: the finer replays' residuals it made (substeps -> rows)."""

    e: np.ndarray
    order: float
    blown: bool
    replays: dict[int, np.ndarray]


def replay_error(prob: Problem, solution: Solution, order: float | None = None,
                 ) -> ReplayError:
    """The integration error of ``solution``'s residuals by Richardson extrapolation with the
    order the replays show: e = (r_h/2 - r_h) / (1 - 2^-p), p the ``observed_order`` of the
    replays with 1, 2 and 4 times the substeps (``ORDER_RANGE``'s lower bound where a replay
    blew up). ``order``: p as a check at coarser substeps measured it, in place of the replay
    with 4 times the substeps; at most ``SCHEME_ORDER`` is used (the scheme's order at coarse
    steps is at most its asymptotic one, and a lower p gives a larger e: the safe side).
    Raises ``ValueError`` for a solution without its residual (it took no step)."""
    if solution.residual is None:
        raise ValueError("replay_error: the solution carries no residual (it took no step)")
    y = solution.y
    coarse = np.asarray(solution.residual)
    fine = np.asarray(residuals(refined(prob), y))
    n_out = prob.n_out
    blown = bool(np.any(fine[:n_out] == BLOWN_RESIDUAL)
                 or np.any(coarse[:n_out] == BLOWN_RESIDUAL))
    replays = {2 * prob.n_substeps: fine}
    if blown:
        order = ORDER_RANGE[0]
    elif order is None:
        finer = replays[4 * prob.n_substeps] = np.asarray(residuals(refined(prob, 4), y))
        order = observed_order(coarse, fine, finer)
    else:
        order = min(max(order, ORDER_RANGE[0]), SCHEME_ORDER)
    return ReplayError((fine - coarse) / (1.0 - 2.0**-order), order, blown, replays)


def discretisation_bias(prob: Problem, solution: Solution,
                        error: ReplayError | None = None) -> dict[str, Any]:
    """How far the integrator's discretisation moves the fitted parameters, in their standard
    errors: the parameters fitted with the problem's substeps minimise the coarse residual
    r_h; with an exact replay they would minimise r_h + e, e the integration error of the
    residuals at the solution (``replay_error``). To first order the fit moves by the
    Gauss-Newton step -(J^T J)^-1 J^T e, computed from the solution's own normal equations
    (no new Jacobian; ``replay_error``'s finer replays, on the programs of the problem's own
    shape).

    ``solution``: the ``least_squares`` result of ``prob`` (with its ``normal`` equations).
    ``error``: its ``replay_error`` where already made (None: made here).
    Returns ``bias_se`` (the largest |shift| / standard error over the fitted theta entries:
    the discretisation moves no fitted parameter by more than this many standard errors),
    ``bias_mahalanobis`` (sqrt of shift^T Cov^-1 shift over the fitted entries: the bound for
    any combination of them), ``output_error`` (the output rows of e, weighted RMS),
    ``order`` (p), ``substeps``, and per fitted theta entry ("name[j]") the predicted
    ``shift_theta`` (exact replay minus this fit, engine coordinates) and ``stderr_theta``
    (segment-robust, ``segment_robust_covariance``, where the log has the segments for it).
    Raises ``ValueError`` for a solution without normal equations."""
    if solution.normal is None or solution.residual is None:
        raise ValueError("discretisation_bias: the solution carries no normal equations "
                         "(it took no step)")
    e, order, blown, _ = replay_error(prob, solution) if error is None else error
    # the output rows of e are the replay's own error, weighted (inf where a replay blew up)
    out_err = math.inf if blown else float(np.sqrt(np.mean(e[: prob.n_out] ** 2)))
    shift, se, labels, fitted, cov = induced_shift(prob, solution, e)
    finite = bool(np.all(np.isfinite(shift)))
    maha = (float(np.sqrt(max(float(shift @ np.linalg.pinv(cov) @ shift), 0.0)))
            if finite and shift.size else (0.0 if finite else math.inf))
    return {"bias_se": float(np.max(np.abs(shift) / se)) if finite and shift.size
            else (0.0 if finite else math.inf),
            "bias_mahalanobis": maha, "output_error": out_err, "order": order,
            "substeps": prob.n_substeps,
            "shift_theta": {labels[i]: float(v) for i, v in zip(fitted, shift)},
            "stderr_theta": {labels[i]: float(v) for i, v in zip(fitted, se)}}
