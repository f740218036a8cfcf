"""``certify_gains`` and ``tune_gains``: the N2 certificate of a gain set and certified gain
tuning (``Certification``, ``Tuning``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.app.api.result import Result, plant_of
from jaxflex.core.certificate import (
    DEFAULT_NUM, DEFAULT_VMAX, CertificateResult, certify, ultimate_bound,
)
from jaxflex.core.controller import CascadeGains
from jaxflex.io.params import Params
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.tune import TuneTask, tune

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@dataclasses.dataclass(frozen=True)
class Certification(CertificateResult, Result):
    """The outcome of ``certify_gains`` (eq. 29-33): ``CertificateResult``'s grid and
    certified range, and the ultimate bound of eq. 32-33 over the same speeds.

    velocities [rad/s]: the grid from 0 to vmax; lambda_min: the smallest eigenvalue of N2
    on it; certified_up_to [rad/s]: the largest speed up to which lambda_min > margin on the
    whole range; certified: the whole grid passes; margin; eps [rad/s]; D_bar, rho_bound,
    e1_bound [rad]: the ultimate bound (rho_bound inf where N2 is not positive definite).
    """

    D_bar: float
    rho_bound: float
    e1_bound: float

    def plot(self) -> Figure:
        """lambda_min(N2) against link speed, with the margin (``plot_lambda_min``).

        **Returns:**

        The figure.
        """
        from jaxflex.app.plots.tune import plot_lambda_min

        curve = {"velocities": self.velocities, "lambda_min": self.lambda_min,
                 "certified_up_to": self.certified_up_to}
        return plot_lambda_min({"gains": curve}, margin=self.margin)


def certify_gains(model: Params | FlexibleJointPlant, gains: CascadeGains | None = None,
                  vmax: float = DEFAULT_VMAX, *, num: int = DEFAULT_NUM, margin: float = 0.0,
                  **options: Any) -> Certification:
    """Certify cascade ``gains`` on a plant over the link speeds 0..vmax (eq. 29-33).

    **Arguments:**

    - `model`: a ``Params`` (its plant is built) or a ``FlexibleJointPlant``.
    - `gains`: the gains; None: those of ``model`` (a ``Params`` with a gains section).
    - `vmax`: the largest link speed [rad/s].
    - `num`: grid points.
    - `margin`: lambda_min must exceed this.
    - `options`: ``eps`` [rad/s] (the friction's smoothing speed) and ``refine`` (bisection
      steps at the boundary), as ``jaxflex.core.certificate.certify``.

    **Returns:**

    A ``Certification``.

    **Raises:**

    ``ValueError`` for a bad range, for no gains, or when float64 is off
    (``jax.config.update("jax_enable_x64", True)``).
    """
    if gains is None:
        if not isinstance(model, Params) or model.gains is None:
            raise ValueError("certify_gains: give gains, or parameters with a gains section")
        gains = model.to_gains()
    plant = plant_of(model)
    c = certify(plant, gains, vmax, num=num, margin=margin, **options)
    b = ultimate_bound(plant, gains, vmax, num=num,
                       **{k: v for k, v in options.items() if k == "eps"})
    return Certification(**{f.name: getattr(c, f.name) for f in dataclasses.fields(c)},
                         D_bar=float(b["D_bar"]), rho_bound=float(b["rho_bound"]),
                         e1_bound=float(b["e1_bound"]))


@dataclasses.dataclass(frozen=True)
class Tuning(Result):
    """The outcome of ``tune_gains``.

    gains: the tuned gains; cost: their cost on the task [rad^2]; initial_gains,
    initial_cost: the start's; v_task [rad/s]: the speed up to which the certificate is
    required; margin: lambda_min's margin (None: tuned without the certificate);
    certified_up_to [rad/s] (None without the certificate); velocities [rad/s], lambda_min:
    the tuned gains' N2 curve (empty without it); starts: per start of the search, the cost,
    RMS error [rad] and constraint value per iteration; evaluations; seconds.
    """

    gains: CascadeGains
    cost: float
    initial_gains: CascadeGains
    initial_cost: float
    v_task: float
    margin: float | None
    certified_up_to: float | None
    velocities: np.ndarray
    lambda_min: np.ndarray
    starts: list[dict[str, Any]]
    evaluations: int
    seconds: float

    def plot(self) -> Figure:
        """RMS tracking error per iteration of each start of the search (``plot_history``).

        **Returns:**

        The figure.
        """
        from jaxflex.app.plots.tune import plot_history

        return plot_history(self.starts)


def tune_gains(model: Params | FlexibleJointPlant, initial: CascadeGains | None = None,
               task: TuneTask | None = None, *, trajectories: Sequence[str] = ("sinusoid",),
               **options: Any) -> Tuning:
    """Tune the cascade gains on a task under the N2 certificate (``jaxflex.tune.tune``).

    **Arguments:**

    - `model`: a ``Params`` (its plant is built) or a ``FlexibleJointPlant``.
    - `initial`: certified start gains; None: those of ``model``'s gains section, else the
      paper's.
    - `task`: what the gains are tuned for; None: the named ``trajectories``
      (``jaxflex.io.presets.trajectory_preset``) with ``TuneTask``'s defaults.
    - `trajectories`: reference names, used when ``task`` is None.
    - `options`: keywords of ``jaxflex.tune.tune`` (``margin``, ``iterations``, ``starts``,
      ``seed``, ``progress``, ...).

    **Returns:**

    A ``Tuning``.

    **Raises:**

    ``ValueError`` for bad settings, for initial gains that are not certified with the
    margin, or when every candidate diverges; float64 must be on.
    """
    from jaxflex.io.presets import paper_gains, trajectory_preset

    if initial is None:
        has = isinstance(model, Params) and model.gains is not None
        initial = model.to_gains() if has else paper_gains()
    if task is None:
        task = TuneTask(trajectories=tuple(trajectory_preset(n) for n in trajectories))
    r = tune(plant_of(model), initial, task, **options)
    cert = r.certificate
    return Tuning(
        gains=r.gains, cost=float(r.cost), initial_gains=r.initial_gains,
        initial_cost=float(r.initial_cost), v_task=float(r.v_task), margin=r.margin,
        certified_up_to=None if cert is None else float(cert.certified_up_to),
        velocities=np.asarray([] if cert is None else cert.velocities),
        lambda_min=np.asarray([] if cert is None else cert.lambda_min),
        starts=r.summary()["starts"], evaluations=int(r.evaluations),
        seconds=float(r.wall_time_s))
