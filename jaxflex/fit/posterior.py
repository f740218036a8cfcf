"""The identification's uncertainty as a distribution of plants.

``jaxflex identify`` writes, beside the estimates, their Gaussian posterior in the
unconstrained coordinates theta of ``jaxflex.fit.space`` (``extra["identification"]
["covariance"]``: the estimate and Cov = s^2 (J^T J)^+ of the fit). ``Posterior`` draws from it
and maps every draw through the space's transforms, so each drawn plant keeps the physical
constraints (every positive parameter > 0, Fs >= Fc) by construction: no draw is clipped or
rejected. Parameters the log could not identify are not in the posterior (the identification
kept them at their initial values and says so); give them a hand-written spread.

A Gaussian in theta is the Laplace approximation of the posterior in the coordinates the fit
used (log for positive parameters): a +-x% relative error is symmetric in log, so draws of a
well-identified parameter are nearly normal and those of a poorly identified one skewed
toward large values, as the data allow.
"""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float

from jaxflex.fit.space import ParamSpace
from jaxflex.io.params import Params
from jaxflex.core.validation import to_device


class Posterior(eqx.Module):
    """Gaussian posterior of an identification in theta coordinates.

    space: the ``ParamSpace`` of the identified names around the identified plant; labels:
    one "name[j]" per flattened entry (sorted names, then joints: ``ravel_pytree``'s order);
    mean (k,), root (k, k) with root @ root.T = inflate^2 Cov; inflate: factor on the standard
    deviations (1: the fit's own; > 1 for model error the residual variance does not see).
    """

    space: ParamSpace
    labels: tuple[str, ...] = eqx.field(static=True)
    mean: Float[Array, " k"]
    root: Float[Array, "k k"]
    inflate: float = eqx.field(static=True, default=1.0)

    @classmethod
    def from_params(cls, params: Params, inflate: float = 1.0) -> Posterior:
        """The posterior recorded in an identified parameter file (``Params``).

        Raises ``ValueError`` when the file has no covariance record (not written by
        ``jaxflex identify``, or by a version before it recorded one), when the record does not
        match the file's values (edited after the identification), when the covariance is not
        symmetric positive semi-definite, or when ``inflate`` is not > 0."""
        if not (math.isfinite(inflate) and inflate > 0):
            raise ValueError(f"posterior: inflate must be a finite number > 0, got {inflate}")
        rec = (params.extra.get("identification") or {}).get("covariance")
        if not isinstance(rec, dict):
            raise ValueError(
                "posterior: the parameter file has no identification covariance "
                "(extra 'identification.covariance'); run 'jaxflex identify' to get one, or "
                "give hand-written spreads instead")
        names = tuple(rec.get("parameters", ()))
        if not names:
            raise ValueError("posterior: the identification identified no parameter")
        space = ParamSpace.build(params.to_plant(), names)
        cap = rec.get("friction_cap")
        if cap is not None:  # the coordinates of a fit whose friction levels were bounded
            space = eqx.tree_at(lambda s: s.friction_cap, space, to_device(float(cap)))
        theta0 = space.theta0()
        flat0, _ = ravel_pytree(theta0)
        n = params.n
        labels = tuple(f"{k}[{j}]" for k in sorted(theta0) for j in range(n))
        if tuple(rec.get("labels", ())) != labels:
            raise ValueError(f"posterior: covariance labels {rec.get('labels')} do not match the "
                             f"identified parameters {labels}")
        mean = np.asarray(rec["theta"], float)
        C = np.asarray(rec["matrix"], float)
        k = len(labels)
        if mean.shape != (k,) or C.shape != (k, k) or not np.all(np.isfinite(C)):
            raise ValueError(f"posterior: expected theta ({k},) and a finite ({k}, {k}) "
                             f"covariance, got {mean.shape} and {C.shape}")
        if not np.allclose(mean, np.asarray(flat0), rtol=1e-6, atol=1e-9):
            raise ValueError("posterior: the covariance record's estimate does not match the "
                             "file's parameter values (was the file edited after identify?)")
        if not np.allclose(C, C.T, rtol=1e-8, atol=1e-300):
            raise ValueError("posterior: the covariance matrix is not symmetric")
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        if np.min(w, initial=0.0) < -1e-9 * max(np.max(np.abs(w), initial=0.0), 1e-300):
            raise ValueError(f"posterior: the covariance is not positive semi-definite "
                             f"(eigenvalue {np.min(w):.3g})")
        root = V * np.sqrt(np.maximum(w, 0.0)) * inflate
        return cls(space=space, labels=labels, mean=jnp.asarray(mean), root=jnp.asarray(root),
                   inflate=float(inflate))

    @property
    def names(self) -> tuple[str, ...]:
        """The identified parameter names (each for all n joints)."""
        return self.space.names

    def physical(self, theta_flat: Float[Array, " k"]) -> dict[str, Float[Array, " n"]]:
        """Physical values (name -> (n,), SI units) of flattened theta coordinates."""
        _, unravel = ravel_pytree(self.space.theta0())
        return self.space.physical(unravel(jnp.asarray(theta_flat)))

    def flat(self, values: dict[str, Array]) -> Float[Array, " k"]:
        """``values`` (name -> (n,)) flattened in ``labels`` order."""
        return jnp.concatenate([jnp.ravel(values[k]) for k in sorted(values)])

    def sample(self, key: jax.Array) -> Float[Array, " k"]:
        """One draw, physical values flattened in ``labels`` order (traceable; vmap over keys).
        The standard normal variate is drawn in float32 and cast, as the sweep's columns."""
        z = jax.random.normal(key, self.mean.shape, jnp.float32).astype(self.mean.dtype)
        return self.flat(self.physical(self.mean + self.root @ z))

    def box(self, confidence: float) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """The box holding the ``confidence`` region of the posterior (physical lo, hi per name,
        (n,) arrays): the bounding box of the chi-square ellipsoid in theta, mapped through
        the transforms (each physical value increases with its own theta and, for Fs = Fc +
        exp(u), with Fc's, so the box's corners map to the physical box's corners)."""
        if not 0 < confidence < 1:
            raise ValueError(f"posterior: confidence must be in (0, 1), got {confidence}")
        import scipy.special  # here: 0.2 s of every command's start (identify's too)

        k = self.mean.shape[0]
        half = math.sqrt(scipy.special.chdtri(k, 1.0 - confidence)) * jnp.sqrt(
            jnp.sum(self.root**2, axis=1))
        lo = self.physical(self.mean - half)
        hi = self.physical(self.mean + half)
        return ({n: np.asarray(v, float) for n, v in lo.items()},
                {n: np.asarray(v, float) for n, v in hi.items()})

    def stderr(self) -> dict[str, np.ndarray]:
        """Standard deviation of each theta entry (log-units for positive parameters:
        ~ relative standard error), name -> (n,)."""
        sd = np.sqrt(np.sum(np.asarray(self.root) ** 2, axis=1))
        out: dict[str, list[float]] = {}
        for lab, v in zip(self.labels, sd):
            out.setdefault(lab.split("[")[0], []).append(float(v))
        return {k: np.asarray(v) for k, v in out.items()}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (labels, mean, covariance incl. inflation)."""
        R = np.asarray(self.root)
        return {"labels": list(self.labels), "theta": np.asarray(self.mean).tolist(),
                "matrix": (R @ R.T).tolist(), "inflate": self.inflate}
