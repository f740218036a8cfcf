"""Parameter files (SPEC section 7): one JSON document, SI units, per-joint lists.

    {"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
     "friction": {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1, "sigma2": 0.2},
     "gains": {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0},
     "effects": {"<name>": {...}}}

``Params`` is a host-side record (plain floats/lists); ``to_plant`` and ``to_gains`` build the
JAX modules. Loading validates before any JAX code runs; saving then loading is exact
(floats are written with ``repr`` precision by ``json``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

from jaxflex.controller import GAIN_NAMES, CascadeGains
from jaxflex.friction import LUGRE_NAMES, LuGre
from jaxflex.plant import DiagonalInertia, FlexibleJointPlant

PLANT_NAMES: tuple[str, ...] = ("I", "J", "K")


class ParamsError(ValueError):
    """A parameter file or mapping that does not follow SPEC section 7."""


def _vector(section: str, name: str, value: Any, n: int | None) -> list[float]:
    vals = value if isinstance(value, (list, tuple)) else [value]
    try:
        out = [float(v) for v in vals]
    except (TypeError, ValueError):
        raise ParamsError(
            f"{section}.{name}: expected a number or a list of numbers, got {value!r}"
        ) from None
    if not out:
        raise ParamsError(f"{section}.{name}: empty list")
    if any(not math.isfinite(v) for v in out):
        raise ParamsError(f"{section}.{name}: values must be finite, got {out}")
    if n is not None and len(out) != n:
        raise ParamsError(f"{section}.{name}: expected {n} value(s) (one per joint), got {len(out)}")
    return out


@dataclasses.dataclass
class Params:
    """Plant, friction, gains and effects for n joints, as plain lists of floats (SI units).

    plant: I [kg m^2], J [kg m^2], K [N m/rad]; friction: the six LuGre parameters (SPEC
    section 2); gains: Ke, KD1, KD2, kv, L1, L2 (SPEC section 3), optional; effects: named
    extra effects (SPEC section 8) with their parameter dicts; extra: other top-level keys kept
    verbatim (e.g. standard errors written by identification).
    """

    plant: dict[str, list[float]]
    friction: dict[str, list[float]]
    gains: dict[str, list[float]] | None = None
    effects: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.plant["I"])

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Params:
        """Validate a SPEC section 7 mapping; raises ``ParamsError`` naming the problem."""
        if not isinstance(d, dict):
            raise ParamsError(f"parameters must be a JSON object, got {type(d).__name__}")
        for sec in ("plant", "friction"):
            if sec not in d or not isinstance(d[sec], dict):
                raise ParamsError(f"missing section '{sec}' (SPEC section 7)")
        n = None
        plant = {}
        for k in PLANT_NAMES:
            if k not in d["plant"]:
                raise ParamsError(f"plant.{k} is missing")
            plant[k] = _vector("plant", k, d["plant"][k], n)
            n = len(plant[k])
        friction = {}
        for k in LUGRE_NAMES:
            if k not in d["friction"]:
                raise ParamsError(f"friction.{k} is missing")
            friction[k] = _vector("friction", k, d["friction"][k], n)
        gains = None
        if d.get("gains") is not None:
            gains = {}
            for k in GAIN_NAMES:
                if k not in d["gains"]:
                    raise ParamsError(f"gains.{k} is missing")
                gains[k] = _vector("gains", k, d["gains"][k], n)
        effects = d.get("effects") or {}
        if not isinstance(effects, dict):
            raise ParamsError("'effects' must be an object mapping effect names to parameters")
        extra = {k: v for k, v in d.items() if k not in ("plant", "friction", "gains", "effects")}
        p = cls(plant=plant, friction=friction, gains=gains, effects=dict(effects), extra=extra)
        p.validate()
        return p

    def validate(self) -> None:
        """Build the JAX modules once so that non-physical values raise ``ParamsError``."""
        try:
            self.to_plant()
            if self.gains is not None:
                self.to_gains()
        except ValueError as e:
            raise ParamsError(str(e)) from None

    def to_dict(self) -> dict[str, Any]:
        """The SPEC section 7 mapping."""
        d: dict[str, Any] = {"plant": self.plant, "friction": self.friction}
        if self.gains is not None:
            d["gains"] = self.gains
        if self.effects:
            d["effects"] = self.effects
        d.update(self.extra)
        return d

    def to_lugre(self) -> LuGre:
        """The LuGre module of these parameters."""
        return LuGre.from_dict(self.friction)

    def to_plant(self, with_effects: bool = True) -> FlexibleJointPlant:
        """The plant of eq. 40 (M = diag(I)) with LuGre friction and, if known, the effects.

        Effects are built from ``jaxflex.effects.EFFECTS``; an unknown name raises.
        """
        from jaxflex.effects import EFFECTS

        plant = FlexibleJointPlant(
            links=DiagonalInertia(I=self.plant["I"]), J=self.plant["J"], K=self.plant["K"],
            friction=self.to_lugre(),
        )
        if with_effects and self.effects:
            effs = []
            for name, kw in self.effects.items():
                if name not in EFFECTS:
                    raise ParamsError(
                        f"unknown effect '{name}'; known effects: {sorted(EFFECTS)}"
                    )
                try:
                    effs.append(EFFECTS[name](**kw))
                except TypeError as e:
                    raise ParamsError(f"effect '{name}': {e}") from None
            plant = plant.with_effects(*effs)
        return plant

    def to_gains(self) -> CascadeGains:
        """The controller gains; raises ``ParamsError`` if the file has none."""
        if self.gains is None:
            raise ParamsError("this parameter file has no 'gains' section")
        return CascadeGains(**self.gains)


def paper_params() -> Params:
    """The paper's link-1 parameters (Tables 1-3, SPEC's corrected Table 2)."""
    return Params.from_dict(
        {
            "plant": {"I": 0.07, "J": 0.005, "K": 6.77},
            "friction": {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1,
                         "sigma2": 0.2},
            "gains": {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0},
        }
    )


def read_json_file(path: str | os.PathLike, error: type[Exception], what: str) -> Any:
    """Parse a JSON file, raising ``error`` naming the file when it is missing or malformed
    (``what``: the kind of file, for the message)."""
    path = Path(path)
    if not path.exists():
        raise error(f"{what} not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise error(f"{path}: not valid JSON ({e})") from None


def load_params(path: str | os.PathLike) -> Params:
    """Read and validate a parameter file (SPEC section 7)."""
    d = read_json_file(path, ParamsError, "parameter file")
    try:
        return Params.from_dict(d)
    except ParamsError as e:
        raise ParamsError(f"{path}: {e}") from None


def save_params(params: Params, path: str | os.PathLike) -> None:
    """Write a parameter file atomically (a failure never leaves a half-written file)."""
    params.validate()
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(params.to_dict(), indent=2) + "\n")
    os.replace(tmp, path)
