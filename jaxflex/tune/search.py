"""The search of gain tuning in log-space: multi-start Adam with the certificate enforced
at every iterate (``adam_search``) and the ascent into the certified set
(``ascend_feasibility``)."""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from jaxflex.core.controller import CascadeGains
from jaxflex.io.progress import Progress


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


def adam_search(
    theta_init: Array, value_and_grad: Callable, feasible: Callable[[Array], tuple[bool, float]],
    *, iterations: int, starts: int, learning_rate: float, spread: float, lo: Array, hi: Array,
    seed: int, progress: Progress | None = None,
) -> tuple[list[tuple[float, np.ndarray]], list[StartRecord], float, int]:
    """The multi-start Adam search of ``tune`` and ``jaxflex.tune.robust.tune_robust`` in
    log-gains theta, with every iterate kept in the certified set.

    ``value_and_grad(theta)`` returns ((log cost, (cost, aux)), gradient) with ``aux``
    holding "rms_error"; ``feasible(theta)`` returns (certified, constraint value). A step
    that leaves the certified set is halved back toward the last certified point; a step into
    a non-finite cost is undone with half the learning rate. The first start is
    ``theta_init`` (certified), the others log-normal perturbations (``spread``) inside
    [lo, hi], pulled back toward it if uncertified. Returns (candidates as (cost, theta),
    per-start records, the cost at ``theta_init``, evaluations). ``progress``
    (``jaxflex.io.progress.Progress``) gets every iteration as one of ``starts`` x
    (``iterations`` + 1), with its start, iteration and cost."""

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
                progress(si * (iterations + 1) + it + 1, starts * (iterations + 1),
                         f"start {si} iteration {it}: cost {cost:.3e}")
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
    (N2 and rest damping) and ``jaxflex.tune.robust.tune_robust`` (N2 over a box)."""
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
