"""``tune``: certified gain tuning of a task (the package docstring), its result
(``TuneResult``) and the compiled cost, constraint and rest-damping functions it calls."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.certificate import DEFAULT_EPS, certify, lambda_min_curve
from jaxflex.core.controller import CascadeGains
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.sensing import StraightThrough
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.tune.search import StartRecord, adam_search, ascend_feasibility, gains_of
from jaxflex.tune.task import TuneTask, max_link_speed, tracking_cost
from jaxflex.core.validation import requires_float64
from jaxflex.io.progress import Progress


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
    progress: Progress | None = None,
) -> TuneResult:
    """Tune the cascade gains on ``task`` under the N2 certificate (module docstring).

    ``margin``: required lambda_min(N2) over |v| <= task.certify_speed(); ``None`` tunes
    without the certificate (for comparisons; the result is then not checked). ``iterations``
    Adam steps per start, ``starts`` starts (the first at ``initial``), ``learning_rate`` in
    log units, ``spread`` the log-normal spread of the other starts, ``box`` the factor by which
    a gain may move from its initial value, ``grid`` speeds on which the constraint is checked.
    ``progress`` (``jaxflex.io.progress.Progress``) gets every iteration of every start.

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
    rest = task_rest_map(plant, model, initial, task) if zeta is not None else None

    def constraint(theta) -> float:
        c = float(_constraint(theta, leak, model, vgrid, jnp.asarray(0.0 if margin is None else margin), eps))
        if margin is None:
            c = math.inf
        if zeta is not None:
            c = min(c, float(damping_value(theta, rest)) - zeta)
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
        if zeta is not None and float(damping_value(jnp.asarray(theta), rest)) < zeta:
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


def task_rest_map(plant: FlexibleJointPlant, model: FlexibleJointPlant, gains: CascadeGains,
                  task: TuneTask) -> Any:
    """The one-sample closed-loop map at rest of ``task``'s configuration.

    **Arguments:**

    - `plant`: the true plant; `model`: the controller's.
    - `gains`: the gains it is built with (replaced by ``rest_damping_of``).
    - `task`: sensing, q2d method, sample time, torque limit and substeps.

    **Returns:**

    ``jaxflex.loop.analyse.rest_map``'s map.
    """
    from jaxflex.loop.analyse import rest_map

    return rest_map(plant, gains, model=model, sensing=task.sensing, q2d_method=task.q2d_method,
                    dt=task.dt, tau_max=task.tau_max, substeps=task.substeps)


def rest_damping_of(theta: jax.Array, rest: Any) -> jax.Array:
    """Smallest damping ratio of the rest modes of ``rest`` (``task_rest_map``) with the
    gains exp(theta), theta = log(gains) (``gains_of``)."""
    from jaxflex.loop.analyse import rest_damping

    g = gains_of(theta, rest.controller.gains.leak)
    return rest_damping(eqx.tree_at(lambda m: m.controller.gains, rest, g))


#: ``rest_damping_of``, compiled.
damping_value = persistent_jit(rest_damping_of)


@persistent_jit
def _constraint_and_grad(theta, leak, model, vgrid, margin, eps, rest, zeta, use_n2):
    def c(th):
        d = rest_damping_of(th, rest) - zeta
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
