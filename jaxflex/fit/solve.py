"""The one solver path of jaxflex, and the one covariance.

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

Covariance: Cov = s^2 (J^T J)^+ from the Jacobian at the optimum over the fitted unknowns
(nuisance start states included, so their uncertainty is accounted for), s^2 the residual
variance per output sample times an ``inflation`` for correlated residuals, mapped to physical
values through the reparametrisation's Jacobian.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from optimistix._solver.gauss_newton import _GaussNewtonState

from jaxflex.tracecache import persistent_jit
from jaxflex.fit.problem import (BLOWN_RESIDUAL, Problem, dynamic_substeps, segment_rows,
                                  segment_slots, slot_rows)
from jaxflex.validation import to_device


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
        lam = 1.0 / jnp.maximum(step_size, 1e-30)
        solve = shooting_damped_solve if self.structure == "shooting" else dense_damped_solve
        dy = solve(state.normal, lam, self.scaling, state.template)
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree_util.tree_leaves(dy)]))
        y_diff = jax.tree_util.tree_map(lambda a: -jnp.where(finite, a, 0.0), dy)
        return y_diff, optx.RESULTS.where(finite, optx.RESULTS.successful,
                                          optx.RESULTS.singular)


def _damping(diag: jax.Array, scaling: str) -> jax.Array:
    if scaling == "marquardt":
        return jnp.maximum(diag, 1e-12 * jnp.maximum(jnp.max(diag, initial=0.0), 1e-300))
    return jnp.ones_like(diag)


def dense_normal_equations(jac: Any, r: jax.Array) -> dict[str, jax.Array]:
    """The normal equations of the Jacobian ``jac`` (a lineax operator) and residual ``r``:
    ``A`` = J^T J (p, p) and ``g`` = J^T r (p,), and the Jacobian ``J`` itself, materialised
    (an m x p matrix; every column is one Jacobian-vector product)."""
    J = jac.as_matrix()
    return {"A": J.T @ J, "g": J.T @ r, "J": J}


def dense_damped_solve(normal: dict[str, jax.Array], lam: jax.Array, scaling: str,
                       template: Any) -> Any:
    """dy solving (A + lam D) dy = g (``dense_normal_equations``) by Cholesky, in the
    structure of ``template`` (the unknowns)."""
    A = normal["A"]
    d = _damping(jnp.diag(A), scaling)
    c, low = jax.scipy.linalg.cho_factor(A + lam * jnp.diag(d))
    dy = jax.scipy.linalg.cho_solve((c, low), normal["g"])
    return ravel_pytree(template)[1](dy)


def dense_newton_step(jac: Any, r: jax.Array, lam: jax.Array, scaling: str) -> Any:
    """The damped Gauss-Newton step dy solving (J^T J + lam D) dy = J^T r with the Jacobian
    materialised (``dense_normal_equations``, ``dense_damped_solve``). Returns dy in the
    structure of the unknowns."""
    template = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jac.in_structure())
    return dense_damped_solve(dense_normal_equations(jac, r), lam, scaling, template)


def shooting_damped_solve(normal: dict[str, jax.Array], lam: jax.Array, scaling: str,
                          template: Any) -> Any:
    """``shooting_newton_step`` from the blocks of ``shooting_blocks`` (``normal``) and a
    template (theta, x0s) of the unknowns."""
    Ntt, Dx = normal["Ntt"], normal["Dx"]
    S, d = Dx.shape[0], Dx.shape[1]
    dam_t = _damping(jnp.diag(Ntt), scaling)
    dam_x = _damping(jnp.diagonal(Dx, axis1=1, axis2=2).reshape(-1), scaling).reshape(S, d)
    Ntt = Ntt + lam * jnp.diag(dam_t)
    Dx = Dx + lam * jax.vmap(jnp.diag)(dam_x)
    theta, x0s = template
    return _arrow_solve(Ntt, normal["Nxt"], Dx, normal["U"], normal["gt"], normal["gx"],
                        ravel_pytree(theta)[1], x0s.shape)


def shooting_newton_step(jac: Any, r: jax.Array, lam: jax.Array, scaling: str) -> Any:
    """The same step as ``dense_newton_step`` for the multiple-shooting problem with free
    segment starts, at a cost linear in the number of segments S (never forming the m x p
    Jacobian).

    Unknowns ``(theta, x0s)``, x0s (S, n_state, n); residual rows ordered as in
    ``Problem.residuals``: the outputs of every segment, then the S - 1 continuity defects.
    The rows of segment s (its outputs and its defect) depend on theta and x_s; its defect
    also on x_{s+1}. The Jacobian blocks come from k + 2 d Jacobian-vector products (d =
    n_state n; the start-state tangents are switched on in every other segment, so that a
    segment's own block and its coupling to the next start separate). The normal equations
    are then an arrow matrix: block-tridiagonal in the starts, dense in theta. The starts are
    eliminated by a block Thomas (block LU) recursion and theta solved from the k x k Schur
    complement; the system is symmetric positive definite (damped), so no pivoting is needed.
    """
    template = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), jac.in_structure())
    return shooting_damped_solve(shooting_blocks(jac, r), lam, scaling, template)


def _arrow_solve(Ntt, Nxt, Dx, U, gt, gx, unravel, x_shape):
    """Solve the arrow system [[Ntt, Nxt^T], [Nxt, T]] (dth, dx) = (gt, gx), T block
    tridiagonal with diagonal blocks Dx and upper blocks U, by block Thomas elimination of the
    starts and the Schur complement in theta; with ``unravel`` None, return the Schur
    complement (theta's information with the starts eliminated) instead."""
    d = Dx.shape[1]
    k = Ntt.shape[0]
    dt = Ntt.dtype
    T = lambda a: jnp.swapaxes(a, -1, -2)
    B = jnp.concatenate([Nxt, gx[:, :, None]], axis=-1)  # right-hand sides (S, d, k + 1)

    def forward(carry, inp):
        Dp, Yp, Up = carry
        Ds, Bs, Us = inp
        M = T(jnp.linalg.solve(Dp, Up))              # U_{s-1}^T D'_{s-1}^{-1}
        Dn = Ds - M @ Up
        Yn = Bs - M @ Yp
        return (Dn, Yn, Us), (Dn, Yn)

    eye = jnp.eye(d, dtype=dt)
    init = (eye, jnp.zeros((d, k + 1), dt), jnp.zeros((d, d), dt))
    _, (Dn, Yn) = jax.lax.scan(forward, init, (Dx, B, U))

    def backward(Xnext, inp):
        Ds, Ys, Us = inp
        X = jnp.linalg.solve(Ds, Ys - Us @ Xnext)
        return X, X

    _, X = jax.lax.scan(backward, jnp.zeros((d, k + 1), dt), (Dn, Yn, U), reverse=True)
    Xt, Xg = X[..., :k], X[..., k]
    St = Ntt - jnp.einsum("sdk,sdl->kl", Nxt, Xt)   # Schur complement: theta's information
    rt = gt - jnp.einsum("sdk,sd->k", Nxt, Xg)
    if unravel is None:
        return St
    c, low = jax.scipy.linalg.cho_factor(St)
    dth = jax.scipy.linalg.cho_solve((c, low), rt)
    dx = Xg - jnp.einsum("sdk,k->sd", Xt, dth)
    return unravel(dth), dx.reshape(x_shape)




def shooting_blocks(jac: Any, r: jax.Array) -> dict[str, Any]:
    """The blocks of the (undamped) normal equations J^T J, J^T r of a free-start
    multiple-shooting problem (see ``shooting_newton_step``): ``Ntt`` (k, k), ``Nxt``
    (S, d, k), ``Dx`` (S, d, d) diagonal and ``U`` (S, d, d) upper blocks of the start-state
    part, ``gt`` (k,), ``gx`` (S, d), and the Jacobian blocks, from the Jacobian's linear
    operator ``jac`` (k + 2 d
    Jacobian-vector products, linear in the log length: ``shooting_jacobian``; a
    ``Problem``'s own blocks need none, ``Problem.residual_blocks`` and ``shooting_normal``)."""
    return shooting_normal(shooting_jacobian(jac, r.shape[0]), r)


def shooting_jacobian(jac: Any, m: int) -> dict[str, jax.Array]:
    """The Jacobian blocks ``Jt``, ``Jx``, ``Jn`` (``shooting_tmv``) of a free-start
    multiple-shooting residual of ``m`` rows from its linear operator ``jac``, by k + 2 d
    Jacobian-vector products: theta's unit vectors, then the start-state ones switched on in
    every other segment, so that a segment's own block and its coupling to the next start
    separate."""
    th_struct, x_struct = jac.in_structure()
    S = x_struct.shape[0]
    d = int(np.prod(x_struct.shape[1:]))
    zeros_th = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), th_struct)
    flat0, unravel = ravel_pytree(zeros_th)
    k = flat0.shape[0]
    dt = x_struct.dtype  # theta may be empty (start-only fits): its ravel has no dtype
    my = (m - (S - 1) * d) // S

    def mv(v_th, v_x):
        return jac.mv((unravel(v_th), v_x.reshape(x_struct.shape)))

    rows = lambda v: segment_rows(v, S, d)  # noqa: E731
    zx = jnp.zeros((S, d), dt)
    G = jnp.moveaxis(rows(jax.vmap(lambda e: mv(e, zx))(jnp.eye(k, dtype=dt))), 0, -1)
    even = (jnp.arange(S) % 2 == 0)[:, None]
    on = lambda mask: jax.vmap(lambda e: mv(jnp.zeros(k, dt), jnp.where(mask, e[None, :], 0.0)))
    Xe = jnp.moveaxis(rows(on(even)(jnp.eye(d, dtype=dt))), 0, -1)   # (S, my+d, d)
    Xo = jnp.moveaxis(rows(on(~even)(jnp.eye(d, dtype=dt))), 0, -1)
    A = jnp.where(even[:, :, None], Xe, Xo)          # own block of segment s
    C = jnp.where(even[:, :, None], Xo, Xe)[:, my:]  # its defect rows w.r.t. x_{s+1}: (S, d, d)
    return {"Jt": G, "Jx": A, "Jn": C}


def shooting_normal(blocks: dict[str, jax.Array], r: jax.Array) -> dict[str, jax.Array]:
    """The normal-equation blocks (``shooting_blocks``) from the Jacobian blocks ``Jt``,
    ``Jx``, ``Jn`` and the residual ``r``; the Jacobian blocks are kept beside them."""
    G, A, C = blocks["Jt"], blocks["Jx"], blocks["Jn"]
    d = C.shape[1]
    my = G.shape[1] - d
    Gd = G[:, my:]                                   # theta part of the defect rows (S, d, k)
    Ad = A[:, my:]
    T = lambda a: jnp.swapaxes(a, -1, -2)  # noqa: E731
    Ntt = jnp.einsum("smk,sml->kl", G, G)
    Dx = jnp.einsum("smd,sme->sde", A, A) + _previous(T(C) @ C)
    U = T(Ad) @ C                                    # N(x_s, x_{s+1}); zero for the last
    Nxt = T(A) @ G + _previous(T(C) @ Gd)            # (S, d, k)
    gt, gx = shooting_tmv(blocks, r)
    return {"Ntt": Ntt, "Nxt": Nxt, "Dx": Dx, "U": U, "gt": gt, "gx": gx,
            "Jt": G, "Jx": A, "Jn": C}


def _previous(a: jax.Array) -> jax.Array:
    """Along the leading (segment) axis, the value of segment s - 1 (zero for the first)."""
    return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]])


def shooting_tmv(blocks: dict[str, jax.Array], w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """J^T w for the Jacobian blocks of ``shooting_blocks`` (``Jt`` (S, my + d, k): every
    segment's rows against theta, ``Jx`` against its own start, ``Jn`` (S, d, d): its defect
    against the next start) and a residual-shaped ``w`` (m,): (theta part (k,), start part
    (S, d))."""
    G, A, C = blocks["Jt"], blocks["Jx"], blocks["Jn"]
    S, d = C.shape[0], C.shape[1]
    my = G.shape[1] - d
    W = segment_rows(w, S, d)
    gt = jnp.einsum("smk,sm->k", G, W)
    gx = jnp.einsum("smd,sm->sd", A, W) + _previous(jnp.einsum("sed,se->sd", C, W[:, my:]))
    return gt, gx


def shooting_mv(blocks: dict[str, jax.Array], v_theta: jax.Array, v_x: jax.Array) -> jax.Array:
    """J v for the Jacobian blocks of ``shooting_blocks`` and a direction (theta part (k,),
    start part (S, d)): residual-shaped (m,), rows ordered as in ``Problem.residuals``."""
    G, A, C = blocks["Jt"], blocks["Jx"], blocks["Jn"]
    d = C.shape[1]
    my = G.shape[1] - d
    R = G @ v_theta + jnp.einsum("smd,sd->sm", A, v_x)
    nxt = jnp.concatenate([v_x[1:], jnp.zeros_like(v_x[:1])])
    R = R.at[:, my:].add(jnp.einsum("sed,sd->se", C, nxt))
    return jnp.concatenate([R[:, :my].reshape(-1), R[:-1, my:].reshape(-1)])


#: The Jacobian blocks of each descent structure that ``BlockJacobian`` keeps.
_JACOBIAN_BLOCKS = {"dense": ("J",), "shooting": ("Jt", "Jx", "Jn")}


class BlockJacobian(eqx.Module):
    """The Jacobian at the solver's last accepted point in the form its state keeps it: the
    blocks the descent formed there (``J`` of ``dense_normal_equations``, or ``Jt``, ``Jx``,
    ``Jn`` of ``shooting_blocks``). The trust region reads it only through ``mv`` (the
    predicted reduction); holding blocks instead of a linearised function means the solver's
    ``init`` traces no linearisation to learn the state's structure (measured: that trace was
    about half of the first fit's compile time in the discrepancy workflow)."""

    blocks: dict[str, jax.Array]
    structure: str = eqx.field(static=True)

    def mv(self, v: Any) -> jax.Array:
        """J v for unknowns-shaped ``v``: residual-shaped (m,)."""
        return blocks_mv(self.blocks, self.structure, v)


def blocks_mv(blocks: dict[str, jax.Array], structure: str, v: Any) -> jax.Array:
    """J v from the Jacobian blocks a descent keeps (``J`` for "dense", ``Jt``, ``Jx``, ``Jn``
    for "shooting") and unknowns-shaped ``v``: residual-shaped (m,)."""
    if structure == "shooting":
        v_theta, v_x = v
        return shooting_mv(blocks, ravel_pytree(v_theta)[0], v_x.reshape(v_x.shape[0], -1))
    return blocks["J"] @ ravel_pytree(v)[0]


def with_gradient(normal: dict[str, jax.Array], structure: str, w: jax.Array) -> dict[str, Any]:
    """The normal equations ``normal`` with their right-hand side J^T r replaced by J^T ``w``
    (``w`` residual-shaped), from the Jacobian blocks they keep: the system whose solution is
    the Gauss-Newton step for the residual ``w``."""
    if structure == "shooting":
        gt, gx = shooting_tmv(normal, w)
        return {**normal, "gt": gt, "gx": gx}
    return {**normal, "g": normal["J"].T @ w}


def undamped_solve(normal: dict[str, jax.Array], structure: str, template: Any) -> jax.Array:
    """(J^T J)^-1 g of the normal equations ``normal`` (structure "dense" or "shooting"),
    flattened; a relative Marquardt damping of 1e-9 keeps directions the data do not see
    (where g is zero too) out of it."""
    solve = shooting_damped_solve if structure == "shooting" else dense_damped_solve
    return ravel_pytree(solve(normal, jnp.asarray(1e-9), "marquardt", template))[0]


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """optimistix's Gauss-Newton machinery (trust region, termination) with the scaled
    damped-Newton descent above: the one least-squares solver of jaxflex. ``geodesic`` > 0
    adds geodesic acceleration (``geodesic_step``) with that bound on |a| / |v|."""

    rtol: float
    atol: float
    norm: Callable = optx.max_norm
    descent: ScaledDampedNewtonDescent = ScaledDampedNewtonDescent()
    search: optx.ClassicalTrustRegion = optx.ClassicalTrustRegion()
    verbose: Callable = eqx.field(static=True, default=lambda **kw: None)
    geodesic: float = eqx.field(static=True, default=0.0)

    def init(self, fn: Callable, y: Any, args: Any, options: dict[str, Any], f_struct: Any,
             aux_struct: Any, tags: frozenset) -> Any:
        """optimistix's Gauss-Newton state, except that its Jacobian is a ``BlockJacobian``
        (zeros until the first accepted point): only the residual's shape ``f_struct`` is
        needed, no linearisation is traced."""
        info_struct = optx.FunctionInfo.ResidualJac(f_struct, None)
        descent_state = self.descent.init(y, info_struct)
        structure = self.descent.structure
        jac = BlockJacobian({k: descent_state.normal[k] for k in _JACOBIAN_BLOCKS[structure]},
                            structure)
        return _GaussNewtonState(
            first_step=jnp.array(True), y_eval=y,
            search_state=self.search.init(y, info_struct),
            f_info=optx.FunctionInfo.ResidualJac(jnp.zeros(f_struct.shape, f_struct.dtype), jac),
            aux=jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), aux_struct),
            descent_state=descent_state, terminate=jnp.array(False),
            result=optx.RESULTS.successful, num_steps=jnp.array(0),
            num_accepted_steps=jnp.array(0), num_steps_since_acceptance=jnp.array(0))

    def step(self, fn: Callable, y: Any, args: Any, options: dict[str, Any], state: Any,
             tags: frozenset) -> tuple[Any, Any, Any]:
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
        dam = jnp.concatenate([_damping(jnp.diag(normal["Ntt"]), descent.scaling),
                               _damping(jnp.diagonal(normal["Dx"], axis1=1, axis2=2).reshape(-1),
                                        descent.scaling)])
    else:
        dam = _damping(jnp.diag(normal["A"]), descent.scaling)
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
    round trip per step (measured on discover's 20 s log: 1.7 of a step's 21 ms were the
    call's dispatch). ``control`` = (limit, decrement bound, progress bound, steps already
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
#: parameters; ``jaxflex.tracecache.FAST_COMPILE_OPTIONS``). Both share one trace.
_steps = persistent_jit(_steps_loop)
_steps_small = persistent_jit(_steps_loop, fast_compile=True)


def _fell(history: jax.Array, window: int, c: float) -> float:
    """On the host, how much ||r||^2 fell over the last ``window`` steps to the cost ``c``
    (``_steps``' ``history``: the cost ``window`` steps back)."""
    return 2.0 * (float(np.asarray(history)[_HISTORY - window]) - c)


def gauss_newton_decrement(normal: dict[str, jax.Array], structure: str,
                           template: Any) -> jax.Array:
    """The Gauss-Newton decrement g^T (J^T J)^{-1} g at the point whose normal equations are
    ``normal`` (``dense_normal_equations`` or ``shooting_blocks``; ``structure`` "dense" or
    "shooting"; ``template`` a zero pytree of the unknowns): the drop of ||r||^2 a full,
    undamped Gauss-Newton step would bring if the residuals were linear. With residuals in
    units of their noise standard deviation it is the squared length of the remaining step in
    standard errors: for any combination c of the unknowns, |c . dy| <= sqrt(decrement)
    stderr(c . y) (standard errors from the same J^T J). A relative Marquardt damping of
    1e-9 keeps directions the data do not see (where g is zero too) out of it; NaN or inf if
    the solve fails."""
    dy = undamped_solve(normal, structure, template)
    g = (jnp.concatenate([normal["gt"], normal["gx"].reshape(-1)]) if structure == "shooting"
         else normal["g"])
    return jnp.dot(g, dy)


@persistent_jit(fast_compile=True)
def _cost(fn: Callable, y: Any, args: Any) -> jax.Array:
    r = fn(y, args)
    return 0.5 * jnp.sum(r**2)


def cost(prob: Problem, y: Any, fn: Callable = problem_residuals) -> float:
    """0.5 ||r||^2 at ``y`` of ``fn(y, prob)`` (default: the problem's residuals; compiled
    once per shape); inf if not finite."""
    c = float(_cost(fn, y, prob))
    return c if math.isfinite(c) else math.inf


#: The normal-equation and Jacobian blocks of "shooting" that hold one entry per segment.
_SEGMENT_BLOCKS = ("Nxt", "Dx", "U", "gx", "Jt", "Jx", "Jn")


@dataclasses.dataclass(frozen=True)
class Padding:
    """How a free-start multiple-shooting problem of ``count`` segments sits in ``slots``
    (``Problem.padded``): ``my`` output residual rows per segment, ``d`` start entries per
    segment. Moves unknowns, residuals and normal blocks between the two layouts, on the host
    (numpy gathers, one transfer: no device program per shape)."""

    count: int
    slots: int
    my: int
    d: int

    @classmethod
    def of(cls, prob: Problem, *values: Any) -> Padding | None:
        """The padding ``least_squares`` gives ``prob`` (None: it runs as it is): a
        ``Problem`` with free starts and more than two segments (its ``segment_slots``, equal
        to its count or not: every count of a bucket runs the one program), not padded
        already, its arrays and ``values`` concrete (inside a trace a problem runs in its own
        shape: the layouts are moved on the host)."""
        if not (isinstance(prob, Problem) and prob.free_starts and prob.segs.active is None):
            return None
        if any(isinstance(a, jax.core.Tracer)
               for a in jax.tree_util.tree_leaves((eqx.filter(prob, eqx.is_array), values))):
            return None
        S = prob.segs.count
        if S <= 2:  # one and two segments have slots of their own
            return None
        slots = segment_slots(S)
        m = prob.segs.y_meas
        return cls(S, slots, int(m.shape[1] * m.shape[2]), int(np.prod(prob.segs.x0.shape[1:])))

    def unknowns(self, y: Any) -> Any:
        """(theta, x0s) with x0s grown to the slots (copies of the last start)."""
        theta, x0s = y
        return theta, to_device(np.asarray(x0s)[slot_rows(self.count, self.slots)])

    def unknowns_back(self, y: Any) -> Any:
        """(theta, x0s) of the data segments."""
        theta, x0s = y
        return theta, to_device(np.asarray(x0s)[: self.count])

    def rows_back(self, r: Any) -> Any:
        """Residual rows of the data segments: their outputs and their S - 1 defects."""
        r = np.asarray(r)
        out = self.slots * self.my
        return to_device(np.concatenate([r[: self.count * self.my],
                                         r[out: out + (self.count - 1) * self.d]]))

    def rows_in(self, r: Any) -> Any:
        """Residual-shaped rows of the data segments in the slots' layout (zero rows for the
        padding's outputs and for the defects into and between padding slots)."""
        r = np.asarray(r)
        n_out = self.count * self.my
        zeros = lambda k: np.zeros(k, r.dtype)  # noqa: E731
        return to_device(np.concatenate([r[:n_out], zeros((self.slots - self.count) * self.my),
                                         r[n_out:], zeros((self.slots - self.count) * self.d)]))

    def blocks_in(self, normal: dict[str, Any]) -> dict[str, Any]:
        """Normal blocks of the data segments in the slots' layout (zero blocks for the
        padding: a slot no residual sees)."""
        def grow(v):
            v = np.asarray(v)
            return to_device(np.concatenate([v, np.zeros((self.slots - self.count,)
                                                          + v.shape[1:], v.dtype)]))
        return {k: (grow(v) if k in _SEGMENT_BLOCKS else v) for k, v in normal.items()}

    def blocks_back(self, normal: dict[str, Any]) -> dict[str, Any]:
        """The normal blocks of the data segments (per-segment blocks cut to S; a padding
        slot adds nothing to the others: its rows are zero)."""
        return {k: (to_device(np.asarray(v)[: self.count]) if k in _SEGMENT_BLOCKS else v)
                for k, v in normal.items()}


def least_squares(
    prob: Any, y0: Any, *, fn: Callable = problem_residuals, rtol: float = 1e-10,
    atol: float = 1e-10, max_steps: int = 200, scaling: str = "identity",
    structure: str = "auto", progress: Callable[[int, float], None] | None = None,
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
    ``progress(step, cost)`` is called after every step. Besides optimistix's test, the run
    ends converged when a rejected trial leaves the trust region below the tolerance on the
    unknowns (MINPACK's xtol test; see ``_step``). ``decrement_tol``: a statistical stop for
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
    (``jaxflex.tracecache.FAST_COMPILE_OPTIONS``; the static map's fit, compiled beside
    identify's solver: 1.0-1.4 -> 0.6 s of XLA).
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
                    progress(steps - k + i + 1, float(ci))
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
    return Solution(y=y, steps=steps, converged=converged,
                    cost=final, reason=reason, seconds=time.perf_counter() - t0,
                    residual=residual, normal=normal,
                    decrement=None if dec is None else float(dec), interrupted=interrupted)


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
    """Trace and keep (``jaxflex.tracecache``) the compiled loop that ``least_squares(prob,
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


#: Error bound factor of a step-doubling estimate: the error of the coarse replay is at most
#: RICHARDSON x (coarse - fine) for a scheme of order >= 1 (e_h = C h^p gives
#: e_h = (y_h - y_h/2) / (1 - 2^-p): 2 for p = 1, 4/3 for p = 2). The Strang-split step is
#: second order only once sigma0 |v| / g(v) h is small; on the paper's plant at 1 kHz the
#: differences 1->2, 2->4, 4->8 substeps fall by 1.6x then 4x, so the first-order bound is the
#: one that holds at coarse steps.
RICHARDSON = 2.0


def refined(prob: Problem, factor: int = 2, traced: bool = False) -> Problem:
    """``prob`` with ``factor`` x its integrator substeps (the same data and unknowns): a
    Python int if ``prob``'s is one, else a traced count (``dynamic_substeps``); ``traced``:
    a traced count in any case (a loop in the program instead of unrolled substeps)."""
    n = prob.n_substeps * int(factor)
    return dataclasses.replace(
        prob, substeps=n if isinstance(prob.substeps, int) and not traced
        else dynamic_substeps(n))


def integration_error(prob: Problem, y: Any) -> float:
    """RMS integration error of ``prob``'s output replay at ``y``, in the problem's weighted
    units (``w_y``; for identification, units of the log's noise), by step doubling: RICHARDSON
    x RMS of the weighted difference between the replay with the problem's substeps and with
    twice as many. Compiles the finer replay once per problem shape."""
    return step_doubling_error(prob, simulated_outputs(prob, y),
                               simulated_outputs(refined(prob), y))


def step_doubling_error(prob: Problem, coarse: jax.Array, fine: jax.Array) -> float:
    """``integration_error`` from replays already made: ``coarse``, ``prob``'s outputs
    (``simulated_outputs``) with its substeps, and ``fine``, with twice as many; inf if
    either is not finite."""
    d = np.asarray(prob.w_y) * (np.asarray(fine) - np.asarray(coarse))  # on the host
    return RICHARDSON * float(np.sqrt(np.mean(d**2))) if np.all(np.isfinite(d)) else math.inf


@persistent_jit(fast_compile=True)
def _induced_step(normal: dict[str, Any], dr: jax.Array, structure: str, template: Any):
    """The undamped Gauss-Newton step (J^T J)^-1 J^T dr at the point whose normal equations are
    ``normal`` (``with_gradient``, ``undamped_solve``), flattened."""
    return undamped_solve(with_gradient(normal, structure, dr), structure, template)


def discretisation_bias(prob: Problem, solution: Solution) -> dict[str, Any]:
    """How far the integrator's discretisation moves the fitted parameters, in their standard
    errors: the parameters fitted with the problem's substeps minimise the coarse residual
    r_h; with an exact replay they would minimise r_h + e, e the integration error of the
    residuals at the solution (step doubling, ``RICHARDSON`` x (r_h/2 - r_h)). To first order
    the fit moves by the Gauss-Newton step -(J^T J)^-1 J^T e, computed from the solution's own
    normal equations (no new Jacobian; one finer replay, compiled once per shape).

    ``solution``: the ``least_squares`` result of ``prob`` (with its ``normal`` equations).
    Returns ``bias_se`` (the largest |shift| / standard error over the fitted theta entries:
    the discretisation moves no fitted parameter by more than this many standard errors),
    ``bias_mahalanobis`` (sqrt of shift^T Cov^-1 shift over the fitted entries: the bound for
    any combination of them), ``output_error`` (``integration_error``, weighted RMS),
    ``substeps``, and per fitted theta entry ("name[j]") the predicted ``shift_theta`` (exact
    replay minus this fit, engine coordinates) and ``stderr_theta`` (segment-robust,
    ``segment_robust_covariance``, where the log has the segments for it). Raises
    ``ValueError`` for a solution without normal equations."""
    if solution.normal is None or solution.residual is None:
        raise ValueError("discretisation_bias: the solution carries no normal equations "
                         "(it took no step)")
    y = solution.y
    structure = "shooting" if "Ntt" in solution.normal else "dense"
    fine = np.asarray(residuals(refined(prob), y))
    e = RICHARDSON * (fine - np.asarray(solution.residual))
    # the output rows of e are RICHARDSON w_y (fine - coarse replay): ``integration_error``
    # without replaying twice more (inf where a replay blew up, as there)
    n_out = prob.n_out
    blown = (np.any(fine[:n_out] == BLOWN_RESIDUAL)
             or np.any(np.asarray(solution.residual)[:n_out] == BLOWN_RESIDUAL))
    out_err = math.inf if blown else float(np.sqrt(np.mean(e[:n_out] ** 2)))
    shift, se, labels, fitted, cov = induced_shift(prob, solution, e)
    finite = bool(np.all(np.isfinite(shift)))
    maha = (float(np.sqrt(max(float(shift @ np.linalg.pinv(cov) @ shift), 0.0)))
            if finite and shift.size else (0.0 if finite else math.inf))
    return {"bias_se": float(np.max(np.abs(shift) / se)) if finite and shift.size
            else (0.0 if finite else math.inf),
            "bias_mahalanobis": maha, "output_error": out_err,
            "substeps": prob.n_substeps,
            "shift_theta": {labels[i]: float(v) for i, v in zip(fitted, shift)},
            "stderr_theta": {labels[i]: float(v) for i, v in zip(fitted, se)}}


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
    structure = "shooting" if "Ntt" in solution.normal else "dense"
    e = np.asarray(e, float)
    pad = Padding.of(prob, y) if structure == "shooting" else None
    normal, e_in, y_in = solution.normal, e, y
    if pad is not None:  # the solve in the slots' layout: compiled once per bucket
        normal, e_in, y_in = pad.blocks_in(normal), pad.rows_in(e), pad.unknowns(y)
    template = jax.tree_util.tree_map(
        lambda a: to_device(np.zeros(np.shape(a), a.dtype)), y_in)
    step = np.asarray(_induced_step(normal, e_in, structure, template))
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


def remaining_step(prob: Problem, solution: Solution) -> float:
    """The largest move of a fitted parameter, in its standard errors (segment-robust where
    the log has the segments for it), that a full Gauss-Newton step from ``solution`` would
    make: the statistical stop judged at the standard errors the fit reports, which a
    model's mismatch on a real log makes far larger than the white noise's. inf without
    normal equations or for a non-finite step."""
    if solution.normal is None or solution.residual is None:
        return math.inf
    shift, se, *_ = induced_shift(prob, solution, solution.residual)
    if not shift.size:
        return 0.0
    return float(np.max(np.abs(shift) / se)) if np.all(np.isfinite(shift)) else math.inf


def simulated_outputs(prob: Problem, y: Any) -> jax.Array:
    """Simulated outputs (S, L, n_out) [rad] of ``prob`` at ``y`` (compiled once per shape;
    a free-start shooting problem once per bucket of segment slots, ``Padding``; one program
    with ``residuals`` and ``gap``, ``Problem.replay``)."""
    out, pad = _replay_in_slots(prob, y)
    if pad is None:
        return out["outputs"]
    return to_device(np.asarray(out["outputs"])[: pad.count])


def gap(prob: Problem, y: Any) -> jax.Array:
    """``prob.gap(y)`` (normalised RMS output error), compiled once per problem shape (a
    free-start shooting problem once per bucket of segment slots, ``Padding``; one program
    with ``simulated_outputs`` and ``residuals``)."""
    return _replay_in_slots(prob, y)[0]["gap"]


def residuals(prob: Problem, y: Any) -> jax.Array:
    """``prob.residuals(y)``, compiled once per problem shape (a free-start shooting problem
    once per bucket of segment slots, ``Padding``; one program with ``simulated_outputs`` and
    ``gap``)."""
    out, pad = _replay_in_slots(prob, y)
    return out["residuals"] if pad is None else pad.rows_back(out["residuals"])


def _replay_in_slots(prob: Problem, y: Any) -> tuple[dict[str, jax.Array], Padding | None]:
    """``Problem.replay`` of ``prob`` at ``y``, a free-start shooting problem in its bucket of
    segment slots (the padding then returned with it, else None)."""
    pad = Padding.of(prob, y)
    if pad is None:
        return _replay(prob, y), None
    return _replay(prob.padded(pad.slots), pad.unknowns(y)), pad


@persistent_jit(fast_compile=True)
def _replay(prob: Problem, y: Any) -> dict[str, jax.Array]:
    return prob.replay(y)


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
    return _arrow_solve(blk["Ntt"], blk["Nxt"], Dx, blk["U"], blk["gt"], blk["gx"], None, None)


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
    fitted: where the posterior of ``jaxflex.robust`` draws, so every draw keeps the
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
    that cluster's residuals induce (``_induced_step`` on the solution's own normal
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
        steps.append(np.asarray(_induced_step(normal, to_device(w), structure, template))[:k][fitted])
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
