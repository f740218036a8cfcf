"""Gain tuning against the N2 stability certificate (paper section 4; docs/spec.md section 4).

Choose the cascade gains (Ke, KD1, KD2, kv, L1, L2 per joint, Table 3) that minimise a
simulated tracking cost over a task, subject to

    lambda_min(N2(v)) >= margin   for all link speeds |v| <= v_task                 (eq. 29-31)

The cost is the mean squared link error of the sampled-data closed loop
(``jaxflex.simulate.simulate_sampled``) over one or more reference trajectories, with encoder
and DAC quantisation, filtered velocities and a torque limit, plus an optional torque penalty.

How it works:

- Gains are positive, so the search runs in log-space, theta = log(gains), inside a box of
  +-log(box) around the initial gains; the objective is log(cost), whose gradient has no
  scale. Gradients go through the whole simulation (``jax.value_and_grad`` of a
  ``lax.scan``); quantisers use a straight-through gradient (``jaxflex.sensing.StraightThrough``),
  since rounding has zero derivative and would cut every feedback path out of the gradient.
- Adam steps, with the certificate *enforced* at every iterate: a step that leaves the
  certified set is cut back (halved) along the segment from the last certified point, and a
  step into a diverged simulation is undone. The iterates are certified points; none is traded
  against the cost.
- Multi-start: the initial gains (which must themselves be certified) and random log-normal
  perturbations of them, each pulled back toward the initial gains if uncertified.
- Final check: the best candidate must pass ``jaxflex.certificate.certify`` up to
  max(v_task, fastest simulated link speed); otherwise the next best is taken.

Units: gains as in ``jaxflex.controller.CascadeGains``; speeds [rad/s]; cost [rad^2].
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.certificate import DEFAULT_EPS, certify, lambda_min_curve, ultimate_bound
from jaxflex.controller import CascadeController, CascadeGains
from jaxflex.plant import FlexibleJointPlant
from jaxflex.presets import rig_sensing
from jaxflex.sensing import AbstractSensing, StraightThrough
from jaxflex.simulate import SimResult, simulate_sampled, tracking_summary
from jaxflex.tracecache import persistent_jit
from jaxflex.trajectory import Trajectory
from jaxflex.validation import requires_float64


def reference_speed(trajectories: Sequence[Trajectory], t_final: float, dt: float) -> float:
    """Fastest reference link speed max |q1d'| [rad/s] of ``trajectories`` over [0, t_final] s,
    sampled every ``dt`` s."""
    ts = jnp.linspace(0.0, t_final, int(t_final / dt) + 1)
    return max(float(jnp.max(jnp.abs(tr.sample(ts, order=1)[:, 1]))) for tr in trajectories)


def certify_speed(trajectories: Sequence[Trajectory], t_final: float, dt: float,
                  velocity_factor: float) -> float:
    """Speed [rad/s] up to which gains for these references must be certified:
    ``velocity_factor`` x the fastest reference speed (at least 1e-3 rad/s)."""
    return velocity_factor * max(reference_speed(trajectories, t_final, dt), 1e-3)


@dataclasses.dataclass(frozen=True)
class TuneTask:
    """What the gains are tuned for.

    trajectories: references (each for the plant's n joints); t_final [s] per run; sensing;
    tau_max [N m] controller torque limit; q2d_method "model" or "filtered" ("reference"
    diverges with the paper's gains); dt [s] sample period; substeps plant steps per sample;
    seed of the measurement noise (common random numbers for all candidates); torque_weight
    [rad^2/(N m)^2] weight of the mean squared torque in the cost (default 1e-6 prices 1 N m
    RMS like 1 mrad RMS error; with 0 the search drifts to gains that chatter at the torque
    limit); velocity_factor: the
    certificate must hold up to velocity_factor x the fastest reference speed;
    min_rest_damping: if set, every mode of the closed loop linearised at rest (plant,
    observer, controller, velocity estimator: ``jaxflex.analyse.rest_damping``) must have at
    least this damping ratio, so that no oscillation persists at rest (None: not required).
    """

    trajectories: tuple[Trajectory, ...]
    t_final: float = 2.0
    sensing: AbstractSensing = dataclasses.field(default_factory=rig_sensing)
    tau_max: float = 2.0
    q2d_method: str = "model"
    dt: float = 1e-3
    substeps: int = 10
    seed: int = 0
    torque_weight: float = 1e-6
    velocity_factor: float = 1.5
    min_rest_damping: float | None = None

    def __post_init__(self) -> None:
        if isinstance(self.trajectories, Trajectory):
            object.__setattr__(self, "trajectories", (self.trajectories,))
        object.__setattr__(self, "trajectories", tuple(self.trajectories))
        if not self.trajectories:
            raise ValueError("TuneTask: needs at least one trajectory")
        if not self.t_final > 0:
            raise ValueError(f"TuneTask: t_final must be > 0 s, got {self.t_final}")
        if not self.tau_max > 0:
            raise ValueError(f"TuneTask: tau_max must be > 0 N m, got {self.tau_max}")
        if self.q2d_method not in ("model", "filtered", "reference"):
            raise ValueError(f"TuneTask: unknown q2d_method {self.q2d_method!r}")
        if self.torque_weight < 0:
            raise ValueError(f"TuneTask: torque_weight must be >= 0, got {self.torque_weight}")
        if not self.velocity_factor >= 1:
            raise ValueError(
                f"TuneTask: velocity_factor must be >= 1, got {self.velocity_factor}")
        if self.min_rest_damping is not None and not -1 < self.min_rest_damping < 1:
            raise ValueError("TuneTask: min_rest_damping must be in (-1, 1) (a damping ratio), "
                             f"got {self.min_rest_damping}")

    def settings(self) -> tuple:
        """The static (hashable) settings of the cost, for caching compiled functions."""
        return (self.t_final, self.tau_max, self.q2d_method, self.dt, self.substeps, self.seed,
                self.torque_weight)

    @classmethod
    def from_settings(cls, trajectories, sensing, settings: tuple) -> "TuneTask":
        """Inverse of ``settings`` (velocity_factor, which the cost does not use, at default)."""
        t_final, tau_max, q2d, dt, substeps, seed, tw = settings
        return cls(tuple(trajectories), t_final, sensing, tau_max, q2d, dt, substeps, seed, tw)

    def reference_speed(self) -> float:
        """Fastest reference link speed max |q1d'| [rad/s] over the task's trajectories."""
        return reference_speed(self.trajectories, self.t_final, self.dt)

    def certify_speed(self) -> float:
        """Speed [rad/s] up to which tuned gains must be certified."""
        return certify_speed(self.trajectories, self.t_final, self.dt, self.velocity_factor)

    def controller(self, model: FlexibleJointPlant, gains: CascadeGains,
                   trajectory: Trajectory) -> CascadeController:
        """The cascade controller of this task for ``gains``."""
        return CascadeController(model=model, gains=gains, trajectory=trajectory,
                                 q2d_method=self.q2d_method, dt=self.dt, tau_max=self.tau_max)


def tracking_cost(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                  model: FlexibleJointPlant | None = None,
                  sensing: AbstractSensing | None = None) -> tuple[Float[Array, ""], dict[str, Array]]:
    """Cost [rad^2] of ``gains`` on ``task``: mean over trajectories and joints of the squared
    RMS link error plus torque_weight x mean squared RMS torque; +inf when a run diverged.

    ``plant`` is the true plant, ``model`` the controller's (default: the plant). Pure; jit and
    grad friendly. Returns (cost, {"rms_error", "tau_rms", "saturation", "diverged"}).
    """
    model = plant if model is None else model
    sensing = task.sensing if sensing is None else sensing
    key = jax.random.PRNGKey(task.seed)
    mets = [
        simulate_sampled(plant, task.controller(model, gains, tr), task.t_final,
                         substeps=task.substeps, sensing=sensing, key=key, save=False,
                         unroll_substeps=False).metrics  # a gradient runs through it
        for tr in task.trajectories
    ]
    rms = jnp.stack([m.rms_error for m in mets])
    tau = jnp.stack([m.tau_rms for m in mets])
    diverged = jnp.any(jnp.stack([m.diverged for m in mets]))
    cost = jnp.mean(rms**2) + task.torque_weight * jnp.mean(tau**2)
    ok = jnp.isfinite(cost) & ~diverged
    cost = jnp.where(ok, cost, jnp.inf)
    aux = {"rms_error": rms, "tau_rms": tau,
           "saturation": jnp.stack([m.saturation_fraction for m in mets]), "diverged": diverged}
    return cost, aux


@dataclasses.dataclass
class StartRecord:
    """One start of the multi-start search: initial and final gains vectors, the cost
    [rad^2], RMS link error [rad] and certificate value (min lambda_min - margin) per
    iteration, halvings that pulled the start or a step back into the certified set, and
    undone divergent steps."""

    theta0: np.ndarray
    theta: np.ndarray
    costs: list[float]
    constraint: list[float]
    rms_errors: list[float] = dataclasses.field(default_factory=list)
    cutbacks: int = 0
    rejected_divergent: int = 0


@dataclasses.dataclass
class TuneResult:
    """Result of ``tune``: the tuned gains, their cost and the initial gains' cost [rad^2],
    the certificate of the tuned gains up to the task speed, the starts, wall time [s]."""

    gains: CascadeGains
    cost: float
    initial_gains: CascadeGains
    initial_cost: float
    certificate: Any
    v_task: float
    margin: float | None
    starts: list[StartRecord]
    wall_time_s: float
    evaluations: int

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary."""
        return {
            "gains": self.gains.to_dict(), "cost": self.cost,
            "initial_gains": self.initial_gains.to_dict(), "initial_cost": self.initial_cost,
            "v_task": self.v_task, "margin": self.margin,
            "certified_up_to": None if self.certificate is None else self.certificate.certified_up_to,
            "starts": [{"cost": s.costs, "rms_error": s.rms_errors, "constraint": s.constraint,
                        "cutbacks": s.cutbacks,
                        "rejected_divergent": s.rejected_divergent} for s in self.starts],
            "wall_time_s": self.wall_time_s, "evaluations": self.evaluations,
        }


def _check_gains_vector(theta: np.ndarray) -> None:
    if not np.all(np.isfinite(theta)):
        raise ValueError("tune: gains must be finite and > 0")


@requires_float64
def tune(
    plant: FlexibleJointPlant,
    initial: CascadeGains,
    task: TuneTask,
    *,
    margin: float | None = 0.05,
    iterations: int = 30,
    starts: int = 3,
    learning_rate: float = 0.1,
    spread: float = 0.5,
    box: float = 100.0,
    seed: int = 0,
    model: FlexibleJointPlant | None = None,
    eps: float = DEFAULT_EPS,
    grid: int = 33,
    progress: Callable[[int, int, float], None] | None = None,
) -> TuneResult:
    """Tune the cascade gains on ``task`` under the N2 certificate (module docstring).

    ``margin``: required lambda_min(N2) over |v| <= task.certify_speed(); ``None`` tunes
    without the certificate (for comparisons; the result is then not checked). ``iterations``
    Adam steps per start, ``starts`` starts (the first at ``initial``), ``learning_rate`` in
    log units, ``spread`` the log-normal spread of the other starts, ``box`` the factor by which
    a gain may move from its initial value, ``grid`` speeds on which the constraint is checked.
    ``progress(start, iteration, cost)`` is called after every iteration.

    Raises ``ValueError`` on bad settings or when ``initial`` is not certified with ``margin``.
    """
    if iterations < 0 or starts < 1:
        raise ValueError(f"tune: need iterations >= 0 and starts >= 1, got {iterations}, {starts}")
    if margin is not None and (not np.isfinite(margin) or margin < 0):
        raise ValueError(f"tune: margin must be finite and >= 0 (or None), got {margin}")
    if not learning_rate > 0 or not box > 1 or spread < 0:
        raise ValueError("tune: need learning_rate > 0, box > 1 and spread >= 0")
    if initial.n != plant.n:
        raise ValueError(f"tune: gains are for {initial.n} joint(s), the plant has {plant.n}")
    t_start = time.perf_counter()
    model = plant if model is None else model
    v_task = task.certify_speed()
    vgrid = jnp.linspace(0.0, v_task, grid)
    st_sensing = StraightThrough(task.sensing)
    theta_init = jnp.log(initial.to_vector())
    leak = initial.leak
    _check_gains_vector(np.asarray(theta_init))
    lo, hi = theta_init - math.log(box), theta_init + math.log(box)

    def value_and_grad(theta):
        return _log_cost_and_grad(theta, leak, plant, model, task.trajectories, st_sensing,
                                  task.settings())

    zeta = task.min_rest_damping
    rest = _rest_map(plant, model, initial, task) if zeta is not None else None

    def constraint(theta) -> float:
        c = float(_constraint(theta, leak, model, vgrid, jnp.asarray(0.0 if margin is None else margin), eps))
        if margin is None:
            c = math.inf
        if zeta is not None:
            c = min(c, float(_damping_value(theta, rest)) - zeta)
        return c

    def feasible(theta) -> tuple[bool, float]:
        c = constraint(theta)
        return c >= 0.0, (c if math.isfinite(c) else 0.0)

    ok0, c0 = feasible(theta_init)
    if not ok0 and zeta is not None:
        # a first phase pushes the gains into the certified set by gradient ascent of the
        # constraint (N2's lambda_min and the rest modes' damping are both differentiable)
        m_arr = jnp.asarray(0.0 if margin is None else margin)

        def c_and_grad(th):
            return _constraint_and_grad(th, leak, model, vgrid, m_arr, eps, rest, zeta,
                                        margin is not None)

        theta_init, phase = ascend_feasibility(theta_init, c_and_grad, feasible, lo, hi)
        ok0, c0 = feasible(theta_init)
    if not ok0:
        raise ValueError(
            f"tune: the initial gains are not certified with margin {margin} up to "
            f"{v_task:.3g} rad/s" + (f" with rest damping >= {zeta}" if zeta is not None else "")
            + f" (constraint value {c0:.3g}); start from certified gains or lower the margin")

    candidates, records, initial_cost, evals = adam_search(
        theta_init, value_and_grad, feasible, iterations=iterations, starts=starts,
        learning_rate=learning_rate, spread=spread, lo=lo, hi=hi, seed=seed,
        progress=progress)

    if not candidates:
        raise ValueError(
            "tune: every simulated candidate diverged (the start"
            + (" found by ascending the rest damping" if zeta is not None else "")
            + " loses the link on the task, e.g. at the torque limit); nothing to certify. "
            "Start from gains that track, or relax the constraints")
    # best first; the final check certifies up to the fastest speed the loop actually reaches
    candidates.sort(key=lambda c: c[0])
    best_cost, best, cert = initial_cost, np.asarray(theta_init), None
    for cost, theta in candidates:
        g = gains_of(jnp.asarray(theta), leak)
        if margin is None:
            best_cost, best = cost, theta
            break
        if zeta is not None and float(_damping_value(jnp.asarray(theta), rest)) < zeta:
            continue
        v_check = max(v_task, max_link_speed(plant, g, task, model))
        if not np.isfinite(v_check):
            continue
        c = certify(model, g, v_check, margin=margin, eps=eps)
        if c.certified:
            best_cost, best, cert = cost, theta, c
            break
    return TuneResult(
        gains=gains_of(jnp.asarray(best), leak), cost=float(best_cost), initial_gains=initial,
        initial_cost=initial_cost, certificate=cert, v_task=v_task, margin=margin,
        starts=records, wall_time_s=time.perf_counter() - t_start, evaluations=evals,
    )


def adam_search(
    theta_init: Array, value_and_grad: Callable, feasible: Callable[[Array], tuple[bool, float]],
    *, iterations: int, starts: int, learning_rate: float, spread: float, lo: Array, hi: Array,
    seed: int, progress: Callable[[int, int, float], None] | None = None,
) -> tuple[list[tuple[float, np.ndarray]], list[StartRecord], float, int]:
    """The multi-start Adam search of ``tune`` and ``jaxflex.robust.tune_robust`` in
    log-gains theta, with every iterate kept in the certified set.

    ``value_and_grad(theta)`` returns ((log cost, (cost, aux)), gradient) with ``aux``
    holding "rms_error"; ``feasible(theta)`` returns (certified, constraint value). A step
    that leaves the certified set is halved back toward the last certified point; a step into
    a non-finite cost is undone with half the learning rate. The first start is
    ``theta_init`` (certified), the others log-normal perturbations (``spread``) inside
    [lo, hi], pulled back toward it if uncertified. Returns (candidates as (cost, theta),
    per-start records, the cost at ``theta_init``, evaluations)."""

    def pull_back(theta_from, cand, max_halvings=30):
        """Largest certified point on the segment from a certified theta_from toward cand."""
        cuts = 0
        while not feasible(cand)[0]:
            cand = theta_from + 0.5 * (cand - theta_from)
            cuts += 1
            if cuts >= max_halvings:
                return theta_from, cuts
        return cand, cuts

    key = jax.random.PRNGKey(seed)
    start_points = [(theta_init, 0)]
    for k in jax.random.split(key, max(starts - 1, 1))[: starts - 1]:
        cand = jnp.clip(theta_init + spread * jax.random.normal(k, theta_init.shape), lo, hi)
        start_points.append(pull_back(theta_init, cand))

    candidates: list[tuple[float, np.ndarray]] = []
    records: list[StartRecord] = []
    initial_cost = float("nan")
    evals = 0
    b1, b2, adam_eps = 0.9, 0.999, 1e-8
    for si, (theta, start_cuts) in enumerate(start_points):
        rec = StartRecord(theta0=np.asarray(theta), theta=np.asarray(theta), costs=[],
                          constraint=[], cutbacks=start_cuts)
        m = jnp.zeros_like(theta)
        v = jnp.zeros_like(theta)
        lr = learning_rate
        prev_theta = None
        for it in range(iterations + 1):
            (val, (cost, aux)), g = value_and_grad(theta)
            evals += 1
            cost = float(cost)
            if si == 0 and it == 0:
                initial_cost = cost
            if not np.isfinite(cost) or not np.all(np.isfinite(np.asarray(g))):
                rec.rejected_divergent += 1
                if prev_theta is None:
                    break
                theta, lr, prev_theta = prev_theta, 0.5 * lr, None
                continue
            rec.costs.append(cost)
            rec.rms_errors.append(float(jnp.sqrt(jnp.mean(aux["rms_error"] ** 2))))
            rec.constraint.append(feasible(theta)[1])
            candidates.append((cost, np.asarray(theta)))
            if progress is not None:
                progress(si, it, cost)
            if it == iterations:
                break
            m = b1 * m + (1 - b1) * g
            v = b2 * v + (1 - b2) * g**2
            mh, vh = m / (1 - b1 ** (it + 1)), v / (1 - b2 ** (it + 1))
            cand = jnp.clip(theta - lr * mh / (jnp.sqrt(vh) + adam_eps), lo, hi)
            new, cuts = pull_back(theta, cand)
            rec.cutbacks += cuts
            prev_theta, theta = theta, new
        rec.theta = np.asarray(theta)
        records.append(rec)

    return candidates, records, initial_cost, evals


def gains_of(theta: Array, leak: ArrayLike = 0.0) -> CascadeGains:
    """The gains of the search coordinates theta = log(gains) (6n,), with the observer
    leakage ``leak`` [rad/s] (not searched: kept at the start gains' value)."""
    return CascadeGains.from_vector(jnp.exp(theta), leak)


def ascend_feasibility(theta: Array, value_and_grad: Callable, feasible: Callable,
                       lo: Array, hi: Array, iterations: int = 300, lr: float = 0.05,
                       ) -> tuple[Array, int]:
    """First phase of a certified search: Adam ascent of a differentiable constraint
    ``value_and_grad(theta) -> (c, dc/dtheta)`` from ``theta`` inside [lo, hi] until
    ``feasible(theta)`` holds with a little room; returns (theta, steps). Used by ``tune``
    (N2 and rest damping) and ``jaxflex.robust.tune_robust`` (N2 over a box)."""
    if feasible(theta)[0]:
        return theta, 0
    m = jnp.zeros_like(theta)
    v = jnp.zeros_like(theta)
    b1, b2 = 0.9, 0.999
    it = 0
    for it in range(iterations):
        _, g = value_and_grad(theta)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g**2
        mh, vh = m / (1 - b1 ** (it + 1)), v / (1 - b2 ** (it + 1))
        theta = jnp.clip(theta + lr * mh / (jnp.sqrt(vh) + 1e-8), lo, hi)
        if feasible(theta)[0]:
            # a few more steps leave room for the search
            for _ in range(5):
                _, g = value_and_grad(theta)
                step = jnp.clip(theta + lr * jnp.sign(jnp.where(jnp.isfinite(g), g, 0.0)), lo, hi)
                if not feasible(step)[0]:
                    break
                theta = step
            return theta, it + 1
    return theta, it + 1


def _rest_map(plant, model, gains, task):
    """The one-sample closed-loop map at rest of ``task``'s configuration (``jaxflex.analyse``)."""
    from jaxflex.analyse import rest_map

    return rest_map(plant, gains, model=model, sensing=task.sensing, q2d_method=task.q2d_method,
                    dt=task.dt, tau_max=task.tau_max, substeps=task.substeps)


def _rest_damping(theta, rest):
    """Smallest damping ratio of the rest modes of ``rest`` with the gains exp(theta)."""
    from jaxflex.analyse import rest_damping

    g = gains_of(theta, rest.controller.gains.leak)
    return rest_damping(eqx.tree_at(lambda m: m.controller.gains, rest, g))


_damping_value = persistent_jit(_rest_damping)


@persistent_jit
def _constraint_and_grad(theta, leak, model, vgrid, margin, eps, rest, zeta, use_n2):
    def c(th):
        d = _rest_damping(th, rest) - zeta
        if not use_n2:
            return d
        return jnp.minimum(
            jnp.min(lambda_min_curve(model, gains_of(th, leak), vgrid, eps)) - margin, d)

    return jax.value_and_grad(c)(theta)


@persistent_jit
def _log_cost_and_grad(theta, leak, plant, model, trajectories, sensing, settings):
    """(log cost, (cost, aux)) and its gradient in theta = log(gains); module-level so that
    repeated ``tune`` calls on same-shaped tasks reuse the compiled function."""
    task = TuneTask.from_settings(trajectories, sensing, settings)

    def objective(th):
        cost, aux = tracking_cost(plant, gains_of(th, leak), task, model, sensing)
        safe = jnp.where(jnp.isfinite(cost), cost, 1.0)
        return jnp.where(jnp.isfinite(cost), jnp.log(safe), jnp.inf), (cost, aux)

    return jax.value_and_grad(objective, has_aux=True)(theta)


@persistent_jit
def _constraint(theta, leak, model, vgrid, margin, eps):
    """min over the speed grid of lambda_min(N2) minus the margin (>= 0: certified)."""
    return jnp.min(lambda_min_curve(model, gains_of(theta, leak), vgrid, eps)) - margin


def simulate_task(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                  model: FlexibleJointPlant | None = None) -> list[SimResult]:
    """Saved closed-loop runs of ``gains`` on each trajectory of ``task`` (for reports)."""
    model = plant if model is None else model
    key = jax.random.PRNGKey(task.seed)
    return [_simulate_saved(plant, task.controller(model, gains, tr), task.t_final,
                            task.substeps, task.sensing, key)
            for tr in task.trajectories]


@persistent_jit
def _simulate_saved(plant, controller, t_final, substeps, sensing, key):
    return simulate_sampled(plant, controller, t_final, substeps=substeps, sensing=sensing,
                            key=key)


def max_link_speed(plant: FlexibleJointPlant, gains: CascadeGains, task: TuneTask,
                   model: FlexibleJointPlant | None = None) -> float:
    """Fastest link speed max |q1'| [rad/s] reached on the task (inf if a run diverged)."""
    runs = simulate_task(plant, gains, task, model)
    if any(bool(r.metrics.diverged) for r in runs):
        return float("inf")
    return max(float(jnp.max(jnp.abs(r.dq1))) for r in runs)


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
