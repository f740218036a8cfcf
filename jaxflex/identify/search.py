"""The search of an identification: every solve recorded (``Search``), the starts, the
refits without what the data cannot determine, and the best end point at the final
discretisation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx

from jaxflex.fit import (
    Problem,
    Solution,
    cost,
    covariance,
    discretisation_bias,
    get_value,
    least_squares,
    remaining_step,
    trace_solver,
)
from jaxflex.runtime.ahead import Ahead
from jaxflex.identify.problem import make_problem
from jaxflex.identify.result import IdentResult, finish, is_settled
from jaxflex.identify.start import DataStart
from jaxflex.identify.static import start_from_static_map
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.io.progress import Progress, silent

#: A model-limited solve that ends at its step cap is converged when a full Gauss-Newton step
#: would move no parameter by more than this many of its reported standard errors.
REMAINING_TOL: float = 0.1


class Search:
    """Every solve of one identification: the attempts written to the file and the end
    points of the full problem's solves, from which the best is taken at the end."""

    def __init__(self, good: float, solve: dict[str, Any], progress: Progress = silent):
        self.good, self.solve, self.progress = good, solve, progress
        self.attempts: list[dict[str, Any]] = []
        self.ends: list[tuple[int, Any]] = []  # (attempt index, y) of the full problem

    def run(self, prob: Problem, y: Any, label: dict[str, Any], max_steps: int,
            full: bool = True, scored: Problem | None = None) -> Solution:
        """One ``least_squares`` solve, recorded; a Ctrl-C inside it ends the whole
        identification (``KeyboardInterrupt``). Every record's ``cost`` is the
        identification's own cost at the solve's end: ``scored``, the problem whose cost that
        is where ``prob`` solves another objective (a warm phase's loosened continuity
        weights, recorded beside it as ``cost_loosened``)."""
        sol = least_squares(prob, y, max_steps=max_steps, **self.solve)
        if sol.interrupted:
            raise KeyboardInterrupt
        if "warm" not in label and not sol.converged and not sol.failed and (
                sol.cost > self.good and sol.normal is not None):
            # a model-limited fit creeping down a valley: converged when the step that
            # remains is small against the standard errors it reports (segment-robust)
            rem = remaining_step(prob, sol)
            if rem <= REMAINING_TOL:
                sol = dataclasses.replace(sol, converged=True, reason=(
                    f"statistical stop at the reported (segment-robust) standard errors: a "
                    f"full Gauss-Newton step would move no parameter by more than {rem:.2g} "
                    f"of them ({sol.reason})"))
        costs = ({"cost": sol.cost} if scored is None
                 else {"cost": cost(scored, sol.y), "cost_loosened": sol.cost})
        self.attempts.append({**label, **costs, "steps": sol.steps,
                              "converged": sol.converged, "reason": sol.reason})
        if full:
            self.ends.append((len(self.attempts) - 1, sol.y))
        if "start" in label:
            self.progress(len(self.attempts), None, f"{label['start']}: cost {sol.cost:.6e} "
                          f"(noise explains <= {self.good:.3e}); {sol.reason}")
        return sol


def starts_of(log: Log, init: Params, free: Sequence[str], prob: Problem, y0: Any,
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
REFIT_TOL: float = 2.0


def fix_unidentified(search: Search, res: IdentResult, prob: Problem, best: Solution,
                      init: Params, y0: Any, log: Log, free: Sequence[str], *,
                      model: str, segment_length: int | None, outputs: Any, output_scale: Any,
                      continuity_weight: float, max_steps: int, good: float, warmed: Any,
                      noise: float, rel_stderr_limit: float,
                      ) -> tuple[Problem, Solution, dict[str, str] | None, int]:
    """Fix what the data cannot determine at its start value and refit the rest, one
    parameter at a time (the least determined first: the largest relative standard error,
    then the names of a null direction, never Fs before Fc), each refit from the user's start
    and, unless that one settles, from the values fitted so far. The refits are kept when the last one's cost is
    within ``REFIT_TOL`` of the free fit's (at the fit's residual scale), and then released
    once from their point; otherwise the free fit is the answer, its poorly determined
    parameters marked at their fitted values. Returns the answer's problem, solution, the
    names fixed (with why; None: none) and the steps taken."""
    fixed_why: dict[str, str] = {}
    cur, sol_cur, total = prob, best, best.steps
    for _ in range(len(prob.space.names)):
        own = [k for k in res.unidentifiable if k in cur.space.fitted_names()
               and not res.why.get(k, "").startswith("kept at its initial value with")]
        if not own:
            break
        worst = max(own, key=lambda k: (k != "Fs" or len(own) == 1,  # fixing Fs caps Fc
                                        "null direction" not in res.why.get(k, ""),
                                        max(res.information_rel_stderr.get(k, [0.0]))))
        keep = [k for k in cur.space.fitted_names() if k != worst]
        if not keep:
            break
        fixed_why[worst] = res.why[worst]
        if worst == "Fs" and "Fc" in keep:
            # Fs's coordinate is its excess over Fc: held, it would move Fs with Fc; a space
            # without Fs fits Fc as a share of the fixed Fs
            sub, _ = make_problem(log, init, keep, model=model, segment_length=segment_length,
                                  substeps=prob.substeps, outputs=outputs,
                                  output_scale=output_scale,
                                  continuity_weight=continuity_weight)
        else:  # the same space, masked at the start: its compiled programs serve the refit
            sub = eqx.tree_at(lambda q: q.space, cur,
                              cur.space.with_mask(keep, cur.space.theta0()))

        def kept(space: Any, y: Any) -> Any:
            """``y`` in the refit's coordinates: the physical values of the names kept (an
            ordered Fs is built on Fc, so with Fc fixed the same coordinate is another Fs)."""
            phys = space.physical_values(y[0])
            return sub.space.theta_of({k: phys[k] for k in keep}), y[1]

        # the user's start first: every parameter at its start value, the fixed one
        # included; the values fitted so far come with the fixed one moved back to its start
        sol = None
        for label, start_of in (("user", lambda: warmed(sub, kept(prob.space, y0))),
                                ("fitted", lambda: kept(cur.space, sol_cur.y))):
            s_ = search.run(sub, start_of(), {"refit_without": list(fixed_why),
                                              "start": label}, max_steps, full=False)
            total += s_.steps
            if sol is None or s_.cost < sol.cost:
                sol = s_
            if is_settled(sol, good):
                break
        res = finish(sub, init, sol.y, steps=total, converged=sol.converged, wall_s=0.0,
                     rel_stderr_limit=rel_stderr_limit, noise_cost=good, log=log,
                     unidentified=dict(fixed_why), solution=sol)
        cur, sol_cur = sub, sol
    if not fixed_why:
        return prob, best, None, total
    scale = max(1.0, best.cost / noise)
    if sol_cur.cost > best.cost + REFIT_TOL * scale:
        # fixing them costs what the data can see: they are determined, if poorly; the free
        # fit is the answer, with them marked (``finish``'s ``poorly``)
        search.attempts.append({"refits_rejected": list(fixed_why),
                                "cost_increase": sol_cur.cost - best.cost,
                                "tolerance": REFIT_TOL * scale})
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


def best_at_final(search: Search, prob: Problem, r_prob: Problem, r_sol: Solution,
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
    discretisation check), made in a background thread (``jaxflex.runtime.ahead``) while
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
