"""The result of an identification (``IdentResult``) and how a solution becomes one
(``finish``: standard errors, identifiability, the parameter file's record).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxflex.fit import (
    Problem,
    Solution,
    covariance,
    get_value,
    segment_robust_covariance,
    set_values,
    simulated_outputs,
)
from jaxflex.identify.links import base_record
from jaxflex.io.logs import Log
from jaxflex.io.params import Params

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
    #: a coupled arm's base parameters (``jaxflex.identify.links.base_record``): name ->
    #: value, standard error (as ``stderr``) and definition; empty for decoupled links
    links: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def adequate(self) -> bool:
        """Whether the model explains the log to its noise level (``model["verdict"]``)."""
        return self.model.get("verdict") == "adequate"

    def table(self) -> str:
        """A short text table: name, value, standard error, relative standard error (or
        "unidentified": fixed at its start value, or at its fitted value and marked)."""
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
        for b, rec in self.links.get("base_parameters", {}).items():
            rows.append(f"base parameter {b} = {rec['definition']}: {rec['value']:.6g} +- "
                        f"{rec['stderr']:.3g}")
        g = self.segments
        if g.get("samples"):
            rows.append(f"segments: {g['segments']} of {g['samples']} samples "
                        f"({g['seconds']:.3g} s, {g['mode']})")
        fitted = set(self.problem.space.fitted_names()) if self.problem is not None else set()
        fixed = [k for k in self.unidentifiable if k not in fitted]
        marked = [k for k in self.unidentifiable if k in fitted]
        if fixed:
            rows.append(f"unidentified, fixed at their start values: {fixed}")
        if marked:
            rows.append(f"not determined by the data, at the values fitted: {marked} "
                        "(identification.parameters gives each one's reason)")
        return "\n".join(rows)


def relative_stderr(stderr: dict[str, Any], phys: dict[str, Any]) -> dict[str, list[float]]:
    """Relative standard errors stderr / |value| per name (lists per joint)."""
    return {k: (np.asarray(stderr[k]) / np.maximum(np.abs(phys[k]), 1e-300)).tolist()
            for k in phys}


def is_settled(sol: Any, good: float) -> bool:
    """Converged: the cost is explained by the noise and the solver met its tolerance."""
    return sol.cost <= good and sol.converged


def reason_of(sol: Any, good: float) -> str:
    """Both halves of the verdict in words: the solver's, then the model's."""
    if is_settled(sol, good):
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
    initial values, with the reason (those of ``prob``'s space that its mask holds, or names
    outside it). ``solution``: the ``jaxflex.fit.Solution`` that ended at ``y``, whose normal
    equations the covariance then reuses."""
    theta, _ = prob.split(y)
    every = prob.space.physical_values(theta)
    phys = {k: every[k] for k in prob.space.fitted_names()}
    cov = covariance(prob, y, solution=solution)
    # identifiability is judged on the information in the data (white residuals); the
    # standard errors reported and the posterior hold for correlated residuals too
    robust = (segment_robust_covariance(prob, solution)
              if solution is not None and solution.y is y else None)
    shown = cov if robust is None else robust
    se = {k: shown["stderr"][k].tolist() for k in phys}
    information = relative_stderr(cov["stderr"], phys)
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
        "free": list(phys) + list(fixed), "model": prob.kind, "cost": cost,
        "noise_cost": noise_cost, "rms_residual": rms, "jacobian_rank": cov["rank"],
        "unknowns": cov["n_free"], "steps": steps, "converged": converged,
        "reason": reason or ("cost explained by noise" if converged else "not converged"),
        "unidentifiable": bad, "parameters": marks,
    }
    out.extra["identification"]["stderr_kind"] = (
        f"segment-robust ({robust['clusters']} segments as clusters)" if robust is not None
        else "white residuals")
    out.extra["identification"]["covariance"] = posterior_record(prob, theta, shown, bad)
    links = base_record(prob.space.plant(theta).links, every, np.asarray(shown["cov_phys"]))
    if links is not None:
        out.extra["identification"]["links"] = links
    rel = relative_stderr(se, phys)
    for k in fixed:
        se[k] = [math.nan] * len(get_value(init, k))
        rel[k] = [math.inf] * len(get_value(init, k))
    res = IdentResult(
        params=out, stderr=se, rel_stderr=rel, cost=cost, rms=rms, rank=cov["rank"],
        n_free=cov["n_free"], singular_values=cov["singular_values"], unidentifiable=bad,
        warnings=msgs, steps=steps, converged=converged, wall_s=wall_s, problem=prob,
        solution=y, reason=out.extra["identification"]["reason"], noise_cost=noise_cost, why=why,
        information_rel_stderr=information, links=links or {},
    )
    return res


def posterior_record(prob: Problem, theta: dict[str, Any], cov: dict[str, Any],
                     exclude: Sequence[str] = ()) -> dict[str, Any]:
    """The identification's Gaussian posterior in the unconstrained coordinates theta
    (``jaxflex.fit.space``), for the file: ``parameters`` (names in the space's order, those
    in ``exclude`` left out: their rows are dropped, i.e. marginalised), ``labels`` (one per
    flattened entry, "name[j]"), ``theta`` (the estimate), ``matrix`` (its covariance) and
    ``friction_cap`` (the space's bound on the friction levels [N m], None: none).
    ``jaxflex.tune.robust.Posterior`` draws from it; every draw maps to physical values that keep
    the constraints (positivity, Fs >= Fc)."""
    fitted = prob.space.fitted_flat()
    # flattened entries in ravel_pytree's order (sorted names, then joints), as fitted_flat
    entries = [(k, j) for k in sorted(theta) for j in range(np.size(theta[k]))]
    flat = np.concatenate([np.ravel(np.asarray(theta[k], float)) for k in sorted(theta)])
    keep = [i for i, (k, _) in enumerate(entries) if fitted[i] and k not in exclude]
    kept = {entries[i][0] for i in keep}
    params = [k for k in prob.space.names if k in kept]
    C = np.asarray(cov["cov_theta"])[np.ix_(keep, keep)]
    cap = float(np.ravel(np.asarray(prob.space.friction_cap))[0])
    return {
        "space": "theta", "parameters": params,
        "labels": [f"{entries[i][0]}[{entries[i][1]}]" for i in keep],
        "theta": [float(flat[i]) for i in keep], "matrix": C.tolist(),
        "friction_cap": cap if math.isfinite(cap) else None,
    }
