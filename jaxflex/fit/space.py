"""Free parameters and their reparametrisation: the one constraint vocabulary of jaxflex.

A free parameter is named as in the parameter file (docs/spec.md section 7): plant ``I``,
``J``, ``K``; friction ``Fc``, ``Fs``, ``vs``, ``sigma0``, ``sigma1``, ``sigma2``; an
effect's parameter as ``"<effect>.<param>"`` (e.g. ``"torque_offset.offset"``); or a field
of a coupled link model as ``"links.<field>"`` (e.g. ``"links.m2"`` of a ``PlanarTwoLink``,
its constraint from the class's ``constraints``). Each nominal and effect name covers all n
joints; a link field has its own size (one value for a scalar field). Every parameter has a
constraint, a string of this vocabulary:

    "positive"      p = exp(u)                    (I, J, K, Fc, vs, sigma0..2; effect sizes;
                                                   u floored at LOG_TINY: p >= 1e-300)
    "nonnegative"   p = exp(u)                    (a value of exactly 0 is floored at 1e-12)
    "positive>=m"   p = m + exp(u)                (a lower bound, e.g. a time constant that a
                                                   fixed-step integrator needs above 1.5 ms)
    "bounded:a,b"   p = a + (b - a) sigmoid(u)
    "ordered"       Fs = Fc + exp(u)              (Fs >= Fc always, docs/spec.md section 2);
                    Fc = Fs sigmoid(u) when Fc is free and Fs is not; with a finite
                    ``ParamSpace.friction_cap`` c: Fc = c sigmoid(u - log c) and
                    Fs = Fc + c sigmoid(u' - log c), so Fc < c and Fs - Fc < c
                    (identify and discover: c = the largest logged torque)
    "free"          p = u
    "fixed"         never fitted (a smoothing width, a structural frequency)
    "tied:K"        copied from the plant's K (a backlash acts on the joint's own spring)

Nominal parameters take their constraint from ``NOMINAL_CONSTRAINTS``, effect parameters from
their class's ``constraints``. A ``ParamSpace`` maps unconstrained coordinates ``theta`` (dict
name -> (n,)) to a plant; with a ``mask`` (data, not structure) some names are pinned at
``fixed`` values, so problems that differ only in which parameters are fitted share one
compiled solver (the discrepancy workflow's candidates).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from jaxflex.core.effects import EFFECTS, unwrap
from jaxflex.core.friction import LUGRE_NAMES
from jaxflex.io.params import PLANT_NAMES, Params
from jaxflex.core.plant import AbstractLinkDynamics, DiagonalInertia, FlexibleJointPlant
from jaxflex.runtime.tracecache import persistent_jit
from jaxflex.core.validation import to_device

_FLOOR = 1e-12

#: The lowest coordinate of a positive parameter (p = exp(u) >= 1e-300): below it exp
#: underflows to 0 in float64 and the plant refuses the parameter (a refit can drive Fc
#: through a flat direction that far). Below it the coordinate has no slope and stays.
LOG_TINY = -690.0

#: Constraint of each nominal parameter (Fs: "ordered" with respect to Fc).
NOMINAL_CONSTRAINTS: dict[str, str] = {
    "I": "positive", "J": "positive", "K": "positive", "Fc": "positive", "Fs": "ordered",
    "vs": "positive", "sigma0": "positive", "sigma1": "nonnegative", "sigma2": "nonnegative",
}


def is_fitted(constraint: str) -> bool:
    """Whether a parameter with this constraint is adjusted by a fit."""
    return not (constraint == "fixed" or constraint.startswith("tied:"))


def _parse(constraint: str) -> tuple[str, float, float]:
    """(transform, a, b) of a constraint string; raises ``ValueError`` for an unknown one."""
    if constraint in ("positive", "nonnegative"):
        return "exp", 0.0, 0.0
    if constraint == "free":
        return "id", 0.0, 0.0
    if constraint == "ordered":
        return "gap", 0.0, 0.0
    m = re.fullmatch(r"positive>=([0-9.eE+-]+)", constraint)
    if m:
        return "lower", float(m.group(1)), 0.0
    m = re.fullmatch(r"bounded:([0-9.eE+-]+),([0-9.eE+-]+)", constraint)
    if m and float(m.group(1)) < float(m.group(2)):
        return "bounded", float(m.group(1)), float(m.group(2))
    raise ValueError(
        f"unknown constraint {constraint!r}; use positive, nonnegative, positive>=m, "
        "bounded:a,b, ordered, free, fixed or tied:K"
    )


LINKS_PREFIX = "links."


def link_field(name: str) -> str | None:
    """The field of ``"links.<field>"``; None for any other name."""
    return name[len(LINKS_PREFIX):] if name.startswith(LINKS_PREFIX) else None


def link_constraint(links: AbstractLinkDynamics, name: str) -> str:
    """The constraint of ``"links.<field>"`` on the link model ``links``; raises
    ``ValueError`` naming the field and the fields the model lets a fit free."""
    field = link_field(name)
    cons = type(links).constraints
    if isinstance(links, DiagonalInertia):
        raise ValueError(f"parameter '{name}': the links are decoupled (M = diag(I)); their "
                         "inertia is the parameter 'I'")
    if field not in cons:
        raise ValueError(
            f"parameter '{name}': {type(links).__name__} has no fitted field '{field}' "
            f"(fitted fields: {sorted(cons)}; the others are geometry)")
    return cons[field]


def constraint_of(name: str, effects: Mapping[str, Any] | None = None) -> str:
    """The constraint string of a named parameter (nominal, or ``"<effect>.<param>"``;
    a link field's is ``link_constraint``'s)."""
    if name in NOMINAL_CONSTRAINTS:
        return NOMINAL_CONSTRAINTS[name]
    eff, dot, par = name.partition(".")
    if not dot:
        raise ValueError(
            f"unknown parameter '{name}'; use {list(PLANT_NAMES)}, {list(LUGRE_NAMES)} or "
            "'<effect>.<param>'"
        )
    if eff not in EFFECTS:
        raise ValueError(f"parameter '{name}': unknown effect '{eff}'; known: {sorted(EFFECTS)}")
    cons = EFFECTS[eff].constraints
    if par not in cons:
        raise ValueError(f"parameter '{name}': effect '{eff}' has no parameter '{par}' "
                         f"(has {sorted(cons)})")
    return cons[par]


def get_value(params: Params, name: str) -> np.ndarray:
    """The (n,) value of a named parameter in a ``Params`` ((1,) for a scalar link field)."""
    field = link_field(name)
    if field is not None:
        if params.links is None or field not in params.links or field == "type":
            raise ValueError(f"parameter '{name}': the parameters have no link model with "
                             f"field '{field}' (a 'links' section, docs/spec.md section 7)")
        return np.atleast_1d(np.asarray(params.links[field], float))
    if name in PLANT_NAMES:
        if name not in params.plant:
            raise ValueError(f"parameter '{name}': the parameters have no plant.{name} (a "
                             "coupled link model: free its fields as 'links.<field>')")
        return np.asarray(params.plant[name], float)
    if name in LUGRE_NAMES:
        return np.asarray(params.friction[name], float)
    eff, _, par = name.partition(".")
    if eff not in params.effects or par not in params.effects[eff]:
        raise ValueError(
            f"parameter '{name}': effect '{eff}' with parameter '{par}' is not in the "
            f"parameters (effects present: {sorted(params.effects)}); add it with a start value"
        )
    return np.atleast_1d(np.asarray(params.effects[eff][par], float))


def set_values(params: Params, values: Mapping[str, Any]) -> Params:
    """A copy of ``params`` with the named values replaced (validated)."""
    d = copy.deepcopy(params.to_dict())
    for name, v in values.items():
        v = np.atleast_1d(np.asarray(v, float)).tolist()
        field = link_field(name)
        if field is not None:
            if "links" not in d or field not in d["links"]:
                raise ValueError(f"parameter '{name}': the parameters have no link model "
                                 f"with field '{field}'")
            d["links"][field] = v[0] if len(v) == 1 else v
        elif name in PLANT_NAMES:
            d["plant"][name] = v
        elif name in LUGRE_NAMES:
            d["friction"][name] = v
        else:
            eff, _, par = name.partition(".")
            d.setdefault("effects", {}).setdefault(eff, {})[par] = v
    return Params.from_dict(d)


def params_of_plant(plant: FlexibleJointPlant, base: Params) -> Params:
    """``base`` with the plant, friction, effect and link values of a plant (diagonal
    inertia, or ``base``'s link model); gated effects are written when their gate is on,
    unwrapped."""
    f = lambda a: [float(v) for v in np.ravel(a)]
    fr = plant.friction
    effects = {}
    for e in plant.effects:
        if float(np.ravel(getattr(e, "gate", 1.0))[0]) > 0:
            effects[e.name] = unwrap(e).params()
    values = {"J": f(plant.J), "K": f(plant.K)}
    links = None
    if base.links is None:
        values = {"I": f(plant.links.I), **values}
    else:
        links = {k: (v if k == "type" else (f(getattr(plant.links, k)) if np.ndim(
            getattr(plant.links, k)) else float(getattr(plant.links, k))))
                 for k, v in base.links.items()}
    return Params(
        plant=values, friction={k: f(getattr(fr, k)) for k in LUGRE_NAMES},
        gains=base.gains, effects=effects, extra=dict(base.extra), links=links,
    )


class ParamSpace(eqx.Module):
    """Map between unconstrained coordinates ``theta`` (dict name -> (n,)) and the plant.

    ``base``: the plant whose leaves are replaced (it may hold ``Gated`` effects); ``names``:
    the parameters in theta; ``transforms``: per name (kind, a, b) from ``_parse``;
    ``effect_index``: the position in ``base.effects`` of an effect parameter (-1 nominal);
    ``sizes``: the number of entries of each name's coordinates (n for a nominal or effect
    parameter, the field's size for a link field);
    ``mask``: per name a boolean (array) whether it is fitted; ``fixed``: per name the
    coordinates used where it is not; ``friction_cap``: the bound [N m] on Fc and on Fs - Fc
    (data, so a new cap compiles nothing; infinite by default, where the maps are exactly
    Fc = exp(u) and Fs = Fc + exp(u')). A friction level above the largest torque a log
    applies could never have been broken: with such a level the bristles act as a spring to
    ground, a non-physical minimum that a fit missing an effect can run into.
    """

    base: FlexibleJointPlant
    names: tuple[str, ...] = eqx.field(static=True)
    transforms: tuple[tuple[str, float, float], ...] = eqx.field(static=True)
    effect_index: tuple[int, ...] = eqx.field(static=True)
    sizes: tuple[int, ...] = eqx.field(static=True)
    mask: dict[str, Array]
    fixed: dict[str, Array]
    friction_cap: Array = eqx.field(default_factory=lambda: to_device(math.inf))

    @classmethod
    def build(cls, base: FlexibleJointPlant, free: Sequence[str]) -> ParamSpace:
        """Check the names in ``free`` against ``base`` and pick each one's transform.

        Raises ``ValueError`` naming an unknown parameter or effect, or one that is not
        fitted by its constraint ("fixed", "tied:...")."""
        free = tuple(dict.fromkeys(free))
        if not free:
            raise ValueError("fit: no free parameters given")
        effect_names = [e.name for e in base.effects]
        transforms, eidx, sizes = [], [], []
        for name in free:
            sizes.append(base.n)
            if name == "I" and not isinstance(base.links, DiagonalInertia):
                raise ValueError(
                    f"free parameter 'I': the links are {type(base.links).__name__}, not "
                    f"M = diag(I); free their fields as 'links.<field>' (fitted fields: "
                    f"{sorted(type(base.links).constraints)})")
            if link_field(name) is not None:
                con = link_constraint(base.links, name)
                if not is_fitted(con):
                    raise ValueError(f"free parameter '{name}' has constraint '{con}' and is "
                                     "not fitted")
                eidx.append(-1)
                sizes[-1] = int(np.size(getattr(base.links, link_field(name))))
                transforms.append(_parse(con))
                continue
            if name in NOMINAL_CONSTRAINTS:
                eidx.append(-1)
            elif "." in name:
                eff = name.partition(".")[0]
                if eff not in effect_names:
                    raise ValueError(
                        f"free parameter '{name}': effect '{eff}' is not in the initial "
                        f"parameters (effects present: {sorted(effect_names)}); add it with a "
                        "start value"
                    )
                eidx.append(effect_names.index(eff))
            else:
                raise ValueError(
                    f"unknown free parameter '{name}'; use {list(PLANT_NAMES)}, "
                    f"{list(LUGRE_NAMES)}, '<effect>.<param>' or 'links.<field>'"
                )
            con = constraint_of(name)
            if not is_fitted(con):
                raise ValueError(f"free parameter '{name}' has constraint '{con}' and is not "
                                 "fitted")
            if name == "Fc" and "Fs" not in free:
                transforms.append(("frac", 0.0, 0.0))
            elif name == "Fc":
                transforms.append(("capped", 0.0, 0.0))
            else:
                transforms.append(_parse(con))
        # Fs is built from Fc: evaluate Fc first.
        order = sorted(range(len(free)), key=lambda i: free[i] != "Fc")
        names = tuple(free[i] for i in order)
        sizes = tuple(sizes[i] for i in order)
        return cls(
            base=base, names=names, transforms=tuple(transforms[i] for i in order),
            effect_index=tuple(eidx[i] for i in order), sizes=sizes,
            mask={k: to_device(True) for k in names},
            fixed={k: to_device(np.zeros(m)) for k, m in zip(names, sizes)},
        )

    def size(self, name: str) -> int:
        """The number of coordinates of ``name``."""
        return self.sizes[self.names.index(name)]

    def with_lower_bound(self, name: str, m: float) -> ParamSpace:
        """The same space with the lower bound of ``name`` (a "positive>=m" parameter, p = a +
        exp(u)) set to ``m`` (its unit): e.g. a time constant that a fixed-step integrator
        keeps stable above a bound proportional to its step, not the class's fixed one."""
        if name not in self.names:
            raise ValueError(f"fit: {name!r} is not a parameter of this space ({self.names})")
        i = self.names.index(name)
        kind, a, b = self.transforms[i]
        if kind != "lower":
            raise ValueError(f"fit: {name!r} has no lower bound to set (transform {kind!r})")
        transforms = list(self.transforms)
        transforms[i] = (kind, float(m), b)
        return dataclasses.replace(self, transforms=tuple(transforms))

    def with_mask(self, fitted: Sequence[str], theta_fixed: dict[str, Array]) -> ParamSpace:
        """The same space fitting only ``fitted``; the others stay at ``theta_fixed``."""
        unknown = sorted(set(fitted) - set(self.names))
        if unknown:
            raise ValueError(f"fit: {unknown} are not parameters of this space ({self.names})")
        mask = {k: to_device(k in fitted) for k in self.names}
        fixed = {k: jnp.asarray(theta_fixed[k]) for k in self.names}
        return eqx.tree_at(lambda s: (s.mask, s.fixed), self, (mask, fixed))

    def fitted_names(self) -> tuple[str, ...]:
        """Names fitted under the current mask (host side)."""
        return tuple(k for k in self.names if bool(self.mask[k]))

    def _current(self, name: str, idx: int) -> Array:
        if link_field(name) is not None:
            return jnp.ravel(getattr(self.base.links, link_field(name)))
        if name == "I":
            return self.base.links.I
        if name in ("J", "K"):
            return getattr(self.base, name)
        if name in LUGRE_NAMES:
            return getattr(self.base.friction, name)
        return getattr(unwrap(self.base.effects[idx]), name.partition(".")[2])

    def physical(self, theta: dict[str, Array]) -> dict[str, Array]:
        """Physical values (dict name -> (n,)) of the coordinates ``theta``."""
        fr = self.base.friction
        out: dict[str, Array] = {}
        for name, (kind, a, b) in zip(self.names, self.transforms):
            t = jnp.where(self.mask[name], theta[name], self.fixed[name])
            if kind == "exp":
                out[name] = jnp.exp(jnp.maximum(t, LOG_TINY))
            elif kind in ("capped", "gap"):
                # cap sigmoid(t - log cap) = exp(t) / (1 + exp(t) / cap): exp(t) exactly while
                # the cap is infinite (the default); written exp(t - softplus(t - log cap)),
                # finite for any t
                soft = jax.nn.softplus(t - jnp.log(self.friction_cap))
                level = jnp.exp(jnp.maximum(t, LOG_TINY) - soft)
                out[name] = level if kind == "capped" else out.get("Fc", fr.Fc) + level
            elif kind == "lower":
                out[name] = a + jnp.exp(t)
            elif kind == "bounded":
                out[name] = a + (b - a) * jax.nn.sigmoid(t)
            elif kind == "frac":
                out[name] = fr.Fs * jax.nn.sigmoid(jnp.maximum(t, LOG_TINY))
            else:
                out[name] = t
        return out

    def theta_of(self, values: Mapping[str, Any]) -> dict[str, Array]:
        """Coordinates of physical ``values`` (dict name -> (n,) or scalar); names not given
        take the base plant's value. Values on a constraint's boundary are moved inside."""
        th: dict[str, np.ndarray] = {}
        cur = {name: np.asarray(values[name], float) if name in values
               else np.asarray(self._current(name, i), float)
               for name, i in zip(self.names, self.effect_index)}
        fc = cur.get("Fc", np.asarray(self.base.friction.Fc, float)) if self.base.friction else 0
        for name, (kind, a, b), m in zip(self.names, self.transforms, self.sizes):
            v = np.broadcast_to(cur[name], (m,))
            if kind == "exp":
                th[name] = np.log(np.maximum(v, _FLOOR))
            elif kind == "lower":
                th[name] = np.log(np.maximum(v - a, _FLOOR))
            elif kind == "bounded":
                r = np.clip((v - a) / (b - a), 1e-9, 1 - 1e-9)
                th[name] = np.log(r / (1 - r))
            elif kind in ("capped", "gap"):
                g = np.maximum(v - fc, 1e-3 * fc) if kind == "gap" else np.maximum(v, _FLOOR)
                cap = float(self.friction_cap)
                g = np.minimum(g, (1 - 1e-9) * cap) if math.isfinite(cap) else g
                th[name] = np.log(g / (1.0 - g / cap))
            elif kind == "frac":
                r = np.clip(v / np.asarray(self.base.friction.Fs, float), 1e-6, 1 - 1e-6)
                th[name] = np.log(r / (1 - r))
            else:
                th[name] = v
        return {k: to_device(v, float) for k, v in th.items()}

    def theta0(self) -> dict[str, Array]:
        """Coordinates of the base plant's values."""
        return self.theta_of({})

    def plant(self, theta: dict[str, Array]) -> FlexibleJointPlant:
        """The base plant with the parameters set from ``theta``; effect parameters with a
        "tied:K" constraint follow the plant's K."""
        if any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(theta)):
            phys = self.physical(theta)
        else:  # concrete: one kept program, not eager operations (its device arrays)
            phys = _physical_on_host(self, theta)[0]
        # one ``tree_at`` for all the names: each call walks the whole plant, which holds
        # every gated effect in discover
        wheres = [_where(name, idx) for name, idx in zip(self.names, self.effect_index)]
        # a link field keeps its own shape (a scalar mass is one coordinate)
        p = eqx.tree_at(lambda q: tuple(w(q) for w in wheres), self.base,
                        tuple(jnp.reshape(phys[name], jnp.shape(w(self.base)))
                              if link_field(name) is not None else phys[name]
                              for name, w in zip(self.names, wheres)))
        tied = [_where(f"{e.name}.{k}", i) for i, e in enumerate(p.effects)
                for k, c in type(unwrap(e)).constraints.items() if c == "tied:K"]
        if tied:
            p = eqx.tree_at(lambda q: tuple(w(q) for w in tied), p, tuple(p.K for _ in tied))
        return p

    def physical_jacobian(self, theta: dict[str, Array]) -> np.ndarray:
        """d physical / d theta over the flattened names (k x k) at ``theta`` (host side)."""
        return np.asarray(_physical_on_host(self, theta)[1])

    def physical_values(self, theta: dict[str, Array]) -> dict[str, np.ndarray]:
        """``physical(theta)`` evaluated on the host, as numpy arrays (one compiled program,
        kept by ``jaxflex.runtime.tracecache``, instead of a handful of eager operations whose
        compilations each new process pays again)."""
        return {k: np.asarray(v) for k, v in _physical_on_host(self, theta)[0].items()}

    def fitted_flat(self) -> np.ndarray:
        """Boolean per flattened theta entry: fitted under the current mask."""
        # on the host, in ravel_pytree's order (sorted names): no compilation per call
        return np.concatenate([np.broadcast_to(np.asarray(self.mask[k]), (self.size(k),))
                               for k in sorted(self.names)]).astype(bool)


@persistent_jit(fast_compile=True)
def _physical_on_host(space: ParamSpace, theta: dict[str, Array]) -> tuple[dict[str, Array],
                                                                            Array]:
    """``space.physical(theta)`` and its Jacobian over the flattened names, compiled once."""
    flat, unravel = ravel_pytree(theta)
    phys_flat = lambda f: ravel_pytree(space.physical(unravel(f)))[0]
    return space.physical(theta), jax.jacfwd(phys_flat)(flat)


def _where(name: str, idx: int):
    field = link_field(name)
    if field is not None:
        return lambda p: getattr(p.links, field)
    if name == "I":
        return lambda p: p.links.I
    if name in ("J", "K"):
        return lambda p: getattr(p, name)
    if name in LUGRE_NAMES:
        return lambda p: getattr(p.friction, name)
    par = name.partition(".")[2]
    return lambda p: getattr(unwrap(p.effects[idx]), par)


def relative(se: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Relative standard error |se / value| (inf where the value is 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(value) > 0, np.abs(se) / np.abs(value), math.inf)
