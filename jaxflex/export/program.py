"""The controller as a rig runs it, the one program every export back end translates.

``SampledController`` is the cascade controller (``jaxflex.core.controller.CascadeController``)
together with what its configuration's sensing makes it compute at each sample: the
velocity source (the controller's dirty derivative, or the steady-state Kalman filter of
``jaxflex.core.estimator`` with its state), and, for the Kalman filter, the DAC's rounding of the
torque it predicts with. Its ``init`` and ``step`` are those of the sampled-data loop
(``jaxflex.sim.simulate.init_controller`` and ``controller_sample``), so that the exported
controller is the certified one. ``rig_controller`` builds it from a parameter file's
``controller`` section and refuses, naming the entry, what an exported controller cannot
run (``ExportError``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.controller import CascadeController, ControllerState, LawOutput
from jaxflex.core.estimator import KalmanEstimator
from jaxflex.core.sensing import AbstractSensing, Sensing
from jaxflex.sim.simulate import REFERENCE_ORDER, controller_sample, init_controller, loop_estimator
from jaxflex.core.trajectory import Taylor

REFERENCE_ROWS: int = REFERENCE_ORDER + 1
"""Rows of the reference a rig gives the exported controller at each sample: q1d and its
derivatives up to the 4th (q2d'' of eq. 16 differentiates eq. 13 twice along the flow)."""


class ExportError(ValueError):
    """A configuration the exported controller cannot run (the message names the entry)."""


def check_exportable(sensing: AbstractSensing) -> None:
    """Refuse a sensing whose controller side the export cannot run.

    **Arguments:**

    - ``sensing``: the sensing a configuration was certified under.

    **Raises:**

    ``ExportError`` naming ``controller.sensing.velocity`` when it is "exact": the
    controller then gets the plant's true velocities, which a rig does not measure.
    """
    if sensing.velocity == "exact":
        raise ExportError(
            "controller.sensing.velocity: 'exact' gives the controller the plant's true "
            "velocities, which a rig does not measure; the exported controller reads angles "
            "only (tune for velocity 'filtered' or 'kalman' to export)")


class SampledController(eqx.Module):
    """The sampled-data controller of one certified configuration.

    ``controller``: the cascade law with its model, gains (observer leak included),
    reference, q2d method, period and torque limit; ``estimator``: the Kalman filter where
    ``sensing.velocity`` is "kalman" (None otherwise); ``sensing``: the sensing the
    configuration was certified under (its velocity source and DAC are part of the
    controller; its encoders and noise are the rig's and are used by the parity run only).
    """

    controller: CascadeController
    estimator: KalmanEstimator | None
    sensing: AbstractSensing

    def __check_init__(self) -> None:
        check_exportable(self.sensing)
        if (self.estimator is None) != (self.sensing.velocity != "kalman"):
            raise ValueError("SampledController: an estimator goes with velocity 'kalman' only")

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.controller.model.n

    def init(self, t0: ArrayLike, q1: Array, q2: Array) -> ControllerState:
        """State at the first sample, time ``t0`` [s], sensed angles q1, q2 [rad] (the loop at
        rest: zero velocities)."""
        q1 = jnp.asarray(q1, jnp.result_type(float))
        zero = jnp.zeros_like(q1)
        return init_controller(self.controller, self.estimator, t0, q1, q2, zero, zero)

    def step(self, state: ControllerState, t: ArrayLike, q1: Array, q2: Array
             ) -> tuple[ControllerState, LawOutput]:
        """One sample at time t [s] from the sensed angles q1, q2 [rad]: the next state and
        the law's output (``tau`` [N m], the command before the DAC)."""
        zero = jnp.zeros_like(jnp.asarray(q1, jnp.result_type(float)))
        new, out, _ = controller_sample(self.controller, self.sensing, self.estimator, state,
                                        jnp.asarray(t, zero.dtype), q1, q2, zero, zero)
        return new, out

    def with_reference(self, derivs: Float[Array, "5 n"], t: ArrayLike) -> SampledController:
        """This controller with the reference given at time t [s] by ``derivs``: rows q1d,
        q1d', ..., q1d^(4) [rad/s^k] (``REFERENCE_ROWS``), as the sampled-data loop hands it
        (``jaxflex.core.trajectory.Taylor``)."""
        derivs = jnp.asarray(derivs)
        if derivs.shape != (REFERENCE_ROWS, self.n):
            raise ValueError(f"SampledController.with_reference: expected derivatives of shape "
                             f"{(REFERENCE_ROWS, self.n)}, got {derivs.shape}")
        ref = Taylor(derivs, jnp.asarray(t, derivs.dtype))
        return eqx.tree_at(lambda s: s.controller.trajectory, self, ref)


def sampled_controller(controller: CascadeController | SampledController,
                       sensing: AbstractSensing | None = None) -> SampledController:
    """A controller as the loop runs it under a sensing.

    **Arguments:**

    - ``controller``: a ``CascadeController`` (a ``SampledController`` is returned as it is).
    - ``sensing``: the sensing (default ``parity_sensing``: the rig's encoders, the dirty
      derivative, no DAC); with velocity "kalman" the loop's Kalman filter is built for it.

    **Returns:**

    The ``SampledController``.

    **Raises:**

    ``ExportError`` for velocity "exact".
    """
    if isinstance(controller, SampledController):
        return controller
    sensing = parity_sensing() if sensing is None else sensing
    return SampledController(controller, loop_estimator(controller, sensing), sensing)


def parity_sensing() -> Sensing:
    """Sensing of the parity run of a bare ``CascadeController``: the rig's 16-bit encoders
    (``jaxflex.io.presets.rig_sensing``), velocities by the dirty derivative, no DAC."""
    from jaxflex.io.presets import rig_sensing

    return rig_sensing(dac_bits=0)


def rig_controller(
    params: Any = None,
    trajectory: Any = None,
    *,
    q2d_method: str | None = None,
    dt: float | None = None,
    tau_max: float | None = None,
    compensation: bool | None = None,
    sensing: str | Mapping[str, Any] | AbstractSensing | None = None,
) -> SampledController:
    """The controller a parameter file certifies, as its ``controller`` section records it.

    **Arguments:**

    - ``params``: ``Params``, a docs/spec.md section 7 mapping, a path, or None (the paper's).
    - ``trajectory``: a name of ``jaxflex.io.presets.TRAJECTORIES`` or a ``Trajectory``.
    - ``q2d_method``, ``dt`` [s], ``tau_max`` [N m], ``compensation``, ``sensing`` (a preset
      name, a mapping of ``Sensing`` fields or a ``Sensing``): as in
      ``jaxflex.export.build_controller``; None takes the section's entry, else
      ``jaxflex.io.presets.DEFAULT_CONTROLLER``'s.

    **Returns:**

    The ``SampledController``: the law with the file's gains (observer leak included) and
    the velocity source, Kalman filter and DAC of the recorded sensing.

    **Raises:**

    ``ExportError`` naming the entry the export cannot run (``controller.sensing.velocity``
    "exact"); ``ParamsError`` for an argument that contradicts the section.
    """
    from jaxflex.export import build_controller
    from jaxflex.io.params import Params, load_params
    from jaxflex.io.presets import controller_config, paper_params, sensing_of

    if params is None:
        params = paper_params()
    elif isinstance(params, (str, os.PathLike)):
        params = load_params(params)
    elif isinstance(params, dict):
        params = Params.from_dict(params)
    given = None if isinstance(sensing, AbstractSensing) else sensing
    cfg = controller_config(params, {"sensing": given})
    sens = sensing if isinstance(sensing, AbstractSensing) else sensing_of(cfg.sensing)
    check_exportable(sens)
    c = build_controller(params, trajectory, q2d_method=q2d_method, dt=dt, tau_max=tau_max,
                         compensation=compensation)
    return SampledController(c, loop_estimator(c, sens), sens)


def describe(sc: SampledController) -> str:
    """One line naming what the controller computes on the rig: its velocity source (with
    the DAC the Kalman filter predicts through), its observer and leak.

    **Arguments:**

    - ``sc``: the controller.

    **Returns:**

    E.g. "Kalman-filter velocities (predicting through a 12-bit DAC over +-2.0 N m),
    observer leak 0.2 rad/s".
    """
    s = sc.sensing
    leak = [float(v) for v in jnp.broadcast_to(sc.controller.gains.leak, (sc.n,))]
    if s.velocity == "kalman":
        vel = "Kalman-filter velocities" + (" and angles" if sc.estimator.angles else "")
        if s.dac_bits:
            vel += f" (predicting through a {_dac(s)})"
    else:
        vel = "dirty-derivative velocities"
    obs = ("paper's observer (no leak)" if not any(leak)
           else f"observer leak {leak if sc.n > 1 else leak[0]} rad/s")
    if not sc.controller.compensation:
        obs = "no friction compensation"
    return f"{vel}, {obs}"


def describe_sensing(sensing: AbstractSensing) -> str:
    """One line naming a sensing's encoder steps [rad] and DAC (the rig side of a run)."""
    r1 = np.ravel(np.asarray(sensing.q1_resolution, dtype=float))
    r2 = np.ravel(np.asarray(sensing.q2_resolution, dtype=float))
    enc = (f"encoder steps {r1[0]:.3g} / {r2[0]:.3g} rad" if r1.size == 1 and r2.size == 1
           else f"encoder steps {r1.tolist()} / {r2.tolist()} rad")
    return f"{enc}, {_dac(sensing) if sensing.dac_bits else 'no DAC'}"


def _dac(sensing: AbstractSensing) -> str:
    rng = np.ravel(np.asarray(sensing.dac_range, dtype=float))
    return f"{sensing.dac_bits}-bit DAC over +-{rng[0] if rng.size == 1 else rng.tolist()} N m"
