"""LuGre friction observer (paper eq. 18-22; docs/spec.md section 3).

    m(v)     = (2/pi) v arctan(kv v)                     (eq. 21, smooth |v|)
    Psi_hat  = (m(q1') + leak) / g(q1')                  (eq. 19; leak = 0 in the paper)
    z_hat'   = q1' - sigma0 Psi_hat z_hat - Ke sigma0 s1 (eq. 20)
    F_hat    = sigma0 z_hat + sigma1 z_hat' + sigma2 q1' (eq. 22)

Units as in ``jaxflex.core.friction``; kv [s/rad]; s1 [rad/s]; Ke [rad/(N m)], so that
Ke sigma0 s1 is a rate [rad/s]; leak [rad/s].

``leak`` (``CascadeGains.leak``, default 0: the paper's observer) is a floor under the smooth
|v|. With leak = 0, Psi_hat(0) = 0, so at rest eq. 20 reads z_hat' = q1' - Ke sigma0 s1: the
observer integrates the tracking error with no leakage, and with the pre-sliding spring
sigma0 of the real friction this integral action makes a growing ~3-4 Hz mode at rest with
the paper's gains (docs/spec.md section 3, "Leakage"). leak > 0 makes z_hat relax at the rate
sigma0 leak / g(0) at rest (a leaky integrator, like the sigma-modification of adaptive
control); the certificate (eq. 29-33) keeps its form with Psi_hat including the leak.
"""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float

from jaxflex.core.friction import LuGre, relax, smooth_abs_observer


class FrictionObserver(eqx.Module):
    """Observer of the LuGre bristle state from the link velocity and the sliding variable s1."""

    friction: LuGre
    Ke: Float[Array, " n"]
    kv: Float[Array, " n"]
    leak: Float[Array, " n"] | float = 0.0

    def psi_hat(self, v: Float[Array, " n"]) -> Float[Array, " n"]:
        """Psi_hat(v) = (m(v) + leak) / g(v) [rad/s / (N m)] (eq. 19, 21; leak = 0 in the
        paper)."""
        return (smooth_abs_observer(v, self.kv) + self.leak) / self.friction.g(v)

    def z_hat_dot(self, v: Array, z_hat: Array, s1: Array) -> Float[Array, " n"]:
        """Observer dynamics z_hat' [rad/s] (eq. 20)."""
        f = self.friction
        return v - f.sigma0 * self.psi_hat(v) * z_hat - self.Ke * f.sigma0 * s1

    def force(self, v: Array, z_hat: Array, z_hat_dot: Array) -> Float[Array, " n"]:
        """Estimated friction F_hat [N m] (eq. 22)."""
        f = self.friction
        return f.sigma0 * z_hat + f.sigma1 * z_hat_dot + f.sigma2 * v

    def step(self, z_hat: Array, v: Array, s1: Array, h: float) -> Float[Array, " n"]:
        """z_hat after one sample of ``h`` seconds with v and s1 held (exact for eq. 20, which is
        linear in z_hat; stable for the stiff rate sigma0 Psi_hat at any h)."""
        f = self.friction
        return relax(z_hat, f.sigma0 * self.psi_hat(v), v - self.Ke * f.sigma0 * s1, h)

