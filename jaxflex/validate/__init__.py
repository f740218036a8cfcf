"""Validation of a parameter set on measured logs: a workflow on the engine.

Per log, three numbers (each from the one implementation of its equation), each beside its
**noise floor**: what the log's measurement noise alone gives a perfect model, so that an error
at its floor says "as good as this log can tell", not "97% wrong":

- **segment replay gap** (open loop): the log cut into segments, each replayed under the
  logged torque from its measured start (``jaxflex.fit.Problem`` with ``free_starts=False``,
  ``jaxflex.fit.gap``): 0 is perfect, 1 as bad as predicting no motion (floor:
  ``segment_gap_floor``);
- **torque prediction error** from the measured motion, ``100 ||tau - tau_hat|| / ||tau||``
  [%], with ``tau_hat`` from the inverse dynamics ``FlexibleJointPlant.torque_residuals``
  (velocities and accelerations by Savitzky-Golay, ``jaxflex.fit.savgol``; LuGre z at its
  steady state, eq. 35): rigid model ``tau_hat = tau + r_link + r_rotor`` with q2 = q1;
  flexible and rotor models ``tau_hat = tau + r_rotor`` (the rotor line of eq. 3 with the
  measured q1 and q2; for "rotor" the link reading passes the ``encoder_skew`` effect);
  (floor: ``torque_noise_floor``, the measurement noise and the torque content faster than
  the measured motion resolves);
- **closed-loop simulation error** in the benchmark metric ``100 ||y - y_sim|| / ||y||`` [%]
  for position, velocity and torque, when the parameters declare the controller that ran
  (the parameter file's top-level ``loop_controller`` section, ``LOOP_TYPES``: ``PPCascade``,
  the EMPS P position / P velocity cascade; ``PDLoop``, a PD on the rotor or link angle;
  ``CascadeLoop``, jaxflex's own cascade) and the log has a reference ``q1d``. Every declared
  loop is a ``jaxflex.core.controller.AbstractControlLaw`` run by one sampled-data scan
  around ``jaxflex.sim.step.model_step`` (rigid or flexible model), the log's q1d sampled as
  the reference (floors: ``closed_loop_noise_floor``).

Beside them, the segment replay's residual analysis as MATLAB's ``resid`` gives it
(``replay_residual_analysis``: autocorrelation and torque cross-correlation with 99% bands,
Ljung-Box whiteness).

Modules: ``loops`` (the declared controllers and the one sampled-data loop), ``closed_loop``
(closed-loop errors and fit), ``replay`` (torque prediction, segment gap, noise floors,
residual analysis), ``workflow`` (``validate``). Returns plain dicts; figures and files are
written by ``jaxflex.app.cli.validate``; ``jaxflex.validate_model`` wraps ``validate`` in a typed
result.
"""

from jaxflex.validate.loops import (
    CascadeLaw,
    CascadeLoop,
    DeclaredLoop,
    LOOP_SECTION,
    LOOP_TYPES,
    PDLaw,
    PDLoop,
    PPCascade,
    PPLaw,
    check_loop_kind,
    loop_controller,
    loop_start,
    need_float64,
    sampled_loop,
    simulate_loop,
    simulate_pp_cascade,
)
from jaxflex.validate.closed_loop import (
    ClosedLoopFit,
    ClosedLoopFitResult,
    RIGID_TERMS,
    ROBUST_BLOCKS,
    benchmark_derivative,
    closed_loop_errors,
    closed_loop_fit,
    closed_loop_noise_floor,
    closed_loop_residuals,
    rel_error_pct,
    rigid_torque,
    rigid_torque_fit,
)
from jaxflex.validate.replay import (
    fast_energy,
    noise_std,
    predicted_torque,
    replay_residual_analysis,
    segment_gap,
    segment_gap_floor,
    torque_noise_floor,
    torque_prediction,
)
from jaxflex.validate.workflow import (
    validate,
)

__all__ = [
    "CascadeLaw",
    "CascadeLoop",
    "ClosedLoopFit",
    "ClosedLoopFitResult",
    "DeclaredLoop",
    "LOOP_SECTION",
    "LOOP_TYPES",
    "PDLaw",
    "PDLoop",
    "PPCascade",
    "PPLaw",
    "RIGID_TERMS",
    "ROBUST_BLOCKS",
    "benchmark_derivative",
    "check_loop_kind",
    "closed_loop_errors",
    "closed_loop_fit",
    "closed_loop_noise_floor",
    "closed_loop_residuals",
    "fast_energy",
    "loop_controller",
    "loop_start",
    "need_float64",
    "noise_std",
    "predicted_torque",
    "rel_error_pct",
    "replay_residual_analysis",
    "rigid_torque",
    "rigid_torque_fit",
    "sampled_loop",
    "segment_gap",
    "segment_gap_floor",
    "simulate_loop",
    "simulate_pp_cascade",
    "torque_noise_floor",
    "torque_prediction",
    "validate",
]
