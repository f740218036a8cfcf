"""Identification of the rotor subsystem (model kind "rotor") by equation error: the torque
the rotor line needs for the measured motion (``jaxflex.validate.predicted_torque``, the one
inverse dynamics) against the logged torque, fitted with the engine
(``jaxflex.fit.least_squares``, ``jaxflex.fit.covariance``).

The rotor kind takes both encoders as measured: the link angle q1 is its input and the motor
angle q2 its output, so with the torque logged too the rotor line

    J q2'' + K (q2 - q1c) + Fm tanh(q2'/w) + bm q2' - c = tau,
    q1c = (1 + scale) (q1 + skew q1' + off)

is checked sample by sample, with no replay. The spring's deflection then carries whatever
the link side does (gravity, a counterbalance, the other axes of an arm). In this line
``-K skew q1'`` and ``bm q2'`` are collinear (q1' ~ q2'), and so are ``-K off`` and ``c``:
fitting all four leaves the information matrix singular. So the fit has two steps
(``studies/kuka_flexible.py`` measures them on the KUKA KR300):

1. *Skew* (``skew_fit``): the same equation divided by K, i.e. the residual in the
   deflection (where the encoder noise enters), with bm = c = 0 and J, K, Fm, the skew and
   the encoder offset free. The skew is then the velocity coefficient of the deflection: the
   encoder time skew if the viscous friction passes through the spring.
2. *Torque* (``torque_fit``): the torque residual with the skew and the encoder offset from
   step 1 held, and the names of ``ROTOR_FREE`` (J, K, Fm, bm, c and the encoder scale)
   free; bm then means bm - K (true skew - estimated skew).

Standard errors: the engine's covariance with the residual variance inflated by the
residual's integrated autocorrelation time (``integrated_autocorrelation``): a model's
mismatch on a real log is correlated in time, and white-residual errors would be too small.

The link encoder's offset and scale against the motor encoder are sensor nuisances that a
recording sets anew (``PER_LOG``): ``refit_per_log`` estimates them on another log, every
other parameter held, before the model's torque is compared there.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.fit import CostBound, ParamSpace, constraint_of, covariance, least_squares, set_values
from jaxflex.fit.inverse import Motion, measured_motion
from jaxflex.identify.start import ROTOR_EFFECTS, StartError, start_from_data
from jaxflex.io.logs import Log
from jaxflex.io.params import Params
from jaxflex.core.validation import requires_float64

#: The names the torque step fits by default (module docstring, step 2).
ROTOR_FREE: tuple[str, ...] = ("J", "K", "motor_friction.Fm", "motor_friction.bm",
                               "torque_offset.offset", "encoder_scale.scale")
#: The names the skew step fits (module docstring, step 1), with bm and c held at 0.
SKEW_FREE: tuple[str, ...] = ("J", "K", "motor_friction.Fm", "encoder_skew.skew",
                              "encoder_skew.offset")
#: Sensor nuisances a recording sets anew: the link encoder's offset and scale against the
#: motor encoder (the KUKA KR300's offset changes between recordings).
PER_LOG: tuple[str, ...] = ("encoder_skew.offset", "encoder_scale.scale")
#: A fitted parameter above this relative standard error is marked not identified (it keeps
#: its fitted value), as ``jaxflex.identify.identify`` marks them.
REL_STDERR_LIMIT: float = 0.5
#: The solver's statistical stop: the step that remains is below sqrt(DECREMENT_TOL)
#: standard errors of white residuals (``jaxflex.fit.least_squares``, ``decrement_tol``).
DECREMENT_TOL: float = 1e-2


class TorqueData(eqx.Module):
    """Data of an equation-error fit: the parameter space, the measured motion
    (``jaxflex.fit.inverse.measured_motion``) and each joint's residual scale (n,) (torque [N m] or
    deflection [rad]: every joint weighs alike); ``deflection`` selects the residual (module
    docstring)."""

    space: ParamSpace
    motion: Motion
    scale: jax.Array
    deflection: bool = eqx.field(static=True, default=False)


def torque_residuals(theta: dict, data: TorqueData) -> jax.Array:
    """(tau_hat - tau) / scale over the samples and joints (sample-major), or in the
    deflection domain (``data.deflection``) (tau_hat - tau) / (K scale)."""
    from jaxflex.validate import predicted_torque

    plant = data.space.plant(theta)
    r = predicted_torque(plant, "rotor", data.motion) - data.motion.tau
    if data.deflection:
        return (r / (plant.K * data.scale)).reshape(-1)
    return (r / data.scale).reshape(-1)


def integrated_autocorrelation(r: np.ndarray, max_lag: int = 1000) -> float:
    """Integrated autocorrelation time [samples] of a residual series (N,) by Geyer's initial
    positive sequence on pairs: 1 + 2 sum rho_k = -1 + 2 sum_m (rho_2m + rho_2m+1), summed
    while the pair sums stay positive (pairs keep a ripple that alternates in sign from lag to
    lag from stopping the sum while a slow model error is still correlated); at least 1."""
    r = np.asarray(r, float) - np.mean(r)
    n = r.size
    f = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[: min(max_lag, n - 1) + 1]
    if acf[0] <= 0:
        return 1.0
    rho = acf / acf[0]
    tau = -1.0
    for m in range(rho.size // 2):
        g = rho[2 * m] + rho[2 * m + 1]
        if g <= 0:
            break
        tau += 2.0 * g
    return float(max(tau, 1.0))


@dataclasses.dataclass
class TorqueFit:
    """One equation-error fit (``fit_equation_error``).

    params: the fitted parameters; stderr: name -> (n,) standard errors [physical units],
    inflated by the residual's autocorrelation time ``tau_int`` [samples]; converged: the
    solver's tolerance met and no parameter at its constraint's boundary; at_bound: those that
    are; steps, cost (0.5 ||r||^2 of the scaled residual), reason, seconds; rank and n_free of
    the Jacobian.
    """

    params: Params
    stderr: dict[str, list[float]]
    converged: bool
    at_bound: list[str]
    steps: int
    cost: float
    reason: str
    seconds: float
    tau_int: float
    rank: int
    n_free: int


def _at_bound(space: ParamSpace, phys: Mapping[str, np.ndarray],
              start: Mapping[str, np.ndarray]) -> list[str]:
    """The parameters that ran to their constraint's boundary: a positive one below 1e-100
    of its start or above 1e100 times it (exp(theta) under- or overflowing), a bounded one
    within 1e-6 of its range from an end."""
    out = []
    for k, (kind, lo, hi) in zip(space.names, space.transforms):
        v, v0 = np.asarray(phys[k], float), np.asarray(start[k], float)
        if constraint_of(k).startswith("positive") and np.any(
                ~((v > 1e-100 * v0) & (v < 1e100 * v0))):
            out.append(k)
        elif kind == "bounded" and np.any(np.minimum(v - lo, hi - v) < 1e-6 * (hi - lo)):
            out.append(k)
    return out


@requires_float64
def fit_equation_error(params: Params, log: Log, free: Sequence[str], *,
                       deflection: bool = False, max_steps: int = 500,
                       scaling: str = "identity") -> TorqueFit:
    """Fit ``free`` of the rotor kind's ``params`` to ``log`` by equation error (module
    docstring).

    Arguments:
        params: the start, with every effect that ``free`` names.
        log: the log (tau, q1, q2).
        free: the fitted names (``jaxflex.fit.ParamSpace``).
        deflection: the residual in the deflection [rad] instead of the torque [N m].
        max_steps: the solver's iteration cap.
        scaling: the solver's damping ("identity" or "marquardt").

    Returns:
        A ``TorqueFit``.

    Raises:
        ValueError: a log without q2 or tau, or a name ``params`` does not hold.
    """
    if log.tau is None or log.q2 is None:
        raise ValueError("identify: the rotor model needs the columns tau, q1 and q2")
    motion = jax.tree.map(jnp.asarray, measured_motion(log, kind="rotor"))
    space = ParamSpace.build(params.to_plant(), list(free))
    x = (np.asarray(log.q2, float) - np.asarray(log.q1, float) if deflection
         else np.asarray(log.tau, float)).reshape(log.N, log.n)
    scale = np.std(x, axis=0)
    if not np.all(scale > 0):
        raise ValueError(f"identify: a joint's {'deflection' if deflection else 'torque'} is "
                         "constant in the log; the rotor line cannot be fitted to it")
    data = TorqueData(space=space, motion=motion, scale=jnp.asarray(scale),
                      deflection=deflection)
    m = int(np.size(log.tau))
    sol = least_squares(data, space.theta0(), fn=torque_residuals, max_steps=max_steps,
                        scaling=scaling, decrement_tol=CostBound(DECREMENT_TOL * 2.0 / m))
    r = np.asarray(torque_residuals(sol.y, data)).reshape(log.N, log.n)
    # the joints' residuals share one variance inflation: the longest correlation time
    tau_int = max(integrated_autocorrelation(r[:, j]) for j in range(log.n))
    cov = covariance(data, sol.y, fn=torque_residuals, inflation=tau_int)
    phys = {k: np.asarray(v, float) for k, v in space.physical(sol.y).items()}
    start = {k: np.asarray(v, float) for k, v in space.physical(space.theta0()).items()}
    at_bound = _at_bound(space, phys, start)
    # a positive parameter that ran to its boundary stays representable; the run-off is
    # reported in ``at_bound`` and ``converged``
    phys = {k: (np.clip(v, np.finfo(float).tiny, np.finfo(float).max)
                if constraint_of(k).startswith("positive") else v) for k, v in phys.items()}
    se = {k: np.asarray(v, float).tolist() for k, v in cov["stderr"].items() if k in phys}
    return TorqueFit(params=set_values(params, phys), stderr=se,
                     converged=bool(sol.converged and not at_bound), at_bound=at_bound,
                     steps=int(sol.steps), cost=float(sol.cost), reason=str(sol.reason),
                     seconds=float(sol.seconds), tau_int=tau_int, rank=int(cov["rank"]),
                     n_free=int(cov["n_free"]))


def skew_fit(params: Params, log: Log, max_steps: int = 500) -> TorqueFit:
    """Step 1 (module docstring): the deflection-domain fit of ``SKEW_FREE`` with bm = c = 0
    (the skew [s] and encoder offset [rad] it gives are held in step 2)."""
    n = params.n
    p0 = set_values(params, {"motor_friction.bm": np.zeros(n), "torque_offset.offset":
                             np.zeros(n)})
    return fit_equation_error(p0, log, SKEW_FREE, deflection=True, max_steps=max_steps,
                              scaling="marquardt")


@dataclasses.dataclass
class RotorResult:
    """Outcome of ``identify_rotor``: the parameters (standard errors under
    ``extra["stderr"]``, the record under ``extra["identification"]``), the two steps' fits,
    the torque error on the log [%] and the wall time [s]."""

    params: Params
    skew: TorqueFit | None
    fit: TorqueFit
    torque_pct: float
    wall_s: float

    @property
    def converged(self) -> bool:
        """Whether both steps converged (``TorqueFit.converged``)."""
        return self.fit.converged and (self.skew is None or self.skew.converged)

    @property
    def reason(self) -> str:
        """How the steps ended, in words."""
        return self.params.extra["identification"]["reason"]

    def table(self) -> str:
        """A short text table: name, value, standard error, relative standard error, and a
        line on how the fit ended."""
        rows = [f"{'param':<24}{'value':>14}{'stderr':>12}{'rel':>12}"]
        for name, se in self.fit.stderr.items():
            vals = np.atleast_1d(_value(self.params, name))
            for j, v in enumerate(vals):
                label = name if len(vals) == 1 else f"{name}[{j}]"
                rel = abs(se[j]) / max(abs(float(v)), 1e-300)
                rel_s = f"{100 * rel:.2f}%" if rel <= 10 else "> 1e3 %"
                rows.append(f"{label:<24}{float(v):>14.6g}{se[j]:>12.3g}{rel_s:>12}")
        if self.skew is not None:
            for name in ("encoder_skew.skew", "encoder_skew.offset"):
                v = np.atleast_1d(_value(self.params, name))
                rows.append(f"{name:<24}" + "".join(f"{float(x):>14.6g}" for x in v)
                            + f"{'(step 1)':>12}")
        rows.append(f"torque error on the log {self.torque_pct:.3g}%; {self.fit.steps} steps "
                    f"(+ {0 if self.skew is None else self.skew.steps} in step 1); converged: "
                    f"{self.converged} ({self.reason}); standard errors inflated by the "
                    f"residual's correlation time ({self.fit.tau_int:.3g} samples)")
        return "\n".join(rows)


def _value(params: Params, name: str) -> np.ndarray:
    from jaxflex.fit import get_value

    return get_value(params, name)


def _record(fit: TorqueFit, params: Params, free: Sequence[str], skew: TorqueFit | None,
            torque_pct: float) -> dict[str, Any]:
    """The parameter file's ``identification`` record of a rotor fit."""
    ends = [("step 1 (skew)", skew), ("step 2 (torque)", fit)] if skew else [("torque", fit)]
    reason = "; ".join(f"{w}: {'converged' if f.converged else 'not converged'} ({f.reason}"
                       + (f"; at the constraint's boundary: {f.at_bound}" if f.at_bound else "")
                       + ")" for w, f in ends)
    marks = {k: _mark(k, fit, params) for k in free}
    rec: dict[str, Any] = {
        "start": {"kind": "rotor", "kind_reason": "the rotor subsystem's identification"},
        "method": "equation error: the torque the rotor line needs for the "
        "measured motion against the logged torque (jaxflex.identify.torque)",
        "free": list(free), "steps": fit.steps, "cost": fit.cost,
        "converged": bool(fit.converged and (skew is None or skew.converged)),
        "reason": reason, "torque_pct": torque_pct, "parameters": marks,
        "jacobian_rank": fit.rank, "unknowns": fit.n_free,
        "stderr_kind": f"white residuals inflated by the residual's integrated autocorrelation "
                       f"time ({fit.tau_int:.3g} samples)",
        "per_log": [k for k in PER_LOG if _has(params, k)],
    }
    if skew is not None:
        rec["skew_step"] = {
            "free": list(SKEW_FREE), "converged": skew.converged, "steps": skew.steps,
            "skew_s": [float(x) for x in _value(skew.params, "encoder_skew.skew")],
            "skew_stderr": skew.stderr.get("encoder_skew.skew"),
            "offset_rad": [float(x) for x in _value(skew.params, "encoder_skew.offset")],
            "K_deflection": [float(x) for x in _value(skew.params, "K")],
            "K_deflection_stderr": skew.stderr.get("K")}
    return rec


def _mark(name: str, fit: TorqueFit, params: Params) -> dict[str, Any]:
    """A fitted name's mark in the file: identified, or not with the reason (at its
    constraint's boundary, in a null direction, or a relative standard error above
    ``REL_STDERR_LIMIT``); every name keeps its fitted value."""
    se = np.asarray(fit.stderr.get(name, [math.nan]), float)
    rel = float(np.max(np.abs(se) / np.maximum(np.abs(_value(params, name)), 1e-300)))
    if name in fit.at_bound:
        return {"identified": False, "reason": "at its constraint's boundary"}
    if not math.isfinite(rel):
        return {"identified": False, "reason": "numerically null direction of the Jacobian"}
    if rel > REL_STDERR_LIMIT:
        return {"identified": False, "reason": f"relative standard error {100 * rel:.3g}% > "
                f"{100 * REL_STDERR_LIMIT:g}% (residuals' correlation time included)"}
    return {"identified": True}


def _has(params: Params, name: str) -> bool:
    eff, dot, par = name.partition(".")
    return not dot or (eff in params.effects and par in params.effects[eff])


@requires_float64
def identify_rotor(log: Log, init: Params | None = None, free: Sequence[str] | None = None,
                   *, pin: Mapping[str, float | Sequence[float]] | None = None,
                   max_steps: int = 500) -> RotorResult:
    """Identify the rotor subsystem from ``log`` by equation error (module docstring).

    Arguments:
        log: the log (tau, q1, q2; docs/spec.md section 6).
        init: the start; None: the log's inverse dynamics (``start_from_data(log,
            "rotor")``, with the ``ROTOR_EFFECTS``).
        free: the names fitted in the torque step; None: ``ROTOR_FREE``. The skew step runs
            when the start has the ``encoder_skew`` effect and neither its skew nor its
            offset is in ``free`` or ``pin``.
        pin: names set to these values on the start and not fitted (a value or one per
            joint).
        max_steps: the solver's iteration cap per step.

    Returns:
        A ``RotorResult``; its ``params.extra["identification"]`` records the method, both
        steps, the torque error on ``log`` [%] and the per-log sensor nuisances
        (``PER_LOG``) that validation re-estimates on another log.

    Raises:
        ValueError: a log without tau or q2, no physical start from the data (``init``
            None), or a name the start lacks.
    """
    from jaxflex.validate import rel_error_pct, torque_prediction

    t0 = time.perf_counter()
    if init is None:
        try:
            init = start_from_data(log, "rotor").params
        except StartError as e:
            raise ValueError(f"identify: no start from the data: {e}; give a start "
                             "(--params)") from None
    pin = dict(pin or {})
    if pin:
        init = set_values(init, {k: np.broadcast_to(np.asarray(v, float), (init.n,))
                                 for k, v in pin.items()})
    free = [k for k in (ROTOR_FREE if free is None else free) if k not in pin]
    missing = [k for k in free if not _has(init, k)]
    if missing:
        raise ValueError(f"identify: the start has no {missing} (the rotor kind's effects: "
                         f"{list(ROTOR_EFFECTS)})")
    skew = None
    held = set(free) | set(pin)
    if ("encoder_skew" in init.effects and "motor_friction" in init.effects
            and not held & {"encoder_skew.skew", "encoder_skew.offset"}):
        skew = skew_fit(init, log, max_steps)
        init = set_values(init, {k: _value(skew.params, k)
                                 for k in ("encoder_skew.skew", "encoder_skew.offset")})
    fit = fit_equation_error(init, log, free, max_steps=max_steps)
    pct = rel_error_pct(log.tau, torque_prediction(fit.params, log, kind="rotor"))
    params = fit.params
    params.extra = dict(params.extra)
    params.extra["stderr"] = dict(fit.stderr)
    params.extra["identification"] = _record(fit, params, free, skew, pct)
    return RotorResult(params=params, skew=skew, fit=fit, torque_pct=pct,
                       wall_s=time.perf_counter() - t0)


@requires_float64
def refit_per_log(params: Params, log: Log, names: Sequence[str] | None = None,
                  max_steps: int = 200) -> tuple[Params, TorqueFit | None]:
    """``params`` with the per-log sensor nuisances re-estimated on ``log`` by equation error
    (every other parameter held).

    Arguments:
        params: a rotor-kind parameter set.
        log: another log of the same axis.
        names: the nuisances; None: the file's ``identification.per_log`` (``PER_LOG`` where
            it has none), those ``params`` holds.
        max_steps: the solver's iteration cap.

    Returns:
        ``(params, fit)``: the refitted parameters and the fit (None, and ``params``
        unchanged, when there is nothing to refit).
    """
    if names is None:
        ident = params.extra.get("identification", {})
        names = ident.get("per_log", PER_LOG) if isinstance(ident, dict) else PER_LOG
    names = [k for k in names if _has(params, k)]
    if not names:
        return params, None
    fit = fit_equation_error(params, log, names, max_steps=max_steps)
    return fit.params, fit
