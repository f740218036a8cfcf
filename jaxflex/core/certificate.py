"""Stability certificate of the cascade controller: the matrix N2 (paper section 4, eq. 24-33;
docs/spec.md section 4).

With rho = [e1, e1', e2, e2', eta] (each block (n,)), eta = Psi_hat(q1') z_tilde and
z_tilde = z - z_hat, the Lyapunov function V = V1 + V2 of eq. 24-26 has

    V' = -rho^T N2(q1') rho + rho^T D                                            (eq. 29)

    N2 = [[ L1^2 (KD1 + a),   L1 a,       -L1 K / 2,   0,    -L1 sigma0 sigma1 / 2 ],
          [ L1 a,             KD1 + a,    -K / 2,      0,    -sigma0 sigma1 / 2    ],
          [ -L1 K / 2,        -K / 2,     L2^2 KD2,    0,     0                    ],
          [ 0,                0,          0,           KD2,   0                    ],
          [ -L1 sigma0 sigma1 / 2, -sigma0 sigma1 / 2, 0, 0, sigma0 Psi#(q1') / Ke ]]

    a = sigma0 sigma1 Ke,   Psi#(v) = 1 / Psi_hat(v) = g(v) / m(v) for |v| >= eps,
    1/eps for |v| < eps                                                          (eq. 30)

    D = dPsi z [L1 sigma0 sigma1, sigma0 sigma1, 0, 0, -sigma0 Psi# / Ke],
    dPsi = Psi(v) - Psi_hat(v) = (|v| - m(v)) / g(v)

(each entry an n x n diagonal block; ``tests/test_certificate.py`` re-derives V' with sympy).
Psi# falls as |q1'| grows, so N2 is positive definite up to some link speed: a gain set is
*certified* over the speeds where lambda_min(N2) > 0 (or > a margin), and the errors are then
ultimately bounded by ||rho|| <= D_bar / lambda_min(N2) (eq. 32-33).

N2 does not depend on the inertia M(q1) (the skew-symmetry of M' - 2C removes it), so the
same certificate holds for the n-link arm.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.controller import CascadeGains
from jaxflex.core.friction import smooth_abs_observer
from jaxflex.core.observer import FrictionObserver
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.trajectory import Trajectory
from jaxflex.core.validation import requires_float64

DEFAULT_EPS: float = 1e-3
"""Tolerance eps [rad/s] of eq. 30 below which Psi# is held at 1/eps."""
DEFAULT_VMAX: float = 5.0
"""Default end [rad/s] of the velocity grid of ``certify``."""
DEFAULT_NUM: int = 301
"""Default number of grid points of ``certify``."""


def _friction(plant: FlexibleJointPlant):
    if plant.friction is None:
        raise ValueError("certificate: the plant has no LuGre friction parameters (N2 needs "
                         "sigma0, sigma1 and g(v))")
    return plant.friction


@requires_float64
def psi_sharp(plant: FlexibleJointPlant, gains: CascadeGains, v: ArrayLike,
              eps: float = DEFAULT_EPS) -> Float[Array, " n"]:
    """Psi#(v) of eq. 30 [N m s/rad]: the inverse of the observer's Psi_hat(v) = (m(v) +
    leak)/g(v) (eq. 19, 21) for |v| >= eps, and 1/eps for |v| < eps where the observer has no
    leakage (Psi_hat(0) = 0, the paper's case); with leak > 0 Psi_hat never vanishes and
    Psi# = 1/Psi_hat everywhere. ``v`` [rad/s], shape (n,) or scalar.

    Double ``where`` keeps gradients finite at v = 0.
    """
    fr = _friction(plant)
    v = jnp.broadcast_to(jnp.asarray(v, jnp.result_type(float)), gains.Ke.shape)
    return sharp_of(lambda s: fr.g(s), v, gains, eps)


def sharp_of(g: Callable[[Array], Array], v: Array, gains: CascadeGains, eps: float) -> Array:
    """Psi#(v) = g(v) / (m(v) + leak) with the eq. 30 cut-off 1/eps at |v| < eps where the
    gains' observer has no leakage; ``g`` maps speeds [rad/s] to g(v) [N m] (of any leading
    shape: ``box_lambda_min`` passes the corners of a box)."""
    leak = jnp.broadcast_to(gains.leak, gains.Ke.shape)
    cut = (jnp.abs(v) < eps) & (leak == 0)
    safe_v = jnp.where(cut, eps, v)
    return jnp.where(cut, 1.0 / eps, g(safe_v) / (smooth_abs_observer(safe_v, gains.kv) + leak))


@requires_float64
def n2_matrix(plant: FlexibleJointPlant, gains: CascadeGains, v: ArrayLike,
              eps: float = DEFAULT_EPS) -> Float[Array, "5n 5n"]:
    """The matrix N2 of eq. 29 at link velocity ``v`` [rad/s] (shape (n,) or a scalar for all
    joints), ordered rho = [e1, e1', e2, e2', eta], each block an n x n diagonal matrix.

    Pure and differentiable in the gains (used as the tuner's constraint).
    """
    fr = _friction(plant)
    p55 = fr.sigma0 * psi_sharp(plant, gains, v, eps) / gains.Ke
    return n2_of(plant.K, fr.sigma0 * fr.sigma1, p55, gains)


def n2_of(K: Array, s01: Array, p55: Array, gains: CascadeGains) -> Float[Array, "5n 5n"]:
    """N2 (eq. 29) from the three plant quantities it depends on: the spring K [N m/rad],
    s01 = sigma0 sigma1 [N m s/rad^2] and p55 = sigma0 Psi#(v) / Ke (its last diagonal
    entry). N2 is *affine* in (K, s01, p55) at fixed gains, so lambda_min(N2), a minimum of
    linear functions of them, is concave in them: its minimum over a box of (K, s01, p55) is
    reached at one of the box's 8 vertices (``box_lambda_min_curve``)."""
    Ke, KD1, KD2, L1, L2 = gains.Ke, gains.KD1, gains.KD2, gains.L1, gains.L2
    a = s01 * Ke
    zero = jnp.zeros_like(Ke)
    rows = [
        [L1**2 * (KD1 + a), L1 * a, -L1 * K / 2, zero, -L1 * s01 / 2],
        [L1 * a, KD1 + a, -K / 2, zero, -s01 / 2],
        [-L1 * K / 2, -K / 2, L2**2 * KD2, zero, zero],
        [zero, zero, zero, KD2, zero],
        [-L1 * s01 / 2, -s01 / 2, zero, zero, p55],
    ]
    return jnp.block([[jnp.diag(jnp.broadcast_to(e, Ke.shape)) for e in row] for row in rows])


@requires_float64
def d_vector(plant: FlexibleJointPlant, gains: CascadeGains, v: ArrayLike, z: ArrayLike,
             eps: float = DEFAULT_EPS) -> Float[Array, " 5n"]:
    """The perturbation D of eq. 29 at link velocity ``v`` [rad/s] and bristle state ``z``
    [rad]: what the smoothing m(v) of |v| (eq. 21) leaves over, through dPsi = Psi - Psi_hat."""
    fr = _friction(plant)
    obs = FrictionObserver(fr, gains.Ke, gains.kv, gains.leak)
    v = jnp.broadcast_to(jnp.asarray(v, jnp.result_type(float)), gains.Ke.shape)
    d_psi = fr.z_rate(v) / fr.sigma0 - obs.psi_hat(v)
    w = d_psi * jnp.asarray(z)
    s01 = fr.sigma0 * fr.sigma1
    zero = jnp.zeros_like(w)
    last = -fr.sigma0 * psi_sharp(plant, gains, v, eps) / gains.Ke * w
    return jnp.concatenate([gains.L1 * s01 * w, s01 * w, zero, zero, last])


def smallest_eigenvalue(N2: Float[Array, "5n 5n"]) -> Float[Array, ""]:
    """lambda_min of an N2 (``n2_of``) from its joints' 5 x 5 blocks.

    N2 is the direct sum of one block per joint, on rho_i = [e1_i, e1'_i, e2_i, e2'_i,
    eta_i], up to a permutation of rho; its eigenvalues are the blocks'. A block's entries
    span many decades (p55 = sigma0 Psi# / Ke reaches 1e21 on a KR300 axis just above eps,
    where lambda_min is about 1e5), and a symmetric eigensolver's error is eps ||B||: solved
    directly, lambda_min comes out wrong by up to its own size, either sign. A positive
    definite block (its form scaled to a unit diagonal has positive eigenvalues) is solved
    as 1 / lambda_max(B^-1), B^-1 formed from that scaled form's eigensystem (well
    conditioned, so accurate): the largest eigenvalue carries a relative error of eps only.
    A block that is not positive definite gives its eigensolver's lambda_min, at most 0.
    The derivative (the tuner's constraint) is the eigensolver's.
    """
    n = N2.shape[0] // 5
    idx = jnp.arange(5)[None, :] * n + jnp.arange(n)[:, None]  # (n, 5): joint i's entries
    blocks = N2[idx[:, :, None], idx[:, None, :]]
    direct = jnp.linalg.eigvalsh(blocks)[:, 0]
    b = jax.lax.stop_gradient(blocks)
    d = jnp.diagonal(b, axis1=-2, axis2=-1)
    pos = jnp.all(d > 0, axis=-1)
    scale = 1.0 / jnp.sqrt(jnp.where(pos[:, None], d, 1.0))
    w, u = jnp.linalg.eigh(b * scale[:, :, None] * scale[:, None, :])  # unit diagonal
    pd = pos & (w[:, 0] > 0)
    # B^-1 = S U diag(1/w) U' S, S the scaling: its largest eigenvalue to relative eps
    inv = jnp.einsum("ni,nij,nj,nkj,nk->nik", scale, u, 1.0 / jnp.where(pd[:, None], w, 1.0),
                     u, scale)
    top = jnp.linalg.eigvalsh(inv)[:, -1]
    accurate = jnp.where(pd, 1.0 / top, jnp.minimum(direct, 0.0))
    # the value to working precision, its derivative the eigensolver's (the same eigenvector)
    return jnp.min(direct + jax.lax.stop_gradient(accurate - direct))


@requires_float64
def lambda_min(plant: FlexibleJointPlant, gains: CascadeGains, v: ArrayLike,
               eps: float = DEFAULT_EPS) -> Float[Array, ""]:
    """Smallest eigenvalue of N2(v) (eq. 29, 31); ``v`` [rad/s] (n,) or a scalar for all joints.
    Positive means V' < 0 outside the ball of eq. 32."""
    return smallest_eigenvalue(n2_matrix(plant, gains, v, eps))


@requires_float64
def lambda_min_curve(plant: FlexibleJointPlant, gains: CascadeGains, velocities: ArrayLike,
                     eps: float = DEFAULT_EPS) -> Float[Array, " N"]:
    """lambda_min(N2) at each speed of ``velocities`` [rad/s] (every joint at that speed).

    N2 is block-diagonal per joint up to a permutation, so this is also the worst joint at
    that speed, and the minimum over the curve is the minimum over the box |q1'_i| <= v.
    """
    vs = jnp.asarray(velocities, jnp.result_type(float))
    return jax.vmap(lambda s: lambda_min(plant, gains, s, eps))(vs)


# compiled once per shape (plant and gains are array leaves, eps static)
_curve_jit = eqx.filter_jit(lambda_min_curve)
_lambda_min_jit = eqx.filter_jit(lambda_min)


@dataclasses.dataclass(frozen=True)
class CertificateResult:
    """Where a gain set is certified (host-side record).

    velocities [rad/s] grid from 0 to vmax; lambda_min (same length) smallest eigenvalue of N2;
    certified_up_to [rad/s]: largest speed up to which lambda_min > margin on the whole range
    [0, speed] (refined between grid points, capped at the grid's end; 0 when N2 fails at rest);
    certified: the whole grid passes; margin, eps [rad/s] as used.
    """

    velocities: np.ndarray
    lambda_min: np.ndarray
    certified_up_to: float
    certified: bool
    margin: float
    eps: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping (the ``jaxflex certify --json`` output)."""
        return {
            "velocities": [float(x) for x in self.velocities],
            "lambda_min": [float(x) for x in self.lambda_min],
            "certified_up_to": float(self.certified_up_to),
            "certified": bool(self.certified),
            "vmax": float(self.velocities[-1]),
            "margin": float(self.margin),
            "eps": float(self.eps),
            "min_lambda_min": float(np.min(self.lambda_min)),
        }


def _check_range(vmax: float, num: int, margin: float, eps: float) -> None:
    if not np.isfinite(vmax) or vmax <= 0:
        raise ValueError(f"certify: vmax must be a finite speed > 0 rad/s, got {vmax}")
    if int(num) < 2:
        raise ValueError(f"certify: the velocity grid needs at least 2 points, got {num}")
    if not np.isfinite(margin) or margin < 0:
        raise ValueError(f"certify: margin must be finite and >= 0, got {margin}")
    if not np.isfinite(eps) or eps <= 0:
        raise ValueError(f"certify: eps must be > 0 rad/s, got {eps}")


@requires_float64
def certify(plant: FlexibleJointPlant, gains: CascadeGains, vmax: float = DEFAULT_VMAX, *,
            num: int = DEFAULT_NUM, margin: float = 0.0, eps: float = DEFAULT_EPS,
            refine: int = 40) -> CertificateResult:
    """Certify ``gains`` on ``plant``: lambda_min(N2) over the speeds 0..vmax [rad/s] and the
    largest speed up to which N2 stays positive definite with ``margin`` (eq. 29-31).

    The boundary between the last passing and the first failing grid point is refined by
    ``refine`` bisection steps. ``CascadeGains`` refuses gains <= 0; bad ranges raise
    ``ValueError``.
    """
    _check_range(vmax, num, margin, eps)
    return _certified_range(
        lambda vel: _curve_jit(plant, gains, vel, eps),
        lambda v: _lambda_min_jit(plant, gains, v, eps), vmax, num, margin, eps, refine)


def _certified_range(curve, point, vmax: float, num: int, margin: float, eps: float,
                     refine: int) -> CertificateResult:
    """``certify``'s grid and bisection for any lambda_min (or lower bound) ``curve(speeds)``
    and ``point(speed)``."""
    vel = np.linspace(0.0, float(vmax), int(num))
    lam = np.asarray(curve(jnp.asarray(vel)))
    ok = lam > margin
    if ok.all():
        up_to = float(vmax)
    elif not ok[0]:
        up_to = 0.0
    else:
        first_bad = int(np.argmin(ok))
        lo, hi = vel[first_bad - 1], vel[first_bad]
        for _ in range(refine):
            mid = 0.5 * (lo + hi)
            lam_mid = float(point(jnp.asarray(mid)))
            lo, hi = (mid, hi) if lam_mid > margin else (lo, mid)
        up_to = float(lo)
    return CertificateResult(vel, lam, up_to, bool(ok.all()), float(margin), float(eps))


N2_PARAMETERS: tuple[str, ...] = ("K", "Fc", "Fs", "vs", "sigma0", "sigma1")
"""The plant parameters N2 depends on (not I, J, sigma2: eq. 29 does not contain them)."""


@dataclasses.dataclass(frozen=True)
class ParameterBox:
    """A box of plants for the certificate: per name of ``N2_PARAMETERS`` the lowest and
    highest value per joint, ``lo[name]``, ``hi[name]`` ((n,) arrays, SI units as in the
    parameter file). Raises ``ValueError`` on an unknown or missing name, lo > hi, or a
    non-physical bound (K, Fc, Fs, vs, sigma0 must be > 0, sigma1 >= 0)."""

    lo: dict[str, np.ndarray]
    hi: dict[str, np.ndarray]

    def __post_init__(self) -> None:
        for side in (self.lo, self.hi):
            if set(side) != set(N2_PARAMETERS):
                raise ValueError(f"ParameterBox: needs exactly {list(N2_PARAMETERS)}, got "
                                 f"{sorted(side)}")
        for k in N2_PARAMETERS:
            lo = np.atleast_1d(np.asarray(self.lo[k], float))
            hi = np.atleast_1d(np.asarray(self.hi[k], float))
            if lo.shape != hi.shape or not np.all(np.isfinite(lo) & np.isfinite(hi)):
                raise ValueError(f"ParameterBox: {k} bounds must be finite and of one shape")
            if np.any(lo > hi):
                raise ValueError(f"ParameterBox: {k} has lo > hi ({lo} > {hi})")
            if (np.any(lo < 0) if k == "sigma1" else np.any(lo <= 0)):
                raise ValueError(f"ParameterBox: {k} must be {'>= 0' if k == 'sigma1' else '> 0'}"
                                 f" over the whole box, got lo = {lo}")
            self.lo[k], self.hi[k] = lo, hi

    @classmethod
    def of_plant(cls, plant: FlexibleJointPlant, rel: float = 0.0) -> ParameterBox:
        """The box +-``rel`` (a fraction) around ``plant``'s values (0: the plant alone)."""
        fr = _friction(plant)
        vals = {"K": plant.K, **{k: getattr(fr, k) for k in N2_PARAMETERS[1:]}}
        vals = {k: np.broadcast_to(np.asarray(v, float), (plant.n,)) for k, v in vals.items()}
        return cls({k: v * (1 - rel) for k, v in vals.items()},
                   {k: v * (1 + rel) for k, v in vals.items()})

    def contains(self, values: dict[str, Any], rtol: float = 1e-12) -> bool:
        """Whether every named value ((n,) per name of ``N2_PARAMETERS``) lies in the box."""
        return all(np.all(np.asarray(values[k]) >= self.lo[k] * (1 - rtol))
                   and np.all(np.asarray(values[k]) <= self.hi[k] * (1 + rtol))
                   for k in N2_PARAMETERS)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready {name: {"lo": [...], "hi": [...]}}."""
        return {k: {"lo": self.lo[k].tolist(), "hi": self.hi[k].tolist()} for k in N2_PARAMETERS}

    def arrays(self) -> dict[str, tuple[Array, Array]]:
        """{name: (lo, hi)} as float64 JAX arrays."""
        return {k: (jnp.asarray(self.lo[k]), jnp.asarray(self.hi[k])) for k in N2_PARAMETERS}


@requires_float64
def box_lambda_min(box: dict[str, tuple[Array, Array]], gains: CascadeGains, v: ArrayLike,
                   eps: float = DEFAULT_EPS) -> Float[Array, ""]:
    """The smallest lambda_min(N2(v)) (eq. 29) over every plant of the box (``ParameterBox
    .arrays()``) at link speed ``v`` [rad/s] (every joint at that speed).

    Exact in the coordinates N2 is affine in, (K, s01 = sigma0 sigma1, p55 = sigma0 Psi#(v)/Ke):
    lambda_min is concave there, so its minimum over their box is at one of its 8 vertices.
    The (K, s01, p55) box is the tightest one holding the image of the parameter box (Psi# =
    g/m is monotone in Fc, Fs and, for fixed Fc, Fs, in vs, so its range is taken over the 8
    corners of (Fc, Fs, vs)); the only slack is that sigma0 enters both s01 and p55 and the
    box treats them as independent. A rigorous lower bound at each speed (between speeds the
    same grid convention as ``certify``)."""
    K, Fc, Fs, vs, s0, s1 = (box[k] for k in N2_PARAMETERS)
    v = jnp.broadcast_to(jnp.asarray(v, jnp.result_type(float)), gains.Ke.shape)

    def corners(s):
        return jnp.stack([fc + (fs - fc) * jnp.exp(-jnp.square(s / w))
                          for fc in Fc for fs in Fs for w in vs])

    psi = [sharp_of(lambda s: jnp.min(corners(s), 0), v, gains, eps),
           sharp_of(lambda s: jnp.max(corners(s), 0), v, gains, eps)]
    p55 = (s0[0] * psi[0] / gains.Ke, s0[1] * psi[1] / gains.Ke)
    s01 = (s0[0] * s1[0], s0[1] * s1[1])
    lams = [smallest_eigenvalue(n2_of(k, s, p, gains)) for k in K for s in s01 for p in p55]
    return jnp.min(jnp.stack(lams))


@requires_float64
def box_lambda_min_curve(box: dict[str, tuple[Array, Array]], gains: CascadeGains,
                         velocities: ArrayLike, eps: float = DEFAULT_EPS) -> Float[Array, " N"]:
    """``box_lambda_min`` at each speed of ``velocities`` [rad/s]."""
    vs = jnp.asarray(velocities, jnp.result_type(float))
    return jax.vmap(lambda s: box_lambda_min(box, gains, s, eps))(vs)


_box_curve_jit = eqx.filter_jit(box_lambda_min_curve)
_box_point_jit = eqx.filter_jit(box_lambda_min)


@requires_float64
def certify_box(box: ParameterBox, gains: CascadeGains, vmax: float = DEFAULT_VMAX, *,
                num: int = DEFAULT_NUM, margin: float = 0.0, eps: float = DEFAULT_EPS,
                refine: int = 40) -> CertificateResult:
    """``certify`` for every plant of ``box`` at once: ``lambda_min`` in the result is the
    lower bound ``box_lambda_min`` over the box, so ``certified_up_to`` [rad/s] holds for each
    plant in it (eq. 29-31)."""
    _check_range(vmax, num, margin, eps)
    arr = box.arrays()
    return _certified_range(
        lambda vel: _box_curve_jit(arr, gains, vel, eps),
        lambda v: _box_point_jit(arr, gains, v, eps), vmax, num, margin, eps, refine)


@requires_float64
def ultimate_bound(plant: FlexibleJointPlant, gains: CascadeGains, vmax: float = DEFAULT_VMAX,
                   *, num: int = DEFAULT_NUM, eps: float = DEFAULT_EPS) -> dict[str, float]:
    """The ultimate bound of eq. 32-33 over link speeds |q1'| <= vmax [rad/s].

    D_bar = max ||D(v, z)|| with |z| <= max g / sigma0 = max(Fs, Fc) / sigma0 (the invariant
    set of the LuGre state, Canudas de Wit et al. 1995), lambda = min lambda_min(N2) over the
    same speeds; ||rho|| <= D_bar / lambda once reached. Returns ``D_bar``, ``lambda_min``,
    ``rho_bound`` (inf if N2 is not positive definite; rho mixes rad, rad/s and eta units)
    and ``e1_bound`` [rad] (the same number, as a bound on |e1| <= ||rho||).
    """
    _check_range(vmax, num, 0.0, eps)
    fr = _friction(plant)
    z_max = jnp.maximum(fr.Fs, fr.Fc) / fr.sigma0
    # |D| peaks just above eps (Psi# dPsi ~ |v| / m(v) there): add a log grid from eps up.
    vel = jnp.concatenate([jnp.linspace(0.0, float(vmax), int(num)),
                           jnp.geomspace(eps, max(float(vmax), 2 * eps), int(num))])
    # D is odd in v times z; the worst case is |z| = z_max with the sign that adds up.
    dnorm = jax.vmap(lambda s: jnp.linalg.norm(d_vector(plant, gains, s, z_max, eps)))(vel)
    d_bar = float(jnp.max(dnorm))
    lam = float(jnp.min(lambda_min_curve(plant, gains, vel, eps)))
    bound = d_bar / lam if lam > 0 else float("inf")
    return {"D_bar": d_bar, "D_bar_at": float(vel[int(jnp.argmax(dnorm))]), "lambda_min": lam,
            "rho_bound": bound, "e1_bound": bound, "vmax": float(vmax), "eps": float(eps)}


@requires_float64
def task_bound(plant: FlexibleJointPlant, gains: CascadeGains, trajectory: Trajectory,
               t_final: float, *, dt: float = 1e-3, speed_factor: float = 1.2,
               num: int = DEFAULT_NUM, eps: float = DEFAULT_EPS) -> dict[str, Any]:
    """The ultimate bound of eq. 32-33 read for a task, in rad.

    The speed range is ``speed_factor`` times the reference's largest speed max |q1d'|
    [rad/s] over [0, t_final] s (sampled every ``dt`` s): the link moves about as fast as its
    reference when it tracks. e1 is the first component of rho, so |e1| <= ||rho|| <=
    D_bar / lambda_min once the ball of eq. 32 is reached (a lower estimate: the ultimate
    bound proper is the smallest level set of V containing that ball, larger by the square
    root of V's condition number). The bound is *vacuous* when it is not below the
    reference's half-range A [rad] (it would allow the link to stand still) or when N2 is
    not positive definite over the speed range (``e1_bound`` inf). Returns
    ``ultimate_bound``'s numbers plus ``e1_bound_rad``, ``reference_half_range_rad``,
    ``bound_over_half_range``, ``task_speed`` [rad/s], ``vacuous`` and ``reason``.
    """
    ts = jnp.arange(int(round(t_final / dt)) + 1) * dt
    r = trajectory.sample(ts, order=1)
    vmax = float(speed_factor * jnp.max(jnp.abs(r[:, 1])))
    half = float(jnp.max(0.5 * (jnp.max(r[:, 0], axis=0) - jnp.min(r[:, 0], axis=0))))
    b = ultimate_bound(plant, gains, max(vmax, 2 * eps), num=num, eps=eps)
    e1 = b["e1_bound"]
    ratio = e1 / half if half > 0 else float("inf")
    if not np.isfinite(e1):
        reason = (f"N2 is not positive definite over |q1'| <= {vmax:.3g} rad/s "
                  f"(lambda_min {b['lambda_min']:.3g}): no bound")
    elif ratio >= 1.0:
        reason = (f"|e1| <= {e1:.3g} rad is {ratio:.3g} times the reference's half-range "
                  f"{half:.3g} rad; D_bar = {b['D_bar']:.3g} (its peak at |q1'| = "
                  f"{b['D_bar_at']:.3g} rad/s, where Psi# ~ 1/eps and the smoothing error of "
                  f"|v| are largest) over lambda_min(N2) = {b['lambda_min']:.3g}")
    else:
        reason = f"|e1| <= {e1:.3g} rad, {ratio:.3g} of the reference's half-range"
    return {**b, "e1_bound_rad": e1, "reference_half_range_rad": half,
            "bound_over_half_range": ratio, "task_speed": vmax,
            "vacuous": bool(not np.isfinite(e1) or ratio >= 1.0), "reason": reason}
