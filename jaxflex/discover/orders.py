"""The order of an added effect's family (``grow``): once a round adds an effect whose class
names a ``higher`` order, that order is fitted in its place, started from the fit
(``AbstractEffect.from_lower``), and kept when it pays by the criterion that adds an effect
(``candidate_score``: F-test, BIC, held-out gain; then polished, the held-out gap lower);
then the next order, while each pays. A round whose candidates are tied grows each tied
family the same way, and a grown member that pays over every other tied member's fit is told
apart from them (``grow_tie``); so does a round whose contest holds a rival with a higher
order (the winner and those rivals as the members: a rival can win at its order 2).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from jaxflex.discover.candidates import CandidateFit, Model, Workspaces
from jaxflex.discover.config import DiscoverConfig
from jaxflex.discover.fitting import settle
from jaxflex.discover.localisation import residual_start
from jaxflex.discover.ranking import autocorrelation_time
from jaxflex.discover.screening import candidate_score, fit_candidate
from jaxflex.core.effects import EFFECTS
from jaxflex.io.logs import Log


def swapped(model: Model, name: str, effect: Any) -> Model:
    """``model`` with its effect ``name`` replaced by ``effect`` (in the same place)."""
    return Model(model.params, [effect if e.name == name else e for e in model.effects],
                 model.starts)


def grow(log: Log, wss: Workspaces, fit: CandidateFit, name: str, cfg: DiscoverConfig,
         say: Callable[[str], None] = lambda s: None,
         ) -> tuple[CandidateFit, str, list[dict[str, Any]]]:
    """The order of effect ``name``'s family that ``log`` asks for, from ``fit`` (a polished
    model holding ``name``): order k + 1 (``EFFECTS[name].higher``) started from the fitted
    order k (``from_lower``, its new parameters from the residual of ``fit``'s model on
    ``log``), fitted with every shared parameter (``fit_candidate``, the residual
    autocorrelation time of ``fit``) in a workspace that holds both orders
    (``Workspaces.holding``: built when first needed) and scored against ``fit`` as a candidate is against its
    base (``candidate_score``); when significant it is polished (``settle``) and kept if it
    is still significant and its held-out gap is lower; then the order above, up to
    ``cfg.max_order``.

    **Arguments:**

    - `log`: the one-joint log of the run.
    - `wss`: the run's workspaces.
    - `fit`: the polished fit holding the effect ``name``.
    - `name`: the registered name of the effect whose family grows.
    - `cfg`: the run's settings (``alpha``, ``min_gain``, ``max_steps``, ``max_order``).
    - `say`: progress lines.

    **Returns:**

    (the fit of the order kept, its registered name, one record per order tried: ``name``,
    ``order``, ``significant``, ``kept``, the score (``F``, ``p_value``, ``dAIC``, ``dBIC``,
    ``gain``, ``gap_test``) and the fitted values, or ``failed`` with the reason)."""
    records: list[dict[str, Any]] = []
    while (higher := EFFECTS[name].higher) is not None and EFFECTS[higher].order <= cfg.max_order:
        ws = wss.holding([*fit.model.active, higher])
        tau_int = autocorrelation_time(ws, fit)
        n_eff = fit.n_res / tau_int
        lower = next(e for e in fit.model.effects if e.name == name)
        start = EFFECTS[higher].from_lower(lower, residual_start(log, fit.model, ws.step))
        f, s, why = fit_candidate(ws, fit, swapped(fit.model, name, start), cfg, tau_int, n_eff)
        rec: dict[str, Any] = {"name": higher, "order": EFFECTS[higher].order}
        records.append(rec)
        if f is None or s is None:
            rec |= {"failed": why, "significant": False, "kept": False}
            say(f"  {EFFECTS[higher].label()}: fit failed ({why})")
            break
        rec |= _record(s, f, higher)
        if not s["significant"]:
            say(f"  {EFFECTS[higher].label()} does not pay: gain {s['gain']:+.3f} p "
                f"{s['p_value']:.2e} dBIC {s['dBIC']:+.1f}")
            break
        polished = settle(ws, f, max_steps=cfg.max_steps * 2, tau_int=tau_int)
        s = candidate_score(fit, polished, n_eff, cfg)
        rec["polished"] = _record(s, polished, higher)
        if not (s["significant"] and polished.gap_test < fit.gap_test):
            say(f"  {EFFECTS[higher].label()} does not pay once polished: gap "
                f"{polished.gap_test:.4f} against {fit.gap_test:.4f}")
            break
        rec["kept"] = True
        say(f"  {EFFECTS[higher].label()} pays: held-out gap {fit.gap_test:.4f} -> "
            f"{polished.gap_test:.4f} (p {s['p_value']:.2e} dBIC {s['dBIC']:+.1f})")
        fit, name = polished, higher
    return fit, name, records


def _record(s: dict[str, Any], f: CandidateFit, name: str) -> dict[str, Any]:
    """A grown order's record: its score against the order below and its fitted values."""
    keys = ("F", "p_value", "dAIC", "dBIC", "gain", "gap_test", "significant")
    return {**{k: s[k] for k in keys}, "kept": False,
            "values": {k.split(".", 1)[1]: v for k, v in f.values.items()
                       if k.startswith(name + ".")}}


def grow_tie(log: Log, wss: Workspaces, fits: dict[str, CandidateFit], tied: Sequence[str],
             winner: str, cfg: DiscoverConfig, say: Callable[[str], None] = lambda s: None,
             ) -> tuple[str, bool, dict[str, CandidateFit], dict[str, str], dict[str, Any]]:
    """A tie of equally sized candidates ``tied`` (polished fits ``fits``, ``winner`` the
    round's pick) judged with their families' orders: each member is grown (``grow``), and a
    member grown above order 1 that pays over every other member's grown fit by the criterion
    that adds an effect (``candidate_score`` against it as the base) is told apart from them.
    Returns (the member the round carries: the one told apart, else ``winner``; whether it
    was told apart; the members' grown fits; their grown names; the record: per member its
    orders and, for each grown member, its score against each other member)."""
    grown, names, record = {}, {}, {"members": {}, "against": {}}
    for k in tied:
        grown[k], names[k], recs = grow(log, wss, fits[k], k, cfg, say)
        record["members"][k] = {"grown": names[k], "order": EFFECTS[names[k]].order,
                                "orders": recs}
    best = None
    for k in tied:
        if EFFECTS[names[k]].order == 1:
            continue
        scores = {}
        for o in tied:
            if o == k or not grown[k].n_par > grown[o].n_par:
                continue  # the criterion compares a model with one of fewer parameters
            tau_int = autocorrelation_time(wss.holding(grown[o].model.active), grown[o])
            scores[o] = _record(candidate_score(grown[o], grown[k], grown[o].n_res / tau_int,
                                                cfg), grown[k], names[k])
        record["against"][k] = scores
        if (len(scores) == len(tied) - 1 and all(v["significant"] for v in scores.values())
                and best is None):
            best = k
    return (best or winner), best is not None, grown, names, record
