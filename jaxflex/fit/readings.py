"""The likelihood of an encoder reading: the angle plus white Gaussian noise, rounded to the
encoder's count, as a least-squares residual (``quantised_residual``) and its slope, for
``jaxflex.fit.Problem``'s output rows (docs/spec.md section 5).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

#: Distance past a reading's cell [noise standard deviations] beyond which
#: ``quantised_residual`` continues with slope 1.
QUANTISED_TAIL: float = 30.0
#: A grid whose half-width is at most this many noise standard deviations is no grid: the
#: residual is the Gaussian e (the rounding adds a variance of 1 / 12 of its square).
READING_GAUSS: float = 1e-3


def _quantised_nll(a: Array, h: Array) -> Array:
    """-log P(|e| = a) of a reading rounded to a grid of half-width h after unit Gaussian
    noise: -log(Phi(h - a) - Phi(-h - a)), a >= 0, from the two complementary error
    functions erfc(|a - h| / sqrt 2) = 2 Phi(-|a - h|) and erfc((a + h) / sqrt 2) = 2 Phi(-a - h),
    both of arguments >= 0, so each keeps its relative precision out to the tail's cap
    (``QUANTISED_TAIL``): inside the cell (a < h) as -log1p(-(the two tails)), outside as
    -log(Phi(h - a) - Phi(-h - a)) from those tails directly."""
    inside = a < h
    near = jax.scipy.special.erfc(jnp.abs(a - h) / jnp.sqrt(2.0))
    far = jax.scipy.special.erfc((a + h) / jnp.sqrt(2.0))
    # each branch finite where it is not taken, so that no NaN reaches a derivative
    near_out = jnp.where(inside, 1.0, near)
    far_out = jnp.where(inside, 0.0, far)
    return jnp.where(inside, -jnp.log1p(-0.5 * (near + far)),
                     -jnp.log(0.5 * (near_out - far_out)))


@jax.custom_jvp
def quantised_residual(e: Array, quantum: Array) -> Array:
    """The output residual r of a reading: the angle plus unit white Gaussian noise, rounded
    to a grid of ``quantum`` (noise standard deviations); ``e`` is the model's angle minus the
    reading. 0.5 r^2 is the reading's negative log-likelihood -log(Phi(h - e) - Phi(-h - e)),
    h = quantum / 2, above its value at e = 0, with r's sign that of e: e itself without a
    grid (``quantum`` <= 2 ``READING_GAUSS``), about 0 inside the reading's cell and |e| - h
    outside it for a grid far coarser than the noise, so that a model anywhere in the cell
    fits the reading (a least-squares residual pulls it to the cell's centre, a bias where
    the angle dwells in one cell). Differentiable in ``e`` (``quantised_slope``); ``quantum``
    is data (its tangent is ignored)."""
    return _residual_parts(e, quantum)[0]


def _residual_parts(e: Array, quantum: Array) -> tuple[Array, Array]:
    """``quantised_residual`` and its slope d r / d e: 0.5 r^2 rises with |e| as the
    likelihood's score nll'(a) = (phi(h - a) - phi(h + a)) / P(a), P(a) = exp(-nll(a)), so
    the slope is nll'(a) / |r| (sqrt of the curvature at e = 0 near it, 1 on the tail)."""
    gauss = 0.5 * quantum <= READING_GAUSS
    h = jnp.where(gauss, 1.0, 0.5 * quantum)
    # far out of the cell (past h + QUANTISED_TAIL) the slope is 1 to within 0.5 %: continue
    # linearly (the normal tail's logarithms lose their digits there)
    a_far = h + QUANTISED_TAIL
    a = jnp.minimum(jnp.abs(e), a_far)
    nll = _quantised_nll(a, h)
    q = 2.0 * (nll - _quantised_nll(jnp.zeros_like(h), h))
    # near e = 0 (or where the difference rounds away) the Taylor term e sqrt(nll''(0))
    small = (a < 1e-4) | (q < 1e-24)
    root = jnp.sqrt(jnp.where(small, 1.0, q))
    tail = jnp.maximum(jnp.abs(e) - a_far, 0.0)
    curv = jnp.sqrt(_quantised_curvature(h))
    r = jnp.where(small, e * curv, jnp.sign(e) * (root + tail))
    log_phi = -0.5 * jnp.log(2.0 * jnp.pi)
    score = (jnp.exp(log_phi - 0.5 * (h - a) ** 2 + nll)
             - jnp.exp(log_phi - 0.5 * (h + a) ** 2 + nll))
    slope = jnp.where(small, curv, jnp.where(tail > 0.0, 1.0, score / root))
    return jnp.where(gauss, e, r), jnp.where(gauss, 1.0, slope)


@quantised_residual.defjvp
def _quantised_residual_jvp(primals: tuple[Array, Array], tangents: tuple[Array, Array],
                            ) -> tuple[Array, Array]:
    e, quantum = primals
    r, slope = _residual_parts(e, quantum)
    return r, slope * tangents[0]


def _quantised_curvature(h: Array) -> Array:
    """d^2/de^2 of ``_quantised_nll`` at e = 0: 2 h phi(h) / (2 Phi(h) - 1)."""
    phi = jnp.exp(-0.5 * h**2) / jnp.sqrt(2.0 * jnp.pi)
    return 2.0 * h * phi / jnp.maximum(jax.scipy.special.erf(h / jnp.sqrt(2.0)), 1e-300)


def quantised_slope(e: Array, quantum: Array) -> Array:
    """d r / d e of ``quantised_residual`` (elementwise)."""
    return _residual_parts(e, quantum)[1]
