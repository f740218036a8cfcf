"""``discover_effects``: which named effect a model misses on a log (``Discovery``)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.app.api.result import Result
from jaxflex.discover import DiscoverConfig, discover
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.io.progress import Progress

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True)
class Discovery(Result):
    """The outcome of ``discover_effects`` (docs/spec.md section 8).

    effect: the answer (the family of the first effect added, "indistinguishable", "none"
    or "unexplained"); order: the order of the answer's family the log asked for (e.g. 2
    for a cogging with its 2nd harmonic; 0 when no effect is the answer); effects: every
    effect added, in order, by registered name (``cogging_2``); orders: each one's order in
    its family; answer: the answer in one line
    with the rivals each round could not tell apart; params: the final model (nominal
    refitted, effects added); gap_before, gap_after, gap_floor: held-out gaps of the refit
    nominal model, the final model and a correct model on this log (dimensionless);
    explained: the share of the excess gap the final model closes; seconds: run time [s];
    report: the full report (``DiscoverResult.to_json``: rounds, scores, evidence,
    localisation, residual analysis); replay: the held-out segments' q1 [rad] measured and
    replayed before and after (``DiscoverResult.held_out_replay``); samples: the samples the
    localisation binned.
    """

    effect: str
    effects: list[str]
    answer: str
    params: Params
    gap_before: float
    gap_after: float
    gap_floor: float
    explained: float
    seconds: float
    report: dict[str, Any]
    replay: dict[str, np.ndarray]
    samples: int
    order: int = 0
    orders: list[int] = dataclasses.field(default_factory=list)

    def plot(self, which: str = "replay") -> Figure:
        """One figure of the run (``jaxflex.app.plots.discover.report_figures``).

        **Arguments:**

        - `which`: "replay" (held-out segments, nominal against final model), "signature"
          (torque residuals against the telling quantity), "scores" (every candidate's
          held-out gap) or "residuals" (the final model's residual analysis).

        **Returns:**

        The figure.

        **Raises:**

        ``ValueError`` for a figure this run does not have.
        """
        from jaxflex.app.plots.discover import report_figures

        figs = report_figures(self.report, self.report["localisation"], self.samples,
                              self.replay)
        if which not in figs:
            raise ValueError(f"Discovery.plot: no figure {which!r}; this run has {sorted(figs)}")
        return figs[which]


def discover_effects(log: Log, nominal: Params | None = None, *,
                     progress: Progress | None = None,
                     **config: Any) -> Discovery:
    """Find the named effect ``nominal`` misses on a one-joint ``log``, add it and refit,
    until nothing significant is left (``jaxflex.discover.discover``).

    **Arguments:**

    - `log`: a one-joint log with t, tau, q1 and q2 (q2 = q1 for a one-encoder axis, with
      ``model="rigid"``).
    - `nominal`: the model to start from (e.g. ``identify_log(log).params``); None: the
      paper's plant.
    - `progress`: the reporter of each line of the run's account
      (``jaxflex.io.progress.Progress``, e.g. ``Printer()``); None: silent.
    - `config`: fields of ``jaxflex.discover.DiscoverConfig`` (``candidates``,
      ``max_effects``, ``model``, ``segment``, ...).

    **Returns:**

    A ``Discovery``.

    **Raises:**

    ``ValueError`` for a multi-joint log, a log too short to split or an unknown candidate;
    ``TypeError`` for a name that is not a field of ``DiscoverConfig``.
    """
    res = discover(log, nominal, DiscoverConfig(**config), progress=progress)
    return Discovery(
        effect=res.effect, effects=list(res.effects), answer=res.answer(), params=res.params,
        gap_before=float(res.gap_before), gap_after=float(res.gap_after),
        gap_floor=float(res.gap_floor), explained=float(res.explained),
        seconds=float(res.seconds), report=res.to_json(), replay=res.held_out_replay(),
        samples=len(res.localisation.series["t"]), order=res.order, orders=res.orders)
