"""Joint identification from one log by gradient through the simulator (SPEC section 5).

Output-error least squares with multiple shooting: the log is cut into S segments of L
samples; each segment starts from its own free initial state (q1, q1', [q2, q2'], z) and is
replayed under the logged torque (zero-order hold) by the model of ``simulators``. Residuals:

    r_out = w_y (y_sim - y_meas)                    y = q1 (and q2 for the flexible model)
    r_def = w_c (x_end(segment s) - x0(segment s+1)) continuity defects, scaled per state

With one segment this is plain single shooting from a free initial state. Short segments keep
an integrating plant (and closed-loop logs, whose torque was computed from the real
position) from drifting, and make the problem far less nonconvex.

Solver: optimistix Levenberg-Marquardt with forward-mode Jacobians through the ``lax.scan``
simulator; the residual's custom JVP uses the block sparsity of multiple shooting (segment s
depends on theta and its own start state only), so a Jacobian costs k + n_state tangents
whatever the number of segments; damped normal equations by Cholesky. A portfolio of
continuation schedules guards against local minima (``identify``). Physical constraints hold
by reparametrisation (``space``). Standard errors come from the Jacobian at the optimum,
Cov = s^2 (J^T J)^+ with s^2 the residual variance, mapped to physical values through the
reparametrisation's Jacobian; the nuisance initial states are part of J, so their uncertainty
is accounted for.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from jaxflex.identify.simulators import MODEL_KINDS, ModelKind, replay
from jaxflex.identify.space import ParamSpace, set_values
from jaxflex.logs import Log
from jaxflex.params import Params
from jaxflex.plant import PlantState

DEFAULT_FREE: tuple[str, ...] = ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")


class IdentificationWarning(UserWarning):
    """Raised (as a warning) for parameters the data cannot identify."""


@dataclasses.dataclass
class IdentResult:
    """Outcome of ``identify``.

    params: identified ``Params`` (standard errors under ``extra["stderr"]``);
    stderr, rel_stderr: dict name -> list per joint (physical units; relative = stderr/|value|);
    cost: final 0.5 sum r^2 (output and continuity residuals, in the weighted units);
    rms: RMS output residual [rad]; rank, n_free: numerical rank of the Jacobian over all
    unknowns and their number; singular_values of the column-scaled Jacobian; unidentifiable:
    names the data cannot identify; warnings: messages; steps: solver steps; converged;
    wall_s: solve time [s]; problem: the ``Problem`` (for re-simulation and benchmarks);
    solution: the solver's final unknowns (theta and segment states); attempts: the
    continuation schedules tried, with their final costs.
    """

    params: Params
    stderr: dict[str, list[float]]
    rel_stderr: dict[str, list[float]]
    cost: float
    rms: float
    rank: int
    n_free: int
    singular_values: list[float]
    unidentifiable: list[str]
    warnings: list[str]
    steps: int
    converged: bool
    wall_s: float
    problem: Problem
    solution: Any
    attempts: list[dict[str, Any]] = dataclasses.field(default_factory=list)

    def table(self) -> str:
        """A short text table: name, value, standard error, relative standard error."""
        rows = [f"{'param':<24}{'value':>14}{'stderr':>12}{'rel':>9}"]
        for name in self.problem.space.names:
            vals = _value_of(self.params, name)
            for j, v in enumerate(vals):
                label = name if len(vals) == 1 else f"{name}[{j}]"
                se, rel = self.stderr[name][j], self.rel_stderr[name][j]
                rows.append(f"{label:<24}{v:>14.6g}{se:>12.3g}{100 * rel:>8.2f}%")
        rows.append(f"RMS output residual {self.rms:.3g}; Jacobian rank {self.rank}/"
                    f"{self.n_free}; {self.steps} steps; converged: {self.converged}")
        return "\n".join(rows)


def _value_of(params: Params, name: str) -> list[float]:
    from jaxflex.identify.space import get_value

    return get_value(params, name).tolist()


class Problem(eqx.Module):
    """The least-squares problem of one log: data, model structure and weights.

    ``residuals(y)`` with ``y = (theta, x0s)`` is the function handed to the solver (and to
    scipy in the benchmark).
    """

    space: ParamSpace
    tau: Array  # (S, L, n)
    y_meas: Array  # (S, L, n_out)
    dt: float = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    outputs: tuple[str, ...] = eqx.field(static=True)
    w_y: Array
    w_def: Array  # (n_state,) weights of continuity defects
    structured: bool = eqx.field(static=True, default=True)

    def state(self, v: Array, aux: Any) -> PlantState:
        """PlantState from a packed segment start vector (q1, dq1, [q2, dq2], z) per joint."""
        if self.kind == "rigid":
            q1, dq1, z = v
            return PlantState(q1=q1, dq1=dq1, q2=q1, dq2=dq1, z=z, aux=aux)
        q1, dq1, q2, dq2, z = v
        return PlantState(q1=q1, dq1=dq1, q2=q2, dq2=dq2, z=z, aux=aux)

    def pack(self, x: PlantState) -> Array:
        """Inverse of ``state`` (aux dropped)."""
        if self.kind == "rigid":
            return jnp.stack([x.q1, x.dq1, x.z])
        return jnp.stack([x.q1, x.dq1, x.q2, x.dq2, x.z])

    def simulate(self, y: tuple[dict[str, Array], Array]) -> tuple[Array, Array]:
        """Simulated outputs (S, L, n_out) and segment end states (S, n_state, n)."""
        theta, x0s = y
        plant = self.space.plant(theta)
        aux = tuple(e.aux_init(plant.n) for e in plant.effects) if plant.effects else None

        def seg(v0, tau):
            xs, x_end = replay(self.kind, plant, self.state(v0, aux), tau, self.dt, self.substeps)
            ys = jnp.concatenate([getattr(xs, o) for o in self.outputs], axis=-1)
            return ys, self.pack(x_end)

        return jax.vmap(seg)(x0s, self.tau)

    def residuals(self, y: tuple[dict[str, Array], Array], args: Any = None) -> Array:
        """Weighted output residuals and continuity defects, flattened.

        With ``structured`` (the default) the function carries a custom JVP that uses the
        multiple-shooting sparsity: segment s depends only on theta and its own start state,
        so its Jacobian is one forward-mode pass with k + n_state*n tangents (vmapped over the
        segments) instead of k + S*n_state*n; a Jacobian-vector product is then a contraction.
        Values and derivatives are the same as without it (a test checks this).
        """
        theta, x0s = y
        th_flat, th_unravel = ravel_pytree(theta)
        S, n_state, n = x0s.shape
        n_y = self.y_meas.shape[1] * self.y_meas.shape[2]
        # The problem's arrays go in as an argument (no closed-over tracers: optimistix traces
        # the residual to a jaxpr); their tangents are ignored (the data are not differentiated).
        dyn, static = eqx.partition(self, eqx.is_array)

        def seg_flat(prob, th, v0, tau):
            plant = prob.space.plant(th_unravel(th))
            aux = tuple(e.aux_init(plant.n) for e in plant.effects) if plant.effects else None
            xs, x_end = replay(prob.kind, plant, prob.state(v0.reshape(n_state, n), aux), tau,
                               prob.dt, prob.substeps)
            ys = jnp.concatenate([getattr(xs, o) for o in prob.outputs], axis=-1)
            return jnp.concatenate([ys.reshape(-1), prob.pack(x_end).reshape(-1)])

        def assemble(prob, out, v0s):
            r_out = prob.w_y * (out[:, :n_y].reshape(prob.y_meas.shape) - prob.y_meas)
            defects = (out[:-1, n_y:] - v0s[1:]) * jnp.repeat(prob.w_def, n)
            return jnp.concatenate([r_out.reshape(-1), defects.reshape(-1)])

        def primal(th, v0s, d):
            prob = eqx.combine(d, static)
            out = jax.vmap(seg_flat, in_axes=(None, None, 0, 0))(prob, th, v0s, prob.tau)
            return assemble(prob, out, v0s)

        args = (th_flat, x0s.reshape(S, n_state * n), dyn)
        if not self.structured:  # plain autodiff through the same function
            return primal(*args)
        res = jax.custom_jvp(primal)

        @res.defjvp
        def res_jvp(primals, tangents):
            th, v0s, d = primals
            dth, dv0s, _ = tangents
            prob = eqx.combine(d, static)

            def seg_and_jac(v0, tau):
                out = seg_flat(prob, th, v0, tau)
                jt, jx = jax.jacfwd(seg_flat, argnums=(1, 2))(prob, th, v0, tau)
                return out, jt, jx

            out, jt, jx = jax.vmap(seg_and_jac)(v0s, prob.tau)
            dout = jnp.einsum("smk,k->sm", jt, dth) + jnp.einsum("smd,sd->sm", jx, dv0s)
            r_out_dot = (prob.w_y * dout[:, :n_y].reshape(prob.y_meas.shape)).reshape(-1)
            def_dot = ((dout[:-1, n_y:] - dv0s[1:]) * jnp.repeat(prob.w_def, n)).reshape(-1)
            return assemble(prob, out, v0s), jnp.concatenate([r_out_dot, def_dot])

        return res(*args)

    @property
    def n_out(self) -> int:
        """Number of output residuals."""
        return int(np.prod(self.y_meas.shape))


def _velocity_estimate(q: np.ndarray, dt: float, half_window: int = 5) -> np.ndarray:
    """Central difference over +-half_window samples (clipped at the ends) [rad/s]."""
    N = q.shape[0]
    i = np.arange(N)
    lo, hi = np.clip(i - half_window, 0, N - 1), np.clip(i + half_window, 0, N - 1)
    return (q[hi] - q[lo]) / ((hi - lo)[:, None] * dt)


def make_problem(
    log: Log, init: Params, free: Sequence[str] = DEFAULT_FREE, *, model: ModelKind = "flexible",
    segment_length: int | None = None, substeps: int = 4, outputs: Sequence[str] | None = None,
    output_scale: float | None = None, continuity_weight: float = 10.0,
) -> tuple[Problem, tuple[dict[str, Array], Array]]:
    """Build the least-squares problem and its starting point from a log (see module doc).

    ``segment_length`` samples per shooting segment (default: the whole log, single
    shooting); a tail shorter than one segment is dropped. ``outputs``: measured channels
    fitted, default ("q1", "q2") for the flexible model when the log has q2, else ("q1",).
    ``output_scale`` [rad]: residuals are divided by it (default: the encoder-noise level
    estimated from the log, at least 1e-6 rad). ``continuity_weight`` scales the defects.
    """
    if model not in MODEL_KINDS:
        raise ValueError(f"identify: model must be one of {MODEL_KINDS}, got {model!r}")
    if log.tau is None or log.q1 is None:
        raise ValueError("identify: the log needs columns tau and q1")
    if log.n != init.n:
        raise ValueError(f"identify: log has {log.n} joint(s), parameters have {init.n}")
    if substeps < 1:
        raise ValueError(f"identify: substeps must be >= 1, got {substeps}")
    space = ParamSpace.build(init, free)
    if outputs is None:
        outputs = ("q1", "q2") if (model == "flexible" and log.q2 is not None) else ("q1",)
    outputs = tuple(outputs)
    for o in outputs:
        if o not in ("q1", "q2") or getattr(log, o) is None:
            raise ValueError(f"identify: output '{o}' is not a position column of this log")
    N = log.N
    L = N if segment_length is None else int(segment_length)
    if not 2 <= L <= N:
        raise ValueError(f"identify: segment_length must be in [2, {N}], got {segment_length}")
    S = N // L
    M = S * L
    dt = log.dt
    tau = log.tau[:M].reshape(S, L, -1)
    y_meas = np.concatenate([getattr(log, o)[:M] for o in outputs], axis=-1).reshape(S, L, -1)
    if output_scale is None:
        # Noise level from second differences of the first output (white noise: var * 6).
        d2 = np.diff(getattr(log, outputs[0]), 2, axis=0)
        output_scale = max(float(np.std(d2) / math.sqrt(6.0)), 1e-6)
    starts = np.arange(S) * L
    q1 = log.q1
    v1 = _velocity_estimate(q1, dt)
    lugre = init.to_lugre()
    z0 = np.asarray(lugre.z_steady(jnp.asarray(v1[starts])))
    if model == "rigid":
        x0s = np.stack([q1[starts], v1[starts], z0], axis=1)
        w_def = np.array([1.0, L * dt / 2, 1.0])
    else:
        q2 = log.q2 if log.q2 is not None else log.q1
        v2 = _velocity_estimate(q2, dt)
        x0s = np.stack([q1[starts], v1[starts], q2[starts], v2[starts], z0], axis=1)
        w_def = np.array([1.0, L * dt / 2, 1.0, L * dt / 2, 1.0])
    w_def = w_def * continuity_weight * math.sqrt(L) / output_scale
    prob = Problem(
        space=space, tau=jnp.asarray(tau), y_meas=jnp.asarray(y_meas), dt=dt, kind=model,
        substeps=substeps, outputs=outputs, w_y=jnp.asarray(1.0 / output_scale),
        w_def=jnp.asarray(w_def),
    )
    return prob, (space.theta0(init), jnp.asarray(x0s))


def _progress_printer(every: int = 1) -> Callable[..., None]:
    def verbose(**kw):
        step = kw["num_steps"][1]
        loss = kw["loss_last_accepted_step"][1]
        jax.lax.cond(
            step % every == 0,
            lambda: jax.debug.print("  [identify] step {s:4d}  cost {c:.6e}", s=step, c=loss),
            lambda: None,
        )

    return verbose


@eqx.filter_jit
def _solve(prob: Problem, y0, rtol: float, atol: float, max_steps: int, verbose):
    # Damped normal equations by Cholesky: the Jacobian is tall (thousands of residuals, tens
    # of unknowns) and a QR of it per step cost more than the Jacobian itself; the LM damping
    # keeps J^T J + lambda D positive definite, and float64 leaves ample room for squaring
    # the condition number here (the acceptance tests in tests/test_identify.py hold).
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    return optx.least_squares(prob.residuals, solver, y0, max_steps=max_steps, throw=False)


def covariance(prob: Problem, y, rank_rtol: float = 1e-9) -> dict[str, Any]:
    """Standard errors of the physical parameters at ``y`` (see module doc).

    Returns dict with ``stderr`` (name -> (n,) array), ``rank``, ``n_free``,
    ``singular_values`` (column-scaled Jacobian), ``null_names`` (parameters with weight in
    the numerically null directions), ``s2`` (residual variance per output sample).
    """
    flat, unravel = ravel_pytree(y)
    r = prob.residuals(y)
    Jm = jax.jacfwd(lambda f: prob.residuals(unravel(f)))(flat)
    Jm, r = np.asarray(Jm), np.asarray(r)
    m, p = Jm.shape
    s2 = float(np.sum(r[: prob.n_out] ** 2) / max(prob.n_out - p, 1))
    scale = np.linalg.norm(Jm, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    U, sv, Vt = np.linalg.svd(Jm / scale, full_matrices=False)
    tol = sv[0] * max(rank_rtol, np.finfo(float).eps * max(m, p))
    keep = sv > tol
    rank = int(keep.sum())
    inv = (Vt[keep].T / sv[keep] ** 2) @ Vt[keep]
    cov_flat = s2 * inv / np.outer(scale, scale)
    theta_flat, theta_unravel = ravel_pytree(y[0])
    k = theta_flat.shape[0]
    cov_theta = cov_flat[:k, :k]
    # Map to physical values through the reparametrisation's Jacobian.
    phys_flat = lambda th: ravel_pytree(prob.space.physical(theta_unravel(th)))[0]
    T = np.asarray(jax.jacfwd(phys_flat)(theta_flat))
    cov_phys = T @ cov_theta @ T.T
    se_flat = np.sqrt(np.maximum(np.diag(cov_phys), 0.0))
    _, phys_unravel = ravel_pytree(prob.space.physical(y[0]))
    se = {k_: np.asarray(v) for k_, v in phys_unravel(jnp.asarray(se_flat)).items()}
    # Names with weight in null directions (theta entries only).
    null_names: list[str] = []
    if rank < p:
        null = Vt[~keep][:, :k]
        mark = np.max(np.abs(null), axis=0) > 0.2
        names_flat = ravel_pytree({n: np.full(np.shape(y[0][n]), i) for i, n in
                                   enumerate(prob.space.names)})[0]
        for i in np.unique(np.asarray(names_flat)[mark]).astype(int):
            null_names.append(prob.space.names[i])
    return {"stderr": se, "rank": rank, "n_free": p, "singular_values": sv.tolist(),
            "null_names": null_names, "s2": s2, "cov_phys": cov_phys}


def identify(
    log: Log, init: Params, free: Sequence[str] = DEFAULT_FREE, *,
    model: ModelKind = "flexible", segment_length: int | None = None, substeps: int = 4,
    outputs: Sequence[str] | None = None, output_scale: float | None = None,
    continuity_weight: float = 10.0,
    warm_start: float | None | Sequence[float | None] = (1e-3, None, 1e-2),
    warm_steps: int = 40, accept_cost: float = 4.0,
    rtol: float = 1e-10, atol: float = 1e-10, max_steps: int = 200,
    rel_stderr_limit: float = 0.5, progress: bool | int = False,
) -> IdentResult:
    """Identify the ``free`` parameters of ``init`` from ``log`` (SPEC section 5).

    ``model``: "flexible" (eq. 3, via ``plant_step``) or "rigid" (eq. 37, Jx = I + J).
    ``segment_length``: samples per multiple-shooting segment (None: single shooting);
    ``substeps``: integrator substeps per sample; ``rtol``/``atol``: Levenberg-Marquardt
    termination; ``max_steps``: iteration cap. A parameter whose relative standard error
    exceeds ``rel_stderr_limit``, or that lies in a numerically null direction of the
    Jacobian, is named in an ``IdentificationWarning`` and in ``IdentResult.unidentifiable``.
    ``progress``: print the cost every ``progress`` steps (True: every step).
    ``warm_start``: with several segments, first solve for at most ``warm_steps`` steps with
    the continuity weight multiplied by this factor (segments nearly independent, a far less
    nonconvex problem), then tighten to the full weight (a continuation; None: off). A
    sequence of factors is a portfolio of such schedules, tried in order from the same start
    until one ends with a cost the noise explains (0.5 ||r||^2 <= ``accept_cost`` x n_out / 2,
    the residuals being scaled by the estimated noise level); otherwise the lowest cost wins.
    The output-error problem has local minima, and which schedule avoids them depends on the
    log (seed 3 of the noisy acceptance test needs the second one).
    """
    prob, y0 = make_problem(
        log, init, free, model=model, segment_length=segment_length, substeps=substeps,
        outputs=outputs, output_scale=output_scale, continuity_weight=continuity_weight,
    )
    verbose = _progress_printer(int(progress)) if progress else False
    schedules = list(warm_start) if isinstance(warm_start, (list, tuple)) else [warm_start]
    if not schedules:
        raise ValueError("identify: warm_start needs at least one schedule (a factor or None)")
    if prob.tau.shape[0] == 1:  # one segment: nothing to loosen
        schedules = [None]
    good = accept_cost * prob.n_out / 2
    t0 = time.perf_counter()
    best = None
    attempts = []
    for factor in schedules:
        y = y0
        if factor is not None:
            loose = eqx.tree_at(lambda q: q.w_def, prob, prob.w_def * factor)
            y = _solve(loose, y, rtol, atol, warm_steps, verbose).value
        sol = _solve(prob, y, rtol, atol, max_steps, verbose)
        r = np.asarray(prob.residuals(sol.value))
        cost = 0.5 * float(r @ r)
        cost = cost if np.isfinite(cost) else math.inf
        attempts.append({"warm_start": factor, "cost": cost,
                         "steps": int(sol.stats["num_steps"])})
        if progress:
            print(f"  [identify] schedule warm_start={factor}: cost {cost:.6e}"
                  f" (noise explains <= {good:.3e})")
        if best is None or cost < best[0]:
            best = (cost, sol)
        if cost <= good:
            break
    sol = best[1]
    y = jax.block_until_ready(sol.value)
    wall = time.perf_counter() - t0
    res = finish(prob, init, y, steps=int(sol.stats["num_steps"]),
                 converged=bool(sol.result == optx.RESULTS.successful), wall_s=wall,
                 rel_stderr_limit=rel_stderr_limit)
    res.attempts = attempts
    res.params.extra["identification"]["attempts"] = attempts
    return res


def finish(
    prob: Problem, init: Params, y, *, steps: int, converged: bool, wall_s: float,
    rel_stderr_limit: float = 0.5,
) -> IdentResult:
    """Build an ``IdentResult`` from a solution ``y`` of ``prob`` (also used by the scipy
    benchmark so that both solvers are judged alike)."""
    phys = {k: np.asarray(v) for k, v in prob.space.physical(y[0]).items()}
    cov = covariance(prob, y)
    se = {k: cov["stderr"][k].tolist() for k in phys}
    rel = {k: (np.asarray(se[k]) / np.maximum(np.abs(phys[k]), 1e-300)).tolist() for k in phys}
    msgs, bad = [], list(cov["null_names"])
    for k in phys:
        if max(rel[k]) > rel_stderr_limit and k not in bad:
            bad.append(k)
    if cov["null_names"]:
        msgs.append(
            f"Jacobian rank {cov['rank']} < {cov['n_free']} unknowns: the data cannot separate "
            f"{cov['null_names']}"
        )
    huge = [k for k in bad if k not in cov["null_names"]]
    if huge:
        msgs.append(
            "relative standard error above "
            f"{100 * rel_stderr_limit:g}% for {huge}: not identifiable from this log "
            "(vs, sigma0, sigma1 need low-speed dwell and frequent reversals)"
        )
    if not converged:
        msgs.append(f"solver stopped after {steps} steps without meeting its tolerance")
    for m in msgs:
        warnings.warn(m, IdentificationWarning, stacklevel=3)
    r = np.asarray(prob.residuals(y))
    cost = 0.5 * float(np.sum(r**2))
    ys, _ = prob.simulate(y)
    rms = float(np.sqrt(np.mean((np.asarray(ys) - np.asarray(prob.y_meas)) ** 2)))
    out = set_values(init, phys)
    out.extra = dict(out.extra)
    out.extra["stderr"] = {k: se[k] for k in phys}
    out.extra["identification"] = {
        "free": list(prob.space.names), "model": prob.kind, "cost": cost, "rms_residual": rms,
        "jacobian_rank": cov["rank"], "unknowns": cov["n_free"], "steps": steps,
        "converged": converged, "unidentifiable": bad,
    }
    return IdentResult(
        params=out, stderr=se, rel_stderr=rel, cost=cost, rms=rms, rank=cov["rank"],
        n_free=cov["n_free"], singular_values=cov["singular_values"], unidentifiable=bad,
        warnings=msgs, steps=steps, converged=converged, wall_s=wall_s, problem=prob,
        solution=y,
    )


def simulate_log(
    params: Params, log: Log, *, model: ModelKind = "flexible", substeps: int = 4,
    x0: PlantState | None = None,
) -> PlantState:
    """Open-loop replay of the whole log's torque through ``params``' model (single shooting
    from rest at the first logged angles unless ``x0`` is given). States (N, n) per field."""
    plant = params.to_plant()
    if x0 is None:
        q2 = log.q2[0] if (log.q2 is not None and model == "flexible") else log.q1[0]
        x0 = plant.init_state(q1=log.q1[0], q2=q2)
    fn = eqx.filter_jit(lambda p, x, u: replay(model, p, x, u, log.dt, substeps)[0])
    return fn(plant, x0, jnp.asarray(log.tau))
