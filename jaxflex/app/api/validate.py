"""``validate_model``: a parameter set's errors on a log beside its noise (``Validation``)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.app.api.result import Result
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.validate import validate

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True)
class Validation(Result):
    """The outcome of ``validate_model`` (``jaxflex.validate``'s module docstring).

    model: the model kind replayed; samples, dt [s]: the log's; gap, gap_noise: the segment
    replay gap and what the log's noise alone gives a perfect model (dimensionless);
    torque_pct, torque_noise_pct: the torque prediction error from the measured motion and
    its noise floor [%]; noise_std: the noise found on each column; closed_loop: position,
    velocity and torque errors [%] of the declared loop with their ``noise_floor``, or None
    (no loop declared or no reference logged); residual_analysis: the segment replay's
    whiteness and cross-correlation tests; series: measured and predicted signals (``t``,
    ``tau``, ``tau_hat``, ``q``, ``closed_loop``).
    """

    model: str
    samples: int
    dt: float
    gap: float
    gap_noise: float
    torque_pct: float
    torque_noise_pct: float
    noise_std: Any
    closed_loop: dict[str, Any] | None
    residual_analysis: dict[str, Any]
    series: dict[str, Any]

    def plot(self) -> Figure:
        """Measured against predicted torque and, where a loop was run, the closed loop's
        position and torque (``plot_validation_log``).

        **Returns:**

        The figure.
        """
        from jaxflex.app.plots.validate import plot_validation_log

        return plot_validation_log(
            self.series, title=f"{self.model} model: torque error {self.torque_pct:.2f}% "
                               f"(noise alone {self.torque_noise_pct:.2f}%), replay gap "
                               f"{self.gap:.3f} (noise alone {self.gap_noise:.3f})")


def validate_model(params: Params, log: Log, *, model: str = "flexible",
                   segment: int | None = None, substeps: int = 4,
                   disturbance: np.ndarray | None = None) -> Validation:
    """Validate ``params`` on ``log``: replay gap, torque prediction and closed-loop error,
    each beside its noise floor (``jaxflex.validate.validate``).

    **Arguments:**

    - `params`: the parameter set (its ``loop_controller`` section declares the loop that
      ran, for the closed-loop error).
    - `log`: the log.
    - `model`: "flexible", "rigid", "rotor" or "link".
    - `segment`: samples per replayed segment; None: the default length.
    - `substeps`: integrator substeps per sample.
    - `disturbance`: a known input disturbance per sample for the closed loop, or None.

    **Returns:**

    A ``Validation``.

    **Raises:**

    ``ValueError`` (or ``jaxflex.io.params.ParamsError``) for a model kind, log or loop section
    the validation cannot use.
    """
    d = validate(params, log, kind=model, segment=segment, substeps=substeps,
                 disturbance=disturbance)
    return Validation(
        model=d["model"], samples=int(d["samples"]), dt=float(d["dt"]), gap=float(d["gap"]),
        gap_noise=float(d["gap_noise"]), torque_pct=float(d["torque_pct"]),
        torque_noise_pct=float(d["torque_noise_pct"]), noise_std=d["noise_std"],
        closed_loop=d["closed_loop"], residual_analysis=d["residual_analysis"],
        series=d["series"])
