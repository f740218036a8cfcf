"""``identify_log``: parameters from a log, as a result of numbers (``Identification``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.api.result import Result
from jaxflex.identify import identify
from jaxflex.logs import Log
from jaxflex.params import Params

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True)
class Identification(Result):
    """The outcome of ``identify_log``.

    params: the identified parameters; stderr, rel_stderr: per fitted name, the standard
    error per joint (physical units) and its ratio to the value; cost: the final
    least-squares cost; rms: RMS output residual [rad]; converged: the solver reached a
    stationary point; adequate: the measurement noise explains the cost; verdict: both
    halves of the verdict in words; unidentifiable: the names the data cannot identify;
    warnings; steps: solver steps; seconds: solve time [s]; t [s], measured, simulated
    ((N, m) [rad]): the fitted outputs, segments joined end to end; outputs: their m names;
    boundaries: the segment joins [s].
    """

    params: Params
    stderr: dict[str, np.ndarray]
    rel_stderr: dict[str, np.ndarray]
    cost: float
    rms: float
    converged: bool
    adequate: bool
    verdict: str
    unidentifiable: list[str]
    warnings: list[str]
    steps: int
    seconds: float
    t: np.ndarray
    measured: np.ndarray
    simulated: np.ndarray
    outputs: list[str]
    boundaries: list[float]

    def plot(self) -> Figure:
        """Measured against simulated outputs and their difference (``plot_identification``).

        **Returns:**

        The figure.
        """
        from jaxflex.plots.identify import plot_identification

        return plot_identification({
            "t": self.t, "measured": self.measured, "simulated": self.simulated,
            "labels": self.outputs, "boundaries": self.boundaries,
            "title": f"identification; RMS residual {self.rms:.3g}"})


def identify_log(log: Log, init: Params | None = None, free: Sequence[str] | None = None, *,
                 model: str = "flexible", **options: Any) -> Identification:
    """Identify the parameters of a plant from ``log`` (docs/spec.md section 5).

    **Arguments:**

    - `log`: the log (``jaxflex.data.load_emps``, ``jaxflex.logs.load_log``, ...).
    - `init`: the start parameters; None: estimated from the log itself.
    - `free`: the names fitted; None: the model kind's default set.
    - `model`: "flexible", "rigid", "rotor", "link" or "auto" (``jaxflex.step.MODEL_KINDS``).
    - `options`: any further keyword of ``jaxflex.identify.identify`` (``segment_length``,
      ``substeps``, ``max_steps``, ``pin``, ...).

    **Returns:**

    An ``Identification``; one that did not converge says so in ``converged`` (the command
    line refuses it without ``--accept-unconverged``).

    **Raises:**

    ``ValueError`` (or ``jaxflex.errors.InputError``) for a log or setting the fit cannot
    use, as ``jaxflex.identify.identify``.
    """
    from jaxflex.plots.identify import fit_traces

    res = identify(log, init, free, model=model, **options)
    tr = fit_traces(res)
    return Identification(
        params=res.params,
        stderr={k: np.asarray(v, float) for k, v in res.stderr.items()},
        rel_stderr={k: np.asarray(v, float) for k, v in res.rel_stderr.items()},
        cost=float(res.cost), rms=float(res.rms), converged=bool(res.converged),
        adequate=bool(res.adequate), verdict=res.reason, unidentifiable=list(res.unidentifiable),
        warnings=list(res.warnings), steps=int(res.steps), seconds=float(res.wall_s),
        t=tr["t"], measured=tr["measured"], simulated=tr["simulated"], outputs=tr["labels"],
        boundaries=tr["boundaries"])
