"""Gain tuning against the N2 stability certificate (paper section 4; docs/spec.md section 4).

Choose the cascade gains (Ke, KD1, KD2, kv, L1, L2 per joint, Table 3) that minimise a
simulated tracking cost over a task, subject to

    lambda_min(N2(v)) >= margin   for all link speeds |v| <= v_task                 (eq. 29-31)

The cost is the mean squared link error of the sampled-data closed loop
(``jaxflex.sim.simulate.simulate_sampled``) over one or more reference trajectories, with encoder
and DAC quantisation, filtered velocities and a torque limit, plus an optional torque penalty.

How it works:

- Gains are positive, so the search runs in log-space, theta = log(gains), inside a box of
  +-log(box) around the initial gains; the objective is log(cost), whose gradient has no
  scale. Gradients go through the whole simulation (``jax.value_and_grad`` of a
  ``lax.scan``); quantisers use a straight-through gradient (``jaxflex.core.sensing.StraightThrough``),
  since rounding has zero derivative and would cut every feedback path out of the gradient.
- Adam steps, with the certificate *enforced* at every iterate: a step that leaves the
  certified set is cut back (halved) along the segment from the last certified point, and a
  step into a diverged simulation is undone. The iterates are certified points; none is traded
  against the cost.
- Multi-start: the initial gains (which must themselves be certified) and random log-normal
  perturbations of them, each pulled back toward the initial gains if uncertified.
- Final check: the best candidate must pass ``jaxflex.core.certificate.certify`` up to
  max(v_task, fastest simulated link speed); otherwise the next best is taken.

Modules: ``task`` (what is tuned for, its cost and runs), ``search`` (Adam under the
certificate), ``workflow`` (``tune``), ``compare`` (gain sets side by side).

Units: gains as in ``jaxflex.core.controller.CascadeGains``; speeds [rad/s]; cost [rad^2].
"""


from jaxflex.tune.task import (
    TuneTask,
    certify_speed,
    max_link_speed,
    reference_speed,
    simulate_task,
    tracking_cost,
)
from jaxflex.tune.search import (
    StartRecord,
    adam_search,
    ascend_feasibility,
    gains_of,
)
from jaxflex.tune.workflow import (
    TuneResult,
    damping_value,
    rest_damping_of,
    task_rest_map,
    tune,
)
from jaxflex.tune.compare import (
    TuneComparison,
    compare,
    evaluate,
)

__all__ = [
    "StartRecord",
    "TuneComparison",
    "TuneResult",
    "TuneTask",
    "adam_search",
    "ascend_feasibility",
    "certify_speed",
    "compare",
    "damping_value",
    "evaluate",
    "gains_of",
    "max_link_speed",
    "reference_speed",
    "rest_damping_of",
    "simulate_task",
    "task_rest_map",
    "tracking_cost",
    "tune",
]
