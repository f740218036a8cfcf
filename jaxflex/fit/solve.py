"""The one solver path of jaxflex, and the one covariance.

Solver: optimistix's Levenberg-Marquardt (a damped-Newton descent inside a trust region) on
``Problem.residuals``, with forward-mode Jacobians (the residual's structured custom JVP) and
the damped normal equations solved by Cholesky. Its ``init`` and ``step`` are compiled once
per problem *shape* and the iteration runs on the host, so

- the step limit is a plain number (no recompilation for another ``max_steps``, a warm stage
  and a final stage share one compilation, and so do all candidates of the discrepancy
  workflow, whose problems differ only in data such as masks and weights);
- progress can be printed and an interrupt (Ctrl-C) ends the loop between steps, returning the
  last accepted point marked unconverged.

Covariance: Cov = s^2 (J^T J)^+ from the Jacobian at the optimum over the fitted unknowns
(nuisance start states included, so their uncertainty is accounted for), s^2 the residual
variance per output sample times an ``inflation`` for correlated residuals, mapped to physical
values through the reparametrisation's Jacobian.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from jaxflex.fit.problem import Problem


@dataclasses.dataclass
class Solution:
    """Outcome of ``least_squares``: unknowns ``y``, accepted ``steps`` taken, whether the
    solver's tolerance was met (``converged``), the final ``cost`` 0.5 ||r||^2 (weighted
    units), ``reason`` in words, ``seconds`` of wall time."""

    y: Any
    steps: int
    converged: bool
    cost: float
    reason: str
    seconds: float


class _WithAux(eqx.Module):
    """A residual function ``fn(y, args)`` in optimistix's form ``(residual, aux)``."""

    fn: Callable

    def __call__(self, y: Any, args: Any) -> tuple[jax.Array, None]:
        return self.fn(y, args), None


def problem_residuals(y: Any, prob: Problem) -> jax.Array:
    """``prob.residuals(y)``: the residual function of every ``Problem``."""
    return prob.residuals(y)


class _ScaledDescentState(eqx.Module):
    f_info: optx.FunctionInfo.ResidualJac


class ScaledDampedNewtonDescent(optx.AbstractDescent):
    """Levenberg-Marquardt's damped Gauss-Newton step

        (J^T J + lambda D) dy = -J^T r

    with ``scaling`` "identity" (D = I, as optimistix's ``DampedNewtonDescent``) or
    "marquardt" (D = diag(J^T J), floored): the step is then invariant to the scale of each
    unknown, which the discrepancy workflow needs because its unknowns mix log-parameters
    whose sensitivities differ by many orders of magnitude (a time constant started on its
    lower bound next to a stiffness); identification with free segment states converges more
    reliably with the identity (its acceptance tests fall into a local minimum with Marquardt's
    scaling, which takes large steps along weakly determined directions such as sigma1).
    lambda = 1 / step_size comes from the trust region (``optx.ClassicalTrustRegion``). The
    damped normal equations are solved by Cholesky: the Jacobian is tall (thousands of
    residuals, tens of unknowns) and float64 leaves ample room for squaring its condition
    number."""

    scaling: str = eqx.field(static=True, default="identity")

    def __check_init__(self) -> None:
        if self.scaling not in ("identity", "marquardt"):
            raise ValueError(f"fit: scaling must be 'identity' or 'marquardt', got {self.scaling!r}")

    def init(self, y: Any, f_info_struct: Any) -> _ScaledDescentState:
        zeros = lambda a: jnp.zeros(a.shape, a.dtype) if isinstance(a, jax.ShapeDtypeStruct) else a
        return _ScaledDescentState(jax.tree_util.tree_map(zeros, f_info_struct))

    def query(self, y: Any, f_info: Any, state: _ScaledDescentState) -> _ScaledDescentState:
        return _ScaledDescentState(f_info)

    def step(self, step_size: jax.Array, state: _ScaledDescentState) -> tuple[Any, optx.RESULTS]:
        jac = state.f_info.jac
        J = jac.as_matrix()
        r = state.f_info.residual
        A = J.T @ J
        g = J.T @ r
        if self.scaling == "marquardt":
            d = jnp.diag(A)
            d = jnp.maximum(d, 1e-12 * jnp.maximum(jnp.max(d), 1e-300))
        else:
            d = jnp.ones(A.shape[0], A.dtype)
        lam = 1.0 / jnp.maximum(step_size, 1e-30)
        c, low = jax.scipy.linalg.cho_factor(A + lam * jnp.diag(d))
        dy = -jax.scipy.linalg.cho_solve((c, low), g)
        finite = jnp.all(jnp.isfinite(dy))
        dy = jnp.where(finite, dy, 0.0)
        y_diff = jax.tree_util.tree_unflatten(
            jax.tree_util.tree_structure(jac.in_structure()),
            _split_like(dy, jac.in_structure()))
        return y_diff, optx.RESULTS.where(finite, optx.RESULTS.successful,
                                          optx.RESULTS.singular)


def _split_like(flat: jax.Array, structure: Any) -> list[jax.Array]:
    """Cut a flat vector into the leaves of a pytree of ``jax.ShapeDtypeStruct``s."""
    leaves = jax.tree_util.tree_leaves(structure)
    out, i = [], 0
    for leaf in leaves:
        size = int(np.prod(leaf.shape))
        out.append(flat[i:i + size].reshape(leaf.shape).astype(leaf.dtype))
        i += size
    return out


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix's Gauss-Newton machinery (trust region, termination) with the scaled
    damped-Newton descent above: the one least-squares solver of jaxflex."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: ScaledDampedNewtonDescent = ScaledDampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
    verbose: Callable = eqx.field(static=True, default=lambda **kw: None)


def _solver(rtol: float, atol: float, scaling: str) -> LevenbergMarquardt:
    return LevenbergMarquardt(rtol=rtol, atol=atol,
                              descent=ScaledDampedNewtonDescent(scaling=scaling))


@eqx.filter_jit
def _init(solver: LevenbergMarquardt, fn: _WithAux, y: Any, args: Any):
    f_struct = jax.eval_shape(lambda: fn(y, args)[0])
    return solver.init(fn, y, args, {}, f_struct, None, frozenset())


@eqx.filter_jit
def _step(solver: LevenbergMarquardt, fn: _WithAux, y: Any, state: Any, args: Any):
    y, state, _ = solver.step(fn, y, args, {}, state, frozenset())
    done, result = solver.terminate(fn, y, args, {}, state, frozenset())
    cost = 0.5 * jnp.sum(state.f_info.residual ** 2)
    return y, state, done, result == optx.RESULTS.successful, cost


@eqx.filter_jit
def _cost(fn: Callable, y: Any, args: Any) -> jax.Array:
    r = fn(y, args)
    return 0.5 * jnp.sum(r**2)


def cost(prob: Problem, y: Any, fn: Callable = problem_residuals) -> float:
    """0.5 ||r||^2 at ``y`` of ``fn(y, prob)`` (default: the problem's residuals; compiled
    once per shape); inf if not finite."""
    c = float(_cost(fn, y, prob))
    return c if math.isfinite(c) else math.inf


def least_squares(
    prob: Any, y0: Any, *, fn: Callable = problem_residuals, rtol: float = 1e-10,
    atol: float = 1e-10, max_steps: int = 200, scaling: str = "identity",
    progress: Callable[[int, float], None] | None = None,
) -> Solution:
    """Levenberg-Marquardt on the residuals ``fn(y, prob)`` from ``y0`` (module docstring).

    ``fn``: a module-level function (its identity keys the compilation cache; default
    ``problem_residuals`` for a ``Problem``, other curve fits pass their own with their data
    as ``prob``); ``rtol``/``atol``: optimistix's Cauchy termination on the change of the unknowns and the
    cost; ``max_steps``: iteration cap (a host-side number, no recompilation); ``scaling``:
    the damping matrix of ``ScaledDampedNewtonDescent`` ("identity" or "marquardt");
    ``progress(step, cost)`` is called after every step. Raises ``ValueError`` for
    ``max_steps < 1``.
    """
    if max_steps < 1:
        raise ValueError(f"fit: max_steps must be >= 1, got {max_steps}")
    t0 = time.perf_counter()
    solver = _solver(rtol, atol, scaling)
    wrapped = _WithAux(fn)
    y = y0
    state = _init(solver, wrapped, y, prob)
    steps, done, ok, reason = 0, False, True, ""
    try:
        while steps < max_steps:
            y, state, done_a, ok_a, c = _step(solver, wrapped, y, state, prob)
            steps += 1
            done, ok = bool(done_a), bool(ok_a)
            if progress is not None:
                progress(steps, float(c))
            if done or not ok:
                break
    except KeyboardInterrupt:
        reason = f"interrupted after {steps} steps"
    y = jax.block_until_ready(y)
    final = cost(prob, y, fn)
    if not reason:
        if done and ok:
            reason = "tolerance met"
        elif not ok:
            reason = "solver failed (non-finite values or a failed linear solve)"
        else:
            reason = f"stopped at max_steps = {max_steps} without meeting the tolerance"
    return Solution(y=y, steps=steps, converged=bool(done and ok and not reason.startswith("int")),
                    cost=final, reason=reason, seconds=time.perf_counter() - t0)


@eqx.filter_jit
def simulated_outputs(prob: Problem, y: Any) -> jax.Array:
    """Simulated outputs (S, L, n_out) [rad] of ``prob`` at ``y`` (compiled once per shape)."""
    return prob.simulate(y)[0]


@eqx.filter_jit
def gap(prob: Problem, y: Any) -> jax.Array:
    """``prob.gap(y)`` (normalised RMS output error), compiled once per problem shape."""
    return prob.gap(y)


@eqx.filter_jit
def residuals(prob: Problem, y: Any) -> jax.Array:
    """``prob.residuals(y)``, compiled once per problem shape."""
    return prob.residuals(y)


@eqx.filter_jit
def _jacobian(prob: Problem, y: Any):
    flat, unravel = ravel_pytree(y)
    return prob.residuals(y), jax.jacfwd(lambda f: prob.residuals(unravel(f)))(flat)


def covariance(
    prob: Problem, y: Any, *, inflation: float = 1.0, rank_rtol: float = 1e-9,
) -> dict[str, Any]:
    """Covariance and standard errors of the physical parameters at ``y`` (module docstring).

    Only the fitted unknowns enter (masked parameters are left out). ``inflation`` multiplies
    the residual variance (e.g. the integrated autocorrelation time of the residuals, in
    samples). Returns a dict: ``stderr`` (name -> (n,) array, physical units; NaN for names
    not fitted), ``cov_phys`` (physical covariance over the flattened names), ``rank``,
    ``n_free`` (fitted unknowns), ``singular_values`` (column-scaled Jacobian),
    ``null_names`` (parameters with weight in numerically null directions), ``s2``, ``rss``
    (sum of squared output residuals, weighted units), ``defects_ss`` (the same of the
    continuity defects), ``n_res`` (output residuals).
    """
    theta, _ = prob.split(y)
    r, Jm = (np.asarray(a) for a in _jacobian(prob, y))
    th_flat, th_unravel = ravel_pytree(theta)
    k = th_flat.shape[0]
    fitted_theta = prob.space.fitted_flat()
    cols = np.ones(Jm.shape[1], bool)
    cols[:k] = fitted_theta
    J = Jm[:, cols]
    m, p = J.shape
    rss = float(np.sum(r[: prob.n_out] ** 2))
    s2 = rss / max(prob.n_out - p, 1) * inflation
    scale = np.linalg.norm(J, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    _, sv, Vt = np.linalg.svd(J / scale, full_matrices=False)
    tol = sv[0] * max(rank_rtol, np.finfo(float).eps * max(m, p)) if sv.size else 0.0
    keep = sv > tol
    rank = int(keep.sum())
    inv = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep]
    cov_cols = s2 * inv / np.outer(scale, scale)
    n_fit = int(fitted_theta.sum())
    cov_theta = np.zeros((k, k))
    fi = np.flatnonzero(fitted_theta)
    cov_theta[np.ix_(fi, fi)] = cov_cols[:n_fit, :n_fit]
    T = prob.space.physical_jacobian(theta)
    cov_phys = T @ cov_theta @ T.T
    se_flat = np.sqrt(np.maximum(np.diag(cov_phys), 0.0))
    se_flat = np.where(fitted_theta, se_flat, np.nan)
    _, phys_unravel = ravel_pytree(prob.space.physical(theta))
    se = {name: np.asarray(v) for name, v in phys_unravel(jnp.asarray(se_flat)).items()}
    null_names: list[str] = []
    if rank < p:
        null = Vt[~keep][:, :n_fit]
        mark = np.max(np.abs(null), axis=0) > 0.2
        ids = ravel_pytree({nm: np.full(np.shape(theta[nm]), i)
                            for i, nm in enumerate(prob.space.names)})[0]
        ids = np.asarray(ids)[fitted_theta]
        null_names = [prob.space.names[int(i)] for i in np.unique(ids[mark])]
    return {"stderr": se, "rank": rank, "n_free": p, "singular_values": sv.tolist(),
            "null_names": null_names, "s2": s2, "cov_phys": cov_phys, "rss": rss,
            "defects_ss": float(np.sum(r[prob.n_out:] ** 2)), "n_res": prob.n_out}
