"""The discovery workflow: ``discover`` for one joint (rounds of screen, fit, contest and
tie, each added effect's family grown to the order the log asks for, until nothing is
significant, then the gap floor and the answer) and ``discover_joints`` for each joint of an
n-joint log.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from jaxflex.discover.candidates import (
    CandidateFit,
    Model,
    Workspace,
    Workspaces,
    fitted_names,
)
from jaxflex.discover.config import (
    DiscoverConfig,
    STABLE_MODE_STEP,
    SolverFailure,
    cannot_act,
    declared_axes,
    nominal_for_model,
    spring_mode,
)
from jaxflex.discover.fitting import (
    fit_model,
    gap_floor,
    made_ahead,
    residual_analysis,
    settle,
    trace_fit,
    without_effect,
)
from jaxflex.discover.localisation import localise, start_effect
from jaxflex.discover.orders import grow, grow_tie
from jaxflex.discover.ranking import (
    autocorrelation_time,
    break_tie,
    contest,
    evidence_weights,
    representative,
    revisit_tie,
    select,
    settle_side_by_side,
    tied,
)
from jaxflex.discover.result import (
    DiscoverResult,
    explained_fraction,
    final_answer,
    unexplained_limit,
)
from jaxflex.discover.screening import (
    candidate_error,
    candidate_score,
    fit_candidate,
    fit_record,
    screen,
    screened_out,
    shortlist,
    training_evidence,
    unresolved,
)
from jaxflex.core.effects import (
    AbstractEffect,
    EFFECTS,
    acts_on_replay,
    candidate_effects,
)
from jaxflex.runtime.ahead import Ahead, all_side_by_side, side_by_side
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.io.presets import paper_params
from jaxflex.io.progress import Progress, silent
from jaxflex.core.validation import requires_float64


#: Rounds ``discover`` repeats on a better base after a winner turned out not to be needed
#: (``without_effect``); each repeat screens every candidate again.
MAX_REBASE = 1


@requires_float64
def discover_joints(
    log: Log, nominal: Params | None = None, config: DiscoverConfig | None = None,
    progress: Progress | None = None, axes: Sequence[str] | None = None,
) -> list[DiscoverResult]:
    """``discover`` on each joint of an n-joint log, with that joint's parameters (a
    parameter file describes independent joints, ``Params.joint``): one answer per joint. A
    coupling between joints that the file does not describe shows up in the joints it
    couples, as an effect or as ``unexplained``. ``axes``: what gravity can do on each of
    the log's joints (``declared_axes``' words, one per joint), where ``nominal`` declares
    nothing (a shipped data set's kinematics). ``progress``: as ``discover``'s, and each
    joint's start as joint j of n."""
    nominal = nominal or paper_params()
    if nominal.n not in (1, log.n):
        raise ValueError(f"discover: the parameters have {nominal.n} joints, the log {log.n}")
    if axes is not None and len(axes) != log.n:
        raise ValueError(f"discover: {len(axes)} axis kinds for a {log.n}-joint log")
    out = []
    for j in range(log.n):
        (progress or silent)(j, log.n, f"joint {j}")
        one = nominal.joint(j if nominal.n > 1 else 0)
        declared = declared_axes(nominal)
        if declared:  # the declaration of this joint (``joint`` drops the extra keys)
            one.extra = {"axis": declared[j if nominal.n > 1 else 0]}
        elif axes is not None:
            one.extra = {"axis": axes[j]}
        out.append(discover(log.joint(j), one, config, progress))
    return out


@requires_float64
def discover(
    log: Log, nominal: Params | None = None, config: DiscoverConfig | None = None,
    progress: Progress | None = None,
) -> DiscoverResult:
    """Run the workflow of the module docstring on a one-joint log (columns t, tau, q1, q2).
    ``progress`` (``jaxflex.io.progress.Progress``) gets each line of the run's account (no
    total); None: silent.

    Raises ``ValueError`` for a multi-joint log or parameters, a log without q2, an unknown
    candidate or one that does not change the replayed outputs (``acts_on_replay``: an
    effect with no hook there), or a log too short for two segments in each part."""
    cfg = config or DiscoverConfig()
    nominal = nominal or paper_params()
    if nominal.n != 1 or log.n != 1:
        raise ValueError(f"discover handles one joint; the parameters have {nominal.n}, the "
                         f"log {log.n} (use discover_joints for an n-joint log)")
    if log.tau is None or log.q1 is None:
        raise ValueError("discover: the log needs columns tau, q1 and q2")
    say = lambda s: (progress or silent)(0, None, s)
    excluded = cannot_act(nominal)
    h = log.dt / cfg.substeps
    nominal, log, model_note = nominal_for_model(nominal, cfg.model, log, h)
    if model_note:
        say(model_note)
    if log.q2 is None:
        raise ValueError("discover: the log needs columns tau, q1 and q2 (a one-encoder log: "
                         "model 'rigid')")
    omega = spring_mode(nominal)
    if not omega * h < STABLE_MODE_STEP:
        raise ValueError(
            f"discover: the nominal model's spring mode, {omega:.4g} rad/s (K "
            f"{float(np.ravel(nominal.plant['K'])[0]):.4g}, I "
            f"{float(np.ravel(nominal.plant['I'])[0]):.4g}, J "
            f"{float(np.ravel(nominal.plant['J'])[0]):.4g}), is too fast for the replay's step "
            f"of {h:.3g} s (omega h = {omega * h:.3g}, RK4 needs < {STABLE_MODE_STEP:.2f}): a "
            "rigid model's stiff spring? Run it as model 'rigid' (--model rigid), or use "
            f"{math.ceil(omega * log.dt / STABLE_MODE_STEP)} or more substeps")
    cands = list(cfg.candidates or [c for c in candidate_effects() if c not in excluded])
    for c in cands:
        if c in excluded:
            raise ValueError(f"candidate effect {c!r}: {excluded[c]} (remove it from the "
                             "candidates, or the declaration from the file)")
    if excluded and not cfg.candidates:
        say(f"not tried: {', '.join(excluded)} ({next(iter(excluded.values()))})")
    for c in cands:
        if c not in EFFECTS:
            raise ValueError(f"unknown candidate effect {c!r}; known: {sorted(EFFECTS)}")
        if not acts_on_replay(c):
            # its parameters would have no derivative: screened as "nothing found", silently
            raise ValueError(
                f"candidate effect {c!r} ({EFFECTS[c].where}) does not change the motion that "
                "discover replays nor its reading: it has none of the hooks "
                "jaxflex.core.effects.REPLAY_HOOKS")
    if not cfg.max_order >= 1:
        raise ValueError(f"discover: max_order must be at least 1, got {cfg.max_order}")
    run = _Run(model_note=model_note)
    try:
        return _discover_run(log, nominal, cfg, cands, say, run)
    except (np.linalg.LinAlgError, FloatingPointError) as e:
        raise SolverFailure(run.stage, e) from e
    finally:
        for ahead in run.aheads:  # no thread is left running, a failed run's included
            ahead.join()


@dataclasses.dataclass
class _Run:
    """Where a ``discover`` run is: the fit under way (for ``SolverFailure``), its
    background work (``made_ahead``, one per workspace), and how its nominal model was read
    (``nominal_for_model``'s note)."""

    stage: str = "the nominal model's refit"
    aheads: list[Ahead] = dataclasses.field(default_factory=list)
    model_note: str = ""
    #: the file's effects kept in the base model, each with the reason
    kept: dict[str, str] = dataclasses.field(default_factory=dict)


def _discover_run(log: Log, nominal: Params, cfg: DiscoverConfig, cands: list[str],
                  say: Callable[[str], None], run: _Run) -> DiscoverResult:
    """``discover``'s workflow after its input checks; ``run`` says where it is."""
    t_start = time.perf_counter()
    nominal = Params.from_dict(nominal.to_dict())
    on_file = nominal.to_plant().effects
    if on_file:  # e.g. an identified torque offset: discovery starts from the bare
        # model, and such an effect is one of its candidates
        say(f"note: the file's effects ({', '.join(nominal.effects)}) are set aside: "
            "discover starts from the model without them and tries them as candidates")
    nominal.effects = {}

    def prepare(ws: Workspace) -> None:
        # the solver traced first, then the held-out programs made in the background
        # (``made_ahead``) while this thread fits
        trace_fit(ws, Model(nominal, []))
        run.aheads.append(made_ahead(ws, nominal))

    def workspaces(kept: Sequence[AbstractEffect]) -> Workspaces:
        # the candidates' workspace (and the effects kept in the base); a family's order
        # k + 1 is in a workspace built once its order k is in the model (``grow``)
        return Workspaces(log, nominal, [*cands, *(e.name for e in kept)], prepare=prepare,
                          segment=cfg.segment, train_frac=cfg.train_frac,
                          substeps=cfg.substeps, max_effects=cfg.max_effects + len(kept))

    wss = workspaces([])
    ws = wss.holding()
    try:
        current = base_fit(ws, Model(nominal, []), cfg, log)
    except (FloatingPointError, ValueError) as e:
        if not on_file:
            raise
        # the file's effects carry what the bare model cannot (a rotor's friction on an
        # axis whose link friction the file leaves at zero): they stay in the base, fitted
        # with it, and their families are not candidates
        why = f"the model without the file's effects cannot be refit on this log ({e})"
        run.kept = {k.name: why for k in on_file}
        say(f"{why}: discover starts from the file's model with them "
            f"({', '.join(run.kept)}), which are not candidates")
        wss = workspaces(on_file)
        ws = wss.holding(run.kept)
        current = base_fit(ws, Model(nominal, list(on_file)), cfg, log)
    say(f"nominal refit: gap train {current.gap_train:.4f} held-out {current.gap_test:.4f}")
    first_fit = current
    loc = localise(log, current.model.params)
    loc_current = loc  # localisation of the current model (recomputed when an effect is added)
    added: list[str] = []
    rounds = []
    rebased = 0  # rounds repeated on a base that a dropped winner improved
    open_ties: list[tuple[int, dict[str, Any], dict[str, AbstractEffect]]] = []
    S, L = ws.train.segs.count, ws.train.segs.length
    while len(added) < cfg.max_effects:
        run.stage = f"round {len(rounds) + 1}: the candidates' screens and fits"
        ws = wss.holding(current.model.active)
        tau_int = autocorrelation_time(ws, current)
        n_eff = current.n_res / tau_int
        series = loc_current.series
        scores, fits, failed, screens = {}, {}, {}, {}
        families = {EFFECTS[a].family_name() for a in [*run.kept, *added]}
        remaining = [name for name in cands if EFFECTS[name].family_name() not in families]
        starts = dict(zip(remaining, all_side_by_side(
            lambda name: start_effect(name, current.model, series, ws.step), remaining)))
        models = {name: Model(current.model.params, list(current.model.effects) + [starts[name]])
                  for name in remaining}
        to_fit = remaining
        if cfg.screen_steps > 0:
            # every candidate is screened (a few training steps and the Gauss-Newton
            # decrement, ``screen``); only the shortlist is fitted fully (held-out starts,
            # gap, two first guesses): the full fits were nine tenths of a run's time
            # (the candidates side by side on the cores: ``side_by_side``)
            reached = {}
            looks = side_by_side(lambda name: screen(
                ws, current, models[name], name, steps=cfg.screen_steps, tau_int=tau_int,
                n_eff=n_eff), remaining)
            for name, (look, error) in zip(remaining, looks):
                if error is not None:
                    screens[name] = {"error": str(candidate_error(error))}
                else:
                    screens[name], reached[name] = look
            # a screen whose few steps did not reach the region where its prediction holds
            # (a lag or backlash started at the typical size) looks again, on from where it
            # got, to 4x the steps in all
            again_names = unresolved(screens, current.rss, alpha=cfg.alpha)
            agains = side_by_side(lambda name: screen(
                ws, current, models[name], name, steps=3 * cfg.screen_steps, tau_int=tau_int,
                n_eff=n_eff, start=reached[name]), again_names)
            for name, (look, error) in zip(again_names, agains):
                if error is not None:
                    candidate_error(error)
                    continue
                again = look[0]
                if "predicted_dAIC" in again:
                    for k in ("steps", "seconds"):  # in all, along one path
                        again[k] += screens[name][k]
                    screens[name] = again | {"first": screens[name]}
            to_fit = shortlist(screens, current.rss, alpha=cfg.alpha, keep=cfg.screen_keep,
                               decisive=cfg.decisive, least=cfg.screen_least)
            for name in remaining:
                if name not in to_fit and "screen_dAIC" in screens[name]:
                    scores[name] = screened_out(screens[name])
                    say(f"  {name:20s} screened out: predicted dAIC "
                        f"{screens[name]['predicted_dAIC']:+.1f} p "
                        f"{screens[name]['predicted_p_value']:.2e} "
                        f"({screens[name]['seconds']:.1f} s)")
                elif name not in to_fit:
                    failed[name] = f"screen failed: {screens[name].get('error', 'non-finite')}"
        fulls = all_side_by_side(lambda name: fit_candidate(ws, current, models[name], cfg,
                                                            tau_int, n_eff), to_fit)
        for name, (f, s, why) in zip(to_fit, fulls):
            if f is None:
                failed[name] = why
                say(f"  {name}: fit failed ({why})")
                continue
            s = fit_record(ws, s, f, screens.get(name))
            scores[name], fits[name] = s, f
            say(f"  {name:20s} gap {f.gap_test:.4f} gain {s['gain']:+.3f} p {s['p_value']:.2e} "
                f"dBIC {s['dBIC']:+.1f} {'*' if s['significant'] else ''} ({f.seconds:.1f} s)")
        if not scores and failed:
            raise SolverFailure(f"round {len(rounds) + 1}: every candidate's fit", str(failed))
        run.stage = f"round {len(rounds) + 1}: the polish of the close candidates"
        winner = select(scores, cfg.parsimony)
        close = contest(scores, winner, cfg.contest)
        polished_fits = settle_side_by_side(ws, fits, close, max_steps=cfg.max_steps * 2,
                                            tau_int=tau_int)
        for k, f in polished_fits.items():
            was = scores[k]
            s = fit_record(ws, candidate_score(current, f, n_eff, cfg), f, was.get("screen"))
            s["seconds"] += was["seconds"]
            s["steps"] += was["steps"]
            s["polished"] = {key: was[key] for key in ("gap_test", "p_value", "dBIC")}
            scores[k], fits[k] = s, f
        if close:
            winner = select(scores, cfg.parsimony)
            gaps = ", ".join(f"{k} {scores[k]['gap_test']:.4f}" for k in close)
            say(f"  close, polished: {gaps}; picked {winner or 'none'}")
        rounds.append({"base_gap_test": current.gap_test, "tau_int": tau_int, "n_eff": n_eff,
                       "contest": close,
                       "scores": scores, "failed": failed, "winner": winner or "none",
                       "screened_out": sorted(k for k, v in scores.items()
                                              if v.get("screened_out")),
                       "tied": tied(scores, winner, cfg.decisive, cfg.tie_alpha),
                       "fitted": {k: {p.split(".", 1)[1]: {"value": f.values[p],
                                                           "stderr": f.stderr[p]}
                                      for p in fitted_names(k)} for k, f in fits.items()},
                       "evidence_aic": evidence_weights(scores, "dAIC"),
                       "evidence_bic": evidence_weights(scores, "dBIC")})
        if winner is None:
            break
        if len(rounds[-1]["tied"]) > 1:
            # the pooled evidence could not tell them apart: each encoder at its own noise
            run.stage = f"round {len(rounds)}: the tie-break of {rounds[-1]['tied']}"
            best, rounds[-1]["tied"], rounds[-1]["tie_break"], polished_tied = break_tie(
                ws, fits, rounds[-1]["tied"], max_steps=cfg.max_steps * 2, tau_int=tau_int,
                decisive=cfg.decisive, tie_alpha=cfg.tie_alpha, settled=polished_fits)
            polished_fits |= polished_tied
            winner = representative(winner, best, rounds[-1]["tied"])
            rounds[-1]["winner"] = winner
            say(f"tie judged output by output: {winner}, still tied {rounds[-1]['tied']}")
        # polish the winner so that the next round's candidates are compared with a converged
        # base, not with one that merely had fewer iterations; an effect that does not lower
        # the held-out gap after this refit is dropped
        # (standard errors inflated by the same residual autocorrelation time as the round's)
        run.stage = f"round {len(rounds)}: the polish of {winner}"
        polished = (polished_fits[winner] if winner in polished_fits else
                    settle(ws, fits[winner], max_steps=cfg.max_steps * 2, tau_int=tau_int))
        if not polished.gap_test < current.gap_test:
            rounds[-1]["winner"] = "none"
            rounds[-1]["dropped"] = {winner: f"held-out gap {polished.gap_test:.4g} after the "
                                             f"refit, not below {current.gap_test:.4g}"}
            say(f"dropped {winner}: the refit did not lower the held-out gap")
            break
        # the effect must still be significant at the polished optimum, against the base
        # refitted from there without it: a candidate's fit can carry the shared parameters
        # out of a local minimum of the base and then let the effect go (its polished
        # magnitude within a standard error of zero)
        run.stage = f"round {len(rounds)}: the refit of the base without {winner}"
        reduced = without_effect(ws, polished, winner, max_steps=cfg.max_steps,
                                 tau_int=tau_int)
        k = polished.n_par - reduced.n_par
        check = training_evidence(reduced.rss, polished.rss, k, polished.n_par,
                                  polished.n_res, n_eff)
        rounds[-1]["still_needed"] = check
        if not (check["p_value"] < cfg.alpha and check["dBIC"] < 0):
            reduced = settle(ws, reduced, max_steps=cfg.max_steps * 2, tau_int=tau_int)
            rounds[-1]["winner"] = "none"
            rounds[-1]["dropped"] = {
                winner: f"not needed at its polished optimum: the base refitted from there "
                        f"without it explains the training segments as well (F "
                        f"{check['F']:.3g}, p {check['p_value']:.3g}, dBIC "
                        f"{check['dBIC']:+.1f}; held-out gap {reduced.gap_test:.4g} without "
                        f"it, {polished.gap_test:.4g} with it)"}
            say(f"dropped {winner}: not needed once the base is refitted from its optimum "
                f"(held-out gap {reduced.gap_test:.4f})")
            if not reduced.rss < current.rss:
                break
            current = reduced  # the better base is kept, repeated round or not
            loc_current = localise(log, current.model.params)
            if rebased >= MAX_REBASE:
                break
            say("the round is repeated on that base")
            rebased += 1
            continue
        grown = winner
        if cfg.max_order > 1:
            # the order of the winner's family (and of each tied member's) that the log asks
            # for: a higher order is kept when it pays as an effect does (``grow``)
            run.stage = f"round {len(rounds)}: the orders of {winner}'s family"
            tie = rounds[-1]["tied"]
            # a rival of the contest whose family has a higher order may overtake the pick at
            # that order (a second-order lag against a delay): judged as a tie is
            rivals = [k for k in close if k != winner and EFFECTS[k].higher is not None]
            if len(tie) > 1 or rivals:
                names_in = list(tie) if len(tie) > 1 else [winner, *rivals]
                members = {k: polished if k == winner else polished_fits.get(k, fits[k])
                           for k in names_in}
                pick, told, grown_fits, names, record = grow_tie(
                    log, wss, members, names_in, winner, cfg, say)
                if len(tie) > 1:
                    rounds[-1]["tie_orders"] = record
                else:
                    rounds[-1]["contest_orders"] = record
                    rounds[-1]["orders"] = record["members"][pick]["orders"]
                if told:
                    rounds[-1]["tied"] = [pick]
                    say(f"{'tie' if len(tie) > 1 else 'contest'} told apart by the order: "
                        f"{EFFECTS[names[pick]].label()}")
                winner, polished, grown = pick, grown_fits[pick], names[pick]
                rounds[-1]["winner"] = winner
            else:
                polished, grown, rounds[-1]["orders"] = grow(log, wss, polished, winner, cfg,
                                                             say)
        rounds[-1]["added"] = grown
        added.append(grown)
        if len(rounds[-1]["tied"]) > 1 and grown == winner:
            # the fitted rivals, to judge the tie again once later effects are in
            open_ties.append((len(added) - 1, rounds[-1],
                              {k: fits[k].model.effects[-1] for k in rounds[-1]["tied"]}))
        current = polished
        loc_current = localise(log, current.model.params)
        say(f"added {EFFECTS[grown].label()}: held-out gap {current.gap_test:.4f}")
    run.stage = "the second look at a tie on the final model"
    ws = wss.holding(current.model.active)
    for at, rnd, rivals in open_ties:
        if at == len(added) - 1:
            continue  # judged on the final base already
        # a tie judged on a base that still missed a later effect, whose residual both rivals
        # absorbed alike (a delay and a lag in front of a motor cogging, 0.6 apart): judged
        # again with every other effect in
        was = rnd["winner"]
        best, rnd["tied"], rnd["tie_revisited"], polished = revisit_tie(
            ws, current, was, rivals, max_steps=cfg.max_steps * 2, tau_int=tau_int,
            decisive=cfg.decisive, tie_alpha=cfg.tie_alpha)
        now = representative(was, best, rnd["tied"])
        rnd["winner"] = now
        added[at] = rnd["added"] = now
        current = polished[now]
        loc_current = localise(log, current.model.params)
        say(f"tie of {sorted(rivals)} judged again with {added}: {now}, still tied {rnd['tied']}")
    for ahead in run.aheads:  # long done: no thread is left running when discover returns
        ahead.join()
    run.stage = "the gap floor's bootstrap (replays of the final model)"
    fl = gap_floor(log, ws, current)
    # "unexplained": the final gap stays significantly above what noise, start errors and
    # integration cost a correct model on this log, and no candidate closed it
    limit = unexplained_limit(fl, cfg.unexplained_factor)
    unexplained = bool(current.gap_test > limit)
    explained = explained_fraction(first_fit.gap_test, current.gap_test, fl["floor"])
    # the round that added the first effect (a round whose winner was dropped comes before it)
    first_tied = next(r["tied"] for r in rounds if r.get("added") == added[0]) if added else []
    answer = final_answer(added, first_tied, unexplained, explained, cfg.explained_min)
    # the answer names the family; its order is the result's ``order``
    order = EFFECTS[answer].order if answer in EFFECTS else 0
    answer = EFFECTS[answer].family_name() if answer in EFFECTS else answer
    run.stage = "the residual analysis of the final model"
    try:
        resid = residual_analysis(ws, current)
    except ValueError as e:  # a residual the statistics refuse is reported, not raised
        resid = {"error": str(e)}
    return DiscoverResult(
        effect=answer, order=order, effects=added, gap_before=first_fit.gap_test,
        gap_after=current.gap_test, gap_floor=fl["floor"], floor=fl,
        unexplained=unexplained, before=first_fit, after=current,
        rounds=rounds, localisation=loc,
        localisation_after=loc_current,
        config=cfg, candidates=cands,
        log_info={"samples": log.N, "dt": log.dt, "train_samples": int(cfg.train_frac * log.N),
                  "segment_samples": L, "train_segments": S,
                  "test_segments": ws.test.segs.count, "model": cfg.model,
                  "model_note": run.model_note},
        seconds=time.perf_counter() - t_start, workspace=ws, tied=list(first_tied),
        explained=explained, residuals=resid,
        not_tried={k: v for k, v in cannot_act(nominal).items() if k not in cands},
        kept=dict(run.kept),
    )


def base_fit(ws: Workspace, model: Model, cfg: DiscoverConfig, log: Log) -> CandidateFit:
    """The base every first-round candidate is compared with: ``model`` refitted on the
    training segments and settled, its held-out gap taken.

    **Raises:** ``FloatingPointError`` where the fit runs a parameter away
    (``check_bounded``); ``ValueError`` where its replay is not finite or replays the
    held-out segments worse than predicting no motion (it does not describe the log)."""
    current = fit_model(ws, model, max_steps=cfg.max_steps * 2, held_out=False)
    # the base every candidate is compared with must not keep a load that the first solve's
    # long early steps pushed past the capacity (``settle``). Its stops stay in the units of
    # white residuals: in the rounds' units (inflated by the first solve's autocorrelation
    # time) it stops earlier and can leave a worse base
    current = settle(ws, current, max_steps=cfg.max_steps * 2)
    if not (math.isfinite(current.gap_test) and math.isfinite(current.rss)):
        raise ValueError(
            "discover: the nominal model's replay of this log is not finite (held-out gap "
            f"{current.gap_test}); check the units of the log and of the nominal parameters "
            f"(sample period {log.dt:g} s, segments of {cfg.segment:g} s)"
        )
    if current.gap_test > 1.0:
        raise ValueError(
            f"discover: the refitted nominal model replays the held-out segments worse than "
            f"predicting no motion (held-out gap {current.gap_test:.3g} > 1): it does not "
            "describe this log; identify it first (jaxflex identify) and pass it with --params"
        )
    return current
