"""The structured linear algebra of the fitting engine: the normal equations J^T J, J^T r of a
least-squares problem and their damped solves, in the two structures the engine knows.

- "dense": the Jacobian materialised (m x p, one Jacobian-vector product per column), the
  damped normal equations solved by Cholesky (the Jacobian is tall and float64 leaves room for
  squaring its condition number);
- "shooting": a multiple-shooting problem with free segment starts, whose normal matrix is an
  arrow (block-tridiagonal in the starts, dense in theta), solved by block Thomas elimination
  of the starts and Cholesky of the Schur complement, in time linear in the log length.

Like a lineax solver, these are parts that a descent (``jaxflex.fit.levenberg_marquardt``)
takes; they hold no loop, no stop and no compilation policy.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from jaxflex.fit.segments import segment_rows


def damping_diagonal(diag: jax.Array, scaling: str) -> jax.Array:
    """The diagonal of the damping matrix D for the normal matrix's diagonal ``diag``: ones for
    ``scaling`` "identity", ``diag`` itself floored at 1e-12 of its largest entry for
    "marquardt"."""
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
    d = damping_diagonal(jnp.diag(A), scaling)
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
    dam_t = damping_diagonal(jnp.diag(Ntt), scaling)
    dam_x = damping_diagonal(jnp.diagonal(Dx, axis1=1, axis2=2).reshape(-1), scaling).reshape(S, d)
    Ntt = Ntt + lam * jnp.diag(dam_t)
    Dx = Dx + lam * jax.vmap(jnp.diag)(dam_x)
    theta, x0s = template
    return arrow_solve(Ntt, normal["Nxt"], Dx, normal["U"], normal["gt"], normal["gx"],
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


def arrow_solve(Ntt: jax.Array, Nxt: jax.Array, Dx: jax.Array, U: jax.Array, gt: jax.Array,
                gx: jax.Array, unravel: Callable[[jax.Array], Any] | None,
                x_shape: tuple[int, ...] | None) -> Any:
    """Solve the arrow system [[Ntt, Nxt^T], [Nxt, T]] (dth, dx) = (gt, gx), T block
    tridiagonal with diagonal blocks Dx and upper blocks U, by block Thomas elimination of the
    starts and the Schur complement in theta.

    **Arguments**: ``Ntt`` (k, k), ``Nxt`` (S, d, k), ``Dx`` and ``U`` (S, d, d), ``gt`` (k,),
    ``gx`` (S, d) (the blocks of ``shooting_normal``, damped or not); ``unravel`` maps a flat
    theta step to the unknowns' structure; ``x_shape`` the shape of the starts.

    **Returns**: (theta step, start steps of ``x_shape``); with ``unravel`` None, the Schur
    complement (k, k) instead (theta's information with the starts eliminated)."""
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
JACOBIAN_BLOCKS = {"dense": ("J",), "shooting": ("Jt", "Jx", "Jn")}


class BlockJacobian(eqx.Module):
    """The Jacobian at the solver's last accepted point in the form its state keeps it: the
    blocks the descent formed there (``J`` of ``dense_normal_equations``, or ``Jt``, ``Jx``,
    ``Jn`` of ``shooting_blocks``). The trust region reads it only through ``mv`` (the
    predicted reduction); holding blocks instead of a linearised function means the solver's
    ``init`` traces no linearisation to learn the state's structure (a trace that would be a
    large part of the first fit's compilation)."""

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
