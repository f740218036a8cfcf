"""LuGre friction (paper eq. 4-7 and 35; docs/spec.md section 2).

    F  = sigma0 z + sigma1 z' + sigma2 v                       (eq. 4)
    z' = v - sigma0 |v| / g(v) z                               (eq. 5)
    g(v) = Fc + (Fs - Fc) exp(-(v/vs)^2)                       (eq. 6)
    F_ss(v) = sign(v) g(v) + sigma2 v                          (eq. 35)

All parameters are per joint, arrays of shape (n,). Units: Fc, Fs [N m]; vs [rad/s];
sigma0 [N m/rad]; sigma1, sigma2 [N m s/rad]; z [rad].
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.validation import as_param, check_nonnegative, check_positive, is_concrete

LUGRE_NAMES: tuple[str, ...] = ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")


def relax(z: Array, rate: Array, target_rate: Array, h: float | Array) -> Array:
    """Exact solution after time ``h`` of ``z' = target_rate - rate * z`` with frozen coefficients.

    ``z(h) = z exp(-rate h) + target_rate (1 - exp(-rate h)) / rate``; as ``rate -> 0`` the
    second term tends to ``target_rate h``. Used for the stiff LuGre state (eq. 5) and the
    observer state (eq. 20): the update is stable for any ``rate >= 0`` and step ``h``
    (docs/spec.md section 9, first pitfall). The double ``where`` keeps gradients finite at rate 0.
    """
    small = rate * h < 1e-8
    safe_rate = jnp.where(small, 1.0, rate)
    phi = jnp.where(small, h * (1.0 - 0.5 * rate * h), -jnp.expm1(-safe_rate * h) / safe_rate)
    return z * jnp.exp(-rate * h) + target_rate * phi


def smooth_abs(v: Array, eps: float = 1e-12) -> Array:
    """|v| with a finite derivative at 0 under ``grad`` (double-where trick)."""
    return jnp.where(jnp.abs(v) > eps, jnp.abs(v), 0.0)


class LuGre(eqx.Module):
    """LuGre friction model parameters for n joints (docs/spec.md section 2, paper eq. 4-7).

    Constraints: Fc, Fs, vs, sigma0 > 0; sigma1, sigma2 >= 0; Fs >= Fc. Violations raise
    ``ValueError`` naming the parameter when the model is built from concrete values.
    """

    Fc: Float[Array, " n"] = eqx.field(converter=as_param)
    Fs: Float[Array, " n"] = eqx.field(converter=as_param)
    vs: Float[Array, " n"] = eqx.field(converter=as_param)
    sigma0: Float[Array, " n"] = eqx.field(converter=as_param)
    sigma1: Float[Array, " n"] = eqx.field(converter=as_param)
    sigma2: Float[Array, " n"] = eqx.field(converter=as_param)

    def __check_init__(self) -> None:
        shapes = {k: jnp.shape(getattr(self, k)) for k in LUGRE_NAMES}
        if len(set(shapes.values())) > 1:
            raise ValueError(f"LuGre: parameters must all have the same shape (n,), got {shapes}")
        check_positive("LuGre", Fc=self.Fc, Fs=self.Fs, vs=self.vs, sigma0=self.sigma0)
        check_nonnegative("LuGre", sigma1=self.sigma1, sigma2=self.sigma2)
        if is_concrete(self.Fs) and is_concrete(self.Fc):
            fs, fc = np.asarray(self.Fs), np.asarray(self.Fc)
            if np.any(fs < fc):
                raise ValueError(
                    f"LuGre: parameter Fs (static friction, {fs.tolist()} N m) must be >= Fc "
                    f"(Coulomb friction, {fc.tolist()} N m)"
                )

    @property
    def n(self) -> int:
        """Number of joints."""
        return int(self.Fc.shape[-1])

    def g(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """Stribeck curve g(v) = Fc + (Fs - Fc) exp(-(v/vs)^2) [N m] (eq. 6); v in rad/s."""
        return self.Fc + (self.Fs - self.Fc) * jnp.exp(-jnp.square(v / self.vs))

    def z_rate(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """Relaxation rate sigma0 |v| / g(v) [1/s] of the bristle state (eq. 5)."""
        return self.sigma0 * smooth_abs(v) / self.g(v)

    def z_dot(self, v: Float[Array, " n"], z: Float[Array, " n"]) -> Float[Array, " n"]:
        """Bristle dynamics z' = v - sigma0 |v| / g(v) z [rad/s] (eq. 5)."""
        return v - self.z_rate(v) * z

    def force(self, v: Float[Array, " n"], z: Float[Array, " n"]) -> Float[Array, " n"]:
        """Friction torque F = sigma0 z + sigma1 z' + sigma2 v [N m] (eq. 4)."""
        return self.sigma0 * z + self.sigma1 * self.z_dot(v, z) + self.sigma2 * v

    def steady_state(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """Static map F_ss(v) = sign(v) g(v) + sigma2 v [N m] at constant velocity (eq. 35)."""
        return jnp.sign(v) * self.g(v) + self.sigma2 * v

    def z_steady(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """Steady bristle deflection z_ss = sign(v) g(v) / sigma0 [rad]."""
        return jnp.sign(v) * self.g(v) / self.sigma0

    def z_bound(self) -> Float[Array, " n"]:
        """The bristle's invariant bound [rad]: the level at standstill, from either direction,
        over sigma0. Eq. 5 moves z toward zero wherever |z| > g(v) / sigma0 and g peaks at
        standstill (eq. 6 with Fs >= Fc), so a motion whose |z| starts within this bound keeps
        it there: no state beyond it is reachable."""
        eps = 1e-6 * self.vs
        return jnp.maximum(self.g(eps), self.g(-eps)) / self.sigma0

    def step_z(self, v: Float[Array, " n"], z: Float[Array, " n"], h: float | Array) -> Array:
        """Advance z by ``h`` seconds with v frozen, exactly (eq. 5 is linear in z for fixed v)."""
        return relax(z, self.z_rate(v), v, h)

    def stiff_step_bound(self, v: Float[Array, " n"], J: ArrayLike) -> Array:
        """Largest explicit RK4 step [s] for the z dynamics at speed v (docs/spec.md section 9)."""
        return 2.8 / (self.sigma1 / jnp.asarray(J) + self.z_rate(v))

    def to_dict(self) -> dict[str, list[float]]:
        """Parameters as plain lists (docs/spec.md section 7 'friction' entry)."""
        return {k: np.asarray(getattr(self, k)).tolist() for k in LUGRE_NAMES}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> LuGre:
        """Build from a mapping with the six names of docs/spec.md section 2; a missing name raises ``ValueError``."""
        missing = [k for k in LUGRE_NAMES if k not in d]
        if missing:
            raise ValueError(f"LuGre: missing friction parameter(s) {missing}")
        return cls(**{k: d[k] for k in LUGRE_NAMES})


def smooth_abs_observer(v: Array, kv: Array) -> Array:
    """m(v) = (2/pi) v arctan(kv v), the observer's smooth |v| (eq. 21)."""
    return (2.0 / math.pi) * v * jnp.arctan(kv * v)

