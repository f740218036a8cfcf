"""The link fields of a coupled arm in an identification (docs/spec.md section 5): which
fields the data can determine (``structural_free``) and the base parameters a fit reports
with their standard errors (``base_record``).

M, C and G of an arm depend on its fields only through its base parameters
(``AbstractLinkDynamics.base_parameters``; for ``PlanarTwoLink`` three, four with gravity),
so freeing more fields than there are base parameters leaves directions no log can see.
Which fields those are follows from the fields' map to the base parameters alone, before any
data: a field is kept when its column of d(base)/d(field) raises the rank of the columns kept
before it (in the order given), else it is fixed at its start value and marked, the
combinations named.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.fit.space import link_field
from jaxflex.io.params import Params
from jaxflex.core.plant import AbstractLinkDynamics, DiagonalInertia

#: Relative singular-value threshold under which a link field adds no base parameter.
RANK_RTOL: float = 1e-9


def _base_jacobian(links: AbstractLinkDynamics, fields: Sequence[str]
                   ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(values (b,), d values / d fields (b, sum of field sizes), names) of the base
    parameters of ``links`` at its own field values."""
    vals = {f: jnp.asarray(getattr(links, f), float) for f in fields}

    def base(v: dict[str, jax.Array]) -> jax.Array:
        m = eqx.tree_at(lambda q: tuple(getattr(q, f) for f in fields), links,
                        tuple(v[f] for f in fields))
        return jnp.stack([jnp.ravel(x) for x in m.base_parameters().values()]).ravel()

    jac = jax.jacfwd(base)(vals)
    cols = np.concatenate([np.asarray(jac[f], float).reshape(-1, int(np.size(vals[f])))
                           for f in fields], axis=1) if fields else np.zeros((0, 0))
    return np.asarray(base(vals)), cols, list(links.base_parameters())


def structural_free(init: Params, free: Sequence[str]) -> tuple[list[str], dict[str, str]]:
    """The free names with the link fields that add no base parameter left out.

    Arguments:
        init: the start, with a coupled link model (``links`` section) or not.
        free: the names to fit (``jaxflex.fit.ParamSpace``).

    Returns:
        (free without the fields left out, field name -> the reason it is fixed at its start
        value, naming the base parameters). Unchanged for decoupled links (M = diag(I)).
    """
    names = [k for k in free if link_field(k) is not None]
    if not names or init.links is None:
        return list(free), {}
    links = init.to_plant(with_effects=False).links
    if isinstance(links, DiagonalInertia):
        return list(free), {}
    _, cols, base = _base_jacobian(links, [link_field(k) for k in names])
    defs = links.base_definitions()
    combos = ", ".join(f"{b} = {defs[b]}" for b in base)
    kept: list[int] = []
    dropped: dict[str, str] = {}
    for i, name in enumerate(names):
        trial = cols[:, kept + [i]]
        norms = np.maximum(np.linalg.norm(trial, axis=0), 1e-300)
        s = np.linalg.svd(trial / norms, compute_uv=False)
        rank = int(np.sum(s > RANK_RTOL * s[0])) if s.size and s[0] > 0 else 0
        if rank == len(kept) + 1 and np.linalg.norm(cols[:, i]) > 0:
            kept.append(i)
        else:
            dropped[name] = (
                f"the arm's dynamics depend on its links only through the base parameters "
                f"({combos}); with {[names[j] for j in kept]} free, '{name}' adds none of them "
                "(fixed at its start value)")
    return [k for k in free if k not in dropped], dropped


def base_record(plant_links: AbstractLinkDynamics, phys: dict[str, Any],
                cov_phys: np.ndarray) -> dict[str, Any] | None:
    """The base parameters of a fitted arm with their standard errors (the covariance of the
    fitted physical values ``cov_phys``, over ``phys``'s names sorted, mapped through
    d(base)/d(field)): ``{"base_parameters": {name: {"value", "stderr", "definition"}},
    "fields": [...]}``. None for decoupled links or no fitted link field."""
    if isinstance(plant_links, DiagonalInertia):
        return None
    order = sorted(phys)
    if not any(link_field(k) is not None for k in order):
        return None
    fields = [link_field(k) for k in order if link_field(k) is not None]
    values, cols, base = _base_jacobian(plant_links, fields)
    # columns of the base Jacobian at the flattened positions of the link fields
    J = np.zeros((len(values), cov_phys.shape[0]))
    at, c = 0, 0
    for k in order:
        m = int(np.size(phys[k]))
        if link_field(k) is not None:
            J[:, at:at + m] = cols[:, c:c + m]
            c += m
        at += m
    var = np.einsum("ij,jk,ik->i", J, np.nan_to_num(cov_phys), J)
    se = np.sqrt(np.maximum(var, 0.0))
    defs = plant_links.base_definitions()
    return {"base_parameters": {b: {"value": float(values[i]), "stderr": float(se[i]),
                                    "definition": defs[b]} for i, b in enumerate(base)},
            "fields": [f"links.{f}" for f in fields]}
