"""Free parameters and their reparametrisation (physical constraints kept by construction).

A free parameter is named like in the parameter file (SPEC section 7): plant ``I``, ``J``,
``K``; friction ``Fc``, ``Fs``, ``vs``, ``sigma0``, ``sigma1``, ``sigma2``; or an effect's
parameter as ``"<effect>.<param>"`` (e.g. ``"torque_offset.offset"``), whose constraint comes
from the effect's ``constraints`` (``"positive"``, ``"nonnegative"`` or ``"free"``). Each name
covers all n joints.

Unconstrained coordinates theta map to physical values by:

    positive / nonnegative:  p = exp(theta)            (I, J, K, Fc, vs, sigma0..2)
    Fs (free):               Fs = Fc + exp(theta)      (so Fs >= Fc always, SPEC section 2)
    Fc free, Fs fixed:       Fc = Fs sigmoid(theta)
    free:                    p = theta
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.friction import LUGRE_NAMES
from jaxflex.params import PLANT_NAMES, Params
from jaxflex.plant import FlexibleJointPlant

_FLOOR = 1e-12


def _effect_constraint(params: Params, name: str) -> str:
    from jaxflex.effects import EFFECTS

    eff, _, par = name.partition(".")
    if eff not in params.effects:
        raise ValueError(
            f"free parameter '{name}': effect '{eff}' is not in the initial parameters "
            f"(effects present: {sorted(params.effects)}); add it with a starting value"
        )
    if par not in params.effects[eff]:
        raise ValueError(
            f"free parameter '{name}': effect '{eff}' has no parameter '{par}' "
            f"(has {sorted(params.effects[eff])})"
        )
    cls = EFFECTS.get(eff)
    return getattr(cls, "constraints", {}).get(par, "free") if cls is not None else "free"


def get_value(params: Params, name: str) -> np.ndarray:
    """The (n,) value of a named parameter in a ``Params``."""
    if name in PLANT_NAMES:
        return np.asarray(params.plant[name], float)
    if name in LUGRE_NAMES:
        return np.asarray(params.friction[name], float)
    eff, _, par = name.partition(".")
    return np.atleast_1d(np.asarray(params.effects[eff][par], float))


def set_values(params: Params, values: dict[str, Any]) -> Params:
    """A copy of ``params`` with the named values replaced (validated)."""
    d = copy.deepcopy(params.to_dict())
    for name, v in values.items():
        v = np.atleast_1d(np.asarray(v, float)).tolist()
        if name in PLANT_NAMES:
            d["plant"][name] = v
        elif name in LUGRE_NAMES:
            d["friction"][name] = v
        else:
            eff, _, par = name.partition(".")
            d["effects"][eff][par] = v
    return Params.from_dict(d)


class ParamSpace(eqx.Module):
    """Map between unconstrained coordinates ``theta`` (dict name -> (n,)) and the plant.

    ``base`` is the plant built from the initial parameters; ``names`` the free parameters;
    ``kinds`` their transform ("exp", "gap" for Fs = Fc + exp, "frac" for Fc = Fs sigmoid,
    "id").
    """

    base: FlexibleJointPlant
    names: tuple[str, ...] = eqx.field(static=True)
    kinds: tuple[str, ...] = eqx.field(static=True)
    effect_index: tuple[int, ...] = eqx.field(static=True)

    @classmethod
    def build(cls, init: Params, free: Sequence[str]) -> ParamSpace:
        """Check the names in ``free`` against ``init`` and pick each one's transform."""
        free = tuple(dict.fromkeys(free))
        if not free:
            raise ValueError("identify: no free parameters given")
        base = init.to_plant()
        kinds, eidx = [], []
        effect_names = [e.name for e in base.effects]
        for name in free:
            if name in PLANT_NAMES or name in LUGRE_NAMES:
                if name == "Fs":
                    kinds.append("gap")
                elif name == "Fc" and "Fs" not in free:
                    kinds.append("frac")
                else:
                    kinds.append("exp")
                eidx.append(-1)
            elif "." in name:
                con = _effect_constraint(init, name)
                kinds.append("exp" if con in ("positive", "nonnegative") else "id")
                eidx.append(effect_names.index(name.partition(".")[0]))
            else:
                raise ValueError(
                    f"identify: unknown free parameter '{name}'; use {list(PLANT_NAMES)}, "
                    f"{list(LUGRE_NAMES)} or '<effect>.<param>'"
                )
        # Fs is built from Fc: evaluate Fc first.
        order = sorted(range(len(free)), key=lambda i: free[i] != "Fc")
        return cls(base=base, names=tuple(free[i] for i in order),
                   kinds=tuple(kinds[i] for i in order), effect_index=tuple(eidx[i] for i in order))

    def _where(self, name: str, idx: int):
        if name == "I":
            return lambda p: p.links.I
        if name in ("J", "K"):
            return lambda p: getattr(p, name)
        if name in LUGRE_NAMES:
            return lambda p: getattr(p.friction, name)
        par = name.partition(".")[2]
        return lambda p: getattr(p.effects[idx], par)

    def physical(self, theta: dict[str, Array]) -> dict[str, Array]:
        """Physical values (dict name -> (n,)) of the coordinates ``theta``."""
        fr = self.base.friction
        out: dict[str, Array] = {}
        for name, kind in zip(self.names, self.kinds):
            t = theta[name]
            if kind == "exp":
                out[name] = jnp.exp(t)
            elif kind == "gap":
                out[name] = out.get("Fc", fr.Fc) + jnp.exp(t)
            elif kind == "frac":
                out[name] = fr.Fs * jax.nn.sigmoid(t)
            else:
                out[name] = t
        return out

    def theta0(self, init: Params) -> dict[str, Array]:
        """Coordinates of the initial values (zero or tiny values are floored)."""
        th = {}
        for name, kind in zip(self.names, self.kinds):
            v = get_value(init, name)
            if kind == "exp":
                th[name] = jnp.log(np.maximum(v, _FLOOR))
            elif kind == "gap":
                fc = get_value(init, "Fc")
                th[name] = jnp.log(np.maximum(v - fc, 1e-3 * fc))
            elif kind == "frac":
                r = np.clip(v / get_value(init, "Fs"), 1e-6, 1 - 1e-6)
                th[name] = jnp.log(r / (1 - r))
            else:
                th[name] = jnp.asarray(v, float)
        return th

    def plant(self, theta: dict[str, Array]) -> FlexibleJointPlant:
        """The base plant with the free parameters set from ``theta``."""
        phys = self.physical(theta)
        p = self.base
        for name, idx in zip(self.names, self.effect_index):
            p = eqx.tree_at(self._where(name, idx), p, phys[name])
        return p
