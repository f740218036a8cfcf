"""Robust gain tuning over a batch of plausible plants, certified on the whole box.

A spread (``jaxflex.sweep.spec``: hand-written distributions and/or an identification's own
posterior, ``"identified"``) says which plants the data allow. ``tune_robust`` chooses the
cascade gains (Table 3) that minimise a *risk measure* of the tracking cost over a batch of
plants drawn from it, subject to the N2 certificate (eq. 29-31) on

- every training plant: lambda_min(N2) >= margin for |q1'| <= v on each, and
- the whole parameter box the spread spans (``spread_box``): the vertex bound of
  ``jaxflex.core.certificate.box_lambda_min`` (exact in the coordinates N2 is affine in), so the
  certificate holds at every plant of the box, drawn or not.

How it works:

- One ``vmap``ped, differentiable pass: each plant of the batch runs the sampled-data loop
  (``simulate_sampled``) with the controller configuration that will run (the spread's q2d
  method, sensing, torque limit, sample time, trajectory); the per-plant cost is the mean
  squared link error plus ``torque_weight`` x mean squared torque, a plant whose run is lost
  (``metrics.diverged``) costs a constant (the lost band squared) and adds no gradient;
  the risk measure (mean, quantile or CVaR, ``RiskMeasure``) of the per-plant costs is the
  objective, log-scaled as in ``jaxflex.tune``. Quantisers pass gradients straight through.
- Samples: *fixed* by default (the same batch every step: sample-average approximation; the
  objective is a deterministic function of the gains, so Adam's steps and the pull-back into
  the certified set compare like with like, and common random numbers keep the noise of the
  batch out of the comparison of candidates); ``resample=True`` draws a fresh batch each
  step (a stochastic gradient: less over-fit to one batch, noisier steps). Either way the
  result is judged on held-out plants (``evaluate_batch``), never on the training batch.
- The search is ``jaxflex.tune.adam_search`` (the same Adam, multi-start and pull-back);
  when the initial gains are not certified on the box, a first phase ascends the
  certificate's lower bound until it holds (no simulation needed).
- Final check: the best candidate must be certified on the box and every training plant up
  to max(v_task, fastest link speed over the batch); otherwise the next best; if none passes
  the result says ``certified = False`` and ``save`` refuses it.

What the certificate covers: N2 is the paper's condition for the observer matched to the
plant; a plant in the box with the controller's *nominal* observer adds mismatch terms that
eq. 29 does not contain. "Certified on the box" means: for every plant of the box, these
gains satisfy the paper's condition. Units as in ``jaxflex.tune``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.special
from jaxtyping import Array, Float

from jaxflex.core.certificate import (
    DEFAULT_EPS,
    N2_PARAMETERS,
    CertificateResult,
    ParameterBox,
    box_lambda_min_curve,
    certify_box,
    lambda_min_curve,
)
from jaxflex.core.controller import CascadeGains
from jaxflex.core.sensing import StraightThrough
from jaxflex.sim.simulate import lost_band, simulate_sampled
from jaxflex.sweep.engine import is_noisy, run_sweep, sample_models
from jaxflex.sweep.spec import SweepSpec
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.trajectory import Trajectory
from jaxflex.io.presets import trajectory_preset
from jaxflex.tune import (StartRecord, adam_search, ascend_feasibility, gains_of,
                          certify_speed, reference_speed)
from jaxflex.core.validation import requires_float64
from jaxflex.io.progress import Progress

RISKS: tuple[str, ...] = ("mean", "quantile", "cvar")


@dataclasses.dataclass(frozen=True)
class RiskMeasure:
    """A risk measure of a batch of per-plant costs x_1..x_N [rad^2].

    "mean": the average; "quantile": the alpha-quantile (linear interpolation between order
    statistics, as ``numpy.quantile``); "cvar": the conditional value at risk, the mean of the
    empirical quantile function over [alpha, 1] (the worst (1 - alpha) fraction, the sample at
    the boundary weighted by the part of it inside; equal to Rockafellar-Uryasev's
    min_t t + E[(x - t)+] / (1 - alpha)). Both are fixed weightings of the sorted costs, so
    their gradients exist almost everywhere (not at ties of order statistics).
    """

    kind: str = "cvar"
    alpha: float = 0.9

    def __post_init__(self) -> None:
        if self.kind not in RISKS:
            raise ValueError(f"risk: kind must be one of {RISKS}, got {self.kind!r}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"risk: alpha must be in (0, 1), got {self.alpha}")

    @classmethod
    def parse(cls, text: str) -> RiskMeasure:
        """From "mean", "quantile:0.95" or "cvar:0.9" (alpha defaults to 0.9)."""
        kind, _, a = str(text).partition(":")
        try:
            alpha = float(a) if a else 0.9
        except ValueError:
            raise ValueError(f"risk: {text!r}: alpha must be a number, e.g. 'cvar:0.9'") from None
        return cls(kind, alpha)

    def __call__(self, x: Float[Array, " N"]) -> Float[Array, ""]:
        """The risk of the costs ``x`` (N,)."""
        if self.kind == "mean":
            return jnp.mean(x)
        xs = jnp.sort(x)
        N = x.shape[0]
        if self.kind == "quantile":
            pos = self.alpha * (N - 1)
            i = int(math.floor(pos))
            f = pos - i
            return xs[i] if i + 1 >= N else (1 - f) * xs[i] + f * xs[i + 1]
        # the empirical quantile function is xs[i] on [i/N, (i+1)/N): CVaR is its mean over
        # [alpha, 1], a fixed weighting of the order statistics
        i = np.arange(N)
        w = np.clip((i + 1) / N - self.alpha, 0.0, 1.0 / N) / (1 - self.alpha)
        return jnp.sum(jnp.asarray(w, xs.dtype) * xs)

    def label(self) -> str:
        """"mean", "quantile:0.95", ... (the ``parse`` form)."""
        return "mean" if self.kind == "mean" else f"{self.kind}:{self.alpha:g}"


@dataclasses.dataclass(frozen=True)
class RobustTask:
    """What the gains are tuned for: the spread ``spec`` (plants, trajectory, horizon,
    controller configuration: q2d method, sensing, torque limit, dt, substeps), the ``risk``
    measure, ``plants`` in the training batch, ``resample`` (fresh batch each step), the
    ``torque_weight`` [rad^2/(N m)^2], ``velocity_factor`` (certify up to this x the fastest
    reference speed) and the ``confidence`` of the box for distributions without bounds."""

    spec: SweepSpec
    risk: RiskMeasure = RiskMeasure()
    plants: int = 64
    resample: bool = False
    torque_weight: float = 1e-6
    velocity_factor: float = 1.5
    confidence: float = 0.95

    def __post_init__(self) -> None:
        if self.plants < 2:
            raise ValueError(f"RobustTask: plants must be >= 2, got {self.plants}")
        if self.torque_weight < 0:
            raise ValueError(f"RobustTask: torque_weight must be >= 0, got {self.torque_weight}")
        if not self.velocity_factor >= 1:
            raise ValueError(f"RobustTask: velocity_factor must be >= 1, got {self.velocity_factor}")
        if not 0 < self.confidence < 1:
            raise ValueError(f"RobustTask: confidence must be in (0, 1), got {self.confidence}")
        if self.spec.nominal.friction is None:
            raise ValueError("RobustTask: the nominal parameters need LuGre friction")

    @property
    def trajectory(self) -> Trajectory:
        """The reference of the spread."""
        return trajectory_preset(self.spec.trajectory)

    def reference_speed(self) -> float:
        """Fastest reference link speed max |q1d'| [rad/s] over the horizon."""
        return reference_speed((self.trajectory,), self.spec.t_final, self.spec.dt)

    def certify_speed(self) -> float:
        """Speed [rad/s] up to which the gains must be certified."""
        return certify_speed((self.trajectory,), self.spec.t_final, self.spec.dt,
                             self.velocity_factor)

    def lost_cost(self) -> float:
        """Cost [rad^2] of a lost run: the mean squared lost band of the reference."""
        ts = jnp.arange(int(round(self.spec.t_final / self.spec.dt))) * self.spec.dt
        band = lost_band(jax.vmap(self.trajectory.position)(ts))
        return float(jnp.mean(band**2))


def spread_box(spec: SweepSpec, confidence: float = 0.95) -> tuple[ParameterBox, dict[str, str]]:
    """The parameter box of N2's plant quantities (``N2_PARAMETERS``) that ``spec`` spans, and
    per name how its bounds were taken: a distribution's support where bounded (uniform,
    loguniform, truncated normal, fixed), its central ``confidence`` interval where not
    (normal, lognormal), the posterior's ``confidence`` box (``Posterior.box``) for
    identified parameters, the nominal value for names not sampled."""
    n = spec.n
    nom = spec.nominal
    vals = {"K": nom.plant["K"], **{k: nom.friction[k] for k in N2_PARAMETERS[1:]}}
    lo = {k: np.array(np.broadcast_to(np.asarray(v, float), (n,))) for k, v in vals.items()}
    hi = {k: v.copy() for k, v in lo.items()}
    how = {k: "nominal" for k in N2_PARAMETERS}
    post_lo, post_hi = (spec.posterior.box(confidence) if spec.posterior is not None
                        else ({}, {}))
    z = scipy.special.ndtri(0.5 + confidence / 2)
    for c in spec.columns:
        name = c.name.split(".", 1)[1]
        if name not in N2_PARAMETERS or c.name.split(".")[0] not in ("plant", "friction"):
            continue
        d = c.dist
        if d.kind == "posterior":
            a, b = post_lo[name][c.joint], post_hi[name][c.joint]
            how[name] = f"posterior {confidence:g} box"
        elif d.kind == "lognormal":
            a, b = math.exp(d.a - z * d.b), math.exp(d.a + z * d.b)
            how[name] = f"lognormal central {confidence:g}"
        elif d.kind == "normal" and not (math.isfinite(d.low) and math.isfinite(d.high)):
            a = max(d.a - z * d.b, d.low)
            b = min(d.a + z * d.b, d.high)
            how[name] = f"normal central {confidence:g}"
        else:
            a, b = d.support()
            how[name] = f"{d.kind} support"
        lo[name][c.joint], hi[name][c.joint] = a, b
    return ParameterBox(lo, hi), how


def sample_batch(spec: SweepSpec, indices: Array) -> tuple[Any, ...]:
    """Stacked (theta, plant, controller, sensing, noise key, fs_raised) of the samples
    ``indices`` of ``spec`` (``jaxflex.sweep.engine.sample_models``, vmapped)."""
    key = spec.cache_key()
    if key not in _BATCH_FNS:
        _BATCH_FNS[key] = jax.jit(jax.vmap(lambda i: sample_models(spec, i)))
    return _BATCH_FNS[key](jnp.asarray(indices))


_BATCH_FNS: dict[str, Callable] = {}


def _with_gains(ctrl, gains):
    return eqx.tree_at(lambda c: c.gains, ctrl, gains)


@persistent_jit
def _risk_and_grad(theta, leak, batch, settings):
    """(log risk, (risk, aux)) and its gradient in theta = log(gains) over the batch."""
    t_final, substeps, noisy, tw, risk, lost = settings
    _, plant, ctrl, sensing, keys, _ = batch

    def per_plant(gains, p, c, s, k):
        m = simulate_sampled(p, _with_gains(c, gains), t_final, substeps=substeps,
                             sensing=StraightThrough(s), key=k if noisy else None,
                             save=False, unroll_substeps=False).metrics  # under a gradient
        cost = jnp.mean(m.rms_error**2) + tw * jnp.mean(m.tau_rms**2)
        bad = m.diverged | ~jnp.isfinite(cost)
        return jnp.where(bad, lost, cost), bad, jnp.max(m.rms_error)

    def objective(th):
        costs, bad, rms = jax.vmap(per_plant, in_axes=(None, 0, 0, 0, 0))(
            gains_of(th, leak), plant, ctrl, sensing, keys)
        r = risk(costs)
        return jnp.log(r), (r, {"rms_error": rms, "costs": costs, "lost": bad})

    return jax.value_and_grad(objective, has_aux=True)(theta)


@persistent_jit
def _sample_lambda_min(gains, plants, vgrid, eps):
    """lambda_min(N2) per plant of the batch over the speed grid (B, V)."""
    return jax.vmap(lambda p: lambda_min_curve(p, gains, vgrid, eps))(plants)


@persistent_jit
def _box_min(gains, box, vgrid, eps):
    return jnp.min(box_lambda_min_curve(box, gains, vgrid, eps))


@persistent_jit
def _max_speed(gains, batch, t_final, substeps, noisy):
    """Fastest link speed max |q1'| [rad/s] per plant of the batch (inf when lost)."""
    _, plant, ctrl, sensing, keys, _ = batch

    def one(p, c, s, k):
        r = simulate_sampled(p, _with_gains(c, gains), t_final, substeps=substeps, sensing=s,
                             key=k if noisy else None, unroll_substeps=False)  # batched
        return jnp.where(r.metrics.diverged, jnp.inf, jnp.max(jnp.abs(r.dq1)))

    return jax.vmap(one)(plant, ctrl, sensing, keys)


@dataclasses.dataclass
class RobustResult:
    """Result of ``tune_robust``: the gains (``certified`` says whether they passed the final
    check; uncertified gains are refused by ``save``), the risk [rad^2] on the training batch,
    the initial gains and their risk, the box and how its bounds were taken, the certificate on
    the box (``CertificateResult``, lambda_min its lower bound) up to ``v_check`` [rad/s], the
    smallest lambda_min over the training plants, starts, wall time [s], evaluations, the
    first phase's steps (0 when the initial gains were certified)."""

    gains: CascadeGains
    certified: bool
    risk: float
    initial_gains: CascadeGains
    initial_risk: float
    task: RobustTask
    box: ParameterBox
    box_how: dict[str, str]
    certificate: CertificateResult | None
    v_check: float
    margin: float
    sample_lambda_min: float
    starts: list[StartRecord]
    wall_time_s: float
    evaluations: int
    feasibility_steps: int = 0

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (the ``certificate`` record written with the gains)."""
        spec = self.task.spec
        return {
            "kind": "robust", "gains": self.gains.to_dict(), "certified": self.certified,
            "risk": self.task.risk.label(), "risk_value": self.risk,
            "initial_gains": self.initial_gains.to_dict(), "initial_risk": self.initial_risk,
            "plants": self.task.plants, "resample": self.task.resample, "seed": spec.seed,
            "margin": self.margin, "v_check": self.v_check,
            "certified_up_to": None if self.certificate is None
            else self.certificate.certified_up_to,
            "box": self.box.to_dict(), "box_bounds": self.box_how,
            "confidence": self.task.confidence,
            "sample_lambda_min": self.sample_lambda_min,
            "controller": {"trajectory": spec.trajectory, "q2d_method": spec.q2d_method,
                           "tau_max": spec.tau_max if math.isfinite(spec.tau_max) else "inf",
                           "dt": spec.dt, "sensing": spec.sensing,
                           "compensation": spec.compensation},
            "starts": [{"cost": s.costs, "rms_error": s.rms_errors, "constraint": s.constraint,
                        "cutbacks": s.cutbacks} for s in self.starts],
            "feasibility_steps": self.feasibility_steps,
            "wall_time_s": self.wall_time_s, "evaluations": self.evaluations,
        }


@requires_float64
def tune_robust(
    task: RobustTask, initial: CascadeGains | None = None, *, margin: float = 0.05,
    iterations: int = 20, starts: int = 2, learning_rate: float = 0.1, spread: float = 0.3,
    box: float = 100.0, seed: int = 0, eps: float = DEFAULT_EPS, grid: int = 33,
    feasibility_iterations: int = 300,
    progress: Progress | None = None,
) -> RobustResult:
    """Tune the cascade gains for every plant of ``task`` (module docstring).

    ``initial`` defaults to the spread's nominal gains. ``margin`` the required lambda_min(N2)
    [same units as N2] on the box and the training plants up to ``task.certify_speed()``;
    ``iterations``, ``starts``, ``learning_rate``, ``spread``, ``box`` as in
    ``jaxflex.tune.tune``; ``grid`` speeds of the constraint; ``feasibility_iterations`` the
    most Adam steps of the first phase. Raises ``ValueError`` on bad settings, or when the
    first phase finds no certified gains."""
    t0 = time.perf_counter()
    if iterations < 0 or starts < 1:
        raise ValueError(f"tune_robust: need iterations >= 0 and starts >= 1, got {iterations}, {starts}")
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"tune_robust: margin must be finite and >= 0, got {margin}")
    spec = task.spec
    initial = spec.nominal.to_gains() if initial is None else initial
    if initial.n != spec.n:
        raise ValueError(f"tune_robust: gains are for {initial.n} joint(s), the plants have {spec.n}")
    pbox, how = spread_box(spec, task.confidence)
    box_arr = pbox.arrays()
    v_task = task.certify_speed()
    vgrid = jnp.linspace(0.0, v_task, grid)
    noisy = is_noisy(spec)
    settings = (spec.t_final, spec.substeps, noisy, task.torque_weight, task.risk,
                task.lost_cost())
    batch0 = sample_batch(spec, jnp.arange(task.plants))
    leak = initial.leak
    plants0 = batch0[1]
    calls = [0]

    def value_and_grad(theta):
        batch = batch0
        if task.resample and calls[0] > 0:
            batch = sample_batch(spec, jnp.arange(task.plants) + calls[0] * task.plants)
        calls[0] += 1
        return _risk_and_grad(theta, leak, batch, settings)

    def constraint(theta) -> float:
        g = gains_of(jnp.asarray(theta), leak)
        return min(float(_box_min(g, box_arr, vgrid, eps)),
                   float(jnp.min(_sample_lambda_min(g, plants0, vgrid, eps)))) - margin

    def feasible(theta) -> tuple[bool, float]:
        c = constraint(theta)
        return c >= 0.0, c

    theta_init = jnp.log(initial.to_vector())
    lo, hi = theta_init - math.log(box), theta_init + math.log(box)
    theta_start, phase = ascend_feasibility(
        theta_init, lambda th: _box_min_and_grad(th, leak, box_arr, vgrid, eps), feasible, lo, hi,
        feasibility_iterations)
    ok, c = feasible(theta_start)
    if not ok:
        raise ValueError(
            f"tune_robust: no gains found that are certified on the box with margin {margin} "
            f"(after {phase} ascent steps the lower bound is {c + margin:.3g}); narrow "
            "the spread, lower the margin or the certified speed range")
    candidates, records, initial_risk, evals = adam_search(
        theta_start, value_and_grad, feasible, iterations=iterations, starts=starts,
        learning_rate=learning_rate, spread=spread, lo=lo, hi=hi, seed=seed, progress=progress)
    if phase:
        (val, (r0, _)), _ = _risk_and_grad(theta_init, leak, batch0, settings)
        initial_risk = float(r0)
    candidates.sort(key=lambda c: c[0])
    (risk_best, best), cert, v_check, certified, lam_s = candidates[0], None, v_task, False, -math.inf
    for cost, theta in candidates:
        g = gains_of(jnp.asarray(theta), leak)
        speeds = np.asarray(_max_speed(g, batch0, spec.t_final, spec.substeps, noisy))
        v = max(v_task, float(np.max(speeds)))
        if not math.isfinite(v):
            continue
        c = certify_box(pbox, g, v, margin=margin, eps=eps)
        lam = float(jnp.min(_sample_lambda_min(g, plants0, jnp.linspace(0.0, v, grid), eps)))
        if c.certified and lam >= margin:
            risk_best, best, cert, v_check, certified, lam_s = cost, theta, c, v, True, lam
            break
    return RobustResult(
        gains=gains_of(jnp.asarray(best), leak), certified=certified, risk=float(risk_best),
        initial_gains=initial, initial_risk=float(initial_risk), task=task, box=pbox,
        box_how=how, certificate=cert, v_check=v_check, margin=margin,
        sample_lambda_min=lam_s, starts=records, wall_time_s=time.perf_counter() - t0,
        evaluations=evals, feasibility_steps=phase)


@persistent_jit
def _box_min_and_grad(theta, leak, box, vgrid, eps):
    return jax.value_and_grad(lambda th: _box_min(gains_of(th, leak), box, vgrid, eps))(theta)


@dataclasses.dataclass(frozen=True)
class HeldOutEvaluation:
    """Result of ``evaluate_batch``: gains on held-out plants of a task's spread.

    **Fields:**

    - ``held_out_plants``: how many plants.
    - ``rms_error`` [rad]: RMS link error per plant; ``lost``: per plant, whether its run
      diverged.
    - ``rms_q50``, ``rms_q95``, ``rms_mean`` [rad]: median, 95% quantile and mean of the RMS
      error over the plants not lost (nan where every plant is lost).
    - ``lost_fraction``: the share of plants lost.
    - ``certified_fraction``: the share of plants whose N2 is positive definite over
      |q1'| <= ``certify_speed`` [rad/s] (``RobustTask.certify_speed``).
    - ``certified_up_to_q05``, ``certified_up_to_q50`` [rad/s]: 5% and 50% quantiles over
      the plants of the speed up to which N2 is positive definite.
    """

    held_out_plants: int
    rms_error: list[float]
    lost: list[bool]
    rms_q50: float
    rms_q95: float
    rms_mean: float
    lost_fraction: float
    certified_fraction: float
    certify_speed: float
    certified_up_to_q05: float
    certified_up_to_q50: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the fields by name."""
        return dataclasses.asdict(self)

    def summary(self) -> dict[str, Any]:
        """``to_dict`` without the per-plant lists (``rms_error``, ``lost``)."""
        return {k: v for k, v in self.to_dict().items() if k not in ("rms_error", "lost")}


@requires_float64
def evaluate_batch(task: RobustTask, gains: CascadeGains, *, samples: int = 1000,
                   seed_offset: int = 1_000_003, eps: float = DEFAULT_EPS, grid: int = 65,
                   chunk_size: int = 250) -> HeldOutEvaluation:
    """``gains`` on ``samples`` held-out plants of the task's spread (seed + ``seed_offset``:
    never the training plants): RMS link error per plant [rad] (the sweep engine), its
    quantiles, the lost fraction, and per plant whether N2 is positive definite over
    |q1'| <= ``task.certify_speed()`` (``certified_fraction``) and the speed [rad/s] up to which
    it is (on a ``grid``-point grid up to 5 x the task speed). ``eps``: the certificate's
    margin on the smallest eigenvalue of N2; ``chunk_size``: plants per sweep chunk."""
    spec = task.spec
    held = spec.with_(nominal=dataclasses.replace(spec.nominal, gains=gains.to_dict()),
                      seed=spec.seed + seed_offset, samples=samples)
    res = run_sweep(held, chunk_size=chunk_size, progress=False, keep_samples=True, shard=False)
    smp = res.samples
    rms = np.asarray(smp["rms_error"], float)
    lost = np.asarray(smp["diverged"], bool)
    idx = np.asarray(smp["index"])
    v_task = task.certify_speed()
    vgrid = np.linspace(0.0, 5 * v_task, grid)
    lam = []
    for i in range(0, samples, chunk_size):
        plants = sample_batch(held, jnp.asarray(idx[i:i + chunk_size]))[1]
        lam.append(np.asarray(_sample_lambda_min(gains, plants, jnp.asarray(vgrid), eps)))
    lam = np.concatenate(lam)
    ok_task = np.all(lam[:, vgrid <= v_task] > 0, axis=1)
    bad = ~(lam > 0)
    first_bad = np.where(bad.any(axis=1), np.argmax(bad, axis=1), grid)
    up_to = np.where(first_bad == 0, 0.0, vgrid[np.maximum(first_bad - 1, 0)])
    rms_ok = np.where(lost, np.nan, rms)
    q = lambda a: float(np.nanquantile(rms_ok, a)) if np.any(~lost) else math.nan
    return HeldOutEvaluation(
        held_out_plants=samples, rms_error=rms.tolist(), lost=lost.tolist(),
        rms_q50=q(0.5), rms_q95=q(0.95), rms_mean=float(np.nanmean(rms_ok)),
        lost_fraction=float(np.mean(lost)),
        certified_fraction=float(np.mean(ok_task)), certify_speed=v_task,
        certified_up_to_q05=float(np.quantile(up_to, 0.05)),
        certified_up_to_q50=float(np.quantile(up_to, 0.5)),
    )
