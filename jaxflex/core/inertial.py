"""Inertial parameters of a serial chain: a physically consistent parametrisation, the
regressor, and the base parameters the data can determine (docs/spec.md section 5 for the
vocabulary of identification).

- **Physical consistency** (Wensing, Kim & Slotine, "Linear matrix inequalities for physically
  consistent inertial parameter identification", IEEE RA-L 2017): a link's ten standard
  parameters phi = (m, h = m c, I_o) (``jaxflex.core.chain.INERTIAL_NAMES``) are those of a rigid
  body with a positive mass distribution iff its 4x4 *pseudo-inertia*

      J = [[Sigma, h], [h^T, m]],   Sigma = 1/2 tr(I_o) 1 - I_o   (the second moment of mass)

  is positive definite (this implies m > 0, I_c > 0 and the triangle inequalities of the
  principal moments).
- **Log-Cholesky parametrisation** (Rucker & Wensing, "Smooth parameterization of rigid-body
  inertia", IEEE RA-L 2022): ten unconstrained reals theta = (alpha, d1, d2, d3, s12, s23,
  s13, t1, t2, t3) give J = U U^T with

      U = e^alpha [[e^d1, s12, s13, t1], [0, e^d2, s23, t2], [0, 0, e^d3, t3], [0, 0, 0, 1]],

  a smooth bijection onto the positive-definite pseudo-inertias (m = e^(2 alpha)). An
  optimiser over theta cannot leave the physical set.
- **Regressor**: the chain's inverse dynamics M q'' + C q' + G (eq. 2-3) is linear in phi, so
  tau = Y(q, q', q'') phi with Y the exact Jacobian (``jax.jacfwd``) of the inverse dynamics
  with respect to phi; no symbolic derivation.
- **Base parameters** (Gautier 1990, numerical form): stack Y at random states; a column that
  is zero everywhere is a parameter no torque depends on (unidentifiable); a column that is a
  linear combination of others can be determined only in a combination. QR with column
  pivoting of the stacked regressor picks r independent columns (r its numerical rank) and
  writes each base parameter as its own column's parameter plus multiples of the dependent
  ones: beta = phi_indep + K phi_dep, K = R11^-1 R12.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.chain import INERTIAL_NAMES, AbstractChain, inertia_entries, inertia_matrix

#: Relative tolerance (to the largest |R_ii| of the pivoted QR) below which a column of the
#: stacked regressor counts as dependent. Regressors are exact to rounding in float64, so a
#: dependent column's |R_ii| sits at about 1e-15 of the largest; 1e-9 leaves a wide gap.
RANK_RTOL: float = 1e-9


# ----- pseudo-inertia and the log-Cholesky parametrisation ------------------------------------

def pseudo_inertia(phi: Float[Array, "... 10"]) -> Float[Array, "... 4 4"]:
    """The pseudo-inertia J = [[Sigma, h], [h^T, m]] [kg m^2, kg m, kg] of standard
    parameters ``phi`` (module docstring)."""
    Io = inertia_matrix(phi[..., 4:])
    eye = jnp.eye(3, dtype=phi.dtype)
    Sigma = 0.5 * jnp.trace(Io, axis1=-2, axis2=-1)[..., None, None] * eye - Io
    h = phi[..., 1:4]
    top = jnp.concatenate([Sigma, h[..., :, None]], -1)
    bottom = jnp.concatenate([h, phi[..., :1]], -1)[..., None, :]
    return jnp.concatenate([top, bottom], -2)


def phi_from_pseudo_inertia(J: Float[Array, "... 4 4"]) -> Float[Array, "... 10"]:
    """Standard parameters from a pseudo-inertia (I_o = tr(Sigma) 1 - Sigma)."""
    Sigma = J[..., :3, :3]
    eye = jnp.eye(3, dtype=J.dtype)
    Io = jnp.trace(Sigma, axis1=-2, axis2=-1)[..., None, None] * eye - Sigma
    return jnp.concatenate([J[..., 3:, 3], J[..., :3, 3], inertia_entries(Io)], -1)


def _log_cholesky_factor(theta: Array) -> Array:
    alpha, d1, d2, d3, s12, s23, s13, t1, t2, t3 = (theta[..., k] for k in range(10))
    z, o = jnp.zeros_like(alpha), jnp.ones_like(alpha)
    U = jnp.stack([
        jnp.stack([jnp.exp(d1), s12, s13, t1], -1),
        jnp.stack([z, jnp.exp(d2), s23, t2], -1),
        jnp.stack([z, z, jnp.exp(d3), t3], -1),
        jnp.stack([z, z, z, o], -1),
    ], -2)
    return jnp.exp(alpha)[..., None, None] * U


def phi_from_log_cholesky(theta: Float[Array, "... 10"]) -> Float[Array, "... 10"]:
    """Standard parameters of the pseudo-inertia J = U U^T of the log-Cholesky coordinates
    ``theta`` (module docstring): physically consistent for every real ``theta``."""
    U = _log_cholesky_factor(jnp.asarray(theta, jnp.result_type(float)))
    return phi_from_pseudo_inertia(U @ jnp.swapaxes(U, -1, -2))


def log_cholesky_from_phi(phi: Float[Array, "... 10"]) -> Float[Array, "... 10"]:
    """The log-Cholesky coordinates of physically consistent standard parameters (the
    inverse of ``phi_from_log_cholesky``); NaN where the pseudo-inertia is not positive
    definite."""
    J = pseudo_inertia(jnp.asarray(phi, jnp.result_type(float)))
    rev = jnp.arange(3, -1, -1)
    L = jnp.linalg.cholesky(J[..., rev, :][..., :, rev])   # J = (P L P)(P L P)^T, P the flip
    U = L[..., rev, :][..., :, rev]                          # upper triangular
    ea = U[..., 3, 3]
    V = U / ea[..., None, None]
    return jnp.stack([jnp.log(ea), jnp.log(V[..., 0, 0]), jnp.log(V[..., 1, 1]),
                      jnp.log(V[..., 2, 2]), V[..., 0, 1], V[..., 1, 2], V[..., 0, 2],
                      V[..., 0, 3], V[..., 1, 3], V[..., 2, 3]], -1)


def is_physically_consistent(phi: ArrayLike, rtol: float = 0.0) -> np.ndarray:
    """Per link, whether its pseudo-inertia is positive definite (smallest eigenvalue >
    ``rtol`` times its largest); host-side check, shape ``phi.shape[:-1]``."""
    ev = np.linalg.eigvalsh(np.asarray(pseudo_inertia(jnp.asarray(phi, float))))
    return ev[..., 0] > rtol * ev[..., -1]


# ----- regressor and base parameters ----------------------------------------------------------

def parameter_names(n: int) -> list[str]:
    """Names of the 10 n standard parameters of an n-link chain, link number appended
    (``m1``, ``mx1``, ..., ``Izz<n>``), in the order of ``chain.phi.ravel()``."""
    return [f"{p}{i + 1}" for i in range(n) for p in INERTIAL_NAMES]


def regressor(chain: AbstractChain, q: Float[Array, " n"], dq: Float[Array, " n"],
              ddq: Float[Array, " n"]) -> Float[Array, "n 10n"]:
    """Y(q, q', q'') with ``chain.inverse_dynamics(q, dq, ddq) = Y @ chain.phi.ravel()``
    [N m per parameter unit] (exact: the inverse dynamics is linear in phi)."""
    Y = jax.jacfwd(lambda p: chain.with_phi(p).inverse_dynamics(q, dq, ddq))(chain.phi)
    return Y.reshape(chain.n, -1)


@dataclasses.dataclass(frozen=True)
class BaseParameters:
    """The parameter combinations of a chain that joint torques determine (host-side record).

    names: the 10 n standard parameters (``parameter_names``); base: the names of the r
    independent columns, one per base parameter; combinations: for each base parameter its
    expression as text ("Izz1 + 0.09 m2 + 0.6 mx2"); K: (r, 10 n - r) array, beta = phi_base
    + K phi_dependent; dependent: the names lumped into the base parameters; unidentifiable:
    the names no joint torque depends on, or that enter only through a combination (each with
    its reason in ``reasons``, as the identification report marks unidentified parameters);
    rank: r; singular_values: of the stacked, column-normalised regressor.
    """

    names: list[str]
    base: list[str]
    combinations: list[str]
    K: np.ndarray
    dependent: list[str]
    unidentifiable: list[str]
    reasons: dict[str, str]
    rank: int
    singular_values: np.ndarray
    projection: np.ndarray  # (r, 10 n): beta = projection @ phi.ravel()

    def values(self, phi: ArrayLike) -> np.ndarray:
        """The base parameters beta (r,) of standard parameters ``phi`` (n, 10)."""
        return self.projection @ np.asarray(phi, float).ravel()

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping."""
        return {"rank": self.rank, "base": dict(zip(self.base, self.combinations)),
                "unidentifiable": dict(self.reasons)}


def _format(name: str, coefs: dict[str, float]) -> str:
    return " ".join([name] + [f"{'-' if c < 0 else '+'} {abs(c):.6g} {k}"
                               for k, c in coefs.items()])


def stacked_regressor(chain: AbstractChain, states: Float[Array, "N 3 n"],
                      joints: tuple[int, ...] | None = None) -> np.ndarray:
    """The regressors at ``states`` (each (q, q', q'')) stacked into (N n_j, 10 n): the rows
    of the torques of ``joints`` (indices; default all n joints)."""
    rows = tuple(range(chain.n)) if joints is None else tuple(int(j) for j in joints)
    Y = _regressors(chain, jnp.asarray(states), rows)
    return np.asarray(Y).reshape(-1, 10 * chain.n)


@eqx.filter_jit
def _regressors(chain: AbstractChain, states: Array, rows: tuple[int, ...]) -> Array:
    """The rows ``rows`` of the regressors at ``states`` (N, 3, n), compiled once per chain
    structure and shape (``rows`` static)."""
    return jax.vmap(lambda s: regressor(chain, s[0], s[1], s[2])[jnp.asarray(rows)])(states)


def random_states(n: int, num: int, seed: int = 0, q_range: float = np.pi,
                  rate: float = 2.0) -> np.ndarray:
    """``num`` random states (q, q', q'') (num, 3, n): q uniform in +-q_range [rad or m],
    q' and q'' normal with scale ``rate`` [1/s, 1/s^2]."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-q_range, q_range, (num, n))
    return np.stack([q, rate * rng.normal(size=(num, n)), rate * rng.normal(size=(num, n))], 1)


def base_parameters(chain: AbstractChain, states: ArrayLike | None = None, num: int = 200,
                    seed: int = 0, rtol: float = RANK_RTOL,
                    joints: tuple[int, ...] | None = None) -> BaseParameters:
    """The base parameters of ``chain``'s inertial parameters (module docstring).

    **Arguments:**

    - ``chain``: its kinematics and gravity matter, its inertial values do not.
    - ``states``: (N, 3, n) states (q, q', q'') at which to stack the regressor; default
      ``num`` random states (``random_states``; pass the states of a trajectory to ask what
      *that* excitation determines).
    - ``rtol``: rank tolerance relative to the largest pivot.
    - ``joints``: the joints whose torques are measured (indices; default all): with a subset
      (the driven axes of an arm whose other joints move without torque sensing), the base
      parameters are those the torques of ``joints`` determine.

    **Returns:** a ``BaseParameters``.
    """
    n = chain.n
    names = parameter_names(n)
    if states is None:
        states = random_states(n, num, seed)
    W = stacked_regressor(chain, np.asarray(states, float), joints)
    norms = np.linalg.norm(W, axis=0)
    # a column at rounding level (an angle's sine at 0 or pi, ...) is a zero column: unscaled
    # it would become a unit column of noise and a pivot
    norms = np.where(norms > 1e-12 * norms.max(), norms, 0.0)
    W = np.where(norms > 0, W, 0.0)
    scale = np.where(norms > 0, norms, 1.0)
    Ws = W / scale                                   # unit columns: the pivots compare shapes
    sv = np.linalg.svd(Ws, compute_uv=False)
    _, R, piv = scipy.linalg.qr(Ws, mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    r = int(np.sum(diag > rtol * diag[0]))
    ind, dep = piv[:r], piv[r:]
    order = np.argsort(ind)                          # base parameters in the parameters' order
    ind = ind[order]
    Ks = scipy.linalg.solve_triangular(R[:r, :r], R[:r, r:])[order]
    K = Ks * scale[None, dep] / scale[ind, None]     # back to the parameters' own units
    K[np.abs(K) < 1e-10 * max(1.0, np.abs(K).max(initial=0.0))] = 0.0
    P = np.zeros((r, 10 * n))
    P[np.arange(r), ind] = 1.0
    P[:, dep] = K
    combos, reasons = [], {}
    for row, i in enumerate(ind):
        coefs = {names[j]: float(K[row, col]) for col, j in enumerate(dep) if K[row, col] != 0}
        combos.append(_format(names[i], coefs))
    for col, j in enumerate(dep):
        if norms[j] == 0 or not np.any(K[:, col]):
            reasons[names[j]] = "no joint torque depends on it"
        else:
            holders = [names[ind[row]] for row in np.nonzero(K[:, col])[0]]
            reasons[names[j]] = f"determined only in combination, lumped into {holders}"
    dependent = [names[j] for j in sorted(dep)]
    return BaseParameters(names=names, base=[names[i] for i in ind], combinations=combos,
                          K=K, dependent=dependent, unidentifiable=dependent,
                          reasons={k: reasons[k] for k in dependent}, rank=r,
                          singular_values=sv, projection=P)
