"""Tuned gains judged against others on a task: cost, certificate and ultimate bound
(``evaluate``), side by side (``compare``, ``TuneComparison``)."""

from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax.numpy as jnp
import numpy as np

from jaxflex.core.certificate import DEFAULT_EPS, certify, lambda_min_curve, ultimate_bound
from jaxflex.core.controller import CascadeGains
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.sim.simulate import SimResult, tracking_summary
from jaxflex.tune.task import TuneTask, simulate_task
from jaxflex.tune.workflow import TuneResult
from jaxflex.core.validation import requires_float64


@requires_float64
def evaluate(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask, *,
             vmax: float | None = None, margin: float = 0.0,
             model: FlexibleJointPlant | None = None, eps: float = DEFAULT_EPS,
             runs: Sequence[SimResult] | None = None) -> dict[str, Any]:
    """Report numbers for one gain set on ``task``: RMS/max link error [rad], torque RMS [N m],
    saturation fraction, fastest link speed [rad/s] per trajectory, the certificate
    (lambda_min over 0..vmax, certified range; vmax default 5 x the task speed) and the
    ultimate bound of eq. 32-33 over the task speeds."""
    model = plant if model is None else model
    runs = simulate_task(plant, gains, task, model) if runs is None else runs
    per = []
    for r in runs:
        s = tracking_summary(r.e1, r.tau)
        s["saturation_fraction"] = float(np.max(np.asarray(r.metrics.saturation_fraction)))
        s["diverged"] = bool(r.metrics.diverged)
        s["max_link_speed"] = float(jnp.max(jnp.abs(r.dq1)))
        per.append(s)
    vmax = 5 * task.certify_speed() if vmax is None else vmax
    cert = certify(model, gains, vmax, margin=margin, eps=eps)
    rms = np.array([np.atleast_1d(p["rms_error"]) for p in per])
    tau = np.array([np.atleast_1d(p["tau_rms"]) for p in per])
    return {
        "gains": gains.to_dict(),
        "rms_error": float(np.sqrt(np.mean(rms**2))),
        "tau_rms": float(np.sqrt(np.mean(tau**2))),
        "per_trajectory": per,
        "certificate": cert.to_dict(),
        "lambda_min_at_task_speed": float(
            np.min(np.asarray(lambda_min_curve(model, gains, [0.0, task.certify_speed()], eps)))),
        "ultimate_bound": ultimate_bound(model, gains, task.certify_speed(), eps=eps),
    }


@dataclasses.dataclass
class TuneComparison:
    """Reference (by default the initial) and tuned gains side by side on a task, for a
    report: the saved runs per trajectory and the numbers of ``evaluate`` (certificate over
    0..``vmax`` [rad/s]), each keyed "initial" and "tuned"."""

    runs: dict[str, list[SimResult]]
    evaluations: dict[str, dict[str, Any]]
    vmax: float

    def summary(self, result: TuneResult, task: TuneTask) -> dict[str, Any]:
        """JSON-ready comparison: the task, both evaluations, the RMS improvement factor and
        the search history of ``result``."""
        ev = self.evaluations
        return {
            "task": {"trajectories": [type(t).__name__ for t in task.trajectories],
                     "t_final": task.t_final, "tau_max": task.tau_max,
                     "q2d_method": task.q2d_method, "dt": task.dt,
                     "certify_speed": result.v_task, "margin": result.margin},
            "initial": ev["initial"], "tuned": ev["tuned"],
            "improvement_rms": ev["initial"]["rms_error"] / ev["tuned"]["rms_error"],
            "search": result.summary(),
        }


@requires_float64
def compare(plant: FlexibleJointPlant, result: TuneResult, task: TuneTask, *,
            model: FlexibleJointPlant | None = None, reference: CascadeGains | None = None,
            eps: float = DEFAULT_EPS, vmax: float | None = None) -> TuneComparison:
    """Simulate and evaluate the reference (default: the initial) gains and the tuned gains
    of ``result`` on ``task``; the certificate is computed over 0..vmax [rad/s] (default
    max(500, 5 x the task speed))."""
    model = plant if model is None else model
    reference = result.initial_gains if reference is None else reference
    vmax = max(500.0, 5 * result.v_task) if vmax is None else vmax
    margin = 0.0 if result.margin is None else result.margin
    gains = {"initial": reference, "tuned": result.gains}
    runs = {k: simulate_task(plant, g, task, model) for k, g in gains.items()}
    ev = {k: evaluate(plant, g, task, vmax=vmax, margin=margin, model=model, eps=eps,
                      runs=runs[k])
          for k, g in gains.items()}
    return TuneComparison(runs=runs, evaluations=ev, vmax=vmax)
