"""Covariance and standard errors of a fit, from the normal equations at its optimum.

Covariance: Cov = s^2 (J^T J)^+ from the Jacobian at the optimum over the fitted unknowns
(nuisance start states included, so their uncertainty is accounted for), s^2 the residual
variance per output sample times an ``inflation`` for correlated residuals, mapped to physical
values through the reparametrisation's Jacobian.

The white-residual covariance (``covariance``), the sandwich over independent clusters
(``cluster_robust_covariance``, ``segment_robust_covariance``), and the first-order move of
the fitted parameters that a change of the residuals induces (``induced_shift``,
``remaining_step``), all from the solution's own normal equations where it has them.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxflex.fit.normal import arrow_solve, shooting_normal, undamped_solve, with_gradient
from jaxflex.fit.padding import Padding
from jaxflex.fit.problem import Problem
from jaxflex.fit.solve import Solution, problem_residuals
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device


@persistent_jit(fast_compile=True)
def induced_step(normal: dict[str, Any], dr: jax.Array, structure: str,
                 template: Any) -> jax.Array:
    """The undamped Gauss-Newton step (J^T J)^-1 J^T dr at the point whose normal equations are
    ``normal`` (``with_gradient``, ``undamped_solve``), flattened."""
    return undamped_solve(with_gradient(normal, structure, dr), structure, template)


@persistent_jit(fast_compile=True)
def _theta_information(prob: Problem, y: Any):
    """Residual and the Schur complement of the normal matrix in theta (starts eliminated)."""
    r, blocks = prob.residual_blocks(y)
    blk = shooting_normal(blocks, r)
    return r, _schur_in_theta({k: blk[k] for k in ("Ntt", "Nxt", "Dx", "U", "gt", "gx")})


@persistent_jit(fast_compile=True)
def _schur_in_theta(blk: dict[str, jax.Array]) -> jax.Array:
    """The Schur complement in theta of the shooting normal blocks (starts eliminated)."""
    Dx = blk["Dx"]
    # a start state that no residual sees (e.g. a measured link state) keeps the
    # elimination defined; it does not change theta's information
    reg = 1e-12 * jnp.maximum(jnp.max(jnp.abs(Dx)), 1e-300)
    Dx = Dx + reg * jnp.eye(Dx.shape[-1], dtype=Dx.dtype)
    return arrow_solve(blk["Ntt"], blk["Nxt"], Dx, blk["U"], blk["gt"], blk["gx"], None, None)


@persistent_jit(fast_compile=True)
def _jacobian(fn: Callable, prob: Any, y: Any):
    flat, unravel = ravel_pytree(y)
    return fn(y, prob), jax.jacfwd(lambda f: fn(unravel(f), prob))(flat)


def covariance(
    prob: Any, y: Any, *, fn: Callable = problem_residuals, inflation: float = 1.0,
    rank_rtol: float = 1e-9, solution: Solution | None = None,
) -> dict[str, Any]:
    """Covariance and standard errors of the physical parameters at ``y`` (module docstring).

    ``prob`` is a ``Problem`` or any fit with a ``space`` (``ParamSpace``) whose unknowns are
    theta alone; ``fn(y, prob)`` its residuals (as for ``least_squares``). Only the fitted
    unknowns enter (masked parameters are left out). ``inflation`` multiplies
    the residual variance (e.g. the integrated autocorrelation time of the residuals, in
    samples). Returns a dict: ``stderr`` (name -> (n,) array, physical units; NaN for names
    not fitted), ``cov_phys`` (physical covariance over the flattened names), ``rank``,
    ``n_free`` (fitted unknowns), ``singular_values`` (column-scaled Jacobian),
    ``null_names`` (parameters with weight in numerically null directions), ``s2``, ``rss``
    (sum of squared output residuals, weighted units), ``defects_ss`` (the same of the
    continuity defects), ``n_res`` (output residuals), ``cov_theta`` (the covariance of the
    unconstrained coordinates theta over the flattened names, zero rows for entries not
    fitted: where the posterior of ``jaxflex.tune.robust`` draws, so every draw keeps the
    constraints). ``solution``: the ``least_squares`` result of ``prob`` that ended at ``y``
    (same object): a multiple-shooting problem then reuses its normal equations, any other
    the Jacobian the dense solver kept (the same numbers, no second linearisation and
    compilation).
    """
    theta = prob.split(y)[0] if hasattr(prob, "split") else y
    if (fn is problem_residuals and isinstance(prob, Problem) and prob.free_starts
            and prob.segs.count > 1):
        reuse = (solution is not None and solution.y is y and solution.normal is not None
                 and "Ntt" in solution.normal)
        pad = Padding.of(prob, y)  # the elimination in the slots' layout (once per bucket)
        if reuse:
            normal = solution.normal if pad is None else pad.blocks_in(solution.normal)
            info = (solution.residual, _schur_in_theta(normal))
        elif pad is None:
            info = _theta_information(prob, y)
        else:
            r, St = _theta_information(prob.padded(pad.slots), pad.unknowns(y))
            info = (pad.rows_back(r), St)
        return _covariance_shooting(prob, info, theta, inflation, rank_rtol)
    if (solution is not None and solution.y is y and solution.normal is not None
            and "J" in solution.normal and solution.residual is not None):
        # the dense solver's own Jacobian at y: no second linearisation and compilation
        r, Jm = np.asarray(solution.residual), np.asarray(solution.normal["J"])
    else:
        r, Jm = (np.asarray(a) for a in _jacobian(fn, prob, y))
    n_out = int(getattr(prob, "n_out", r.size))
    th_flat, th_unravel = ravel_pytree(theta)
    k = th_flat.shape[0]
    fitted_theta = prob.space.fitted_flat()
    cols = np.ones(Jm.shape[1], bool)
    cols[:k] = fitted_theta
    J = Jm[:, cols]
    m, p = J.shape
    rss = float(np.sum(r[: n_out] ** 2))
    s2 = rss / max(n_out - p, 1) * inflation
    scale = np.linalg.norm(J, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    _, sv, Vt = np.linalg.svd(J / scale, full_matrices=False)
    tol = sv[0] * max(rank_rtol, np.finfo(float).eps * max(m, p)) if sv.size else 0.0
    keep = sv > tol
    rank = int(keep.sum())
    inv = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep]
    cov_cols = s2 * inv / np.outer(scale, scale)
    n_fit = int(fitted_theta.sum())
    null = Vt[~keep][:, :n_fit].T if rank < p else np.zeros((n_fit, 0))
    return _covariance_report(prob, theta, cov_cols[:n_fit, :n_fit], null, rank=rank, n_free=p,
                              singular_values=sv.tolist(), s2=s2, rss=rss,
                              defects_ss=float(np.sum(r[n_out:] ** 2)), n_res=n_out)


def segment_robust_covariance(prob: Problem, solution: Solution) -> dict[str, Any] | None:
    """Covariance of the fitted parameters that holds when the residuals are correlated in
    time (a model's mismatch on a real log; quantisation of a slow encoder): the sandwich
    with the multiple-shooting segments as independent clusters (``cluster_robust_covariance``
    over each segment's output rows). About the white-residual covariance (``covariance``)
    when the noise is white; larger by the residuals' correlation time where they are not.

    ``solution``: the ``least_squares`` result of ``prob``. Returns None when it carries no
    normal equations or the log has fewer than (fitted parameters + 2) segments; else
    ``cluster_robust_covariance``'s dict."""
    if not isinstance(prob, Problem):
        return None
    S = prob.segs.count
    rows = prob.n_out // S  # output rows are (segment, sample, column) ordered
    return cluster_robust_covariance(
        prob, solution, [np.arange(s * rows, (s + 1) * rows) for s in range(S)])


def cluster_robust_covariance(prob: Any, solution: Solution,
                              clusters: Sequence[np.ndarray]) -> dict[str, Any] | None:
    """Cluster-robust (sandwich) covariance of the fitted parameters: H^-1 (sum_c g_c g_c^T)
    H^-1 x C / (C - 1), g_c = J_c^T r_c the gradient of the residual rows of cluster c (index
    arrays into ``solution.residual``, in ``prob``'s layout; the clusters independent of each
    other, the rows within one correlated in any way). Each H^-1 g_c is the Gauss-Newton step
    that cluster's residuals induce (``induced_step`` on the solution's own normal
    equations: no new Jacobian, one compiled solve; with multiple shooting the start states'
    elimination is included, in the slots' layout).

    ``prob``: a ``Problem`` or any fit with a ``space`` whose unknowns are theta alone (as for
    ``covariance``); ``solution``: its ``least_squares`` result. Returns None when the
    solution carries no normal equations, there are fewer than (fitted parameters + 2)
    clusters (too few to estimate a covariance from) or a step is not finite; else
    ``covariance``'s ``stderr``, ``cov_theta`` and ``cov_phys``, with ``clusters`` (their
    count)."""
    if solution.normal is None or solution.residual is None:
        return None
    fitted = np.flatnonzero(prob.space.fitted_flat())
    C = len(clusters)
    if C < fitted.size + 2:
        return None
    y = solution.y
    structure = "shooting" if "Ntt" in solution.normal else "dense"
    pad = Padding.of(prob, y) if structure == "shooting" else None
    normal, y_in = solution.normal, y
    if pad is not None:  # the solve in the slots' layout: compiled once per bucket
        normal, y_in = pad.blocks_in(normal), pad.unknowns(y)
    template = jax.tree_util.tree_map(
        lambda a: to_device(np.zeros(np.shape(a), a.dtype)), y_in)
    theta = prob.split(y)[0] if hasattr(prob, "split") else y
    k = ravel_pytree(theta)[0].shape[0]
    r = np.asarray(solution.residual)
    steps = []
    for rows in clusters:
        w = np.zeros_like(r)
        w[rows] = r[rows]
        w = pad.rows_in(w) if pad is not None else w
        steps.append(np.asarray(induced_step(normal, to_device(w), structure, template))[:k][fitted])
    D = np.asarray(steps)
    if not np.all(np.isfinite(D)):  # a blown replay or a failed solve: nothing to estimate
        return None
    rep = _covariance_report(prob, theta, C / (C - 1) * D.T @ D, np.zeros((fitted.size, 0)))
    return {"stderr": rep["stderr"], "cov_theta": rep["cov_theta"],
            "cov_phys": rep["cov_phys"], "clusters": C}


def _covariance_report(prob: Any, theta: Any, cov_fit: np.ndarray, null: np.ndarray,
                       **stats: Any) -> dict[str, Any]:
    """Map the covariance of the fitted theta entries to physical standard errors and name the
    parameters with weight in the null directions (columns of ``null``); ``stats`` pass on."""
    fitted_theta = prob.space.fitted_flat()
    k = fitted_theta.size
    fi = np.flatnonzero(fitted_theta)
    cov_theta = np.zeros((k, k))
    cov_theta[np.ix_(fi, fi)] = cov_fit
    T = prob.space.physical_jacobian(theta)
    cov_phys = T @ cov_theta @ T.T
    se_flat = np.sqrt(np.maximum(np.diag(cov_phys), 0.0))
    se_flat = np.where(fitted_theta, se_flat, np.nan)
    se, at = {}, 0  # ravel_pytree's order: sorted names
    for name, v in sorted(prob.space.physical_values(theta).items()):
        se[name] = se_flat[at:at + v.size].reshape(v.shape)
        at += v.size
    null_names: list[str] = []
    if null.shape[1]:
        mark = np.max(np.abs(null), axis=1) > 0.2
        ids = ravel_pytree({nm: np.full(np.shape(theta[nm]), i)
                            for i, nm in enumerate(prob.space.names)})[0]
        ids = np.asarray(ids)[fitted_theta]
        null_names = [prob.space.names[int(i)] for i in np.unique(ids[mark])]
    return {"stderr": se, "null_names": null_names, "cov_phys": cov_phys,
            "cov_theta": cov_theta, **stats}


def _covariance_shooting(prob: Problem, info: tuple[Any, Any], theta: Any, inflation: float,
                         rank_rtol: float) -> dict[str, Any]:
    """``covariance`` of a free-start multiple-shooting problem in time linear in the log
    length: theta's covariance is s^2 times the inverse of the Schur complement of the normal
    matrix (the segment starts eliminated, so their uncertainty is accounted for), the same
    numbers as the dense route; singular values and rank are those of theta's part after the
    elimination (the starts are taken as determined)."""
    r, St = (np.asarray(a) for a in info)
    n_out = prob.n_out
    S = prob.segs.count
    d = int(np.prod(prob.segs.x0.shape[1:]))
    fitted_theta = prob.space.fitted_flat()
    fi = np.flatnonzero(fitted_theta)
    St = St[np.ix_(fi, fi)]
    p = int(fi.size) + S * d
    rss = float(np.sum(r[:n_out] ** 2))
    s2 = rss / max(n_out - p, 1) * inflation
    scale = np.sqrt(np.maximum(np.diag(St), 0.0))
    scale = np.where(scale > 0, scale, 1.0)
    w, V = np.linalg.eigh(St / np.outer(scale, scale))
    order = np.argsort(w)[::-1]
    w, V = w[order], V[:, order]
    sv = np.sqrt(np.maximum(w, 0.0))
    tol = sv[0] * max(rank_rtol, np.finfo(float).eps * max(r.size, p)) if sv.size else 0.0
    keep = sv > tol
    inv = (V[:, keep] / sv[keep] ** 2) @ V[:, keep].T
    return _covariance_report(prob, theta, s2 * inv / np.outer(scale, scale), V[:, ~keep],
                              rank=int(keep.sum()) + S * d, n_free=p,
                              singular_values=sv.tolist(), s2=s2, rss=rss,
                              defects_ss=float(np.sum(r[n_out:] ** 2)), n_res=n_out)


def _induced(prob: Problem, solution: Solution, e: Any) -> tuple[np.ndarray, Any, Any]:
    """The undamped Gauss-Newton step (J^T J)^-1 J^T e at ``solution`` from its own normal
    equations, flattened, with the unknowns it applies to and the padding they sit in (as
    ``least_squares`` solves: the slots' layout of a shooting problem; None: the problem's
    own)."""
    y = solution.y
    structure = "shooting" if "Ntt" in solution.normal else "dense"
    e = np.asarray(e, float)
    pad = Padding.of(prob, y) if structure == "shooting" else None
    normal, e_in, y_in = solution.normal, e, y
    if pad is not None:  # the solve in the slots' layout: compiled once per bucket
        normal, e_in, y_in = pad.blocks_in(normal), pad.rows_in(e), pad.unknowns(y)
    template = jax.tree_util.tree_map(
        lambda a: to_device(np.zeros(np.shape(a), a.dtype)), y_in)
    return np.asarray(induced_step(normal, e_in, structure, template)), y_in, pad


def induced_shift(prob: Problem, solution: Solution, e: Any,
                  ) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray, np.ndarray]:
    """The first-order move -(J^T J)^-1 J^T e of the fitted parameters that a change ``e``
    of the residuals (rows as ``prob``'s residual) induces at ``solution``, from its own
    normal equations, beside their standard errors (segment-robust where the log has the
    segments for it, else white).

    Returns ``(shift, stderr, labels, fitted, cov)``: the shift and standard error of each
    fitted theta entry (engine coordinates), every entry's "name[j]" label, the indices of
    the fitted entries among them, and their covariance."""
    y = solution.y
    step = _induced(prob, solution, e)[0]
    theta = prob.split(y)[0] if hasattr(prob, "split") else y
    k = ravel_pytree(theta)[0].shape[0]
    fitted = np.flatnonzero(prob.space.fitted_flat())
    shift = -step[:k][fitted]  # the Gauss-Newton step solves (J^T J) d = -J^T e
    robust = segment_robust_covariance(prob, solution)
    cov = (robust if robust is not None else covariance(prob, y, solution=solution))[
        "cov_theta"][np.ix_(fitted, fitted)]
    se = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    labels = [f"{k}[{j}]" for k in sorted(theta) for j in range(np.size(theta[k]))]
    return shift, se, labels, fitted, cov


def induced_point(prob: Problem, solution: Solution, e: Any, fraction: float = 1.0) -> Any:
    """The unknowns of ``solution`` moved by ``fraction`` of the first-order move
    -(J^T J)^-1 J^T e that a change ``e`` of the residuals induces (``induced_shift``'s move
    of every unknown, the segments' start states included): to first order, the minimum of
    the residuals r + ``fraction`` e. None where the move is not finite."""
    step, y_in, pad = _induced(prob, solution, e)
    if not np.all(np.isfinite(step)):
        return None
    flat, unravel = ravel_pytree(y_in)
    moved = unravel(flat - fraction * to_device(step))
    return pad.unknowns_back(moved) if pad is not None else moved


def remaining_step(prob: Problem, solution: Solution) -> float:
    """The largest move of a fitted parameter, in its standard errors (segment-robust where
    the log has the segments for it), that a full Gauss-Newton step from ``solution`` would
    make: the statistical stop judged at the standard errors the fit reports, which a
    model's mismatch on a real log makes far larger than the white noise's. inf without
    normal equations, for a non-finite step, or for normal equations whose covariance cannot
    be formed (non-finite entries: the step cannot be judged)."""
    if solution.normal is None or solution.residual is None:
        return math.inf
    try:
        shift, se, *_ = induced_shift(prob, solution, solution.residual)
    except np.linalg.LinAlgError:
        return math.inf
    if not shift.size:
        return 0.0
    return float(np.max(np.abs(shift) / se)) if np.all(np.isfinite(shift)) else math.inf
