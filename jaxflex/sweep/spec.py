"""Spread files: which quantities are uncertain and how they are distributed (host side).

A spread file is one JSON document (SI units), for example::

    {"nominal": "paper",
     "trajectory": "sinusoid", "t_final": 2.0, "substeps": 10,
     "controller": {"compensation": true, "q2d_method": "model", "tau_max": 2.0},
     "sensing": "ideal",
     "samples": 1000, "seed": 0,
     "uncertain": {
        "plant.*":          {"dist": "uniform", "rel": 0.2},
        "friction.sigma0":  {"dist": "loguniform", "low": 50.0, "high": 200.0},
        "sensing.q1_noise": {"dist": "uniform", "low": 0.0, "high": 1e-4},
        "limits.tau_max":   {"dist": "normal", "rel_std": 0.05, "low": 1.0},
        "effects.torque_offset.offset": {"dist": "normal", "mean": 0.0, "std": 0.01}}}

``"identified": "ident.json"`` (or ``{"file": "ident.json", "inflate": 2.0}``) draws the
parameters an identification determined from its own posterior (``jaxflex.fit.posterior``:
the estimate and covariance in the fit's unconstrained coordinates, so every draw keeps
positivity and Fs >= Fc), jointly, with the correlations the data leave; ``inflate`` widens
the standard deviations (model error the residuals do not see). Quantities the log could not
see go under ``uncertain`` as usual (naming a posterior entry there is refused). Without a
``nominal`` entry the identified file is the nominal.

``nominal`` is ``"paper"``, a parameter-file path (docs/spec.md section 7, relative to the spread file)
or an inline parameter mapping; the controller always uses the nominal model and gains, the
true plant of each sample is drawn from the spread (robustness, not adaptation).

Names: ``plant.{I,J,K}``, ``friction.{Fc,Fs,vs,sigma0,sigma1,sigma2}``,
``sensing.{q1_noise,q2_noise,q1_resolution,q2_resolution}``, ``limits.tau_max`` and
``effects.<effect>.<parameter>`` for any registered effect (``jaxflex.core.effects.EFFECTS``);
``group.*`` applies one distribution to every name of a group. A name with n joints gives n
columns (``friction.Fc[0]``, ...), each drawn independently. ``name[j]`` targets one joint.

Distributions (``rel`` and ``rel_std`` are fractions of the nominal value):
``fixed`` (value), ``uniform`` (low, high | rel), ``normal`` (mean, std | rel_std; optional
truncation low/high), ``lognormal`` (median (default nominal), sigma of log),
``loguniform`` (low, high | factor: nominal/factor .. nominal*factor).

Bad specifications raise ``SpreadError`` (a ``ValueError``) naming the entry: unknown names or
distributions, missing or extra fields, empty ranges, and distributions whose support breaks a
physical constraint (e.g. a normal inertia that can go negative).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.core.controller import Q2D_METHODS
from jaxflex.fit.posterior import Posterior
from jaxflex.core.friction import LUGRE_NAMES
from jaxflex.io.params import PLANT_NAMES, Params, ParamsError, load_params, read_json_file
from jaxflex.io.presets import SENSING_PRESETS, TRAJECTORIES, paper_params, sensing_of
from jaxflex.core.sensing import SENSING_FIELDS
from jaxflex.sweep.distributions import (
    Distribution,
    SpreadError,
    parse_distribution,
    spread_number,
)
from jaxflex.core.validation import check_keys, did_you_mean

SENSING_NAMES: tuple[str, ...] = ("q1_noise", "q2_noise", "q1_resolution", "q2_resolution")
LIMIT_NAMES: tuple[str, ...] = ("tau_max",)
GROUPS: dict[str, tuple[str, ...]] = {
    "plant": PLANT_NAMES, "friction": LUGRE_NAMES, "sensing": SENSING_NAMES, "limits": LIMIT_NAMES,
}
# Lower bound of each quantity's physical range: (bound, strict). Effects are checked by their
# own classes at build time (concrete values only), so only their declared support is used.
_POSITIVE = {f"plant.{k}" for k in PLANT_NAMES} | {
    "friction.Fc", "friction.Fs", "friction.vs", "friction.sigma0", "limits.tau_max"
}
_NONNEG = {"friction.sigma1", "friction.sigma2"} | {f"sensing.{k}" for k in SENSING_NAMES}

@dataclasses.dataclass(frozen=True)
class Column:
    """One sampled scalar: ``group.name`` (effects: ``effects.<effect>.<param>``), joint index,
    its distribution, its label, and its nominal value (None where the nominal has none)."""

    name: str
    joint: int
    dist: Distribution
    label: str
    nominal: float | None = None

    @property
    def nominal_or_center(self) -> float:
        """The nominal value, or the distribution's centre where there is none."""
        return self.nominal if self.nominal is not None else self.dist.center_scale()[0]


@dataclasses.dataclass
class SweepSpec:
    """A validated spread: nominal parameters, task, and the sampled columns.

    Units SI. ``t_final`` [s] horizon per sample; ``dt`` [s] controller period; ``substeps``
    plant steps per sample; ``band_dt`` [s] spacing of the error-band time grid.
    """

    nominal: Params
    columns: list[Column]
    trajectory: str = "sinusoid"
    t_final: float = 2.0
    dt: float = 1e-3
    substeps: int = 10
    compensation: bool = True
    q2d_method: str = "model"
    tau_max: float = math.inf
    sensing: dict[str, Any] = dataclasses.field(default_factory=dict)
    effects: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    samples: int = 1000
    seed: int = 0
    band_dt: float = 0.01
    posterior: Posterior | None = None

    @property
    def n(self) -> int:
        """Number of joints."""
        return self.nominal.n

    @property
    def band_stride(self) -> int:
        """Controller samples between two points of the error-band time grid (``band_dt``
        rounded to a multiple of ``dt``, at least 1)."""
        return max(1, round(self.band_dt / self.dt))

    @property
    def labels(self) -> list[str]:
        """Column labels, in sample-vector order."""
        return [c.label for c in self.columns]

    def fs_fc_pairs(self) -> list[tuple[int, float, int, float]]:
        """Per joint where Fc or Fs is sampled: (column of Fc or -1, nominal Fc, column of Fs
        or -1, nominal Fs) [N m]; the sampler redraws a pair that breaks Fs >= Fc."""
        col = {(c.name, c.joint): i for i, c in enumerate(self.columns)}
        out = []
        for j in range(self.n):
            i_fc, i_fs = col.get(("friction.Fc", j), -1), col.get(("friction.Fs", j), -1)
            if i_fc >= 0 or i_fs >= 0:
                out.append((i_fc, float(self.nominal.friction["Fc"][j]), i_fs,
                            float(self.nominal.friction["Fs"][j])))
        return out

    def fs_below_fc_possible(self) -> bool:
        """Whether a draw can give Fs < Fc on some joint (both supports overlap): such draws
        are redrawn, so the sweep samples the spread conditioned on Fs >= Fc."""
        for i_fc, fc0, i_fs, fs0 in self.fs_fc_pairs():
            fc_hi = self.columns[i_fc].dist.support()[1] if i_fc >= 0 else fc0
            fs_lo = self.columns[i_fs].dist.support()[0] if i_fs >= 0 else fs0
            if fs_lo < fc_hi:
                return True
        return False

    def with_(self, **changes: Any) -> SweepSpec:
        """A copy with some fields replaced (e.g. ``compensation=False``)."""
        return dataclasses.replace(self, **changes)

    def cache_key(self) -> str:
        """The spec's content without the sample count (the only field a compiled per-sample
        function does not depend on), as a string: the key of compiled-function caches."""
        d = self.to_dict()
        d.pop("samples")
        return json.dumps(d, sort_keys=True, default=str)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able description (for result files)."""
        return {
            "nominal": self.nominal.to_dict(), "trajectory": self.trajectory,
            "t_final": self.t_final, "dt": self.dt, "substeps": self.substeps,
            "compensation": self.compensation, "q2d_method": self.q2d_method,
            "tau_max": self.tau_max if math.isfinite(self.tau_max) else "inf",
            "sensing": self.sensing, "effects": self.effects, "samples": self.samples,
            "seed": self.seed, "band_dt": self.band_dt,
            "columns": [dataclasses.asdict(c) for c in self.columns],
            **({"posterior": self.posterior.to_dict()} if self.posterior is not None else {}),
        }


_TOP_KEYS = {
    "nominal", "identified", "trajectory", "t_final", "dt", "substeps", "controller", "sensing", "samples",
    "seed", "uncertain", "band_dt",
}


def _nominal(d: Any, base: Path | None) -> Params:
    if d is None or d == "paper":
        return paper_params()
    try:
        if isinstance(d, str):
            p = Path(d)
            if not p.is_absolute() and base is not None:
                p = base / p
            return load_params(p)
        if isinstance(d, dict):
            return Params.from_dict(d)
    except ParamsError as e:
        raise SpreadError(f"nominal: {e}") from None
    raise SpreadError(f"nominal: expected 'paper', a parameter-file path or an object, got {d!r}")


def _identified(d: Any, base: Path | None) -> tuple[Params | None, Posterior | None]:
    """The ``identified`` entry: a parameter-file path written by ``jaxflex identify``, or
    {"file": path, "inflate": factor on its standard deviations (default 1)}."""
    if d is None:
        return None, None
    if isinstance(d, str):
        d = {"file": d}
    if not isinstance(d, dict) or not isinstance(d.get("file"), str):
        raise SpreadError("identified: expected a parameter-file path written by 'jaxflex "
                          f"identify', or {{\"file\": path, \"inflate\": 1.0}}, got {d!r}")
    check_keys(d, ("file", "inflate"), where="identified: ", what="field", error=SpreadError)
    inflate = spread_number("identified", "inflate", d.get("inflate", 1.0))
    params = _nominal(d["file"], base)
    try:
        return params, Posterior.from_params(params, inflate=inflate)
    except ValueError as e:
        raise SpreadError(f"identified: {d['file']}: {e}") from None


def _posterior_columns(post: Posterior, params: Params, taken: set[tuple[str, int]]) -> list[Column]:
    """One column per entry of the identification's posterior (drawn jointly); an entry also
    given under ``uncertain`` is refused (the data already say how uncertain it is)."""
    lo, hi = post.box(1 - 1e-9)
    estimate = {k: np.asarray(v) for k, v in post.physical(post.mean).items()}
    cols = []
    for i, lab in enumerate(post.labels):
        name, j = lab[:-1].split("[")
        j = int(j)
        if name in PLANT_NAMES:
            full = f"plant.{name}"
        elif name in LUGRE_NAMES:
            full = f"friction.{name}"
        else:
            full = "effects." + name
        if (full, j) in taken:
            raise SpreadError(
                f"uncertain: {full} is drawn from the identification's posterior ('identified'); "
                "remove it from 'uncertain' (or identify without it)")
        est = float(estimate[name][j])
        cols.append(Column(name=full, joint=j, label=full if params.n == 1 else f"{full}[{j}]",
                           dist=Distribution("posterior", float(i), est, float(lo[name][j]),
                                             float(hi[name][j])), nominal=est))
    return cols


def _sensing(d: Any) -> dict[str, Any]:
    if d is None:
        d = "ideal"
    if isinstance(d, str):
        if d not in SENSING_PRESETS:
            raise SpreadError(f"sensing: preset must be one of {SENSING_PRESETS}, got {d!r}")
    elif isinstance(d, dict):
        bad = set(d) - set(SENSING_FIELDS)
        if bad:
            raise SpreadError(f"sensing: unknown field(s) {sorted(bad)}; known: {sorted(SENSING_FIELDS)}")
    else:
        raise SpreadError(f"sensing: expected a preset name {SENSING_PRESETS} or an object, got {d!r}")
    try:
        s = sensing_of(d)
    except (TypeError, ValueError) as e:
        raise SpreadError(f"sensing: {e}") from None
    out = {k: float(np.asarray(getattr(s, k)).reshape(-1)[0]) for k in SENSING_NAMES}
    out.update(velocity=s.velocity, dac_bits=int(s.dac_bits), dac_range=float(np.asarray(s.dac_range).reshape(-1)[0]))
    return out


def _check_support(where: str, name: str, dist: Distribution) -> None:
    lo, _hi = dist.support()
    if name in _POSITIVE and not lo > 0 and not (dist.kind == "lognormal"):
        raise SpreadError(
            f"{where}: {name} must stay > 0 but this distribution can give {lo}; "
            "use bounds > 0 (uniform/loguniform), a truncated normal with low > 0, or lognormal"
        )
    if name in _NONNEG and lo < 0:
        raise SpreadError(
            f"{where}: {name} must stay >= 0 but this distribution can give {lo}; "
            "use bounds >= 0 or a truncated normal with low >= 0"
        )


def _split_index(key: str) -> tuple[str, int | None]:
    if key.endswith("]") and "[" in key:
        base, idx = key[:-1].split("[", 1)
        try:
            return base, int(idx)
        except ValueError:
            raise SpreadError(f"uncertain.{key}: joint index must be an integer") from None
    return key, None


def parse_spread(d: Any, base: Path | None = None) -> SweepSpec:
    """Validate a spread mapping (see the module docstring); raises ``SpreadError``."""
    from jaxflex.core.effects import EFFECTS

    if not isinstance(d, dict):
        raise SpreadError(f"a spread must be a JSON object, got {type(d).__name__}")
    check_keys(d, sorted(_TOP_KEYS), what="top-level key", error=SpreadError)
    identified, posterior = _identified(d.get("identified"), base)
    nominal = identified if "nominal" not in d and identified is not None else _nominal(
        d.get("nominal"), base)
    n = nominal.n
    traj = d.get("trajectory", "sinusoid")
    if traj not in TRAJECTORIES:
        raise SpreadError(f"trajectory must be one of {TRAJECTORIES}, got {traj!r}")
    if nominal.gains is None:
        raise SpreadError("nominal: the parameters need a 'gains' section for the controller")
    ctrl = d.get("controller", {}) or {}
    if not isinstance(ctrl, dict):
        raise SpreadError("controller: expected an object")
    check_keys(ctrl, ("compensation", "q2d_method", "tau_max"), where="controller: ",
               what="field", error=SpreadError)
    if ctrl.get("q2d_method", "model") not in Q2D_METHODS:
        raise SpreadError(f"controller.q2d_method must be one of {Q2D_METHODS}, got {ctrl['q2d_method']!r}")
    if not isinstance(ctrl.get("compensation", True), bool):
        raise SpreadError("controller.compensation must be true or false")
    tau_max = ctrl.get("tau_max", math.inf)
    if tau_max in (None, "inf"):
        tau_max = math.inf
    if isinstance(tau_max, bool) or not isinstance(tau_max, (int, float)) or not tau_max > 0:
        raise SpreadError(f"controller.tau_max must be a number > 0 (or 'inf'), got {tau_max!r}")

    def pos(key, default, integer=False):
        v = d.get(key, default)
        ok = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok or not v > 0 or (not integer and not math.isfinite(v)):
            kind = "a positive integer" if integer else "a finite number > 0"
            raise SpreadError(f"{key} must be {kind}, got {v!r}")
        return v

    t_final, dt = float(pos("t_final", 2.0)), float(pos("dt", 1e-3))
    band_dt = float(pos("band_dt", 0.01))
    if t_final < dt:
        raise SpreadError(f"t_final ({t_final} s) must be at least one controller period ({dt} s)")
    seed = d.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SpreadError(f"seed must be an integer >= 0, got {seed!r}")

    nominal_vals = {"plant": nominal.plant, "friction": nominal.friction,
                    "sensing": {k: [v] * n for k, v in _sensing(d.get("sensing")).items() if k in SENSING_NAMES},
                    "limits": {"tau_max": [tau_max] * n}}
    sensing = _sensing(d.get("sensing"))
    unc = d.get("uncertain", {}) or {}
    if not isinstance(unc, dict):
        raise SpreadError("uncertain: expected an object mapping names to distributions")
    effects: dict[str, dict[str, Any]] = {k: dict(v) for k, v in nominal.effects.items()}
    entries: dict[tuple[str, int], tuple[str, Any]] = {}
    for key, dist in unc.items():
        base_name, joint = _split_index(key)
        parts = base_name.split(".")
        if parts[0] == "effects":
            if len(parts) != 3:
                raise SpreadError(f"uncertain.{key}: effect entries are named effects.<effect>.<parameter>")
            if parts[1] not in EFFECTS:
                raise SpreadError(f"uncertain.{key}: unknown effect {parts[1]!r}"
                                  f"{did_you_mean(parts[1], sorted(EFFECTS))}; known: {sorted(EFFECTS)}")
            names = [base_name]
        elif parts[0] in GROUPS and len(parts) == 2:
            if parts[1] == "*":
                names = [f"{parts[0]}.{k}" for k in GROUPS[parts[0]]]
            elif parts[1] in GROUPS[parts[0]]:
                names = [base_name]
            else:
                raise SpreadError(
                    f"uncertain.{key}: unknown name {parts[1]!r} in group {parts[0]!r}"
                    f"{did_you_mean(parts[1], GROUPS[parts[0]])}; known: {list(GROUPS[parts[0]])}"
                )
        else:
            raise SpreadError(
                f"uncertain.{key}: names are <group>.<name> with group in {sorted(GROUPS)} "
                f"or effects.<effect>.<parameter>{did_you_mean(parts[0], sorted(GROUPS) + ['effects'])}"
            )
        if parts[0] == "limits" and not math.isfinite(tau_max) and isinstance(dist, dict) and (
            {"rel", "rel_std", "factor"} & set(dist) or (dist.get("dist") == "normal" and "mean" not in dist)
        ):
            raise SpreadError(f"uncertain.{key}: controller.tau_max is infinite; give absolute bounds")
        joints = range(n) if joint is None else [joint]
        if joint is not None and not 0 <= joint < n:
            raise SpreadError(f"uncertain.{key}: joint index {joint} out of range for {n} joint(s)")
        for nm in names:
            for j in joints:
                entries[(nm, j)] = (key, dist)  # later, more specific entries override
    columns: list[Column] = []
    if posterior is not None:
        columns = _posterior_columns(posterior, identified, set(entries))
    for (nm, j), (key, dist) in entries.items():
        parts = nm.split(".")
        if parts[0] == "effects":
            nomv = effects.get(parts[1], {}).get(parts[2])
            nom = None if nomv is None else float(np.broadcast_to(np.asarray(nomv, float), (n,))[j])
        else:
            nom = float(nominal_vals[parts[0]][parts[1]][j])
            nom = nom if math.isfinite(nom) else None
        dd = parse_distribution(f"uncertain.{key}", dist, nom)
        _check_support(f"uncertain.{key}", nm, dd)
        label = nm if n == 1 else f"{nm}[{j}]"
        columns.append(Column(name=nm, joint=j, dist=dd, label=label, nominal=nom))
        if parts[0] == "effects":
            effects.setdefault(parts[1], {})
    # every sampled effect must be constructible: its other parameters come from the nominal
    for name, kw in effects.items():
        cls = EFFECTS.get(name)
        if cls is None:
            raise SpreadError(f"nominal effect {name!r} is not a known effect; known: {sorted(EFFECTS)}")
        sampled = {c.name.split(".")[2] for c in columns if c.name.startswith(f"effects.{name}.")}
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = (set(kw) | sampled) - fields
        if unknown:
            raise SpreadError(f"effect {name!r} has no parameter(s) {sorted(unknown)}; it has {sorted(fields)}")
        try:
            cls(**{**kw, **{k: 1.0 for k in sampled}})
        except TypeError as e:
            raise SpreadError(f"effect {name!r}: {e}") from None
        except ValueError:
            pass  # value checks happen per sample; only the structure is checked here
    samples = pos("samples", 1000, integer=True)
    for j in range(n):  # LuGre needs Fs >= Fc (docs/spec.md section 2)
        sup = {}
        for nm in ("Fc", "Fs"):
            c = next((c for c in columns if c.name == f"friction.{nm}" and c.joint == j), None)
            v = float(nominal.friction[nm][j])
            sup[nm] = c.dist.support() if c is not None else (v, v)
        if sup["Fs"][1] < sup["Fc"][0] or (sup["Fs"][1] == sup["Fc"][0] and sup["Fs"] != sup["Fc"]):
            where = "" if n == 1 else f"[{j}]"
            raise SpreadError(
                f"friction.Fs{where} is always drawn below friction.Fc{where} (Fs up to "
                f"{sup['Fs'][1]:g}, Fc from {sup['Fc'][0]:g} N m); LuGre needs Fs >= Fc: give "
                "Fs a range above Fc's")
    return SweepSpec(
        nominal=nominal, columns=columns, trajectory=traj, t_final=t_final, dt=dt,
        substeps=pos("substeps", 10, integer=True), compensation=ctrl.get("compensation", True),
        q2d_method=ctrl.get("q2d_method", "model"), tau_max=float(tau_max), sensing=sensing,
        effects=effects, samples=samples, seed=seed, band_dt=band_dt, posterior=posterior,
    )


def load_spread(path: str | os.PathLike) -> SweepSpec:
    """Read and validate a spread file; a relative ``nominal`` path is read beside it."""
    path = Path(path)
    d = read_json_file(path, SpreadError, "spread file")
    try:
        return parse_spread(d, base=path.parent)
    except SpreadError as e:
        raise SpreadError(f"{path}: {e}") from None


def uniform_spread(rel: float = 0.2, groups: tuple[str, ...] = ("plant", "friction"), **kw: Any) -> dict[str, Any]:
    """A spread mapping with every name of ``groups`` uniform within +-rel of nominal."""
    d: dict[str, Any] = {"uncertain": {f"{g}.*": {"dist": "uniform", "rel": rel} for g in groups}}
    d.update(kw)
    return d
