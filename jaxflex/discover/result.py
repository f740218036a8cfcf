"""The outcome of a discovery run (``DiscoverResult``) and how the answer is drawn from its
rounds (``final_answer``, ``effect_ties``, ``unexplained_limit``, ``explained_fraction``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxflex.discover.candidates import CandidateFit, Workspace
from jaxflex.discover.config import DiscoverConfig
from jaxflex.discover.fitting import held_out_traces
from jaxflex.discover.localisation import Localisation
from jaxflex.core.effects import EFFECTS
from jaxflex.io.params import Params


@dataclasses.dataclass
class DiscoverResult:
    """Outcome of ``discover``.

    effect: the family of the first effect added (its order in ``order``; a family of one
    is the effect's own name), "indistinguishable" (an effect is missing, but the first
    round's best candidates explain the log equally well within its noise, ``tied``, so
    naming one would be a guess), "none" (the final gap is at the floor) or "unexplained"
    (the gap stays significantly above the floor and no candidate closes it: none was added,
    or those added close less than ``explained_min`` of the gap's excess over the floor,
    ``explained``, and are listed in ``effects`` as a partial explanation only; something is
    missing that the library does not describe; the localisation says where to look);
    tied: the first round's candidates that the data cannot tell apart (``tied``; one name,
    the effect, when the answer is decided; empty when none was added); the ties of every
    round are in ``effects_tied`` and in the one-line ``answer``;
    order: the order of the answer's family that the log asked for (``jaxflex.discover.orders``:
    e.g. 2 for a cogging with its 2nd harmonic; 1 for a family's simplest member and for a
    family of one; 0 when no effect is the answer);
    effects: all added, in order, by their registered names (a family's order above 1 by its
    own name, e.g. ``cogging_2``; ``families`` and ``orders`` name each as a family and an
    order) (in a tie the model carries one representative so that
    later rounds have a base: the held-out gap's pick while it stays tied, ``representative``;
    a tie is judged again on the final model, ``revisit_tie``, and the representative may
    change); gap_before,
    gap_after, gap_floor: held-out gaps of the refit nominal and the final model, and the gap
    a correct model reaches on this log (``gap_floor``'s bootstrap; ``floor`` holds its
    details); unexplained: the final gap is above ``unexplained_factor`` x floor + 3
    floor_sd, whether or not effects were added; explained: the share of the nominal
    refit's excess gap over the floor that the final model closes (``explained_fraction``);
    before, after: the two fits; rounds: per
    round the base gap,
    the residual autocorrelation time, the effective count, every candidate's score and the
    winner; localisation: of the refit nominal model (and of the final one); config; log_info;
    seconds; workspace: the problems (for replays in plots); residuals: the final model's
    residual analysis on the held-out segments (``residual_analysis``: MATLAB's ``resid``);
    not_tried: the candidates left out because the file's declared axis says they cannot act
    (``cannot_act``), each with the reason; kept: the file's effects kept in the base model
    (fitted with it, their families not candidates) because the model without them could
    not be refit on the log, each with the reason (empty: the file's effects were set aside
    and tried as candidates).
    """

    effect: str
    effects: list[str]
    gap_before: float
    gap_after: float
    gap_floor: float
    floor: dict[str, Any]
    unexplained: bool
    before: CandidateFit
    after: CandidateFit
    rounds: list[dict[str, Any]]
    localisation: Localisation
    localisation_after: Localisation
    config: DiscoverConfig
    candidates: list[str]
    log_info: dict[str, Any]
    seconds: float
    workspace: Workspace
    tied: list[str] = dataclasses.field(default_factory=list)
    explained: float = 0.0
    residuals: dict[str, Any] = dataclasses.field(default_factory=dict)
    not_tried: dict[str, str] = dataclasses.field(default_factory=dict)
    order: int = 0
    kept: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def families(self) -> list[str]:
        """The family of each effect added, in order (``AbstractEffect.family_name``)."""
        return [EFFECTS[e].family_name() for e in self.effects]

    @property
    def orders(self) -> list[int]:
        """The order of each effect added within its family, in order."""
        return [EFFECTS[e].order for e in self.effects]

    @property
    def effects_tied(self) -> list[list[str]]:
        """Per effect added, the candidates its round could not tell apart from it (the
        effect first; ``effect_ties``): a tie of any round, not only the first's."""
        return effect_ties(self.rounds)

    def answer(self) -> str:
        """The answer in one line: ``effect`` (with its order above 1: "cogging order 2"),
        then every effect added with the rivals its round could not tell apart from it
        ("a | b": one of them, the data cannot say which)."""
        head = f"{self.effect} order {self.order}" if (self.order or 0) > 1 else self.effect
        ties = self.effects_tied
        if not ties:
            return head
        return f"{head}: {', then '.join(' | '.join(t) for t in ties)}"

    @property
    def params(self) -> Params:
        """The final model's parameters (nominal refitted, effects added)."""
        return self.after.model.params

    def held_out_replay(self) -> dict[str, Any]:
        """The link angle q1 on the held-out segments, measured and replayed by the refit
        nominal and the final model (each from its own fitted starts).

        **Returns:**

        ``{"t0": (S,) segment starts [s], "dt": sample time [s], "measured", "before",
        "after": (S, L) q1 [rad]}`` as numpy arrays.
        """
        ws = self.workspace
        return {"t0": np.asarray(ws.test.segs.t0), "dt": float(ws.test.dt),
                "measured": np.asarray(ws.test.segs.y_meas)[..., 0],
                "before": held_out_traces(ws, self.before)[..., 0],
                "after": held_out_traces(ws, self.after)[..., 0]}

    @property
    def candidate_scores(self) -> dict[str, dict[str, Any]]:
        """Scores of every candidate in the first round (those the screen left out marked
        ``screened_out``, without a held-out gap: ``screened_out``)."""
        return self.rounds[0]["scores"] if self.rounds else {}

    def effect_params(self) -> dict[str, dict[str, dict[str, Any]]]:
        """Per added effect, its parameters with value, standard error, and whether fixed."""
        out: dict[str, dict[str, dict[str, Any]]] = {}
        for e in self.after.model.effects:
            out[e.name] = {
                k.split(".", 1)[1]: {"value": v, "stderr": self.after.stderr.get(k)}
                for k, v in self.after.values.items() if k.startswith(e.name + ".")
            }
            for k, v in e.params().items():
                if k not in out[e.name]:
                    out[e.name][k] = {"value": float(np.ravel(v)[0]), "stderr": None,
                                      "fixed": True}
        return out

    def evidence(self) -> dict[str, Any]:
        """How sure the answer is: per round the Akaike weights of "none" and every candidate
        (``evidence_weights``), and per added effect its fitted magnitude with standard error
        and the held-out gap after it."""
        gaps = {r["winner"]: r["scores"][r["winner"]]["gap_test"] for r in self.rounds
                if r["winner"] in r["scores"]}
        return {
            "rounds": [{"winner": r["winner"], "tied": r.get("tied", []),
                        "aic_weights": r.get("evidence_aic", {}),
                        "bic_weights": r.get("evidence_bic", {})} for r in self.rounds],
            "tied": {k: {"aic_weight": self.rounds[0].get("evidence_aic", {}).get(k),
                         "gap_test": self.rounds[0]["scores"][k]["gap_test"],
                         "params": {p: v for p, v in self.rounds[0].get("fitted", {})
                                    .get(k, {}).items()}}
                     for k in self.tied} if self.rounds else {},
            "added": {e: {"params": self.effect_params().get(e, {}), "gap_test": gaps.get(e)}
                      for e in self.effects},
            "answer_weight": (self.rounds[0].get("evidence_aic", {}).get(self.effects[0])
                              if self.effects and self.rounds else
                              (self.rounds[0].get("evidence_aic", {}).get("none")
                               if self.rounds else None)),
        }

    def to_json(self) -> dict[str, Any]:
        """The report (report.json) as plain JSON types."""
        nominal = {k: v for k, v in self.before.values.items()}
        return {
            "effect": self.effect, "order": self.order, "effects": list(self.effects),
            "families": self.families, "orders": self.orders, "tied": list(self.tied),
            "effects_tied": self.effects_tied, "answer": self.answer(),
            "gap_before": self.gap_before, "gap_after": self.gap_after,
            "gap_metric": "normalised RMS error of simulated q1 and q2 (q1 alone where the log's "
                          "two columns are one encoder's) over held-out segments "
                          "(open-loop replay under logged torque from start states fitted "
                          "with the parameters fixed), relative to the measured motion within "
                          "each segment",
            "gap_floor": self.gap_floor, "floor": self.floor,
            "unexplained": self.unexplained, "explained_fraction": self.explained,
            "evidence": self.evidence(),
            "nominal_refit": {"values": nominal, "stderr": self.before.stderr},
            "effect_params": self.effect_params(),
            "final_values": self.after.values, "final_stderr": self.after.stderr,
            "converged": self.after.converged,
            "rounds": self.rounds, "candidate_scores": self.candidate_scores,
            "localisation": self.localisation.summary,
            "localisation_final": self.localisation_after.summary,
            "telling_quantity": (EFFECTS[self.effect].telling
                                 if self.effects and self.effect in EFFECTS else None),
            "config": dataclasses.asdict(self.config) | {"candidates": self.candidates},
            "log": self.log_info, "seconds": self.seconds,
            "residual_analysis": self.residuals, "not_tried": dict(self.not_tried or {}),
            "kept": dict(self.kept or {}),
        }


def effect_ties(rounds: Sequence[dict[str, Any]]) -> list[list[str]]:
    """Per effect added, in order, the candidates its round could not tell apart from it
    (the effect first, named with its order above 1 (``AbstractEffect.label``: "cogging
    order 2"), then its rivals by name; the effect alone when its round decided), from the
    rounds' records (``tied``, after any second look: ``revisit_tie``; ``added``, the order
    the round's family grew to). Rounds whose winner was dropped or that added nothing are
    skipped."""
    out = []
    for r in rounds:
        w = r["winner"]
        if w == "none":
            continue
        added = r.get("added", w)
        name = EFFECTS[added].label() if added in EFFECTS else added
        out.append([name] + sorted(k for k in r.get("tied", []) if k != w))
    return out


def final_answer(added: Sequence[str], tied: Sequence[str], unexplained: bool,
                 explained: float, explained_min: float) -> str:
    """``discover``'s answer (``DiscoverResult.effect``) from the effects ``added`` in order,
    the first round's ``tied`` candidates, whether the final gap stays ``unexplained``, and
    the share of the excess gap the final model closes (``explained``, against
    ``explained_min``): the first effect added, "indistinguishable" when its round left a
    tie, "unexplained" when the final gap stays above the limit and nothing was added or
    what was added closes less than ``explained_min`` of the excess (a partial explanation),
    else "none"."""
    if added and not (unexplained and explained < explained_min):
        return "indistinguishable" if len(tied) > 1 else added[0]
    return "unexplained" if unexplained else "none"


def unexplained_limit(floor: dict[str, float], factor: float) -> float:
    """The held-out gap above which a model leaves something unexplained on its log: ``factor``
    times the noise floor plus three of the floor's standard deviations (``gap_floor``'s
    ``floor`` and ``floor_sd``; ``DiscoverConfig.unexplained_factor``)."""
    return factor * floor["floor"] + 3.0 * floor["floor_sd"]


def explained_fraction(before: float, after: float, floor: float) -> float:
    """The share of the held-out gap's excess over the floor that a model closes: (before -
    after) / (before - floor), clipped to [0, 1] (gaps: ``Problem.gap``, dimensionless; 0
    when ``before`` is not above the floor)."""
    excess = before - floor
    if not excess > 0.0:
        return 0.0
    return float(min(1.0, max(0.0, (before - after) / excess)))
