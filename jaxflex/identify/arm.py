"""A serial arm identified as one coupled rigid-body model by linear least squares on its
inverse dynamics (IDIM-LS; the weighted form IDIM-WLS of Gautier & Poignet, "Extended Kalman
filtering and weighted least squares dynamic identification of robot", Control Eng. Practice
2001, the method of the EMPS benchmark's reference).

For the driven joints j of a chain (``jaxflex.core.chain.AbstractChain``, from DH parameters
or a URDF; docs/spec.md section 1), the motor torque referred to the link side is the link
line of eq. 3 plus the rotor line's inertia (the spring torque K (q2 - q1) of eq. 3 is
eliminated between the two lines, so K does not appear and both encoders are used):

    tau_j = [M(q) q'' + C(q, q') q' + G(q)]_j + Ja_j qm_j'' + Fv_j qm_j' + Fc_j sign(qm_j')
            + c_j + k_b b_j(q)

with q the link angles of *all* joints of the chain (joints without a torque sensor enter at
their measured motion: their inertial forces act on the driven joints through the coupling
terms of M and C), qm_j the motor angle referred to the link, Ja_j [kg m^2] the rotor
inertia, Fv_j [N m s/rad] and Fc_j [N m] viscous and Coulomb friction at the motor (the rigid
model of eq. 37 per joint), c_j [N m] a torque offset, and b(q) [N m] a known torque (a weight
counterbalance) with its scale k_b = 1 or fitted.

The bracket is Y(q, q', q'') phi with Y the exact regressor of ``jaxflex.core.inertial``; the
torques of the driven joints determine only the base parameters beta = P phi
(``jaxflex.core.inertial.base_parameters`` with ``joints``), so Y phi = Y_b beta with Y_b the
columns of the independent parameters. Stacking the samples gives tau = A x, x = (beta, Ja,
Fv, Fc, c, k_b), solved by least squares with rows weighted by each joint's residual
standard deviation (two passes: ordinary, then weighted). Derivatives by zero-phase
Savitzky-Golay filtering (``jaxflex.fit.savgol``, the one numerical differentiation of logs).

A least-squares beta need not belong to any physical arm. ``consistent_fit`` refits with each
link's standard parameters in log-Cholesky coordinates (``jaxflex.core.inertial``: positive mass,
positive-definite pseudo-inertia for every value) and says whether the data cost rises by
more than the 95 % chi-square quantile of the base-parameter count, i.e. whether the plain
estimate's confidence region holds a physical arm.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from jaxflex.core.chain import AbstractChain
from jaxflex.fit import savgol
from jaxflex.fit.inverse import rigid_regressors
from jaxflex.core.inertial import (BaseParameters, base_parameters, log_cholesky_from_phi,
                              phi_from_log_cholesky, pseudo_inertia, random_states,
                              stacked_regressor)

#: Savitzky-Golay window [samples] and polynomial degree of the derivatives.
WINDOW: int = 31
ORDER: int = 3
#: Per-joint terms beside the rigid body, in the order of ``ArmFit.names``: rotor inertia
#: Ja [kg m^2], viscous Fv [N m s/rad] and Coulomb Fc [N m] friction, torque offset c [N m].
JOINT_TERMS: tuple[str, ...] = ("Ja", "Fv", "Fc", "c")
#: Name of the known torque's scale.
KNOWN_SCALE: str = "k_b"


@dataclasses.dataclass(frozen=True)
class ArmMotion:
    """Measured motion and torques of an arm log, with their derivatives.

    Attributes:
        t: time [s] (N,).
        q, dq, ddq: link angles [rad], velocities [rad/s], accelerations [rad/s^2] of all
            n joints of the chain (N, n).
        qm, dqm, ddqm: motor angles referred to the link side, and derivatives, of the
            driven joints (N, m).
        tau: motor torques referred to the link side [N m] of the driven joints (N, m).
        joints: the driven joints' indices in the chain (m,).
    """

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    qm: np.ndarray
    dqm: np.ndarray
    ddqm: np.ndarray
    tau: np.ndarray
    joints: tuple[int, ...]

    @property
    def states(self) -> np.ndarray:
        """(N, 3, n) stacks (q, q', q'') for ``jaxflex.core.inertial.stacked_regressor``."""
        return np.stack([self.q, self.dq, self.ddq], axis=1)


def motion_from_angles(t: ArrayLike, q: ArrayLike, qm: ArrayLike, tau: ArrayLike,
                       joints: Sequence[int], window: int = WINDOW,
                       held: Sequence[int] = ()) -> ArmMotion:
    """An ``ArmMotion`` from sampled angles, derivatives by Savitzky-Golay filtering.

    **Arguments:**

    - ``t`` [s] (N,), uniformly sampled.
    - ``q`` [rad] (N, n): link angles of all chain joints.
    - ``qm`` [rad] (N, m): motor angles (link-referred) of the driven ``joints``.
    - ``tau`` [N m] (N, m): their link-referred motor torques.
    - ``joints``: the driven joints' chain indices (m,).
    - ``window``: Savitzky-Golay window [samples] (odd), degree ``ORDER``.
    - ``held``: chain joints to hold at their mean angle, at rest (their motion left out).

    **Returns:** the ``ArmMotion``.

    **Raises:** ``ValueError`` for shapes that disagree.
    """
    t = np.asarray(t, float)
    q, qm, tau = (np.array(x, float) for x in (q, qm, tau))
    joints = tuple(int(j) for j in joints)
    N = t.shape[0]
    if q.ndim != 2 or q.shape[0] != N or qm.shape != (N, len(joints)) or tau.shape != qm.shape:
        raise ValueError(f"motion_from_angles: need q (N, n), qm and tau (N, {len(joints)}) "
                         f"for N = {N}, got {q.shape}, {qm.shape}, {tau.shape}")
    dt = float((t[-1] - t[0]) / (N - 1))
    d = [savgol(q, dt, k, window, ORDER) for k in (0, 1, 2)]
    d[0] = q
    for h in held:
        d[0][:, h] = np.mean(q[:, h])
        d[1][:, h] = 0.0
        d[2][:, h] = 0.0
    return ArmMotion(t=t, q=d[0], dq=d[1], ddq=d[2], qm=qm,
                     dqm=savgol(qm, dt, 1, window, ORDER), ddqm=savgol(qm, dt, 2, window, ORDER),
                     tau=tau, joints=joints)


def kuka_arm_motion(trajectory: str, wrist: str = "measured", window: int = WINDOW) -> ArmMotion:
    """Axes 1-3 of a KUKA KR300 recording as the driven joints of the six-axis chain
    (``jaxflex.data.kr300.kuka_kr300_chain``): link angles of axes 1-3 from the link-side
    encoders, of axes 4-6 from their motor encoders (link-referred; they have no link
    encoders), motor angles and link-referred torques of axes 1-3 (``jaxflex.data.load_kuka``).

    **Arguments:** ``trajectory``: "A", "B" or "C"; ``wrist``: "measured" (axes 4-6 at their
    recorded motion) or "held" (at their mean angle, at rest); ``window`` [samples].

    **Returns:** the ``ArmMotion`` (joints (0, 1, 2)).

    **Raises:** ``ValueError`` for an unknown trajectory or wrist choice.
    """
    from jaxflex.data import load_kuka
    from jaxflex.data.kr300 import load_kuka_wrist

    if wrist not in ("measured", "held"):
        raise ValueError(f"kuka_arm_motion: wrist must be 'measured' or 'held', got {wrist!r}")
    log = load_kuka(trajectory, (1, 2, 3))
    w = load_kuka_wrist(trajectory)
    q = np.concatenate([log.q1, w["q"]], axis=1)
    return motion_from_angles(log.t, q, log.q2, log.tau, (0, 1, 2), window,
                              held=(3, 4, 5) if wrist == "held" else ())


def kuka_counterbalance(motion: ArmMotion) -> np.ndarray:
    """The known torque b (N, 3) [N m] of the KUKA arm: the hydraulic counterbalance on
    axis 2 (``jaxflex.data.kr300.hydraulic_counterbalance``) at the link angle, 0 elsewhere."""
    from jaxflex.data.kr300 import hydraulic_counterbalance

    b = np.zeros_like(motion.tau)
    b[:, 1] = hydraulic_counterbalance(motion.q[:, 1])
    return b


def joint_columns(motion: ArmMotion) -> np.ndarray:
    """The per-joint columns (N, m, 4 m) (``JOINT_TERMS`` per joint, joint-major): joint j's
    row holds qm_j'', qm_j', sign(qm_j'), 1 in its own four columns."""
    N, m = motion.tau.shape
    cols = rigid_regressors(motion.dqm, motion.ddqm)                  # (N, m, 4)
    out = np.zeros((N, m, 4 * m))
    for j in range(m):
        out[:, j, 4 * j:4 * j + 4] = cols[:, j]
    return out


@eqx.filter_jit
def _inverse_dynamics(chain: AbstractChain, states: Array, rows: tuple[int, ...]) -> Array:
    """Rows ``rows`` of M q'' + C q' + G at ``states`` (N, 3, n) [N m]."""
    return jax.vmap(lambda s: chain.inverse_dynamics(s[0], s[1], s[2])[jnp.asarray(rows)])(
        states)


@dataclasses.dataclass(frozen=True)
class _Design:
    """The model of the module docstring on one motion: tau = fixed + A x.

    A (N, m, p): the free base parameters' regressor columns, the per-joint columns, the known
    torque's column when its scale is fitted; fixed (N, m): the rigid-body torque of the fixed
    base parameters at their prior values, plus the known torque when its scale is 1."""

    A: np.ndarray
    fixed: np.ndarray


def _design(chain: AbstractChain, base: BaseParameters | None, free: Sequence[str],
            motion: ArmMotion, known: np.ndarray | None, fit_known: bool) -> _Design:
    """The ``_Design`` of ``motion``; the prior values of the base parameters are those of
    ``chain.phi`` (Y phi = Y_b beta, so the prior torque is the chain's inverse dynamics)."""
    N, m = motion.tau.shape
    states = jnp.asarray(motion.states)
    fixed = np.asarray(_inverse_dynamics(chain, states, motion.joints))
    parts = []
    if free:
        Y = stacked_regressor(chain, motion.states, motion.joints).reshape(N, m, -1)
        cols = [base.names.index(b) for b in free]
        beta0 = base.values(chain.phi)
        idx = [base.base.index(b) for b in free]
        parts.append(Y[:, :, cols])
        fixed = fixed - Y[:, :, cols] @ beta0[idx]
    parts.append(joint_columns(motion))
    if known is not None:
        if fit_known:
            parts.append(known[:, :, None])
        else:
            fixed = fixed + known
    return _Design(A=np.concatenate(parts, axis=-1), fixed=fixed)


def _weighted_ls(A: np.ndarray, y: np.ndarray, sigma: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of (N, m, p) A x = (N, m) y with joint j's rows divided by sigma_j;
    returns x, its standard errors (white residual) and the column-scaled singular values."""
    Aw = (A / sigma[None, :, None]).reshape(-1, A.shape[-1])
    yw = (y / sigma[None, :]).reshape(-1)
    scale = np.linalg.norm(Aw, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    U, s, Vt = np.linalg.svd(Aw / scale, full_matrices=False)
    xs = Vt.T @ ((U.T @ yw) / s)
    x = xs / scale
    r = yw - Aw @ x
    s2 = float(r @ r) / max(Aw.shape[0] - Aw.shape[1], 1)
    cov = (Vt.T / s**2) @ Vt / np.outer(scale, scale) * s2
    return x, np.sqrt(np.maximum(np.diag(cov), 0.0)), s


def _solve(d: _Design, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                  np.ndarray]:
    """IDIM-WLS on a design: an ordinary pass for each joint's residual scale, then the
    weighted pass; returns x, stderr, sigma [N m] (m,), singular values."""
    y = tau - d.fixed
    x, _, _ = _weighted_ls(d.A, y, np.ones(tau.shape[1]))
    sigma = np.std(y - d.A @ x, axis=0)
    x, se, sv = _weighted_ls(d.A, y, sigma)
    return x, se, np.std(y - d.A @ x, axis=0), sv


@dataclasses.dataclass(frozen=True)
class ArmFit:
    """An arm identified by ``identify_arm``.

    Attributes:
        chain: the chain (kinematics, gravity, and the prior inertial parameters ``phi`` that
            give the fixed base parameters their values).
        base: the base parameters the driven joints' torques determine (None when
            ``free`` is empty and none were given).
        free: the base parameters estimated (the others held at the prior's values).
        joints: the driven joints' chain indices.
        names: the estimated parameters: ``free``, then ``JOINT_TERMS`` per driven joint
            (``Ja1``, ``Fv1``, ..., numbered by chain joint), then ``KNOWN_SCALE`` when fitted.
        values, stderr: estimates and standard errors (white residual, weighted LS) in the
            units of the module docstring.
        sigma: residual standard deviation per driven joint [N m] (the weights).
        singular_values: of the weighted, column-normalised design (conditioning).
        fit_known: whether the known torque's scale was fitted (else 1).
    """

    chain: AbstractChain
    base: BaseParameters | None
    free: tuple[str, ...]
    joints: tuple[int, ...]
    names: list[str]
    values: np.ndarray
    stderr: np.ndarray
    sigma: np.ndarray
    singular_values: np.ndarray
    fit_known: bool

    def value(self, name: str) -> float:
        """The estimate of parameter ``name``."""
        return float(self.values[self.names.index(name)])

    @property
    def condition(self) -> float:
        """Condition number of the weighted, column-normalised design."""
        s = self.singular_values
        return float(s[0] / s[-1])

    def base_values(self) -> np.ndarray:
        """All r base parameters: the estimated ones and the prior's values of the others.

        **Raises:** ``ValueError`` when the fit was made without a base set."""
        if self.base is None:
            raise ValueError("ArmFit.base_values: the fit held all inertias at the prior "
                             "without a base set; pass base= to identify_arm")
        beta = self.base.values(self.chain.phi)
        for k, b in enumerate(self.free):
            beta[self.base.base.index(b)] = self.values[k]
        return beta

    def predict(self, motion: ArmMotion, known: ArrayLike | None = None) -> np.ndarray:
        """Motor torques [N m] (N, m) of the identified model on ``motion``; ``known``: the
        known torque b (N, m) (required when the fit used one)."""
        kn = None if known is None else np.asarray(known, float)
        d = _design(self.chain, self.base, self.free, motion, kn, self.fit_known)
        return d.fixed + d.A @ self.values

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: parameters with standard errors, base combinations,
        conditioning, per-joint residual scale."""
        return {"parameters": {k: {"value": float(v), "stderr": float(s)}
                               for k, v, s in zip(self.names, self.values, self.stderr)},
                "free_base": {b: self.base.combinations[self.base.base.index(b)]
                              for b in self.free},
                "rank": None if self.base is None else self.base.rank,
                "condition": self.condition,
                "sigma": [float(s) for s in self.sigma]}


def arm_base(chain: AbstractChain, joints: Sequence[int], num: int = 200) -> BaseParameters:
    """The structural base parameters of ``chain`` for the torques of ``joints``: from
    ``num`` random states of all joints (``jaxflex.core.inertial.base_parameters``)."""
    return base_parameters(chain, states=random_states(chain.n, num), joints=tuple(joints))


def identify_arm(chain: AbstractChain, motion: ArmMotion, known: ArrayLike | None = None,
                 fit_known: bool = False, free: Sequence[str] | None = None,
                 base: BaseParameters | None = None) -> ArmFit:
    """Identify the coupled arm by IDIM-WLS (module docstring).

    **Arguments:**

    - ``chain``: kinematics and gravity of the whole chain (all joints of ``motion.q``); its
      ``phi`` is the prior that fixes the base parameters not in ``free``.
    - ``motion``: the identification log (``motion_from_angles``, ``kuka_arm_motion``).
    - ``known``: a known torque b [N m] (N, m) on the driven joints (a counterbalance), or
      None; ``fit_known``: fit its scale k_b instead of taking 1.
    - ``free``: the base parameters to estimate (names in ``base.base``); None: all of them
      (plain IDIM-LS), ``()``: none (the prior's inertias, only the per-joint terms fitted).
    - ``base``: the base parameters; default ``arm_base`` (the structural set, not one
      log's excitation; not computed when ``free`` is empty).

    **Returns:** an ``ArmFit``.

    **Raises:** ``ValueError`` for a motion whose joints do not fit the chain, or a name in
    ``free`` that is not a base parameter.
    """
    if motion.q.shape[1] != chain.n or max(motion.joints) >= chain.n:
        raise ValueError(f"identify_arm: motion has {motion.q.shape[1]} joints, driven "
                         f"{motion.joints}; the chain has {chain.n}")
    if base is None and free != ():
        base = arm_base(chain, motion.joints)
    free = tuple(base.base) if free is None else tuple(free)
    unknown = [b for b in free if b not in base.base]
    if unknown:
        raise ValueError(f"identify_arm: {unknown} are not base parameters; the base "
                         f"parameters are {base.base}")
    kn = None if known is None else np.asarray(known, float)
    d = _design(chain, base, free, motion, kn, fit_known)
    x, se, sigma, sv = _solve(d, motion.tau)
    names = list(free) + [f"{k}{j + 1}" for j in motion.joints for k in JOINT_TERMS]
    if kn is not None and fit_known:
        names.append(KNOWN_SCALE)
    return ArmFit(chain=chain, base=base, free=free, joints=motion.joints, names=names,
                  values=x, stderr=se, sigma=sigma, singular_values=sv,
                  fit_known=bool(kn is not None and fit_known))


def essential_parameters(chain: AbstractChain, motion: ArmMotion, known: ArrayLike | None = None,
                         max_rel_stderr: float = 0.1, base: BaseParameters | None = None
                         ) -> tuple[str, ...]:
    """The base parameters a log determines (the essential parameters of Pham & Gautier,
    ICRA 1991, in backward-elimination form): starting from all, drop the one with the
    largest relative standard error |stderr / value| until every one left is below
    ``max_rel_stderr``; the dropped ones keep the prior's values (``identify_arm``'s
    ``free``).

    **Returns:** the names of the kept base parameters (possibly empty).
    """
    if base is None:
        base = arm_base(chain, motion.joints)
    kn = None if known is None else np.asarray(known, float)
    d = _design(chain, base, tuple(base.base), motion, kn, False)
    beta0 = base.values(chain.phi)
    free = list(range(base.rank))
    n_extra = d.A.shape[-1] - base.rank
    while free:
        fixed_idx = [i for i in range(base.rank) if i not in free]
        dd = _Design(A=d.A[:, :, free + list(range(base.rank, base.rank + n_extra))],
                     fixed=d.fixed + d.A[:, :, fixed_idx] @ beta0[fixed_idx])
        x, se, _, _ = _solve(dd, motion.tau)
        rel = np.abs(se[:len(free)]) / np.maximum(np.abs(x[:len(free)]), 1e-300)
        if rel.max() < max_rel_stderr:
            break
        free.pop(int(np.argmax(rel)))
    return tuple(base.base[i] for i in free)


def torque_error_pct(tau: ArrayLike, tau_hat: ArrayLike) -> list[float]:
    """Per joint, ``100 ||tau - tau_hat|| / ||tau||`` [%] over all samples (the motor-torque
    error of ``jaxflex.validate.rel_error_pct``)."""
    from jaxflex.validate import rel_error_pct

    tau, tau_hat = np.asarray(tau), np.asarray(tau_hat)
    return [rel_error_pct(tau[:, j], tau_hat[:, j]) for j in range(tau.shape[1])]


# ----- a physically consistent refit ----------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class ConsistentFit:
    """The arm refitted with physically consistent links (``consistent_fit``).

    Attributes:
        phi: standard parameters (n, 10) of a physical arm (every pseudo-inertia positive
            definite).
        extras: the per-joint terms (and k_b) in ``ArmFit.names``' order after the base ones.
        cost, cost_ls: weighted data cost (sum of squared weighted residuals) of this fit and
            of the plain least squares, with the plain fit's weights.
        threshold: the 95 % chi-square quantile of the base-parameter count.
        ls_physical: True when a physical arm with cost - cost_ls <= threshold was found
            (the plain estimate's confidence region holds one), False when the optimiser
            converged above it, None when it stopped above it unconverged (undecided: the
            found cost bounds the constrained minimum from above only).
        converged: the optimiser's status.
    """

    phi: np.ndarray
    extras: np.ndarray
    cost: float
    cost_ls: float
    threshold: float
    ls_physical: bool | None
    converged: bool

    def predict(self, fit: ArmFit, motion: ArmMotion, known: ArrayLike | None = None
                ) -> np.ndarray:
        """Motor torques [N m] (N, m) of the physical arm on ``motion``."""
        return dataclasses.replace(fit, values=self.base_values(fit)).predict(motion, known)

    def base_values(self, fit: ArmFit) -> np.ndarray:
        """The parameter vector in ``fit.names``' order: base parameters of ``phi``, then
        ``extras``."""
        return np.concatenate([fit.base.values(self.phi), self.extras])


def _regularise(phi: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """``phi`` with eps [kg m^2] added to each second moment (Sigma + eps 1): a point mass or
    a planar body becomes a body with a positive-definite pseudo-inertia."""
    J = np.array(pseudo_inertia(jnp.asarray(phi, float)))
    J[..., :3, :3] += eps * np.eye(3)
    Sigma = J[..., :3, :3]
    Io = np.trace(Sigma, axis1=-2, axis2=-1)[..., None, None] * np.eye(3) - Sigma
    out = np.array(phi, float)
    out[..., 4:] = np.stack([Io[..., 0, 0], Io[..., 0, 1], Io[..., 0, 2], Io[..., 1, 1],
                             Io[..., 1, 2], Io[..., 2, 2]], -1)
    return out


def consistent_fit(fit: ArmFit, motion: ArmMotion, known: ArrayLike | None = None,
                   phi0: ArrayLike | None = None, prior: float = 1e-3,
                   max_nfev: int = 500) -> ConsistentFit:
    """Refit ``fit``'s model on ``motion`` with physically consistent links (module
    docstring): the standard parameters in log-Cholesky coordinates, the per-joint terms
    free, the same weights, by trust-region least squares (``scipy.optimize.least_squares``).

    **Arguments:**

    - ``fit``: the plain estimate of all base parameters (its weights, names, base set).
    - ``motion``, ``known``: as for ``identify_arm``.
    - ``phi0``: start (n, 10), default ``fit.chain.phi`` (nominal inertias), regularised to a
      positive-definite pseudo-inertia.
    - ``prior``: weight of a pull toward the start's log-Cholesky coordinates that keeps the
      directions the torques do not see in place (the data part of the cost is reported).
    - ``max_nfev``: evaluation budget.

    **Returns:** a ``ConsistentFit``.

    **Raises:** ``ValueError`` for a ``fit`` that held some base parameters at the prior, or
    a start that is not physical.
    """
    import scipy.optimize
    import scipy.stats

    chain = fit.chain
    if tuple(fit.free) != tuple(fit.base.base):
        raise ValueError("consistent_fit: needs a fit of all base parameters (free=None)")
    kn = None if known is None else np.asarray(known, float)
    N, m = motion.tau.shape
    Y = stacked_regressor(chain, motion.states, motion.joints).reshape(N, m, -1)
    d = _design(chain, fit.base, fit.free, motion, kn, fit.fit_known)
    A, y = d.A, motion.tau - d.fixed
    r_b = fit.base.rank
    X = A[:, :, r_b:]
    w = 1.0 / fit.sigma
    Yw = jnp.asarray((Y * w[None, :, None]).reshape(-1, Y.shape[-1]))
    Xw = jnp.asarray((X * w[None, :, None]).reshape(-1, X.shape[-1]))
    yw = jnp.asarray((y * w[None, :]).reshape(-1))
    n = chain.n
    start = _regularise(np.asarray(chain.phi if phi0 is None else phi0, float))
    th0 = np.asarray(log_cholesky_from_phi(jnp.asarray(start)))
    if not np.all(np.isfinite(th0)):
        bad = [i + 1 for i in range(n) if not np.all(np.isfinite(th0[i]))]
        raise ValueError(f"consistent_fit: the start's links {bad} are not physically "
                         "consistent (pass a physical phi0)")
    z0 = np.concatenate([th0.ravel(), fit.values[r_b:]])

    def data_residual(z: Array) -> Array:
        phi = phi_from_log_cholesky(z[:10 * n].reshape(n, 10)).ravel()
        return Yw @ phi + Xw @ z[10 * n:] - yw

    def residual(z: Array) -> Array:
        return jnp.concatenate([data_residual(z), prior * (z[:10 * n] - th0.ravel())])

    res = jax.jit(residual)
    # the chain rule by hand: d(Yw phi)/dtheta = Yw dphi/dtheta, with the small (10 n, 10 n)
    # Jacobian of the log-Cholesky map from jax
    dphi = jax.jit(jax.jacfwd(lambda th: phi_from_log_cholesky(th.reshape(n, 10)).ravel()))
    Yw_np, Xw_np = np.asarray(Yw), np.asarray(Xw)
    eye = prior * np.eye(10 * n, 10 * n + Xw_np.shape[1])

    def jac(z: np.ndarray) -> np.ndarray:
        top = np.concatenate([Yw_np @ np.asarray(dphi(jnp.asarray(z[:10 * n]))), Xw_np], 1)
        return np.concatenate([top, eye], 0)

    sol = scipy.optimize.least_squares(lambda z: np.asarray(res(jnp.asarray(z))), z0, jac=jac,
                                       method="trf", x_scale="jac", max_nfev=max_nfev)
    z = sol.x
    phi = np.asarray(phi_from_log_cholesky(jnp.asarray(z[:10 * n].reshape(n, 10))))
    cost = float(np.sum(np.asarray(data_residual(jnp.asarray(z))) ** 2))
    r_ls = (A @ fit.values - y) * w[None, :]
    cost_ls = float(np.sum(r_ls**2))
    thr = float(scipy.stats.chi2.ppf(0.95, r_b))
    converged = bool(sol.status > 0)
    physical = True if cost - cost_ls <= thr else (False if converged else None)
    return ConsistentFit(phi=phi, extras=z[10 * n:], cost=cost, cost_ls=cost_ls, threshold=thr,
                         ls_physical=physical, converged=converged)


__all__ = ["ArmFit", "ArmMotion", "ConsistentFit", "JOINT_TERMS", "KNOWN_SCALE",
           "arm_base", "consistent_fit", "essential_parameters", "identify_arm", "joint_columns", "kuka_arm_motion",
           "kuka_counterbalance", "motion_from_angles", "torque_error_pct"]
