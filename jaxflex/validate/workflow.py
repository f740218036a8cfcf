"""``validate``: every validation number of a parameter set on one log, each beside its noise
floor (the package docstring).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.validate.closed_loop import closed_loop_errors, rel_error_pct
from jaxflex.validate.replay import (
    replay_residual_analysis,
    segment_gap,
    segment_gap_floor,
    torque_noise_floor,
    torque_prediction,
)


def validate(
    params: Params, log: Log, *, kind: str = "flexible", segment: int | None = None,
    substeps: int = 4, disturbance: np.ndarray | None = None,
) -> dict[str, Any]:
    """All validation numbers of ``params`` on one ``log`` (module docstring), each beside
    what the log's noise alone gives a perfect model: ``gap`` and ``gap_noise``
    (``segment_gap_floor``), ``torque_pct`` and ``torque_noise_pct`` (``torque_noise_floor``;
    ``noise_std`` the noise found on each column), and ``closed_loop`` (dict of
    position/velocity/torque errors [%] with their ``noise_floor``,
    ``closed_loop_noise_floor``; or None), and ``residual_analysis``
    (``replay_residual_analysis``). ``series`` holds the measured and predicted
    signals for figures."""
    tau_hat = torque_prediction(params, log, kind=kind)
    floor = torque_noise_floor(params, log, kind=kind, tau_hat=tau_hat)
    out: dict[str, Any] = {
        "model": kind, "samples": log.N, "dt": log.dt,
        "gap": segment_gap(params, log, kind=kind, length=segment, substeps=substeps),
        "gap_noise": segment_gap_floor(params, log, kind=kind, length=segment,
                                       substeps=substeps),
        "torque_pct": rel_error_pct(log.tau, tau_hat),
        "torque_noise_pct": floor["pct"], "noise_std": floor["std"],
        "residual_analysis": replay_residual_analysis(params, log, kind=kind, length=segment,
                                                      substeps=substeps),
    }
    loop_kind = {"rotor": "rigid", "link": "flexible"}.get(kind, kind)
    cl = closed_loop_errors(params, log, kind=loop_kind,
                            disturbance=disturbance, substeps=max(2, substeps // 2))
    out["closed_loop"] = None if cl is None else {k: v for k, v in cl.items() if k != "series"}
    out["series"] = {"t": log.t, "tau": log.tau, "tau_hat": tau_hat, "q": log.q1,
                     "closed_loop": None if cl is None else cl["series"]}
    return out
