"""Parameter files (docs/spec.md section 7): one JSON document, SI units, per-joint lists.

    {"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
     "friction": {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1, "sigma2": 0.2},
     "gains": {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0},
     "effects": {"<name>": {...}},
     "controller": {"q2d_method": "model", "dt": 0.001, "tau_max": 2.0, "compensation": true,
                    "sensing": "rig", "trajectory": "sinusoid"}}

``Params`` is a host-side record (plain floats/lists); ``to_plant`` and ``to_gains`` build the
JAX modules. ``build_plant`` is the one place that turns plant, friction and effect values
into a ``FlexibleJointPlant``; it also takes arrays, traced ones included (the sweep builds
its sampled plants with it). The optional ``controller`` section (``ControllerConfig``)
records the controller configuration the gains were tuned and certified for, so that
``export`` and ``run-loop`` use the same one. Loading validates before any JAX code runs;
saving then loading is exact (floats are written with ``repr`` precision by ``json``).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import difflib
import json
import math
import os
import warnings
from pathlib import Path
from collections.abc import Callable, Iterator, Mapping
from typing import Any

from jaxtyping import ArrayLike

from jaxflex.core.controller import GAIN_NAMES, Q2D_METHODS, CascadeGains
from jaxflex.io.arms import dh_links, kuka_kr300_links, urdf_links
from jaxflex.core.effects import EFFECTS
from jaxflex.core.friction import LUGRE_NAMES, LuGre
from jaxflex.core.plant import AbstractLinkDynamics, DiagonalInertia, FlexibleJointPlant, PlanarTwoLink
from jaxflex.core.sensing import SENSING_FIELDS, Sensing
from jaxflex.core.validation import check_keys, did_you_mean

PLANT_NAMES: tuple[str, ...] = ("I", "J", "K")
#: The coupled link models a parameter file's ``links`` section may name (its ``type``): each
#: one's builder, called with the fields as keywords, its required fields and its optional
#: ones (docs/spec.md section 7). A shipped arm is built by its data module from its own
#: tables.
LINK_TYPES: dict[str, Callable[..., AbstractLinkDynamics]] = {
    "planar_two_link": PlanarTwoLink, "kuka_kr300": kuka_kr300_links, "dh": dh_links,
    "urdf": urdf_links,
}
LINK_FIELDS: dict[str, tuple[str, ...]] = {
    "planar_two_link": ("m1", "m2", "l1", "lc1", "lc2", "I1", "I2", "g"),
    "kuka_kr300": ("payload", "q4", "q5", "q6"),
    "dh": ("a", "d", "alpha", "mass", "com", "inertia"),
    "urdf": ("path",),
}
LINK_OPTIONAL: dict[str, tuple[str, ...]] = {
    "dh": ("offset", "joints", "gravity"), "urdf": ("gravity",),
}
#: The fields of a ``links`` section that hold text (the others hold numbers or lists).
LINK_TEXT: tuple[str, ...] = ("type", "path", "joints")


class ParamsError(ValueError):
    """A parameter file or mapping that does not follow docs/spec.md section 7."""


def build_links(links: Mapping[str, Any]) -> AbstractLinkDynamics:
    """The coupled link model of a ``links`` section: ``{"type": <LINK_TYPES key>, <field>:
    value, ...}`` (a ``PlanarTwoLink``: masses [kg], lengths [m], inertias [kg m^2], g
    [m/s^2]; the KUKA KR300's axes 1-3, ``jaxflex.io.arms.kuka_kr300_links``: payload
    [kg], wrist angles [rad]; a chain from its DH table, ``jaxflex.io.arms.dh_links``, or
    from a URDF, ``jaxflex.io.arms.urdf_links``). Raises ``ParamsError`` naming an unknown
    type (and the known ones), a missing or unknown field, or what the builder refuses."""
    kind = check_link_fields(links)
    try:
        return LINK_TYPES[kind](**{k: v for k, v in links.items() if k != "type"})
    except ValueError as e:
        raise ParamsError(f"links ({kind}): {e}") from None


def check_link_fields(links: Mapping[str, Any]) -> str:
    """The ``type`` of a ``links`` section whose fields are its type's (``LINK_FIELDS``, all
    present, and ``LINK_OPTIONAL``); raises ``ParamsError`` naming an unknown type, an
    unknown field or the missing ones."""
    kind = links.get("type")
    if kind not in LINK_TYPES:
        raise ParamsError(f"links.type: expected one of {sorted(LINK_TYPES)}, got {kind!r}")
    fields = LINK_FIELDS[kind]
    check_keys({k: v for k, v in links.items() if k != "type"},
               fields + LINK_OPTIONAL.get(kind, ()), where=f"links ({kind}): ", what="field",
               error=ParamsError)
    missing = [k for k in fields if k not in links]
    if missing:
        raise ParamsError(f"links ({kind}): missing field(s) {missing}")
    return kind


def _link_value(name: str, v: Any) -> Any:
    """A ``links`` field's value checked: text for ``LINK_TEXT``'s fields, else a finite
    number or a (nested) list of them."""
    where = f"links.{name}"
    if name in LINK_TEXT:
        if not isinstance(v, str):
            raise ParamsError(f"{where}: expected text, got {v!r}")
        return v
    if isinstance(v, list):
        return [_link_value(name, x) for x in v]
    return _number(where, v)


def build_plant(
    plant: Mapping[str, ArrayLike],
    friction: Mapping[str, ArrayLike] | None = None,
    effects: Mapping[str, Mapping[str, Any]] | None = None,
    links: Mapping[str, Any] | None = None,
) -> FlexibleJointPlant:
    """The plant of eq. 3 from plant values J [kg m^2], K [N m/rad] and either I [kg m^2]
    (M = diag(I), eq. 40) or a coupled link model (``links``, ``build_links``), the six
    LuGre values (docs/spec.md section 2; ``None``: no friction) and named effects
    (``jaxflex.core.effects.EFFECTS`` name -> keyword arguments), each a number or an (n,) array.

    Traceable: the values may be JAX tracers (the modules' value checks then skip them), so
    ``vmap`` over sampled parameters builds one plant per sample. Raises ``ParamsError`` for
    an unknown effect or effect arguments its class does not take, and ``ValueError`` from
    the modules for concrete non-physical values.
    """
    built = FlexibleJointPlant(
        links=DiagonalInertia(I=plant["I"]) if links is None else build_links(links),
        J=plant["J"], K=plant["K"],
        friction=None if friction is None else LuGre.from_dict(friction),
    )
    if not effects:
        return built
    effs = []
    for name, kw in effects.items():
        if name not in EFFECTS:
            raise ParamsError(f"unknown effect '{name}'; known effects: {sorted(EFFECTS)}")
        try:
            effs.append(EFFECTS[name](**kw))
        except TypeError as e:
            raise ParamsError(f"effect '{name}': {e}") from None
    return built.with_effects(*effs)


CONTROLLER_KEYS: tuple[str, ...] = (
    "q2d_method", "dt", "tau_max", "compensation", "sensing", "trajectory",
)


# top-level keys the tools write besides the sections (kept verbatim on reading);
# "loop_controller" declares the loop that ran on a rig for ``jaxflex validate`` (the EMPS
# P/P cascade {"type": "pp_cascade", ...}, a PD loop {"type": "pd", ...} or jaxflex's cascade
# {"type": "cascade", ...}; read by ``jaxflex.validate.loop_controller``); "axis" declares the
# physics the log's owner knows (read by ``jaxflex.discover.declared_axes``)
EXTRA_KEYS: tuple[str, ...] = ("stderr", "identification", "discover", "source", "description",
                               "comment", "notes", "units", "meta", "loop_controller",
                               "certificate", "axis", "link_side")
SECTIONS: tuple[str, ...] = ("plant", "friction", "gains", "effects", "controller", "links")


def _positive_number(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise ParamsError(f"{where}: expected a finite number > 0, got {v!r}")
    return float(v)


@dataclasses.dataclass(frozen=True)
class ControllerConfig:
    """The controller configuration a gain set was tuned and certified for (the parameter
    file's optional ``controller`` section); ``None`` marks an entry the file does not record.

    q2d_method: how q2d' and q2d'' are obtained (``jaxflex.core.controller.Q2D_METHODS``);
    dt [s]: sample period; tau_max [N m]: torque limit; compensation: friction compensation
    on; sensing: a sensing preset name (``jaxflex.io.presets.SENSING_PRESETS``) or the fields of
    a ``jaxflex.core.sensing.Sensing``; trajectory: a trajectory name
    (``jaxflex.io.presets.TRAJECTORIES``) or the names of several (the first is the default).
    Preset and trajectory *names* are checked where they are resolved
    (``jaxflex.io.presets.controller_setup``), which sits above this module.
    """

    q2d_method: str | None = None
    dt: float | None = None
    tau_max: float | None = None
    compensation: bool | None = None
    sensing: str | dict[str, Any] | None = None
    trajectory: str | tuple[str, ...] | None = None

    @classmethod
    def from_dict(cls, d: Any) -> ControllerConfig:
        """Validate a ``controller`` section; raises ``ParamsError`` naming the entry (an
        unknown key with the closest known one)."""
        if not isinstance(d, dict):
            raise ParamsError(f"controller: expected an object, got {type(d).__name__}")
        check_keys(d, CONTROLLER_KEYS, where="controller: ", error=ParamsError)
        out: dict[str, Any] = {}
        if "q2d_method" in d:
            if d["q2d_method"] not in Q2D_METHODS:
                raise ParamsError(f"controller.q2d_method: expected one of {list(Q2D_METHODS)}, "
                                  f"got {d['q2d_method']!r}")
            out["q2d_method"] = d["q2d_method"]
        for k in ("dt", "tau_max"):
            if k in d:
                out[k] = _positive_number(f"controller.{k}", d[k])
        if "compensation" in d:
            if not isinstance(d["compensation"], bool):
                raise ParamsError("controller.compensation: expected true or false, got "
                                  f"{d['compensation']!r}")
            out["compensation"] = d["compensation"]
        if "sensing" in d:
            out["sensing"] = _sensing_entry(d["sensing"])
        if "trajectory" in d:
            tr = d["trajectory"]
            names = [tr] if isinstance(tr, str) else tr
            if not isinstance(names, list) or not names or not all(
                    isinstance(x, str) and x for x in names):
                raise ParamsError("controller.trajectory: expected a trajectory name or a "
                                  f"non-empty list of names, got {tr!r}")
            out["trajectory"] = tr if isinstance(tr, str) else tuple(tr)
        return cls(**out)

    def to_dict(self) -> dict[str, Any]:
        """The ``controller`` section: the recorded entries only."""
        out: dict[str, Any] = {}
        for k in CONTROLLER_KEYS:
            v = getattr(self, k)
            if v is not None:
                out[k] = list(v) if isinstance(v, tuple) else (dict(v) if isinstance(v, dict) else v)
        return out

    @property
    def trajectory_name(self) -> str | None:
        """The recorded trajectory, or the first of several (None if none is recorded)."""
        return self.trajectory[0] if isinstance(self.trajectory, tuple) else self.trajectory

    def resolve(self, given: Mapping[str, Any], flags: Mapping[str, str] | None = None,
                source: str = "the parameter file") -> ControllerConfig:
        """This configuration with each entry of ``given`` (field name -> value; ``None``: not
        given) filled in where nothing is recorded.

        A given value that contradicts a recorded one raises ``ParamsError`` naming the
        option (``flags``: field name -> option name for the message) and ``source``: gains
        certified for one configuration are not silently used in another. A given trajectory
        agrees when it is one of the recorded names (and is then the one used); dt agrees to
        1e-9 relative.
        """
        flags = flags or {}
        out: dict[str, Any] = {}
        check_keys(given, CONTROLLER_KEYS, where="controller: ", error=ParamsError)
        for k, v in given.items():
            rec = getattr(self, k)
            if v is None:
                continue
            if rec is None:
                out[k] = v
                continue
            if k == "dt":
                same = math.isclose(float(v), rec, rel_tol=1e-9)
            elif k == "trajectory" and isinstance(rec, tuple):
                same = v in rec
            else:
                same = v == rec
            if not same:
                raise ParamsError(
                    f"{flags.get(k, k)} {v!r} contradicts controller.{k} = "
                    f"{self.to_dict()[k]!r} recorded in {source} (the gains were tuned and "
                    "certified for it); leave the option out, or tune again for the new setting")
            out[k] = v
        return dataclasses.replace(self, **out)

    def with_defaults(self, defaults: ControllerConfig) -> ControllerConfig:
        """Entries not recorded here taken from ``defaults``."""
        return dataclasses.replace(self, **{
            k: getattr(defaults, k) for k in CONTROLLER_KEYS
            if getattr(self, k) is None and getattr(defaults, k) is not None})


def _sensing_entry(v: Any) -> str | dict[str, Any]:
    if isinstance(v, str) and v:
        return v
    if not isinstance(v, dict):
        raise ParamsError("controller.sensing: expected a sensing preset name or an object of "
                          f"Sensing fields, got {v!r}")
    check_keys(v, SENSING_FIELDS, where="controller.sensing: ", what="field", error=ParamsError)
    try:
        Sensing(**v)
    except (TypeError, ValueError) as e:
        raise ParamsError(f"controller.sensing: {e}") from None
    return dict(v)


def _number(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ParamsError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def _vector(section: str, name: str, value: Any, n: int | None) -> list[float]:
    vals = value if isinstance(value, (list, tuple)) else [value]
    # a JSON string ("6.77") or boolean (true) is a mistake, not a number to convert
    if any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in vals):
        hint = " (write the number without quotes)" if any(isinstance(v, str) for v in vals) else ""
        raise ParamsError(
            f"{section}.{name}: expected a number or a list of numbers, got {value!r}{hint}"
        )
    out = [float(v) for v in vals]
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

    plant: I [kg m^2], J [kg m^2], K [N m/rad] (no I where ``links`` is given); friction: the
    six LuGre parameters (docs/spec.md section 2); gains: Ke, KD1, KD2, kv, L1, L2 (docs/spec.md
    section 3), optional; effects: named extra effects (docs/spec.md section 8) with their
    parameter dicts; extra: other top-level keys kept verbatim (e.g. standard errors written
    by identification); controller: the controller configuration the gains were tuned for
    (``ControllerConfig``), optional; links: a coupled link model (``build_links``: its
    ``type`` and fields as floats) in place of M = diag(I), optional.
    """

    plant: dict[str, list[float]]
    friction: dict[str, list[float]]
    gains: dict[str, list[float]] | None = None
    effects: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    controller: ControllerConfig | None = None
    links: dict[str, Any] | None = None

    @property
    def n(self) -> int:
        """Number of joints."""
        return len(self.plant["J"])

    def joint(self, j: int) -> Params:
        """The one-joint parameters of joint ``j`` (0-based; a parameter file describes
        independent joints, so this is exact); extra keys are dropped."""
        if not 0 <= j < self.n:
            raise ParamsError(f"joint {j} out of range for {self.n} joint(s)")
        if self.links is not None:
            raise ParamsError(f"joint {j}: the joints of a coupled arm (links "
                              f"{self.links['type']!r}) are not independent")
        pick = lambda sec: {k: [v[j]] for k, v in sec.items()}
        eff = {name: {k: ([v[j]] if isinstance(v, list) else v) for k, v in kw.items()}
               for name, kw in self.effects.items()}
        return Params(plant=pick(self.plant), friction=pick(self.friction),
                      gains=None if self.gains is None else pick(self.gains), effects=eff,
                      controller=self.controller)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Params:
        """Validate a docs/spec.md section 7 mapping; raises ``ParamsError`` naming the problem."""
        if not isinstance(d, dict):
            raise ParamsError(f"parameters must be a JSON object, got {type(d).__name__}")
        for k in d:  # a misspelled section ('gain') is refused, not kept as an extra key
            if k not in SECTIONS + EXTRA_KEYS:
                close = difflib.get_close_matches(k, SECTIONS, n=1, cutoff=0.6)
                if close or not k.startswith("x_"):
                    raise ParamsError(
                        f"unknown top-level key '{k}'{did_you_mean(k, SECTIONS)}; sections: "
                        f"{list(SECTIONS)}; other keys written by the tools: {list(EXTRA_KEYS)} "
                        "(prefix your own with 'x_')")
        for sec in ("plant", "friction"):
            if sec not in d:
                raise ParamsError(f"missing section '{sec}' (docs/spec.md section 7)")
            if not isinstance(d[sec], dict):
                raise ParamsError(f"section '{sec}' must be an object, got {type(d[sec]).__name__}")
        check_keys(d["plant"], PLANT_NAMES, where="plant: ", error=ParamsError)
        check_keys(d["friction"], LUGRE_NAMES, where="friction: ", error=ParamsError)
        links = d.get("links")
        if links is not None:
            if not isinstance(links, dict):
                raise ParamsError(f"section 'links' must be an object, got {type(links).__name__}")
            if "I" in d["plant"]:
                raise ParamsError("plant.I: a file with a 'links' section describes the link "
                                  "inertia there; remove plant.I")
            check_link_fields(links)
            links = {k: _link_value(k, v) for k, v in links.items()}
        n = None
        plant = {}
        for k in PLANT_NAMES if links is None else ("J", "K"):
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
            if not isinstance(d["gains"], dict):
                raise ParamsError(f"section 'gains' must be an object, got {type(d['gains']).__name__}")
            check_keys(d["gains"], GAIN_NAMES + ("leak",), where="gains: ", error=ParamsError)
            gains = {}
            for k in GAIN_NAMES:
                if k not in d["gains"]:
                    raise ParamsError(f"gains.{k} is missing")
                gains[k] = _vector("gains", k, d["gains"][k], n)
            if "leak" in d["gains"]:  # optional: the observer's leakage (0: the paper's)
                gains["leak"] = _vector("gains", "leak", d["gains"]["leak"], n)
                if any(x < 0 for x in gains["leak"]):
                    raise ParamsError(f"gains.leak: must be >= 0 rad/s, got {gains['leak']}")
        effects = d.get("effects") or {}
        if not isinstance(effects, dict):
            raise ParamsError("'effects' must be an object mapping effect names to parameters")
        check_keys(effects, sorted(EFFECTS), where="effects: ", what="effect", error=ParamsError)
        for name, kw in effects.items():
            if not isinstance(kw, dict):
                raise ParamsError(f"effects.{name}: expected an object of parameters, got {kw!r}")
            fields = tuple(f.name for f in dataclasses.fields(EFFECTS[name]))
            check_keys(kw, fields, where=f"effects.{name}: ", what="parameter", error=ParamsError)
            for k, v in kw.items():
                _vector(f"effects.{name}", k, v, None)
        controller = None
        if d.get("controller") is not None:
            controller = ControllerConfig.from_dict(d["controller"])
        extra = {k: v for k, v in d.items() if k not in SECTIONS}
        cert = extra.get("certificate")
        if isinstance(cert, dict) and cert.get("gains") is not None and cert["gains"] != gains:
            raise ParamsError(
                "the gains differ from those the 'certificate' entry was issued for (edited "
                "after 'jaxflex tune --spread'?): tune again, or remove the 'certificate' entry "
                "to use these gains uncertified")
        p = cls(plant=plant, friction=friction, gains=gains, effects=dict(effects), extra=extra,
                controller=controller, links=links)
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
        """The docs/spec.md section 7 mapping."""
        d: dict[str, Any] = {"plant": self.plant, "friction": self.friction}
        if self.gains is not None:
            d["gains"] = self.gains
        if self.effects:
            d["effects"] = self.effects
        if self.controller is not None:
            d["controller"] = self.controller.to_dict()
        if self.links is not None:
            d["links"] = dict(self.links)
        d.update(self.extra)
        return d

    def to_lugre(self) -> LuGre:
        """The LuGre module of these parameters."""
        return LuGre.from_dict(self.friction)

    def to_plant(self, with_effects: bool = True) -> FlexibleJointPlant:
        """The plant of eq. 3 (M = diag(I), eq. 40, or the ``links`` model) with LuGre
        friction and, if known, the effects (``build_plant``); an unknown effect name raises
        ``ParamsError``."""
        return build_plant(self.plant, self.friction, self.effects if with_effects else None,
                           links=self.links)

    def to_gains(self) -> CascadeGains:
        """The controller gains; raises ``ParamsError`` if the file has none."""
        if self.gains is None:
            raise ParamsError("this parameter file has no 'gains' section")
        return CascadeGains(**self.gains)


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


def identification_problems(params: Params, rel_limit: float = 0.5) -> list[str]:
    """What makes an identification result unfit for downstream use, in words (empty if
    nothing): the fit did not converge (``extra["identification"]["converged"]`` false), or a
    parameter's relative standard error exceeds ``rel_limit`` without the result marking it
    ``"identified": false`` (files written before identify marked them)."""
    ident = params.extra.get("identification")
    if not isinstance(ident, dict):
        return []
    out = []
    if ident.get("converged") is False:
        out.append(f"the identification did not converge ({ident.get('reason', 'no reason given')})")
    marked = ident.get("parameters", {})
    stderr = params.extra.get("stderr", {})
    for name, se in stderr.items() if isinstance(stderr, dict) else ():
        if name in marked:
            continue
        try:
            val = (params.plant.get(name) or params.friction.get(name))
            rel = max(abs(float(s)) / max(abs(float(v)), 1e-300) for s, v in zip(se, val))
        except (TypeError, ValueError):
            continue
        if rel > rel_limit:
            out.append(f"{name} has a relative standard error of {100 * rel:.3g}% and is not "
                       "marked as unidentified")
    return out


_ACCEPT_UNCONVERGED: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "accept_unconverged", default=False)


@contextlib.contextmanager
def accepting_unconverged(accept: bool = True) -> Iterator[None]:
    """Within the block, ``load_params`` takes identification files that did not converge
    (as the command line's ``--accept-unconverged`` does for a whole command), wherever the
    library loads one (a sweep's spread, an export, a workflow given a path).

    **Arguments:**

    - ``accept``: take them (True) or refuse them (False) within the block.
    """
    token = _ACCEPT_UNCONVERGED.set(bool(accept))
    try:
        yield
    finally:
        _ACCEPT_UNCONVERGED.reset(token)


def load_params(path: str | os.PathLike, *, accept_unconverged: bool | None = None) -> Params:
    """Read and validate a parameter file (docs/spec.md section 7).

    A file written by ``identify`` that did not converge, or that holds parameters the data
    could not determine without marking them, is refused (``ParamsError`` naming why) unless
    ``accept_unconverged`` is true. ``None`` takes the setting of the enclosing
    ``accepting_unconverged`` block (refused outside one). A relative ``links.path`` (a
    URDF) is taken from the parameter file's folder."""
    d = read_json_file(path, ParamsError, "parameter file")
    links = d.get("links") if isinstance(d, dict) else None
    if isinstance(links, dict) and isinstance(links.get("path"), str):
        # a file the links section names (a URDF) is found beside the parameter file
        d["links"] = {**links, "path": str(Path(path).parent / links["path"])}
    try:
        params = Params.from_dict(d)
    except ParamsError as e:
        raise ParamsError(f"{path}: {e}") from None
    if accept_unconverged is None:
        accept_unconverged = _ACCEPT_UNCONVERGED.get()
    problems = [] if accept_unconverged else identification_problems(params)
    if problems:
        raise ParamsError(
            f"{path}: refused: {'; '.join(problems)}. Re-run the identification, or use the "
            "file anyway with --accept-unconverged"
        )
    note = model_limited_note(params)
    if note:
        warnings.warn(f"{path}: {note}", ModelLimitedWarning, stacklevel=2)
    return params


class ModelLimitedWarning(UserWarning):
    """A parameter file from a converged identification whose model the noise does not
    explain (the normal result on a real rig's log): used, with this one-line note."""


def model_limited_note(params: Params) -> str:
    """The one-line note on a model-limited identification (``identification.model``), or
    "" for an adequate one or a file without the verdict."""
    ident = params.extra.get("identification")
    model = ident.get("model") if isinstance(ident, dict) else None
    if not isinstance(model, dict) or model.get("verdict") != "model-limited":
        return ""
    ratio = model.get("cost_over_noise")
    size = f" (cost {ratio:.3g} x what the noise explains)" if isinstance(ratio, float) else ""
    return f"a model-limited identification{size}: the model leaves something unexplained"


def save_params(params: Params, path: str | os.PathLike) -> None:
    """Write a parameter file atomically (a failure never leaves a half-written file)."""
    params.validate()
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(params.to_dict(), indent=2) + "\n")
    os.replace(tmp, path)
