"""The distributions of a spread file's uncertain quantities (``Distribution``: fixed,
uniform, truncated normal, lognormal, loguniform, and the joint posterior of an
identification) and how one is read from its JSON entry (``parse_distribution``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp

from jaxflex.io.errors import InputError

_DIST_FIELDS: dict[str, tuple[set[str], ...]] = {
    # each tuple entry is one accepted set of fields (besides 'dist')
    "fixed": ({"value"},),
    "uniform": ({"low", "high"}, {"rel"}),
    "normal": ({"mean", "std"}, {"std"}, {"rel_std"}),
    "lognormal": ({"median", "sigma"}, {"sigma"}),
    "loguniform": ({"low", "high"}, {"factor"}),
}
_TRUNC = {"normal"}


class SpreadError(InputError):
    """A spread file that does not follow the format of ``jaxflex.sweep.spec``."""


@dataclasses.dataclass(frozen=True)
class Distribution:
    """One scalar distribution, already resolved against its nominal value.

    kind: 'fixed' | 'uniform' | 'normal' | 'lognormal' | 'loguniform' | 'posterior'; a, b: its
    two numbers (value/-, low/high, mean/std, log-median/sigma, log-low/log-high; posterior:
    the entry's index in ``SweepSpec.posterior.labels``/its estimate); low, high: truncation
    of 'normal' (+-inf if none), the 1 - 1e-9 confidence box of a 'posterior' entry (drawn
    jointly with the other entries of the identification's posterior).
    """

    kind: str
    a: float
    b: float = 0.0
    low: float = -math.inf
    high: float = math.inf

    def support(self) -> tuple[float, float]:
        """Smallest interval holding every draw."""
        if self.kind == "fixed":
            return self.a, self.a
        if self.kind == "uniform":
            return self.a, self.b
        if self.kind == "normal":
            return self.low, self.high
        if self.kind == "lognormal":
            return 0.0, math.inf  # open at 0
        if self.kind == "posterior":
            return self.low, self.high
        return math.exp(self.a), math.exp(self.b)

    def center_scale(self) -> tuple[float, float]:
        """A centre and scale used to standardise the column (numerics only)."""
        if self.kind == "fixed":
            return self.a, 1.0
        if self.kind in ("uniform",):
            return 0.5 * (self.a + self.b), max(0.5 * (self.b - self.a), 1e-300)
        if self.kind == "normal":
            return self.a, max(self.b, 1e-300)
        if self.kind == "posterior":
            return self.b, max(0.5 * (self.high - self.low), 1e-300)
        if self.kind == "lognormal":
            return math.exp(self.a), max(math.exp(self.a) * self.b, 1e-300)
        lo, hi = math.exp(self.a), math.exp(self.b)
        return 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-300)

    def sample(self, key: jax.Array) -> jax.Array:
        """One draw (a scalar in the default float dtype).

        The random variate is drawn in float32 and then cast, so that a sample's parameters
        are the same in float64 and float32 runs (24-bit resolution is far below any spread).
        """
        if self.kind == "posterior":
            raise ValueError("a posterior column is drawn jointly (Posterior.sample), not alone")
        dt = jnp.result_type(float)
        f32 = jnp.float32
        if self.kind == "fixed":
            return jnp.asarray(self.a, dt)
        if self.kind == "uniform":
            return self.a + (self.b - self.a) * jax.random.uniform(key, (), f32).astype(dt)
        if self.kind == "normal":
            if math.isinf(self.low) and math.isinf(self.high):
                return self.a + self.b * jax.random.normal(key, (), f32).astype(dt)
            lo, hi = (self.low - self.a) / self.b, (self.high - self.a) / self.b
            x = self.a + self.b * jax.random.truncated_normal(key, lo, hi, (), f32).astype(dt)
            return jnp.clip(x, self.low, self.high)  # float32 rounding at the bounds
        if self.kind == "lognormal":
            return jnp.exp(self.a + self.b * jax.random.normal(key, (), f32).astype(dt))
        return jnp.exp(self.a + (self.b - self.a) * jax.random.uniform(key, (), f32).astype(dt))


def spread_number(where: str, field: str, v: Any) -> float:
    """A finite number of a spread entry.

    **Arguments:**

    - `where`: the entry's name, for the message.
    - `field`: the field's name.
    - `v`: its JSON value.

    **Returns:**

    ``v`` as a float.

    **Raises:**

    ``SpreadError`` for a bool, a non-number or a non-finite value.
    """
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise SpreadError(f"{where}: '{field}' must be a finite number, got {v!r}")
    return float(v)


def parse_distribution(where: str, d: Any, nominal: float | None) -> Distribution:
    """A ``Distribution`` from its JSON entry; ``nominal`` resolves rel/rel_std/factor/median."""
    if not isinstance(d, dict):
        raise SpreadError(f"{where}: expected an object like {{\"dist\": \"uniform\", \"rel\": 0.2}}, got {d!r}")
    kind = d.get("dist")
    if kind not in _DIST_FIELDS:
        raise SpreadError(f"{where}: 'dist' must be one of {sorted(_DIST_FIELDS)}, got {kind!r}")
    fields = set(d) - {"dist"}
    trunc = {"low", "high"} & fields if kind in _TRUNC else set()
    core = fields - trunc
    if kind in _TRUNC and {"mean", "std"} <= fields:
        core = fields - trunc
    if core not in _DIST_FIELDS[kind]:
        want = " or ".join("/".join(sorted(s)) for s in _DIST_FIELDS[kind])
        extra = " (+ optional low/high truncation)" if kind in _TRUNC else ""
        raise SpreadError(f"{where}: a '{kind}' distribution takes {want}{extra}, got {sorted(fields)}")
    g = {k: spread_number(where, k, d[k]) for k in fields}
    needs_nominal = core & {"rel", "rel_std", "factor"} or (kind == "normal" and "mean" not in core) or (
        kind == "lognormal" and "median" not in core
    )
    if needs_nominal and nominal is None:
        raise SpreadError(f"{where}: no nominal value to scale; give absolute bounds")
    if kind == "fixed":
        return Distribution("fixed", g["value"])
    if kind == "uniform":
        if "rel" in g:
            if g["rel"] < 0:
                raise SpreadError(f"{where}: 'rel' must be >= 0, got {g['rel']}")
            lo, hi = sorted((nominal * (1 - g["rel"]), nominal * (1 + g["rel"])))
        else:
            lo, hi = g["low"], g["high"]
        if not hi > lo:
            raise SpreadError(f"{where}: uniform needs low < high, got low={lo}, high={hi}")
        return Distribution("uniform", lo, hi)
    if kind == "normal":
        mean = g.get("mean", nominal)
        std = g["std"] if "std" in g else abs(nominal) * g["rel_std"]
        if not std > 0:
            raise SpreadError(f"{where}: the standard deviation must be > 0, got {std}")
        lo, hi = g.get("low", -math.inf), g.get("high", math.inf)
        if not hi > lo:
            raise SpreadError(f"{where}: truncation needs low < high, got low={lo}, high={hi}")
        return Distribution("normal", mean, std, lo, hi)
    if kind == "lognormal":
        med = g.get("median", nominal)
        if not med > 0 or not g["sigma"] > 0:
            raise SpreadError(f"{where}: lognormal needs median > 0 and sigma > 0, got {med}, {g['sigma']}")
        return Distribution("lognormal", math.log(med), g["sigma"])
    if "factor" in g:
        if not g["factor"] > 1 or not nominal > 0:
            raise SpreadError(f"{where}: loguniform needs factor > 1 and a nominal > 0")
        lo, hi = nominal / g["factor"], nominal * g["factor"]
    else:
        lo, hi = g["low"], g["high"]
    if not (lo > 0 and hi > lo):
        raise SpreadError(f"{where}: loguniform needs 0 < low < high, got low={lo}, high={hi}")
    return Distribution("loguniform", math.log(lo), math.log(hi))
