"""Reference trajectories q1d(t) [rad] for n joints; derivatives by automatic differentiation.

The cascade controller needs q1d and its derivatives up to 4th order (q2d'' contains the
reference's 4th derivative; paper eq. 13, 16). Each trajectory only defines ``position(t)``;
``derivatives`` obtains the rest with nested forward-mode differentiation. The paper's tasks
(and their names) are in ``jaxflex.io.presets``.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from jaxflex.core.validation import as_param


class Trajectory(eqx.Module):
    """Abstract reference trajectory."""

    @abc.abstractmethod
    def position(self, t: Float[Array, ""]) -> Float[Array, " n"]:
        """q1d(t) [rad] at time t [s]."""

    def derivatives(self, t: ArrayLike, order: int = 4) -> Float[Array, "k n"]:
        """Stack [q1d, q1d', ..., q1d^(order)] at time t [s] (units rad/s^k), shape (order+1, n)."""
        t = jnp.asarray(t, dtype=jnp.result_type(float))
        fns = [self.position]
        for _ in range(order):
            f = fns[-1]
            fns.append(lambda tt, f=f: jax.jvp(f, (tt,), (jnp.ones_like(tt),))[1])
        return jnp.stack([f(t) for f in fns])

    def sample(self, t: Float[Array, " N"], order: int = 0) -> Float[Array, "N k n"]:
        """Derivatives at many times, shape (N, order+1, n)."""
        return jax.vmap(lambda tt: self.derivatives(tt, order))(jnp.asarray(t))


class Taylor(Trajectory):
    """q1d near ``t0`` [s] from its derivatives there: sum_k derivs[k] (t - t0)^k / k!.

    ``derivs`` (k+1, n): [q1d, q1d', ..., q1d^(k)] at t0 (units rad/s^j). At t = t0 the
    position and every derivative up to order k are exactly the given ones (forward-mode
    derivatives of the polynomial at t - t0 = 0). The sampled-data loop hands the controller
    the reference at each sample this way (``jaxflex.sim.simulate.simulate_sampled``): the
    reference's derivatives are evaluated once per sample, where XLA would otherwise copy a
    sinusoid's sine and cosine into every kernel that uses one of its derivatives (17 float64
    evaluations per sample, most of a batched sweep's time on a CPU).
    """

    derivs: Float[Array, "k n"]
    t0: Float[Array, ""]

    def position(self, t: Array) -> Array:
        tau = t - self.t0
        acc = self.derivs[-1]
        for k in range(self.derivs.shape[0] - 2, -1, -1):  # Horner: d_k + tau/(k+1) (...)
            acc = self.derivs[k] + acc * (tau / (k + 1))
        return acc


class Sinusoid(Trajectory):
    """q1d = offset + amplitude sin(2 pi frequency t + phase); amplitude [rad], frequency [Hz]."""

    amplitude: Float[Array, " n"] = eqx.field(converter=as_param)
    frequency: Float[Array, " n"] = eqx.field(converter=as_param)
    phase: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)
    offset: Float[Array, " n"] = eqx.field(converter=as_param, default=0.0)

    def __check_init__(self) -> None:
        if not isinstance(self.frequency, jax.core.Tracer) and bool(jnp.any(self.frequency <= 0)):
            raise ValueError(f"Sinusoid: frequency must be > 0 Hz, got {self.frequency}")

    def position(self, t: Array) -> Array:
        return self.offset + self.amplitude * jnp.sin(2 * math.pi * self.frequency * t + self.phase)


def _smootherstep9(s: Array) -> Array:
    """Degree-9 rest-to-rest polynomial: p(0)=0, p(1)=1, derivatives 1..4 vanish at both ends."""
    return s**5 * (126.0 + s * (-420.0 + s * (540.0 + s * (-315.0 + 70.0 * s))))


class RestToRest(Trajectory):
    """Piecewise rest-to-rest polynomial through waypoints [rad], one segment per duration [s].

    Each segment is the degree-9 polynomial whose first four derivatives vanish at both ends,
    so q1d is four times continuously differentiable. Peak |derivative k| of a segment of
    amplitude A and duration T is c_k A / T^k (c_1 = 2.46, c_2 = 9.37, c_3 = 46.0, c_4 = 307).
    Waypoints have shape (m+1, n) (or (m+1,) for one joint), durations (m,).
    """

    waypoints: Float[Array, "m1 n"] = eqx.field(converter=lambda w: jnp.asarray(w, float))
    durations: Float[Array, " m"] = eqx.field(converter=lambda d: jnp.atleast_1d(jnp.asarray(d, float)))
    t0: Float[Array, ""] = eqx.field(converter=lambda x: jnp.asarray(x, float), default=0.0)

    def __check_init__(self) -> None:
        w = self.waypoints
        if w.ndim not in (1, 2) or w.shape[0] != self.durations.shape[0] + 1:
            raise ValueError(
                f"RestToRest: need len(waypoints) == len(durations) + 1, got waypoints "
                f"{w.shape} and durations {self.durations.shape}"
            )
        if not isinstance(self.durations, jax.core.Tracer) and bool(jnp.any(self.durations <= 0)):
            raise ValueError(f"RestToRest: durations must be > 0 s, got {self.durations}")

    def position(self, t: Array) -> Array:
        w = self.waypoints if self.waypoints.ndim == 2 else self.waypoints[:, None]
        starts = self.t0 + jnp.concatenate([jnp.zeros(1), jnp.cumsum(self.durations)[:-1]])
        s = jnp.clip((t - starts) / self.durations, 0.0, 1.0)  # (m,)
        steps = _smootherstep9(s)[:, None] * (w[1:] - w[:-1])  # (m, n)
        return w[0] + jnp.sum(steps, axis=0)


class Multisine(Trajectory):
    """Sum of sines: q1d = offset + sum_k a_k sin(2 pi f_k t + phi_k), for excitation.

    amplitudes [rad] and frequencies [Hz] have shape (K,) or (K, n); phases [rad] likewise.
    """

    amplitudes: Array = eqx.field(converter=lambda a: jnp.asarray(a, float))
    frequencies: Array = eqx.field(converter=lambda a: jnp.asarray(a, float))
    phases: Array = eqx.field(converter=lambda a: jnp.asarray(a, float))
    offset: Array = eqx.field(converter=as_param, default=0.0)

    def position(self, t: Array) -> Array:
        terms = self.amplitudes * jnp.sin(2 * math.pi * self.frequencies * t + self.phases)
        out = jnp.sum(terms, axis=0)
        return self.offset + jnp.atleast_1d(out)

    @classmethod
    def schroeder(
        cls, rms: float, f_min: float, f_max: float, count: int, n: int = 1
    ) -> Multisine:
        """Schroeder-phased multisine with ``count`` log-spaced tones in [f_min, f_max] Hz and
        the given RMS [rad] (low crest factor, good for identification)."""
        if not (0 < f_min < f_max) or count < 1 or rms <= 0:
            raise ValueError("Multisine.schroeder: need 0 < f_min < f_max, count >= 1, rms > 0")
        k = jnp.arange(1, count + 1)
        f = jnp.geomspace(f_min, f_max, count)
        ph = -math.pi * k * (k - 1) / count
        a = jnp.full((count,), rms * math.sqrt(2.0 / count))
        if n > 1:
            f, ph, a = (jnp.tile(x[:, None], (1, n)) for x in (f, ph, a))
        return cls(amplitudes=a, frequencies=f, phases=ph)



class SampledReference(Trajectory):
    """A reference known by uniformly spaced samples (a logged q1d): on each sample interval
    the degree-5 polynomial through the six nearest samples (Lagrange interpolation), so that
    the position and its derivatives (up to the 4th, as the cascade needs) exist at any t.
    At the sample instants the derivatives are those of a 6-point stencil (error O(dt^2) for
    the 4th); outside the samples the end polynomials extrapolate.

    samples [rad] shape (N, n) (or (N,) for one joint), N >= 6; dt [s] the sample period;
    t0 [s] the time of the first sample. Samples rounded to few digits amplify in the high
    derivatives (a 4th derivative divides by dt^4): give the reference at full precision.
    """

    samples: Float[Array, "N n"] = eqx.field(converter=lambda a: jnp.asarray(a, float))
    dt: float = eqx.field(static=True)
    t0: float = eqx.field(static=True, default=0.0)

    def __check_init__(self) -> None:
        if self.samples.ndim not in (1, 2) or self.samples.shape[0] < 6:
            raise ValueError("SampledReference: need samples of shape (N, n) or (N,) with N >= 6, "
                             f"got {self.samples.shape}")
        if not self.dt > 0:
            raise ValueError(f"SampledReference: dt must be > 0 s, got {self.dt}")

    def position(self, t: Array) -> Array:
        y = self.samples if self.samples.ndim == 2 else self.samples[:, None]
        s = (t - self.t0) / self.dt
        i = jnp.clip(jnp.floor(s), 2, y.shape[0] - 4)
        u = s - i  # position within the stencil's nodes -2..3
        nodes = jnp.arange(-2.0, 4.0)
        diff = u - nodes
        # Lagrange basis: w_j = prod_{m != j} (u - x_m) / (x_j - x_m)
        rows = [jnp.prod(jnp.delete(diff, j)) / jnp.prod(jnp.delete(nodes[j] - nodes, j))
                for j in range(6)]
        window = jax.lax.dynamic_slice_in_dim(y, i.astype(int) - 2, 6, axis=0)
        return jnp.stack(rows) @ window


class HeldSamples(eqx.Module):
    """A signal known by uniformly spaced samples and held over each sample period (a logged
    reference or disturbance as a sampled-data controller reads it): ``at(t)`` is the sample
    nearest to ``t``, the first before the log and the last after it.

    samples shape (N, n) in the signal's unit; dt [s] the sample period; t0 [s] the time of
    the first sample.
    """

    samples: Float[Array, "N n"] = eqx.field(converter=lambda a: jnp.asarray(a, float))
    dt: float = eqx.field(static=True)
    t0: float = eqx.field(static=True, default=0.0)

    def __check_init__(self) -> None:
        if self.samples.ndim != 2 or self.samples.shape[0] < 1:
            raise ValueError("HeldSamples: need samples of shape (N, n), got "
                             f"{self.samples.shape}")
        if not self.dt > 0:
            raise ValueError(f"HeldSamples: dt must be > 0 s, got {self.dt}")

    def at(self, t: ArrayLike) -> Array:
        """The sample (n,) held at time ``t`` [s]."""
        k = jnp.round((jnp.asarray(t) - self.t0) / self.dt).astype(int)
        return self.samples[jnp.clip(k, 0, self.samples.shape[0] - 1)]
