"""Screening and scoring the candidates of one round: a few Levenberg-Marquardt steps from
the current fit and the Gauss-Newton decrement (``screen``), the shortlist fitted fully
(``shortlist``, ``fit_candidate``), and each fit's training evidence (F-test, AIC, BIC:
``training_evidence``, ``score``).
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import scipy.special

from jaxflex.discover.candidates import (
    CandidateFit,
    Model,
    Workspace,
    fitted_count,
    fitted_names,
    within_capacity,
)
from jaxflex.discover.config import DiscoverConfig
from jaxflex.discover.fitting import (
    FIT_SOLVER,
    check_bounded,
    fit_model,
    relative_stop,
    segment_errors,
)
from jaxflex.fit import covariance, least_squares


def training_evidence(base_rss: float, rss: float, k: int, n_par: int, n_res: int,
                      n_eff: float) -> dict[str, float]:
    """F-test and BIC/AIC differences (effective count ``n_eff``) of a model with training
    residual sum of squares ``rss`` and ``n_par`` fitted unknowns (``k`` more than the base)
    over a base with ``base_rss`` (same ``n_res`` residuals, units of the segments' RMS
    motion). The F-test's residual degrees of freedom are the effective count less the share
    of it the fitted unknowns (parameters and start states) take, n_eff (1 - n_par / n_res)."""
    dof = max(n_eff * (1.0 - n_par / max(n_res, 1)), 1.0)
    drss = max(base_rss - rss, 0.0)
    F = (drss / k) / (rss / dof) if rss > 0 else math.inf
    p = float(scipy.special.fdtrc(k, dof, F))  # the F distribution's survival at F
    ll = lambda r: n_eff * math.log(max(r, 1e-300) / n_eff)  # noqa: E731
    return {
        "F": float(F), "p_value": p,
        "dBIC": ll(rss) - ll(base_rss) + k * math.log(n_eff),
        "dAIC": ll(rss) - ll(base_rss) + 2 * k,
    }


def score(base: CandidateFit, cand: CandidateFit, n_eff: float) -> dict[str, float]:
    """F-test, BIC/AIC difference (effective count) and held-out gain of ``cand`` over ``base``
    (``training_evidence`` of their training residuals)."""
    return {
        **training_evidence(base.rss, cand.rss, cand.n_par - base.n_par, cand.n_par,
                            cand.n_res, n_eff),
        "gap_test": cand.gap_test, "gain": 1.0 - cand.gap_test / base.gap_test,
    }


def screen(ws: Workspace, base: CandidateFit, model: Model, name: str, *, steps: int,
           tau_int: float, n_eff: float, start: Any = None) -> tuple[dict[str, Any], Any]:
    """The cheap look at candidate ``name`` (``model``: the base's model with the candidate's
    start added) that decides whether it is fitted fully (``shortlist``): at most ``steps``
    Levenberg-Marquardt steps on the training segments from the base's fitted starts (no
    held-out fit, no gap), then the Gauss-Newton decrement there, the further drop of the
    training residual a full Gauss-Newton step would bring. From the base's optimum with a
    candidate that starts at no effect, one step's decrement is the score (Rao) test of the
    candidate; the few steps carry a start that is an effect already (a lag or a backlash of
    the typical size, a cogging from the residual's spectrum) toward its optimum first.

    Returns (JSON-ready) ``rss`` (training residual sum of squares reached, units of the
    segments' RMS motion), ``decrement``, ``rss_predicted`` (rss - decrement, at least 1e-6
    rss), the ``training_evidence`` of both against the base (``screen_*`` keys: the fit
    reached; ``predicted_*``: the prediction), the candidate's parameter values and standard
    errors at the point reached (``params``: name -> {value, stderr}), ``steps`` and
    ``seconds``; and, beside the record, the training unknowns reached (``start``: a screen's
    unknowns to go on from, instead of the base's starts with the candidate's start)."""
    t0 = time.perf_counter()
    train, _, theta0 = ws.for_model(model)
    if start is None:
        start = (theta0, within_capacity(base.starts, train.space.plant(theta0)))
    sol = least_squares(train, start, max_steps=steps,
                        decrement_tol=relative_stop(train.n_out, tau_int), **FIT_SOLVER)
    r = np.asarray(sol.residual)[: train.n_out] if sol.residual is not None else None
    rss = float(np.sum(r**2)) if r is not None and np.all(np.isfinite(r)) else math.inf
    dec = sol.decrement if sol.decrement is not None and math.isfinite(sol.decrement) else 0.0
    pred = max(rss - max(dec, 0.0), 1e-6 * rss)
    k = fitted_count(name)
    n_par = base.n_par + k
    out: dict[str, Any] = {"rss": rss, "decrement": dec, "rss_predicted": pred,
                           "steps": sol.steps}
    if math.isfinite(rss):
        for tag, value in (("screen", rss), ("predicted", pred)):
            ev = training_evidence(base.rss, value, k, n_par, base.n_res, n_eff)
            out |= {f"{tag}_{key}": v for key, v in ev.items()}
        check_bounded(train.space, sol.y[0])
        cov = covariance(train, sol.y, inflation=tau_int, solution=sol)
        phys = train.space.physical_values(sol.y[0])
        out["params"] = {p.split(".", 1)[1]: {"value": float(np.ravel(phys[p])[0]),
                                              "stderr": float(np.ravel(cov["stderr"][p])[0])}
                         for p in fitted_names(name)}
    out["seconds"] = time.perf_counter() - t0
    return out, sol.y


def candidate_error(error: Exception) -> Exception:
    """``error`` when it is a candidate's own failure (a ``ValueError`` or
    ``FloatingPointError`` of its fit: reported, the other candidates go on); anything else
    (a bug, an interrupt) is raised."""
    if isinstance(error, (ValueError, FloatingPointError)):
        return error
    raise error


def candidate_score(base: CandidateFit, fit: CandidateFit, n_eff: float,
                    cfg: DiscoverConfig) -> dict[str, Any]:
    """``score`` of ``fit`` against ``base`` and whether it is significant: F-test p below
    ``cfg.alpha``, a lower BIC and a held-out gain of at least ``cfg.min_gain``."""
    s = score(base, fit, n_eff)
    s["significant"] = bool(s["p_value"] < cfg.alpha and s["dBIC"] < 0
                            and s["gain"] >= cfg.min_gain)
    return s


def fit_record(ws: Workspace, s: dict[str, Any], fit: CandidateFit,
               screen: dict[str, Any] | None) -> dict[str, Any]:
    """A round's score entry of a fully fitted candidate: its ``candidate_score`` ``s`` with
    the fit's seconds, steps and convergence, its per-segment held-out errors
    (``segment_errors``), not screened out, and its ``screen`` record when it had one."""
    s = s | {"seconds": fit.seconds, "steps": fit.steps, "converged": bool(fit.converged),
             "segment_errors": segment_errors(ws, fit).tolist(), "screened_out": False}
    if screen is not None:
        s["screen"] = screen
    return s


def fit_candidate(ws: Workspace, base: CandidateFit, model: Model, cfg: DiscoverConfig,
                  tau_int: float, n_eff: float,
                  ) -> tuple[CandidateFit | None, dict[str, Any] | None, str]:
    """The full fit of one candidate (``model``: ``base``'s model with the candidate's start
    added) with its ``score`` against ``base`` and whether it is significant (F-test p below
    ``cfg.alpha``, lower BIC, held-out gain at least ``cfg.min_gain``): (fit, score, "") or
    (None, None, why every fit failed).

    Two first guesses of the start states, both from training data only: the base's fitted
    starts (close for most candidates), and, when that fit is not significant, the log's
    start estimates; the fit with the lower training residual is kept. Each alone leaves some
    candidates in a local minimum: the base's starts have absorbed what the base misses (a
    hardening spring stayed at its first guess), the estimates put some segments in another
    friction regime (an asymmetric friction stopped at 80% of its size)."""
    f, s, why = None, None, ""
    for first in ((base.starts, base.test_starts), None):
        try:
            g = fit_model(ws, model, max_steps=cfg.max_steps, tau_int=tau_int, starts=first)
        except Exception as e:  # noqa: BLE001 - a candidate's own failure is reported
            why = str(candidate_error(e))
            continue
        if not (math.isfinite(g.gap_test) and math.isfinite(g.rss)):
            why = f"non-finite held-out gap {g.gap_test} or residual {g.rss}"
            continue
        if f is None or g.rss < f.rss:
            f = g
            s = candidate_score(base, f, n_eff, cfg)
        if s["significant"]:
            break
    return (f, s, "") if f is not None else (None, None, why)


def shortlist(screens: dict[str, dict[str, Any]], base_rss: float, *, alpha: float,
              keep: float, decisive: float, least: int) -> list[str]:
    """The screened candidates (``screen``) to fit fully, best predicted Akaike difference
    first: those that could be significant (predicted F-test p-value below ``alpha`` and a
    lower predicted BIC; significance also needs a held-out gain, which the screen does not
    see) and either explain at least ``keep`` of the predicted drop of the training residual
    (from ``base_rss``) of the best of them (so that a smaller candidate nearly as good, which
    ``select`` prefers, is fitted too) or come within ``decisive`` of its predicted Akaike
    difference (so that a rival that ``tied`` might not tell apart is fitted too); and in any
    case the ``least`` best with a negative predicted Akaike difference."""
    ok = {k: s for k, s in screens.items() if "predicted_dAIC" in s}
    order = sorted(ok, key=lambda k: ok[k]["predicted_dAIC"])
    could = [k for k in order if _could_be_significant(ok[k], alpha)]
    chosen = [k for k in order[:least] if ok[k]["predicted_dAIC"] < 0]
    if could:
        drop = {k: base_rss - ok[k]["rss_predicted"] for k in could}
        best = could[0]
        chosen += [k for k in could
                   if drop[k] >= keep * max(drop.values())
                   or ok[k]["predicted_dAIC"] <= ok[best]["predicted_dAIC"] + decisive]
    return [k for k in order if k in chosen]


def unresolved(screens: dict[str, dict[str, Any]], base_rss: float, *,
               alpha: float) -> list[str]:
    """The screened candidates (``screen``) that could be significant (as in ``shortlist``)
    but whose screen fit achieved less than half the drop of the training residual (from
    ``base_rss``) that it predicts: the start is far from where the residual is linear in the
    candidate, so the prediction is not to be trusted either way; ``discover`` screens them
    again with more steps (a lag started far from its value can screen worse than the base
    after a few steps and be the best candidate once it has a few more)."""
    return [k for k, s in screens.items() if "predicted_dAIC" in s
            and _could_be_significant(s, alpha)
            and base_rss - s["rss"] < 0.5 * (base_rss - s["rss_predicted"])]


def _could_be_significant(rec: dict[str, Any], alpha: float) -> bool:
    """A screen (``screen``) whose predicted training residual would pass the F-test at
    ``alpha`` and lower the BIC (significance also needs a held-out gain)."""
    return rec["predicted_p_value"] < alpha and rec["predicted_dBIC"] < 0


def screened_out(rec: dict[str, Any]) -> dict[str, Any]:
    """A round's score entry for a candidate the screen left out (``shortlist``): not fitted
    fully, so no held-out gap, gain or per-segment errors (None, never estimated), not
    significant; its F, p_value, dBIC and dAIC are those of the training residual its screen
    fit reached (``screen``; an unconverged fit, so they understate what a full fit could
    give), the screen record under ``screen``."""
    return {"screened_out": True, "significant": False, "gap_test": None, "gain": None,
            "F": rec["screen_F"], "p_value": rec["screen_p_value"], "dBIC": rec["screen_dBIC"],
            "dAIC": rec["screen_dAIC"], "seconds": rec["seconds"], "steps": rec["steps"],
            "screen": rec}
