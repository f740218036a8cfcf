"""Choosing among fitted candidates: the residuals' effective sample count, paired held-out
tests, the pick (``select``), the polish of close rivals before it (``contest``), ties the data
cannot break (``tied``, ``break_tie``, ``revisit_tie``) and the Akaike and Schwarz weights of a
round (``evidence_weights``).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np
import scipy.special

from jaxflex.discover.candidates import CandidateFit, Model, Workspace, fitted_count
from jaxflex.discover.fitting import fit_model, held_out_mse, settle
from jaxflex.core.effects import AbstractEffect
from jaxflex.fit import residuals
from jaxflex.runtime.ahead import all_side_by_side


def paired_p_value(worse: Sequence[float], better: Sequence[float]) -> float:
    """One-sided paired t-test [-] that model ``better`` replays the same held-out segments
    better than ``worse``, on the log ratio of their per-segment RMS errors
    (``segment_errors``): small when the advantage holds segment after segment, near 0.5 or
    above when it comes from a few segments (a start state that one model happens to
    forgive) or is absent."""
    d = np.log(np.maximum(np.asarray(worse, float), 1e-300)) - np.log(
        np.maximum(np.asarray(better, float), 1e-300))
    if d.size < 2:
        return 1.0
    sd = float(np.std(d, ddof=1))
    if sd == 0.0:
        return 0.0 if float(np.mean(d)) > 0 else 1.0
    t = float(np.mean(d)) / (sd / math.sqrt(d.size))
    return float(scipy.special.stdtr(d.size - 1, -t))  # Student's t survival at t


# ----------------------------------------------------------------------------- selection


def effective_count(r: np.ndarray, max_lag: int = 2000) -> float:
    """Integrated autocorrelation time [samples] of a residual (S, L): 1 + 2 sum rho_k up to
    the first non-positive rho (Geyer's initial positive sequence, simplified)."""
    r = r - r.mean(axis=1, keepdims=True)
    var = float(np.mean(r**2))
    if var == 0:
        return 1.0
    tau = 1.0
    for k in range(1, min(max_lag, r.shape[1] - 1)):
        rho = float(np.mean(r[:, k:] * r[:, :-k])) / var
        if rho <= 0:
            break
        tau += 2 * rho
    return tau


def output_residuals(ws: Workspace, fit: CandidateFit) -> np.ndarray:
    """``fit``'s training residuals (S, L, C) per segment, sample and output (q1, q2), in the
    units of the segments' RMS motion (the problem's output weight)."""
    train, _, _ = ws.for_model(fit.model)
    S, L = train.segs.count, train.segs.length
    y = (ws.theta_of(fit), fit.starts)
    return np.asarray(residuals(train, y))[: train.n_out].reshape(S, L, -1)


def autocorrelation_time(ws: Workspace, fit: CandidateFit) -> float:
    """The integrated autocorrelation time [samples] of ``fit``'s training residuals, the
    largest over its outputs (``effective_count`` per segment): the factor by which
    correlated residuals inflate the standard errors and shrink the effective count."""
    r = output_residuals(ws, fit)
    return max(effective_count(r[..., c]) for c in range(r.shape[-1]))


def output_evidence(ws: Workspace, fit: CandidateFit) -> dict[str, Any]:
    """The evidence of ``fit`` output by output (q1, q2), for ``break_tie``: the training
    residual sum of squares ``rss`` (units of the segments' RMS motion), its integrated
    autocorrelation time ``tau`` [samples] and sample count ``count`` per output, and the
    held-out mean squared error ``held_out_mse`` [rad^2] per segment and output (S, C)."""
    r = output_residuals(ws, fit)
    return {"rss": [float(np.sum(r[..., c] ** 2)) for c in range(r.shape[-1])],
            "tau": [effective_count(r[..., c]) for c in range(r.shape[-1])],
            "count": int(r.shape[0] * r.shape[1]),
            "held_out_mse": held_out_mse(ws, fit)}


def settle_side_by_side(ws: Workspace, fits: dict[str, CandidateFit], names: Sequence[str],
                        *, max_steps: int, tau_int: float) -> dict[str, CandidateFit]:
    """``settle`` of the fits ``names`` of ``fits``, side by side (``side_by_side``)."""
    return dict(zip(names, all_side_by_side(
        lambda k: settle(ws, fits[k], max_steps=max_steps, tau_int=tau_int), names)))


def contest(scores: dict[str, dict[str, Any]], winner: str | None,
            factor: float) -> list[str]:
    """The candidates a round's pick could turn on (sorted; empty when there is no rival):
    ``winner`` and every significant rival whose held-out gap is within ``factor`` of the
    winner's (those with a lower gap that ``select`` passed over for fewer parameters
    included). Their full fits stop after a few dozen steps, far from their optimum where the
    residual is flat, so their gaps can be several times what each reaches and their order
    can flip between nearly equal bases: the pick between them is made once each is
    polished (``settle``)."""
    if winner is None or factor <= 1.0:
        return []
    w = scores[winner]["gap_test"]
    rivals = [k for k, s in scores.items() if s["significant"] and k != winner
              and s["gap_test"] <= factor * w]
    return sorted([winner, *rivals]) if rivals else []


def break_tie(ws: Workspace, fits: dict[str, CandidateFit], names: Sequence[str], *,
              max_steps: int, tau_int: float, decisive: float = 10.0,
              tie_alpha: float = 0.05, settled: Collection[str] = (),
              ) -> tuple[str, list[str], dict[str, Any], dict[str, CandidateFit]]:
    """Tell apart candidates ``names`` that ``tied`` could not, with the evidence of each
    encoder at its own noise level. Returns (winner, still tied (sorted, winner included),
    a record per candidate, the polished fits). ``settled``: names whose fits are polished
    already (``contest``).

    Why: the fits and ``tied`` weigh q1 and q2 alike, in rad, so the pooled residual is
    the link encoder's, and the pooled count is divided by the larger autocorrelation time
    of the two. The rotor encoder is finer (50x in the generator, the motor side of a
    gearbox on a rig) and it carries what the applied torque does first: a delay and a lag
    can differ clearly on q2 while the pooled residual, nearly all q1's, cannot tell them
    apart.

    How: every candidate is polished first (``settle``, as the winner always is), since
    30 steps leave the q2 residual far from its optimum.
    Then each output is a Gaussian likelihood with its own variance and its own effective
    count n / tau_c (tau_c the largest autocorrelation time of output c among the
    candidates): -2 log L = sum_c n_eff,c log rss_c + const. The winner has the lowest. A rival is
    told apart when its Akaike difference (same parameter count) is at least ``decisive``
    and a one-sided paired test on the held-out segments (``paired_p_value`` of the per-segment
    errors, each output scaled by the winner's held-out mean square error) gives p at most
    ``tie_alpha``. The fits minimise the pooled residual, not this likelihood: each
    candidate is judged at its own least-squares optimum."""
    polished = {k: fits[k] for k in names if k in settled}
    polished |= settle_side_by_side(ws, fits, [k for k in names if k not in settled],
                                    max_steps=max_steps, tau_int=tau_int)
    ev = {k: output_evidence(ws, f) for k, f in polished.items()}
    winner, still, record = tie_by_output(ev, decisive, tie_alpha)
    for k, f in polished.items():
        record["candidates"][k]["gap_test"] = f.gap_test
    return winner, still, record, polished


def revisit_tie(ws: Workspace, final: CandidateFit, winner: str,
                rivals: dict[str, AbstractEffect], *, max_steps: int, tau_int: float,
                decisive: float = 10.0, tie_alpha: float = 0.05,
                ) -> tuple[str, list[str], dict[str, Any], dict[str, CandidateFit]]:
    """``break_tie`` again on the final model: ``final`` carries ``winner``, and each rival
    (its fitted instance from the tied round, ``rivals``) is swapped in for it and the model
    refitted from ``final``'s values and start states. Returns ``break_tie``'s tuple."""
    fits = {winner: final}
    m = final.model
    for k, eff in rivals.items():
        if k != winner:
            swapped = Model(m.params, [eff if e.name == winner else e for e in m.effects],
                            m.starts)
            fits[k] = fit_model(ws, swapped, max_steps=max_steps, tau_int=tau_int,
                                starts=(final.starts, final.test_starts), held_out=False)
    return break_tie(ws, fits, sorted(fits), max_steps=max_steps, tau_int=tau_int,
                     decisive=decisive, tie_alpha=tie_alpha)


def representative(held_out: str, by_output: str, still: Sequence[str]) -> str:
    """The candidate a round carries after ``break_tie``: its per-output winner
    ``by_output`` when that told the others apart, else the held-out gap's pick ``held_out``
    (``select``) while it is still tied: a verdict the per-output test did not reach does not
    replace the round's own rule (carried instead, a candidate the per-output ranking
    merely preferred can leave the next rounds a worse base)."""
    return held_out if len(still) > 1 and held_out in still else by_output


def tie_by_output(ev: dict[str, dict[str, Any]], decisive: float = 10.0,
                  tie_alpha: float = 0.05) -> tuple[str, list[str], dict[str, Any]]:
    """``break_tie``'s verdict on the candidates' evidence per output (``output_evidence``
    each): (winner, still tied (sorted, winner included), record). The winner has the lowest
    sum_c n_eff,c log rss_c; a rival is told apart when its difference is at least
    ``decisive`` and the paired held-out test gives p at most ``tie_alpha``."""
    names = sorted(ev)
    C = len(ev[names[0]]["rss"])
    n_eff = [ev[names[0]]["count"] / max(ev[k]["tau"][c] for k in names) for c in range(C)]
    crit = {k: sum(n_eff[c] * math.log(max(ev[k]["rss"][c], 1e-300)) for c in range(C))
            for k in names}
    winner = min(names, key=lambda k: crit[k])
    ref = np.maximum(np.mean(np.asarray(ev[winner]["held_out_mse"]), axis=0), 1e-300)

    def seg_err(k: str) -> np.ndarray:
        return np.sqrt(np.mean(np.asarray(ev[k]["held_out_mse"]) / ref, axis=1))

    record = {}
    for k in names:
        d = crit[k] - crit[winner]
        p = paired_p_value(seg_err(k), seg_err(winner)) if k != winner else None
        record[k] = {"rss_outputs": list(ev[k]["rss"]), "tau_outputs": list(ev[k]["tau"]),
                     "dAIC_outputs": d, "paired_p": p,
                     "told_apart": bool(k != winner and d >= decisive and p <= tie_alpha)}
    still = sorted(k for k in names if not record[k]["told_apart"])
    return winner, still, {"n_eff_outputs": n_eff, "winner": winner, "candidates": record}


def select(scores: dict[str, dict[str, Any]], parsimony: float = 0.1) -> str | None:
    """The winner among significant candidates: those whose held-out gap is within
    ``parsimony`` (relative) of the best, then the fewest fitted parameters, then the lowest
    gap. (A two-parameter effect can mimic a one-parameter one, e.g. gravity with a free rest
    angle far from the motion looks like a constant torque; held-out gaps then tie.)"""
    sig = [k for k, s in scores.items() if s["significant"]]
    if not sig:
        return None
    best = min(scores[k]["gap_test"] for k in sig)
    near = [k for k in sig if scores[k]["gap_test"] <= best * (1 + parsimony)]
    return min(near, key=lambda k: (fitted_count(k), scores[k]["gap_test"]))


def tied(scores: dict[str, dict[str, Any]], winner: str | None, decisive: float = 10.0,
         tie_alpha: float = 0.05) -> list[str]:
    """The candidates the data cannot tell apart from ``winner`` (winner included, sorted):
    significant ones with as many fitted parameters that are not told apart. A rival is told
    apart only when both kinds of evidence are decisive: the training evidence (its Akaike
    difference to the winner at least ``decisive``; Burnham and Anderson: a rival more than
    10 above has essentially no support) and the held-out evidence segment by segment
    (``paired_p_value`` of the scores' ``segment_errors`` at most ``tie_alpha``; the Akaike
    count treats the samples as independent, the segments' start-state errors are not, and a
    held-out gap can come from a few segments whose start one model happens to forgive).
    Rivals that are not told apart explain the log equally well within its noise: naming one
    of them would be a guess. Empty when there is no winner."""
    if winner is None:
        return []
    w = scores[winner]

    def told_apart(k: str) -> bool:
        e_k, e_w = scores[k].get("segment_errors"), w.get("segment_errors")
        held_out = e_k is not None and e_w is not None and paired_p_value(e_k, e_w) <= tie_alpha
        return held_out and scores[k]["dAIC"] - w["dAIC"] >= decisive

    return sorted(k for k, s in scores.items() if s["significant"]
                  and fitted_count(k) == fitted_count(winner)
                  and (k == winner or not told_apart(k)))


def evidence_weights(scores: dict[str, dict[str, Any]], key: str = "dAIC") -> dict[str, float]:
    """Akaike (``key`` "dAIC") or Schwarz ("dBIC") weights of "none" (the current model,
    difference 0) and every scored candidate: exp(-d/2) normalised, the probability that each
    is the best of those considered, in the information criterion's sense."""
    d = {"none": 0.0, **{k: float(s[key]) for k, s in scores.items()}}
    lo = min(d.values())
    w = {k: math.exp(-0.5 * (v - lo)) for k, v in d.items()}
    tot = sum(w.values())
    return {k: v / tot for k, v in w.items()}
