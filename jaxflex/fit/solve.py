"""The one solver path of jaxflex: ``least_squares``, its step loop and its stops.

Solver: optimistix's Levenberg-Marquardt (a damped-Newton descent inside a trust region) on
``Problem.residuals``, with forward-mode Jacobians (the residual's structured custom JVP) and
the damped normal equations solved by Cholesky. Its ``init`` and a loop of steps
(``_steps``) are compiled once per problem *shape*; the loop runs up to a number of steps
given at run time (about a second's worth) and the host calls it again, so

- the step limit is a plain number (no recompilation for another ``max_steps``, a warm stage
  and a final stage share one compilation, and so do all candidates of the discrepancy
  workflow, whose problems differ only in data such as masks and weights);
- progress can be printed and an interrupt (Ctrl-C) ends the run between calls, returning the
  last accepted point marked unconverged;
- the stops (tolerances, the statistical and the progress stop) are judged inside the loop, so
  a step costs no dispatch and no round trip to the host.

A trial the trust region rejects costs one simulation (``LevenbergMarquardt.step`` judges it on
its residual and linearises only at accepted points), and the normal equations are formed once
per accepted point; the final residual and normal equations come back in the ``Solution``, so
the final cost and the covariance need no further compilation of the residual.

The parts: the descent and trust region in ``jaxflex.fit.levenberg_marquardt``, the
structured linear solves in ``jaxflex.fit.normal``, the segment slots in
``jaxflex.fit.padding``; covariance in ``jaxflex.fit.uncertainty``, replay in
``jaxflex.fit.replay``, the integrator's error in ``jaxflex.fit.discretisation``.
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

from jaxflex.fit.levenberg_marquardt import LevenbergMarquardt, ScaledDampedNewtonDescent
from jaxflex.fit.normal import gauss_newton_decrement
from jaxflex.fit.padding import Padding
from jaxflex.fit.problem import Problem
from jaxflex.fit.replay import residuals as replay_residuals
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device
from jaxflex.io.progress import Progress


@dataclasses.dataclass
class Solution:
    """Outcome of ``least_squares``: unknowns ``y``, accepted ``steps`` taken, whether the
    solver's tolerance was met (``converged``), the final ``cost`` 0.5 ||r||^2 (weighted
    units), ``reason`` in words, ``seconds`` of wall time; ``residual`` r at ``y`` and
    ``normal``, the undamped normal equations there (the blocks of ``shooting_blocks`` or
    ``dense_normal_equations``), which ``covariance`` reuses instead of linearising again;
    ``decrement``, the Gauss-Newton decrement at ``y`` (``gauss_newton_decrement``: the drop
    of ||r||^2 a further full Gauss-Newton step would bring were the residuals linear)."""

    y: Any
    steps: int
    converged: bool
    cost: float
    reason: str
    seconds: float
    residual: Any = None
    normal: dict[str, Any] | None = None
    decrement: float | None = None
    #: the run ended on Ctrl-C (``y`` is the last accepted point); workflows stop there
    interrupted: bool = False
    #: the solver failed (non-finite values or a failed linear solve): ``y`` is the last
    #: accepted point, but its ``normal`` equations may hold non-finite entries
    failed: bool = False


class _WithAux(eqx.Module):
    """A residual function ``fn(y, args)`` in optimistix's form ``(residual, aux)``;
    ``blocks(y, args)``, where given, the residual and its Jacobian blocks
    (``problem_residual_blocks``), which the solver then takes instead of linearising ``fn``."""

    fn: Callable
    blocks: Callable | None = None

    def __call__(self, y: Any, args: Any) -> tuple[jax.Array, None]:
        return self.fn(y, args), None


def problem_residuals(y: Any, prob: Problem) -> jax.Array:
    """``prob.residuals(y)``: the residual function of every ``Problem``."""
    return prob.residuals(y)


def problem_residual_blocks(y: Any, prob: Problem) -> tuple[jax.Array, dict[str, jax.Array]]:
    """``prob.residual_blocks(y)``: the residual of a free-start multiple-shooting ``Problem``
    and its Jacobian blocks."""
    return prob.residual_blocks(y)


def _solver(rtol: float, atol: float, scaling: str, structure: str,
            geodesic: float) -> LevenbergMarquardt:
    return LevenbergMarquardt(rtol=rtol, atol=atol, geodesic=geodesic,
                              descent=ScaledDampedNewtonDescent(scaling=scaling,
                                                                structure=structure))


@persistent_jit(fast_compile=True)
def _init(solver: LevenbergMarquardt, fn: _WithAux, y: Any, args: Any):
    f_struct = jax.eval_shape(lambda: fn(y, args)[0])
    return solver.init(fn, y, args, {}, f_struct, None, frozenset())


def _one_step(solver: LevenbergMarquardt, fn: _WithAux, y: Any, state: Any, args: Any):
    y, state, _ = solver.step(fn, y, args, {}, state, frozenset())
    done, result = solver.terminate(fn, y, args, {}, state, frozenset())
    cost = 0.5 * jnp.sum(state.f_info.residual ** 2)
    # MINPACK's xtol test: the last trial was rejected and the trust region has shrunk until
    # the next trial step is within the tolerance on the unknowns (Cauchy's y-part). No step
    # larger than the tolerance lowers the cost: the point is stationary to that tolerance
    # (at a zero-residual optimum the cost is at rounding level and every trial is rejected,
    # so optimistix's test, which needs an accepted step, would never fire).
    y_scale = jax.tree_util.tree_map(lambda a: solver.atol + solver.rtol * jnp.abs(a), y)
    trial = jax.tree_util.tree_map(lambda a, b, c: jnp.abs(a - b) / c, state.y_eval, y, y_scale)
    stalled = (state.num_steps_since_acceptance > 0) & (solver.norm(trial) < 1)
    decrement = gauss_newton_decrement(state.descent_state.normal, solver.descent.structure,
                                       state.descent_state.template)
    return y, state, done, result == optx.RESULTS.successful, cost, stalled, decrement


@dataclasses.dataclass(frozen=True)
class CostBound:
    """A bound ``scale * cost + const`` in units of ||r||^2 as a function of the cost
    0.5 ||r||^2 (``least_squares``' ``decrement_tol`` and ``stall``), or the larger of that
    and ``other`` = (scale, const): a callable the compiled loop evaluates itself, so that the
    run takes many steps per call (any other callable is evaluated on the host after every
    step)."""

    scale: float
    const: float = 0.0
    other: tuple[float, float] = (0.0, -math.inf)

    def __call__(self, c: float) -> float:
        return max(self.scale * c + self.const, self.other[0] * c + self.other[1])


def _device_bound(bound: float | Callable[[float], float] | None,
                  ) -> tuple[bool, list[float]]:
    """(judged on the host, [scale, constant, other scale, other constant]) of a stop's bound
    for ``_steps`` (off: constants of -inf)."""
    off = [0.0, -math.inf, 0.0, -math.inf]
    if bound is None:
        return False, off
    if isinstance(bound, CostBound):
        return False, [float(bound.scale), float(bound.const), float(bound.other[0]),
                       float(bound.other[1])]
    if callable(bound):
        return True, off
    return False, [0.0, float(bound), 0.0, -math.inf]


#: Why ``_steps`` stopped: still running (its step limit), failed (non-finite values or a
#: failed linear solve), optimistix's tolerance, the statistical stop, MINPACK's xtol test,
#: the progress stop (``least_squares``' ``stall``).
_RUNNING, _FAILED, _TOLERANCE, _DECREMENT, _XTOL, _STALLED = range(6)
#: Most steps one call of ``_steps`` runs (the length of the cost trace it returns), and the
#: steps of a run's first call (later ones take about a second each).
_CHUNK, _FIRST_CHUNK = 32, 8
#: The longest window of ``least_squares``' progress stop (``stall``).
_HISTORY = 64


def _steps_loop(solver: LevenbergMarquardt, fn: _WithAux, y: Any, state: Any, args: Any,
                control: jax.Array, history: jax.Array):
    """Up to ``control[0]`` solver steps in one compiled loop, ending at the first that meets a
    stop (the codes above): the host loop's work without a dispatch and a device-to-host
    round trip per step. ``control`` = (limit, decrement bound, progress bound, steps already
    run, progress window W <= ``_HISTORY``), each bound as ``CostBound``'s two pieces (scale
    and constant, twice: the larger of ``scale * cost + const`` in units of ||r||^2; a
    constant of -inf: off), and ``history`` the costs of the last ``_HISTORY`` + 1 steps
    (oldest first), carried from call to call; every window shares the program. Returns (y,
    state, steps run, stop code, cost, decrement, history, the costs of the steps run
    (``_CHUNK``, NaN after the last))."""
    limit, dec_a, dec_b, dec_a2, dec_b2, stall_a, stall_b, stall_a2, stall_b2, before, window = (
        control[i] for i in range(11))
    back = (_HISTORY - window).astype(jnp.int32)  # where the cost W steps back sits

    def cond(carry):
        return (carry[0] < limit) & (carry[3] == _RUNNING)

    def body(carry):
        k, y, state, _, _, _, hist, trace = carry
        y, state, done, ok, c, stalled, dec = _one_step(solver, fn, y, state, args)
        at = lambda a, b, a2, b2: jnp.maximum(a * c + b, a2 * c + b2)  # noqa: E731 - CostBound
        hist = jnp.concatenate([hist[1:], c[None]])
        fell = 2.0 * (jax.lax.dynamic_index_in_dim(hist, back, keepdims=False) - c)
        stall = (before + k + 1 > window) & (fell < at(stall_a, stall_b, stall_a2, stall_b2))
        small = dec < at(dec_a, dec_b, dec_a2, dec_b2)
        code = jnp.select([~ok, done, small, stalled, stall],
                          [_FAILED, _TOLERANCE, _DECREMENT, _XTOL, _STALLED],
                          _RUNNING).astype(jnp.int32)
        return (k + 1, y, state, code, c, dec, hist, trace.at[k].set(c))

    zero = jnp.zeros((), history.dtype)
    carry = (jnp.zeros((), jnp.int32), y, state, jnp.asarray(_RUNNING, jnp.int32), zero, zero,
             history,
             jnp.full((_CHUNK,), jnp.nan, history.dtype))
    k, y, state, code, c, dec, hist, trace = jax.lax.while_loop(cond, body, carry)
    return y, state, k, code, c, dec, hist, trace


#: ``_steps_loop`` compiled for run speed (XLA's defaults), and for compile speed
#: (``least_squares(small=True)``: a small fit run once, e.g. the static map's four
#: parameters; ``jaxflex.runtime.tracecache.FAST_COMPILE_OPTIONS``). Both share one trace.
_steps = persistent_jit(_steps_loop)
_steps_small = persistent_jit(_steps_loop, fast_compile=True)


def _fell(history: jax.Array, window: int, c: float) -> float:
    """On the host, how much ||r||^2 fell over the last ``window`` steps to the cost ``c``
    (``_steps``' ``history``: the cost ``window`` steps back)."""
    return 2.0 * (float(np.asarray(history)[_HISTORY - window]) - c)


@persistent_jit(fast_compile=True)
def _cost(fn: Callable, y: Any, args: Any) -> jax.Array:
    r = fn(y, args)
    return 0.5 * jnp.sum(r**2)


def cost(prob: Problem, y: Any, fn: Callable = problem_residuals) -> float:
    """0.5 ||r||^2 at ``y`` of ``fn(y, prob)`` (default: the problem's residuals, from the
    program that also gives its simulated outputs and gap, ``jaxflex.fit.replay``; another
    ``fn`` compiled once per shape); inf if not finite."""
    if fn is problem_residuals and isinstance(prob, Problem):
        return residual_cost(replay_residuals(prob, y))
    c = float(_cost(fn, y, prob))
    return c if math.isfinite(c) else math.inf


def residual_cost(r: Any) -> float:
    """0.5 ||r||^2 of residual rows already made (``cost``'s measure), on the host; inf if
    not finite."""
    r = np.asarray(r)
    c = 0.5 * float(np.sum(r * r))
    return c if math.isfinite(c) else math.inf


def least_squares(
    prob: Any, y0: Any, *, fn: Callable = problem_residuals, rtol: float = 1e-10,
    atol: float = 1e-10, max_steps: int = 200, scaling: str = "identity",
    structure: str = "auto", progress: Progress | None = None,
    decrement_tol: float | Callable[[float], float] | None = None, geodesic: float = 0.0,
    bucket: bool = True, stall: tuple[int, float | Callable[[float], float]] | None = None,
    small: bool = False,
) -> Solution:
    """Levenberg-Marquardt on the residuals ``fn(y, prob)`` from ``y0`` (module docstring).

    ``fn``: a module-level function (its identity keys the compilation cache; default
    ``problem_residuals`` for a ``Problem``, other curve fits pass their own with their data
    as ``prob``); ``rtol``/``atol``: optimistix's Cauchy termination on the change of the unknowns and the
    cost; ``max_steps``: iteration cap (a host-side number, no recompilation); ``scaling``:
    the damping matrix of ``ScaledDampedNewtonDescent`` ("identity" or "marquardt");
    ``structure``: "dense", "shooting" (free-start multiple shooting, linear in the log
    length) or "auto" (shooting for a ``Problem`` with free starts and several segments);
    ``progress`` (``jaxflex.io.progress.Progress``) gets every step, of ``max_steps``, with
    its cost. Besides optimistix's test, the run
    ends converged when a rejected trial leaves the trust region below the tolerance on the
    unknowns (MINPACK's xtol test; see ``_one_step``). ``decrement_tol``: a statistical stop for
    residuals in units of their noise standard deviation: the run also ends converged at an
    accepted point whose Gauss-Newton decrement (``gauss_newton_decrement``, in units of
    chi-square) is below ``decrement_tol``, i.e. the step that remains is smaller than
    sqrt(decrement_tol) standard errors in every direction, far inside what the noise lets the
    data determine (None: off; the tolerances alone decide); a callable of the current cost
    0.5 ||r||^2 gives the bound at each point instead (for residuals in other units: e.g.
    ``CostBound(0.01 * 2 / m)``, 0.01 * 2 c / m, measures the decrement in units of the
    residual variance the fit itself estimates, so the step that remains is below 0.1 of the
    standard errors ``covariance`` reports; a ``CostBound`` is judged inside the compiled
    loop, any other callable on the host after every step). ``geodesic``: > 0 turns on
    geodesic acceleration (``geodesic_step``) with this bound on 2 |a| / |v| (0.75 is the
    usual choice; 0: plain Levenberg-Marquardt). ``bucket``: a free-start multiple-shooting
    ``Problem`` of more than 2 segments is solved in ``segment_slots`` slots (inert padding
    segments, ``Problem.padded``; the solution, residual and normal equations are cut back to
    the data), so logs of other lengths share the compiled solver (False: its own shape).
    ``small``: a small fit that a run makes once or twice (a handful of unknowns, a cheap
    residual): its loop is compiled for compile speed, not run speed
    (``jaxflex.runtime.tracecache.FAST_COMPILE_OPTIONS``; e.g. the static map's fit).
    Raises ``ValueError`` for
    ``max_steps < 1`` or a negative ``decrement_tol``.
    """
    if max_steps < 1:
        raise ValueError(f"fit: max_steps must be >= 1, got {max_steps}")
    if decrement_tol is not None and not callable(decrement_tol) and not decrement_tol >= 0:
        raise ValueError(f"fit: decrement_tol must be >= 0, a callable or None, "
                         f"got {decrement_tol}")
    if stall is not None and not 1 <= int(stall[0]) <= _HISTORY:
        raise ValueError(f"fit: the stall window must be 1 to {_HISTORY} steps, got {stall[0]}")
    t0 = time.perf_counter()
    prob, y, pad, solver, wrapped = _setup(prob, y0, fn, rtol, atol, scaling, structure,
                                           geodesic, bucket)
    state = _init(solver, wrapped, y, prob)
    # the stops run on the device (``_steps``) when their bounds are numbers or ``CostBound``s;
    # any other callable is judged here, after every single step
    dec_on_host, dec_bound = _device_bound(decrement_tol)
    window = int(stall[0]) if stall is not None else 1
    stall_on_host, stall_bound = _device_bound(None if stall is None else stall[1])
    one_at_a_time = dec_on_host or stall_on_host
    history = _empty_history()  # costs, the last W back included
    loop = _steps_small if small else _steps
    steps, code, c, dec, chunk, interrupted = 0, _RUNNING, None, None, _FIRST_CHUNK, False
    try:
        while steps < max_steps and code == _RUNNING:
            limit = 1 if one_at_a_time else min(chunk, max_steps - steps, _CHUNK)
            control = _control(limit, dec_bound, stall_bound, steps, window)
            t_call = time.perf_counter()
            y, state, k_a, code_a, c_a, dec_a_, history, trace = loop(
                solver, wrapped, y, state, prob, control, history)
            k, code, c, dec = int(k_a), int(code_a), float(c_a), float(dec_a_)
            steps += k  # before the progress calls: y and state are k steps on already
            if progress is not None:
                for i, ci in enumerate(np.asarray(trace)[:k]):
                    progress(steps - k + i + 1, max_steps,
                             f"step {steps - k + i + 1:4d}  cost {float(ci):.6e}")
            # about a second a call: an interrupt is seen between calls
            chunk = int(np.clip(1.0 / max((time.perf_counter() - t_call) / max(k, 1), 1e-6),
                                1, _CHUNK))
            if code == _RUNNING and dec_on_host and dec < decrement_tol(c):
                code = _DECREMENT
            if code == _RUNNING and stall_on_host and steps > window and (
                    _fell(history, window, c) < stall[1](c)):
                code = _STALLED
    except KeyboardInterrupt:
        interrupted = True
    y = jax.block_until_ready(y)
    # the state's residual is the one at y (that of the last accepted point): no second
    # compilation of the residual for the final cost
    final = cost(prob, y, fn) if c is None else float(c)
    final = final if math.isfinite(final) else math.inf
    residual = None if c is None else state.f_info.residual
    normal = None if c is None else state.descent_state.normal
    if pad is not None:
        y = pad.unknowns_back(y)
        residual = None if residual is None else pad.rows_back(residual)
        normal = None if normal is None else pad.blocks_back(normal)
    if interrupted:
        reason = f"interrupted after {steps} steps"
    elif code == _DECREMENT:
        bound = decrement_tol(c) if callable(decrement_tol) else decrement_tol
        reason = (f"statistical stop: a full Gauss-Newton step would lower ||r||^2 "
                  f"by {dec:.3g} < {bound:.3g}")
    elif code == _XTOL:
        reason = ("tolerance met (the trust region shrank below the tolerance on the "
                  "unknowns without a step that lowers the cost)")
    elif code == _STALLED:
        limit_c = stall[1](c) if callable(stall[1]) else stall[1]
        reason = (f"stalled: ||r||^2 fell by {_fell(history, window, c):.3g} < {limit_c:.3g} "
                  f"over the last {window} steps (not converged)")
    elif code == _TOLERANCE:
        reason = "tolerance met"
    elif code == _FAILED:
        reason = "solver failed (non-finite values or a failed linear solve)"
    else:
        reason = f"stopped at max_steps = {max_steps} without meeting the tolerance"
    converged = code in (_TOLERANCE, _DECREMENT, _XTOL) and not interrupted
    if code == _FAILED and normal is not None and not all(
            bool(np.all(np.isfinite(np.asarray(v)))) for v in jax.tree_util.tree_leaves(normal)):
        normal = None  # not the equations of y: whoever needs them linearises y afresh
    return Solution(y=y, steps=steps, converged=converged,
                    cost=final, reason=reason, seconds=time.perf_counter() - t0,
                    residual=residual, normal=normal,
                    decrement=None if dec is None else float(dec), interrupted=interrupted,
                    failed=code == _FAILED and not interrupted)


def _setup(prob: Any, y0: Any, fn: Callable, rtol: float, atol: float, scaling: str,
           structure: str, geodesic: float, bucket: bool,
           ) -> tuple[Any, Any, Padding | None, LevenbergMarquardt, _WithAux]:
    """``least_squares``' problem, start, padding, solver and residual function as its
    compiled loop sees them (arguments as there)."""
    if structure == "auto":
        shooting = isinstance(prob, Problem) and prob.free_starts and prob.segs.count > 1
        structure = "shooting" if shooting else "dense"
    # a shooting problem runs in its bucket of segment slots (``segment_slots``), so that a
    # log of another length reuses the compiled step; the solution is cut back to the data
    pad = (Padding.of(prob, y0) if (bucket and structure == "shooting"
                                    and fn is problem_residuals) else None)
    if pad is not None:
        prob, y0 = prob.padded(pad.slots), pad.unknowns(y0)
    solver = _solver(rtol, atol, scaling, structure, geodesic)
    own_blocks = structure == "shooting" and fn is problem_residuals
    return prob, y0, pad, solver, _WithAux(fn, problem_residual_blocks if own_blocks else None)


def _control(limit: int, dec_bound: list[float], stall_bound: list[float], steps: int,
             window: int) -> jax.Array:
    """``_steps``' control vector: (limit, the decrement's and the progress stop's bounds as
    ``_device_bound`` gives them, steps already run, progress window)."""
    return to_device(np.array([limit, *dec_bound, *stall_bound, steps, window], float))


def _empty_history() -> jax.Array:
    """``_steps``' cost history before the first step (no cost yet: inf)."""
    return to_device(np.full(_HISTORY + 1, np.inf))


def trace_solver(
    prob: Any, y0: Any, *, fn: Callable = problem_residuals, rtol: float = 1e-10,
    atol: float = 1e-10, scaling: str = "identity", structure: str = "auto",
    geodesic: float = 0.0, bucket: bool = True, small: bool = False, **loop_options: Any,
) -> bool:
    """Trace and keep (``jaxflex.runtime.tracecache``) the compiled loop that ``least_squares(prob,
    y0, ...)`` with the same options will run, without compiling it or taking a step: the
    part of a first solve that holds Python's interpreter lock. A caller that then hands the
    solve to a background thread (``jaxflex.identify.compile_ahead``) lets it compile on one
    core while this thread works on the other, instead of both tracing by turns. Runs the
    solver's small start program (``_init``). ``small``: as ``least_squares``' (which of its
    two compiled loops). ``loop_options``: ``least_squares``' other options (``max_steps``,
    ``decrement_tol``, ``stall``, ``progress``), which do not change the program and are
    ignored. Returns True when a kept program now serves the solve, False
    when the trace cache is off (nothing is traced)."""
    del loop_options
    prob, y, _, solver, wrapped = _setup(prob, y0, fn, rtol, atol, scaling, structure,
                                         geodesic, bucket)
    state = _init(solver, wrapped, y, prob)
    off = _device_bound(None)[1]  # the control's values do not shape the program
    loop = _steps_small if small else _steps
    return loop.prepare(solver, wrapped, y, state, prob, _control(1, off, off, 0, 1),
                        _empty_history())
