"""The ``--map`` language (docs/spec.md section 6.4): each log column as an expression of a
file's variables (struct paths, selections, products and quotients, a unit suffix to SI)."""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.io.logs.log import COLUMN_UNITS, LOG_COLUMNS, LogError

#: Unit suffixes of a mapping expression (``q1=enc_deg:deg``): factor to SI.
UNIT_FACTORS: dict[str, float] = {
    "rad": 1.0, "deg": np.pi / 180.0, "s": 1.0, "ms": 1e-3, "us": 1e-6, "m": 1.0,
    "mm": 1e-3, "rad/s": 1.0, "deg/s": np.pi / 180.0, "rpm": 2.0 * np.pi / 60.0,
    "Nm": 1.0, "N": 1.0, "mNm": 1e-3,
}
# Units guessed from a variable's name suffix (inspect); the log columns have their own. The
# longest matching suffix wins, so ``_deg_per_s`` is a speed, not a time.
_NAME_UNITS: tuple[tuple[str, str], ...] = (
    ("_deg", "deg"), ("_rad", "rad"), ("_nm", "N m"), ("_Nm", "N m"), ("_mNm", "mN m"),
    ("_ms", "ms"), ("_mm", "mm"), ("_s", "s"), ("_m", "m"), ("_V", "V"), ("_A", "A"),
    ("_rpm", "rpm"), ("_deg_per_s", "deg/s"), ("_rad_per_s", "rad/s"), ("_degps", "deg/s"),
    ("_radps", "rad/s"), ("_m_per_s", "m/s"),
    ("_mm_per_s", "mm/s"), ("_deg_per_s2", "deg/s^2"), ("_rad_per_s2", "rad/s^2"),
    ("_m_per_s2", "m/s^2"), ("_per_s", "1/s"),
)


def name_unit(name: str) -> str:
    """The unit a variable's name tells (a log column's, or the longest known suffix of
    ``_NAME_UNITS``: ``act_vel_deg_per_s`` -> ``deg/s``); "" when it tells none."""
    leaf = name.rsplit(".", 1)[-1]
    if leaf in COLUMN_UNITS:
        return COLUMN_UNITS[leaf]
    hits = [(len(suf), u) for suf, u in _NAME_UNITS if leaf.endswith(suf)]
    return max(hits)[1] if hits else ""
#: A time column advancing by this much or more per sample [s] is taken for milliseconds.
MS_SUSPECT_PERIOD: float = 0.5


def flatten_variables(raw: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Struct fields as dotted paths (``rec.time_cont``) -> array; arrays stay as they are."""
    out: dict[str, Any] = {}
    for k, v in raw.items():
        if isinstance(v, dict):
            out.update(flatten_variables(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def describe_variables(raw: Mapping[str, Any], limit: int = 40) -> str:
    """'name (shape), ...' of a file's variables, struct fields as paths."""
    items = [f"{k} {tuple(np.shape(v))}" for k, v in flatten_variables(raw).items()]
    more = f", ... ({len(items) - limit} more)" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more if items else "none"


def _split_top(text: str, seps: str) -> list[tuple[str, str]]:
    """Split at separator characters outside brackets: [(separator before, piece), ...]."""
    out, depth, cur, sep = [], 0, "", ""
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth -= 1
        if ch in seps and depth == 0:
            out.append((sep, cur))
            cur, sep = "", ch
        else:
            cur += ch
    out.append((sep, cur))
    return out


def split_unit(expr: str) -> tuple[str, str | None]:
    """``"x[:,1]:deg"`` -> (``"x[:,1]"``, ``"deg"``); no suffix -> (expr, None)."""
    parts = _split_top(expr, ":")
    if len(parts) > 1:
        unit = parts[-1][1].strip()
        if unit in UNIT_FACTORS:
            return expr[: len(expr) - len(parts[-1][1]) - 1], unit
        if re.fullmatch(r"[A-Za-z/]+", unit):
            raise LogError(f"unknown unit suffix ':{unit}' in '{expr}'; known: "
                           f"{sorted(UNIT_FACTORS)}")
    return expr, None


_TERM = re.compile(r"^(?P<neg>-?)(?P<path>[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*)"
                   r"(?:\[(?P<idx>[^\]]*)\])?$")


def _index(spec: str, term: str) -> tuple:
    out: list[Any] = []
    for part in (p.strip() for p in spec.split(",")):
        try:
            if ":" in part:
                out.append(slice(*[int(s) if s.strip() else None for s in part.split(":")]))
            else:
                out.append(int(part))
        except ValueError:
            raise LogError(f"mapping term '{term}': bad selection [{spec}] (use integers and "
                           "slices, e.g. [0], [:,1], [0:3])") from None
    return tuple(out)


def _lookup(term: str, raw: Mapping[str, Any], where: str) -> np.ndarray:
    """One factor of a mapping expression: a variable, a struct path, with a selection."""
    if term in raw and not isinstance(raw[term], dict):  # e.g. a CSV header "tau[0]"
        try:
            return np.asarray(raw[term], dtype=float)
        except (TypeError, ValueError):
            raise LogError(f"{where}variable '{term}' is not numeric") from None
    m = _TERM.match(term)
    if not m:
        raise LogError(f"{where}mapping term '{term}' is neither a number nor a variable "
                       "(name, struct path a.b, optional selection [i] or [:,j])")
    node: Any = raw
    walked = ""
    for name in m.group("path").split("."):
        if not isinstance(node, Mapping):
            raise LogError(f"{where}mapping term '{term}': '{walked}' is an array, not a struct")
        if name not in node:
            what = f"struct '{walked}' has no field '{name}' (fields: {sorted(node)})" if walked \
                else (f"mapping refers to variable '{name}' which is not in the file "
                      f"(variables: {describe_variables(raw)})")
            raise LogError(f"{where}{what}")
        node = node[name]
        walked = f"{walked}.{name}" if walked else name
    if isinstance(node, Mapping):
        fields = sorted(node)
        raise LogError(f"{where}variable '{walked}' is a struct with fields {fields}; name one, "
                       f"e.g. '{walked}.{fields[0] if fields else 'field'}'")
    a = np.asarray(node)
    if a.dtype == object:
        raise LogError(f"{where}variable '{walked}' holds MATLAB cells or objects, not numbers")
    if m.group("idx") is not None:
        idx = _index(m.group("idx"), term)
        try:
            a = a[idx]
        except IndexError:
            raise LogError(f"{where}mapping term '{term}': selection [{m.group('idx')}] is out "
                           f"of range for shape {a.shape}") from None
    try:
        a = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise LogError(f"{where}variable '{walked}' is not numeric") from None
    return -a if m.group("neg") else a


def evaluate(expr: str, raw: Mapping[str, Any], where: str = "") -> np.ndarray:
    """Evaluate a mapping expression (docs/spec.md section 6.4) on a file's variables.

    ``expr``: factors joined by ``*`` or ``/``; a factor is a number or a variable with an
    optional struct path and selection (``para.u[0]``, ``rec.pos[:,1]``); an optional unit
    suffix (``:deg``, ``:ms``, ... ``UNIT_FACTORS``) converts the result to SI. A single-value
    factor acts as a scalar. Returns the array; raises ``LogError`` naming the problem.
    """
    body, unit = split_unit(expr.strip())
    out: Any = None
    for sep, term in _split_top(body, "*/"):
        term = term.strip()
        if not term:
            raise LogError(f"{where}mapping expression '{expr}' has an empty factor")
        try:
            val: Any = float(term)
        except ValueError:
            val = _lookup(term, raw, where)
            val = val.reshape(()) if val.size == 1 else val
        try:
            out = val if out is None else (out / val if sep == "/" else out * val)
        except ValueError:
            raise LogError(f"{where}mapping expression '{expr}': factors of shapes "
                           f"{np.shape(out)} and {np.shape(val)} do not multiply") from None
    a = np.asarray(out, dtype=float)
    if unit is not None:
        a = a * UNIT_FACTORS[unit]
    return a.reshape(()) if a.size == 1 else a


def _parse_items(text: str, source: str) -> dict[str, str]:
    out = {}
    for _, item in _split_top(text.replace("\n", ","), ","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise LogError(f"{source}mapping item {item!r} must look like column=variable")
        k, v = (s.strip() for s in item.split("=", 1))
        if k not in LOG_COLUMNS:
            raise LogError(f"{source}mapping: unknown log column '{k}'; known columns: "
                           f"{list(LOG_COLUMNS)}")
        if k in out:
            raise LogError(f"{source}mapping: column '{k}' mapped twice")
        out[k] = v
    return out


def parse_mapping(text: str | None) -> dict[str, str] | None:
    """Parse a CLI mapping into a dict (None stays None).

    ``text``: comma-separated ``column=expression`` items (``"tau=gtau*vir,q1=qm,q2=qm"``;
    commas inside ``[...]`` belong to the selection), or ``@FILE``: a map file with one item
    per line (or comma-separated), ``#`` starting a comment. Raises ``LogError`` for an item
    without ``=``, an unknown column, a column mapped twice, or a missing map file.
    """
    if text is None or not text.strip():
        return None
    text = text.strip()
    if text.startswith("@"):
        path = Path(text[1:])
        if not path.exists():
            raise LogError(f"map file not found: {path}")
        lines = [ln.split("#", 1)[0] for ln in path.read_text().splitlines()]
        return _parse_items("\n".join(lines), f"{path}: ")
    return _parse_items(text, "")


#: SI unit of a log column converted from each unit suffix of a mapping (``q1=x:mm`` -> m).
_SI_OF_SUFFIX = {"m": "m", "mm": "m", "rad": "rad", "deg": "rad", "N": "N", "Nm": "N m",
                 "mNm": "N m"}


def axis_units(mapping: Mapping[str, str] | None, linear: bool = False) -> tuple[str, str]:
    """(position unit, torque unit) of a log's axis for labels and messages: ``("m", "N")``
    for a prismatic axis (``linear``, or a mapping that converts q1 or q2 from ``:m`` or
    ``:mm``, or tau from ``:N``), ``("rad", "N m")`` otherwise."""
    if not linear and mapping:
        units = {c: _SI_OF_SUFFIX.get(split_unit(mapping[c])[1] or "", "")
                 for c in ("q1", "q2", "tau") if c in mapping}
        linear = "m" in (units.get("q1"), units.get("q2")) or units.get("tau") == "N"
    return ("m", "N") if linear else ("rad", "N m")


def map_option(mapping: Mapping[str, str] | None, **changes: str) -> str:
    """The ``--map`` option, quoted for a shell, of ``mapping`` with the items ``changes``
    set: a message's suggestion keeps every item the user gave, so it runs as printed."""
    import shlex

    items = {**(mapping or {}), **changes}
    text = ",".join(f"{k}={v}" for k, v in items.items())
    return "--map " + (f"'{text}'" if "'" not in text else shlex.quote(text))
