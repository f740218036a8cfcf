"""The verdict of an identification, in two parts (docs/spec.md section 5):

- the solver's: a stationary point was reached (the solver's tolerance or statistical stop),
  or not (a step cap, a failure, an interrupt);
- the model's: *adequate* when the measurement noise explains the cost (the residual at the
  noise level), else *model-limited*: the residual's size against the noise, its colour (the
  whiteness test and correlation time of ``jaxflex.fit.residual_analysis``), whether it
  correlates with the input, and where in the log it sits.

A converged, model-limited fit is the normal result on a real rig's log: the best the model
can do, with what it leaves described. Only a solver that did not converge makes a result
unfit for downstream use.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from jaxflex.fit import Problem, simulated_outputs

#: The segments named in ``where`` (the largest shares of the residual).
WORST_SEGMENTS: int = 3


def model_verdict(prob: Problem, y: Any, cost: float, noise_cost: float, accept_cost: float,
                  ) -> dict[str, Any]:
    """The model's half of the verdict for the solution ``y`` of ``prob``.

    Arguments:
        prob: the identification problem (``make_problem``), outputs in rad (m on a
            prismatic axis).
        y: its solution (theta and start states).
        cost: the solution's cost 0.5 ||r||^2 in the problem's weighted units.
        noise_cost: the cost the measurement noise alone gives (``noise_cost``).
        accept_cost: the factor on ``noise_cost`` below which the model is adequate.

    Returns:
        ``{"verdict": "adequate" | "model-limited", "cost_over_noise", "channels": {label:
        {"rms", "white", "p_white", "correlation_time", "input_lag", "input_peak"}},
        "where": [{"t0", "t1", "share"}], "summary", "friction_never_slides"}``:
        ``input_lag`` [samples] is the lag
        of the largest cross-correlation of the residual with the joint's input (positive:
        the input leads) and ``input_peak`` its value, None where it lies within the band;
        ``where`` the segments holding the largest shares of the squared output residual;
        ``friction_never_slides`` a sentence per joint whose fitted friction never leaves
        its presliding regime over the log (``_never_slides``), also in the summary.
    """
    from jaxflex.fit.residual_analysis import analyse_residual  # scipy.stats: loaded here

    ratio = cost / noise_cost if noise_cost > 0 else math.inf
    adequate = bool(cost <= accept_cost * noise_cost)
    sim = np.asarray(simulated_outputs(prob, y), float)
    meas = np.asarray(prob.segs.y_meas, float)
    active = (np.ones(sim.shape[0], bool) if prob.segs.active is None
              else np.asarray(prob.segs.active, bool))
    sim, meas = sim[active], meas[active]
    r = sim - meas  # (S, L, n_out)
    tau = np.asarray(prob.segs.tau, float)[active]
    if tau.ndim == 4:  # subsystem models carry the measured motion beside the torque
        tau = tau[:, :, 0, :]
    n = tau.shape[-1]
    channels = {}
    for c in range(r.shape[-1]):
        name, j = prob.outputs[c // n], c % n
        label = name if n == 1 else f"{name}[{j}]"
        e = r[:, :, c].reshape(-1)
        entry: dict[str, Any] = {"rms": float(np.sqrt(np.mean(e ** 2)))}
        try:
            a = analyse_residual(e, tau[:, :, j].reshape(-1))
        except ValueError:
            channels[label] = entry
            continue
        peak = int(np.argmax(np.abs(a.cross_correlation)))
        inside = abs(a.cross_correlation[peak]) <= a.cross_band
        entry.update(white=a.white, p_white=a.p_white, correlation_time=a.correlation_time,
                     input_lag=None if inside else int(a.cross_lags[peak]),
                     input_peak=None if inside else float(a.cross_correlation[peak]))
        channels[label] = entry
    per_seg = np.sum(r ** 2, axis=(1, 2))
    total = float(np.sum(per_seg)) or 1.0
    t0 = np.asarray(prob.segs.t0, float)[active]
    span = prob.segs.length * prob.dt
    order = np.argsort(per_seg)[::-1][:WORST_SEGMENTS]
    where = [{"t0": float(t0[i]), "t1": float(t0[i] + span), "share": float(per_seg[i] / total)}
             for i in order]
    sticking = _never_slides(prob, y, meas)
    if adequate:
        summary = f"adequate: the noise explains the cost ({ratio:.3g} x what it gives)"
    else:
        colour = ", ".join(
            f"{k} {'white' if v.get('white') else 'coloured'}"
            + (f" (correlation time {v['correlation_time']:.3g} samples)"
               if v.get("correlation_time", 1) > 1.5 else "")
            for k, v in channels.items())
        seg = where[0] if where else None
        summary = (f"model-limited: cost {ratio:.3g} x what the noise gives; residual {colour}"
                   + (f"; largest share {100 * seg['share']:.0f}% in {seg['t0']:.3g}-"
                      f"{seg['t1']:.3g} s" if seg else ""))
    if sticking:
        summary += "; " + "; ".join(sticking)
    return {"verdict": "adequate" if adequate else "model-limited", "cost_over_noise": ratio,
            "channels": channels, "where": where, "summary": summary,
            "friction_never_slides": sticking}


def _never_slides(prob: Problem, y: Any, meas: np.ndarray) -> list[str]:
    """One sentence per joint whose fitted LuGre friction never leaves its presliding
    regime over the log (eq. 5: the bristle deflection reaches Fs / sigma0 [rad] before the
    friction slides): a presliding range wider than the measured link travel means the
    bristles act as a spring to ground, the fit's stand-in for an effect the model lacks."""
    base = prob.space.base
    if base.friction is None or "q1" not in prob.outputs:
        return []
    phys = prob.space.physical_values(prob.split(y)[0])
    fs = np.broadcast_to(np.asarray(phys.get("Fs", base.friction.Fs), float), (base.n,))
    s0 = np.broadcast_to(np.asarray(phys.get("sigma0", base.friction.sigma0), float), (base.n,))
    c0 = prob.outputs.index("q1") * base.n
    out = []
    for j in range(base.n):
        travel = float(np.ptp(meas[:, :, c0 + j]))
        reach = float(fs[j] / s0[j])
        if reach > travel:
            who = "" if base.n == 1 else f"joint {j}: "
            out.append(f"{who}the fitted friction never slides (presliding range Fs / sigma0 = "
                       f"{reach:.3g} rad > the log's travel {travel:.3g} rad): its bristles act "
                       "as a spring to ground, a stand-in for an effect the model lacks (a "
                       "torque offset, gravity, a spring)")
    return out
