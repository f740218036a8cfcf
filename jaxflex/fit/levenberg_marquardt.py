"""Levenberg-Marquardt as optimistix composes it: a damped Gauss-Newton descent
(``ScaledDampedNewtonDescent``, whose linear solves are the structured ones of
``jaxflex.fit.normal``) inside a trust region (``optx.ClassicalTrustRegion``), with an optional
geodesic acceleration and optimistix's Cauchy termination. ``LevenbergMarquardt`` is an
``optx.AbstractLeastSquaresSolver`` with a state of its own (``LMState``): a rejected trial costs
one residual evaluation, and the Jacobian is taken (and the normal equations formed) only at
accepted points.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree

from jaxflex.fit.normal import (JACOBIAN_BLOCKS, BlockJacobian, blocks_mv, damping_diagonal,
                                dense_damped_solve, dense_normal_equations, shooting_blocks,
                                shooting_damped_solve, shooting_normal, with_gradient)


class _ScaledDescentState(eqx.Module):
    # the undamped normal equations at the last accepted point (formed once per Jacobian;
    # every damping the trust region tries reuses them) and a zero template of the unknowns
    normal: dict[str, jax.Array]
    template: Any


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
    number. ``structure`` "shooting" solves the same equations of a multiple-shooting problem
    with free starts in time linear in the log length (``shooting_newton_step``). The normal
    equations J^T J, J^T r are formed once per accepted point (``query``); a rejected trial
    only re-solves them with a larger damping (``step``)."""

    scaling: str = eqx.field(static=True, default="identity")
    structure: str = eqx.field(static=True, default="dense")

    def __check_init__(self) -> None:
        if self.scaling not in ("identity", "marquardt"):
            raise ValueError(f"fit: scaling must be 'identity' or 'marquardt', got {self.scaling!r}")
        if self.structure not in ("dense", "shooting"):
            raise ValueError(f"fit: structure must be 'dense' or 'shooting', got {self.structure!r}")

    def init(self, y: Any, f_info_struct: Any) -> _ScaledDescentState:
        """Zero normal equations of the shapes ``query`` forms, from the unknowns ``y`` and the
        residual's shape (``f_info_struct``): no linearisation is traced."""
        template = jax.tree_util.tree_map(jnp.zeros_like, y)
        dt = jax.tree_util.tree_leaves(template)[0].dtype
        m = f_info_struct.residual.shape[0]
        if self.structure == "shooting":
            theta, x0s = template
            k = ravel_pytree(theta)[0].shape[0]
            S = x0s.shape[0]
            d = int(np.prod(x0s.shape[1:]))
            my = (m - (S - 1) * d) // S
            shapes = {"Ntt": (k, k), "Nxt": (S, d, k), "Dx": (S, d, d), "U": (S, d, d),
                      "gt": (k,), "gx": (S, d), "Jt": (S, my + d, k), "Jx": (S, my + d, d),
                      "Jn": (S, d, d)}
        else:
            p = ravel_pytree(template)[0].shape[0]
            shapes = {"A": (p, p), "g": (p,), "J": (m, p)}
        return _ScaledDescentState({k: jnp.zeros(v, dt) for k, v in shapes.items()}, template)

    def query(self, y: Any, f_info: Any, state: _ScaledDescentState) -> _ScaledDescentState:
        """The undamped normal equations at an accepted point, from its residual and Jacobian
        (``f_info``: a ``BlockJacobian`` or a linear operator)."""
        if self.structure == "shooting":
            # the residual's own Jacobian blocks where it has them (``residual_blocks``),
            # else probed from its linear operator
            blk = (shooting_normal(f_info.jac.blocks, f_info.residual)
                   if isinstance(f_info.jac, BlockJacobian)
                   else shooting_blocks(f_info.jac, f_info.residual))
            normal = {k: blk[k] for k in state.normal}
        else:
            normal = dense_normal_equations(f_info.jac, f_info.residual)
        return _ScaledDescentState(normal, state.template)

    def step(self, step_size: jax.Array, state: _ScaledDescentState) -> tuple[Any, optx.RESULTS]:
        """The damped step for the trust region's ``step_size`` (lambda = 1 / step_size), zero
        and ``RESULTS.singular`` where the solve is not finite."""
        lam = 1.0 / jnp.maximum(step_size, 1e-30)
        solve = shooting_damped_solve if self.structure == "shooting" else dense_damped_solve
        dy = solve(state.normal, lam, self.scaling, state.template)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree_util.tree_leaves(dy)]))
        y_diff = jax.tree_util.tree_map(lambda a: -jnp.where(finite, a, 0.0), dy)
        return y_diff, optx.RESULTS.where(finite, optx.RESULTS.successful,
                                          optx.RESULTS.singular)


class LMState(eqx.Module):
    """The state of ``LevenbergMarquardt`` between steps (the fields of optimistix's
    Gauss-Newton state): the trial point ``y_eval`` and whether it is the ``first_step``; the
    trust region's ``search_state``; ``f_info`` (residual and ``BlockJacobian``) and ``aux`` at
    the last accepted point; the descent's state (its normal equations); whether to
    ``terminate`` and the ``result``; step counts."""

    first_step: jax.Array
    y_eval: Any
    search_state: Any
    f_info: optx.FunctionInfo.ResidualJac
    aux: Any
    descent_state: Any
    terminate: jax.Array
    result: optx.RESULTS
    num_steps: jax.Array
    num_accepted_steps: jax.Array
    num_steps_since_acceptance: jax.Array


class LevenbergMarquardt(optx.AbstractLeastSquaresSolver):
    """optimistix's Gauss-Newton machinery (trust region, termination) with the scaled
    damped-Newton descent above: the one least-squares solver of jaxflex. ``geodesic`` > 0
    adds geodesic acceleration (``geodesic_step``) with that bound on |a| / |v|."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: ScaledDampedNewtonDescent = ScaledDampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
    geodesic: float = eqx.field(static=True, default=0.0)

    def init(self, fn: Callable, y: Any, args: Any, options: dict[str, Any], f_struct: Any,
             aux_struct: Any, tags: frozenset) -> LMState:
        """optimistix's Gauss-Newton state, except that its Jacobian is a ``BlockJacobian``
        (zeros until the first accepted point): only the residual's shape ``f_struct`` is
        needed, no linearisation is traced."""
        info_struct = optx.FunctionInfo.ResidualJac(f_struct, None)
        descent_state = self.descent.init(y, info_struct)
        structure = self.descent.structure
        jac = BlockJacobian({k: descent_state.normal[k] for k in JACOBIAN_BLOCKS[structure]},
                            structure)
        return LMState(
            first_step=jnp.array(True), y_eval=y,
            search_state=self.search.init(y, info_struct),
            f_info=optx.FunctionInfo.ResidualJac(jnp.zeros(f_struct.shape, f_struct.dtype), jac),
            aux=jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), aux_struct),
            descent_state=descent_state, terminate=jnp.array(False),
            result=optx.RESULTS.successful, num_steps=jnp.array(0),
            num_accepted_steps=jnp.array(0), num_steps_since_acceptance=jnp.array(0))

    def step(self, fn: Callable, y: Any, args: Any, options: dict[str, Any], state: LMState,
             tags: frozenset) -> tuple[Any, LMState, Any]:
        """optimistix's Gauss-Newton step (``optx.AbstractGaussNewton.step``: trust-region
        acceptance, Cauchy termination on an accepted step, then the descent), except that
        the trial point is first judged on its residual alone and the Jacobian is taken only
        when the trial is accepted: a rejected trial costs one simulation instead of one with
        all the Jacobian's tangents (``Problem.residuals``' JVP), and the normal equations are
        formed once per accepted point (``ScaledDampedNewtonDescent.query``)."""
        f_eval, aux_eval = fn(state.y_eval, args)
        # the trust region reads only the trial's residual (``as_min``): the Jacobian slot
        # holds the last accepted one, unused
        trial = optx.FunctionInfo.ResidualJac(f_eval, state.f_info.jac)
        step_size, accept, search_result, search_state = self.search.step(
            state.first_step, y, state.y_eval, state.f_info, trial, state.search_state)
        jac_dyn, jac_static = eqx.partition(state.f_info.jac, eqx.is_array)
        desc_dyn, desc_static = eqx.partition(state.descent_state, eqx.is_array)

        def accepted(_):
            if getattr(fn, "blocks", None) is not None and jac_static.structure == "shooting":
                # the residual's Jacobian blocks as it computes them: no linearisation
                f_new, blocks = fn.blocks(state.y_eval, args)
                aux_new = None
                info = optx.FunctionInfo.ResidualJac(f_new, BlockJacobian(blocks, "shooting"))
            else:
                f_new, lin, aux_new = jax.linearize(lambda u: fn(u, args), state.y_eval,
                                                    has_aux=True)
                lin_op = lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: state.y_eval),
                                                   tags)
                info = optx.FunctionInfo.ResidualJac(f_new, lin_op)
            desc = self.descent.query(state.y_eval, info, state.descent_state)
            # the state keeps the descent's blocks, not the linearised function
            jac = BlockJacobian({k: desc.normal[k] for k in jac_static.blocks},
                                jac_static.structure)
            y_diff = jax.tree_util.tree_map(lambda a, b: a - b, state.y_eval, y)
            terminate = cauchy_termination(self.rtol, self.atol, self.norm, state.y_eval, y_diff,
                                           f_new, f_new - state.f_info.residual)
            return (state.y_eval, f_new, eqx.filter(jac, eqx.is_array), aux_new,
                    eqx.filter(desc, eqx.is_array), terminate)

        def rejected(_):
            return (y, state.f_info.residual, jac_dyn, state.aux, desc_dyn, jnp.array(False))

        y_new, f_res, jac_dyn, aux, desc_dyn, terminate = jax.lax.cond(
            accept, accepted, rejected, None)
        f_info = optx.FunctionInfo.ResidualJac(f_res, eqx.combine(jac_dyn, jac_static))
        descent_state = eqx.combine(desc_dyn, desc_static)
        y_descent, descent_result = self.descent.step(step_size, descent_state)
        if self.geodesic > 0:
            y_descent = geodesic_step(fn, args, y_new, f_res, self.descent, descent_state,
                                      step_size, y_descent, self.geodesic)
        y_eval = jax.tree_util.tree_map(lambda a, b: a + b, y_new, y_descent)
        result = optx.RESULTS.where(search_result == optx.RESULTS.successful, descent_result,
                                    search_result)
        prev_aux = jax.tree_util.tree_map(lambda a, b: jnp.where(state.first_step, a, b), aux,
                                          state.aux)
        del aux_eval
        state = dataclasses.replace(
            state, first_step=jnp.array(False), y_eval=y_eval, search_state=search_state,
            f_info=f_info, aux=aux, descent_state=descent_state, terminate=terminate,
            result=result, num_steps=state.num_steps + 1,
            num_accepted_steps=state.num_accepted_steps + jnp.where(accept, 1, 0),
            num_steps_since_acceptance=jnp.where(accept, 0,
                                                 state.num_steps_since_acceptance + 1))
        return y_new, state, prev_aux

    def terminate(self, fn: Callable, y: Any, args: Any, options: dict[str, Any],
                  state: LMState, tags: frozenset) -> tuple[jax.Array, optx.RESULTS]:
        """Whether the last step met the Cauchy test (``cauchy_termination``), and its result."""
        return state.terminate, state.result

    def postprocess(self, fn: Callable, y: Any, aux: Any, args: Any, options: dict[str, Any],
                    state: LMState, tags: frozenset, result: optx.RESULTS,
                    ) -> tuple[Any, Any, dict[str, Any]]:
        """``y`` and ``aux`` as they are, no statistics."""
        return y, aux, {}



def geodesic_step(fn: Callable, args: Any, y: Any, r: jax.Array,
                  descent: ScaledDampedNewtonDescent, state: _ScaledDescentState,
                  step_size: jax.Array, v: Any, alpha: float, h: float = 0.1) -> Any:
    """Levenberg-Marquardt's step ``v`` with geodesic acceleration (Transtrum, Machta &
    Sethna, Phys. Rev. E 83, 036701, 2011; as in GSL's ``multifit_nlinear`` with acceleration):
    v + a / 2, a = -(J^T J + lambda D)^{-1} J^T r_vv, where r_vv, the residual's second
    directional derivative along v, comes from one extra residual evaluation,
    r_vv = (2 / h) ((r(y + h v) - r(y)) / h - J v). It bends the step along a curved narrow
    valley of the cost (e.g. LuGre's Fs and vs trading off against each other), where plain
    Levenberg-Marquardt creeps with a small trust region. The acceleration is used only when
    2 |a| / |v| <= ``alpha`` (norms in the damping metric D; the second-order term must stay a
    correction), else ``v`` alone. J, J^T come from the Jacobian blocks kept in ``state``
    (no further Jacobian-vector products)."""
    normal = state.normal
    flat_v, unravel = ravel_pytree(v)
    shooting = descent.structure == "shooting"
    Jv = blocks_mv(normal, descent.structure, v)
    r_h, _ = fn(jax.tree_util.tree_map(lambda a, b: a + h * b, y, v), args)
    rvv = (2.0 / h) * ((r_h - r) / h - Jv)
    rhs = with_gradient(normal, descent.structure, rvv)
    if shooting:
        dam = jnp.concatenate([damping_diagonal(jnp.diag(normal["Ntt"]), descent.scaling),
                               damping_diagonal(jnp.diagonal(normal["Dx"], axis1=1, axis2=2).reshape(-1),
                                        descent.scaling)])
    else:
        dam = damping_diagonal(jnp.diag(normal["A"]), descent.scaling)
    solve = shooting_damped_solve if shooting else dense_damped_solve
    lam = 1.0 / jnp.maximum(step_size, 1e-30)
    acc = -ravel_pytree(solve(rhs, lam, descent.scaling, state.template))[0]
    ratio = 2.0 * jnp.sqrt(jnp.sum(dam * acc**2) / jnp.sum(dam * flat_v**2))
    use = jnp.isfinite(ratio) & (ratio <= alpha)
    return unravel(flat_v + jnp.where(use, 0.5 * acc, 0.0))


def cauchy_termination(rtol: float, atol: float, norm: Callable, y: Any, y_diff: Any,
                       f: jax.Array, f_diff: jax.Array) -> jax.Array:
    """optimistix's Cauchy test: |y_diff| < atol + rtol |y| and |f_diff| < atol + rtol |f|
    in ``norm`` (both), i.e. neither the unknowns nor the residuals moved on this step."""
    y_conv = norm(jax.tree_util.tree_map(lambda d, a: jnp.abs(d) / (atol + rtol * jnp.abs(a)),
                                         y_diff, y)) < 1
    f_conv = norm(jnp.abs(f_diff) / (atol + rtol * jnp.abs(f))) < 1
    return y_conv & f_conv
