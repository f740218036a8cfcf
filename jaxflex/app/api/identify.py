"""``identify_log``: parameters from a log, as a result of numbers (``Identification``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.app.api.result import Result
from jaxflex.identify import identify
from jaxflex.io.logs import Log
from jaxflex.io.params import Params

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
        from jaxflex.app.plots.identify import plot_identification

        return plot_identification({
            "t": self.t, "measured": self.measured, "simulated": self.simulated,
            "labels": self.outputs, "boundaries": self.boundaries,
            "title": f"identification; RMS residual {self.rms:.3g}"})


def identify_log(log: Log, init: Params | None = None, free: Sequence[str] | None = None, *,
                 model: str = "flexible", link_side: str | Sequence[str] | None = None,
                 **options: Any) -> Identification:
    """Identify the parameters of a plant from ``log`` (docs/spec.md section 5).

    **Arguments:**

    - `log`: the log (``jaxflex.data.load_emps``, ``jaxflex.io.logs.load_log``, ...).
    - `init`: the start parameters; None: estimated from the log itself.
    - `free`: the names fitted; None: the model kind's default set.
    - `model`: "flexible", "rigid", "rotor", "link" or "auto" (``jaxflex.sim.step.MODEL_KINDS``;
      "auto": the kind the encoders and ``link_side`` suggest,
      ``jaxflex.identify.start.suggest_model``). The rotor kind is fitted by equation error
      on the torque from the measured motion (``jaxflex.identify.torque.identify_rotor``),
      as the command line fits it; its outputs are then the measured and predicted torque.
    - `link_side`: "single" or "coupled" (one per joint, or one for all): what a
      single-joint model can describe of the link side (a shipped data set's own:
      ``NamedData.link_side``); None: "single".
    - `options`: any further keyword of ``jaxflex.identify.identify`` (``segment_length``,
      ``substeps``, ``max_steps``, ``pin``, ...).

    **Returns:**

    An ``Identification``; one that did not converge says so in ``converged`` (the command
    line refuses it without ``--accept-unconverged``).

    **Raises:**

    ``ValueError`` (or ``jaxflex.io.errors.InputError``) for a log or setting the fit cannot
    use, as ``jaxflex.identify.identify``.
    """
    from jaxflex.identify.start import check_model, link_sides
    from jaxflex.app.plots.identify import fit_traces

    side = link_sides(None if link_side is None else (
        link_side if isinstance(link_side, str) else list(link_side)), log.n)
    kind, _ = check_model(log, model, side)
    if kind == "rotor":
        return _rotor(log, init, free, **options)
    res = identify(log, init, free, model=kind, **options)
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


def _rotor(log: Log, init: Params | None, free: Sequence[str] | None,
           **options: Any) -> Identification:
    """``identify_log`` for the rotor kind: ``identify_rotor`` (options: ``pin``,
    ``max_steps``), the outputs the measured and predicted torque [N m]."""
    from jaxflex.fit import get_value
    from jaxflex.identify.torque import identify_rotor
    from jaxflex.validate import torque_prediction

    unknown = sorted(set(options) - {"pin", "max_steps"})
    if unknown:
        raise ValueError(f"identify_log: the rotor kind takes the options pin and max_steps, "
                         f"not {unknown}")
    res = identify_rotor(log, init, free, **options)
    tau_hat = np.asarray(torque_prediction(res.params, log, kind="rotor"))
    resid = np.asarray(log.tau) - tau_hat
    stderr = {k: np.asarray(v, float) for k, v in res.fit.stderr.items()}
    values = {k: np.abs(np.atleast_1d(np.asarray(get_value(res.params, k), float)))
              for k in stderr}
    rel = {k: stderr[k] / np.maximum(values[k], 1e-300) for k in stderr}
    ident = res.params.extra["identification"]
    return Identification(
        params=res.params, stderr=stderr, rel_stderr=rel,
        cost=float(0.5 * np.sum(resid**2)), rms=float(np.sqrt(np.mean(resid**2))),
        converged=bool(res.converged), adequate=False,
        verdict=f"torque error {res.torque_pct:.3g}% on the log; {res.reason}",
        unidentifiable=[k for k, v in ident.get("parameters", {}).items()
                        if isinstance(v, dict) and v.get("identified") is False],
        warnings=[], steps=int(res.fit.steps + (0 if res.skew is None else res.skew.steps)),
        seconds=float(res.wall_s), t=np.asarray(log.t), measured=np.asarray(log.tau),
        simulated=tau_hat, outputs=[f"tau[{j}]" for j in range(log.n)], boundaries=[])
