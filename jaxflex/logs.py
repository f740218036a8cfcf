"""Logs of measured (or simulated) runs (docs/spec.md section 6): load, validate, save.

A log is a table sampled at a fixed period with columns (SI units, link-referred)

    t [s], tau [N m] applied motor torque, q1 [rad] link angle, q2 [rad] rotor angle,
    optional q1d [rad] reference, F [N m] measured friction, v [rad/s] velocity.

For n joints a column ``c`` is stored as ``c[0]``, ..., ``c[n-1]`` in a CSV header (a single
joint may use the bare name). Formats: CSV with a header row, ``.npz`` and MATLAB ``.mat``
(v5/v7, read with scipy; structs become nested dicts, row vectors are accepted). A
``mapping`` builds each log column from the file's variables (docs/spec.md section 6.4): struct
paths (``rec.time_cont``), selections (``x[0]``, ``x[:,1]``), products and quotients with
numbers or factors from the file (``para.u[0]*rec.act_torque_abs_nm[0]``, ``gtau*vir``) and a
unit suffix converting to SI (``:deg``, ``:ms``); ``@FILE`` reads a map file.
``inspect_file`` lists a file's variables for writing a mapping.

Everything here is host-side numpy; a bad log raises ``LogError`` (a ``ValueError``) naming
the problem before any JAX code runs.
"""

from __future__ import annotations

import dataclasses
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.errors import InputError

LOG_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2", "q1d", "F", "v")
REQUIRED_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2")
_UNITS = {"t": "s", "tau": "N m", "q1": "rad", "q2": "rad", "q1d": "rad", "F": "N m",
          "v": "rad/s"}


class LogError(InputError):
    """A log that does not follow docs/spec.md section 6 (the message names the problem)."""


@dataclasses.dataclass(frozen=True)
class Log:
    """A validated log: ``t`` (N,) [s] and the other columns (N, n) float64 arrays or None.

    Build with ``Log.from_arrays`` (validates) or ``load_log``. ``dt`` is the sample period.
    """

    t: np.ndarray
    tau: np.ndarray | None = None
    q1: np.ndarray | None = None
    q2: np.ndarray | None = None
    q1d: np.ndarray | None = None
    F: np.ndarray | None = None
    v: np.ndarray | None = None
    source: str = ""

    @property
    def N(self) -> int:
        """Number of samples."""
        return int(self.t.shape[0])

    @property
    def n(self) -> int:
        """Number of joints."""
        for c in LOG_COLUMNS[1:]:
            a = getattr(self, c)
            if a is not None:
                return int(a.shape[1])
        return 1

    @property
    def dt(self) -> float:
        """Sample period [s] (mean spacing)."""
        return float((self.t[-1] - self.t[0]) / (self.N - 1))

    def columns(self) -> tuple[str, ...]:
        """Names of the columns present."""
        return tuple(c for c in LOG_COLUMNS if getattr(self, c) is not None)

    def joint(self, j: int) -> Log:
        """The one-joint log of joint ``j`` (0-based): every (N, n) column cut to (N, 1)."""
        if not 0 <= j < self.n:
            raise LogError(f"joint {j} out of range for a log of {self.n} joint(s)")
        kw = {c: (None if getattr(self, c) is None else getattr(self, c)[:, j:j + 1])
              for c in LOG_COLUMNS[1:]}
        return dataclasses.replace(self, **kw, source=f"{self.source} joint {j}")

    def slice(self, start: int = 0, stop: int | None = None) -> Log:
        """Samples ``start:stop`` as a new log (time kept, not shifted)."""
        kw = {c: (None if getattr(self, c) is None else getattr(self, c)[start:stop])
              for c in LOG_COLUMNS}
        return dataclasses.replace(self, **kw)

    @classmethod
    def from_arrays(
        cls, *, required: Sequence[str] = REQUIRED_COLUMNS, time_rtol: float = 1e-3,
        source: str = "", **columns: Any,
    ) -> Log:
        """Validate columns and build a log; raises ``LogError`` naming the problem.

        Checks: every ``required`` column present; no unknown column; each column numeric,
        finite (no NaN/inf), 1-D (N,) or 2-D (N, n) with one common N and n; at least 2
        samples; time strictly increasing and uniform within ``time_rtol`` of the period.
        """
        where = f"{source}: " if source else ""
        unknown = sorted(set(columns) - set(LOG_COLUMNS))
        if unknown:
            raise LogError(f"{where}unknown column(s) {unknown}; known columns: {list(LOG_COLUMNS)}")
        cols = {k: v for k, v in columns.items() if v is not None}
        missing = [c for c in required if c not in cols]
        if missing:
            raise LogError(
                f"{where}missing column(s) {missing} (required: {list(required)}; present: "
                f"{sorted(cols)})"
            )
        if "t" not in cols:
            raise LogError(f"{where}missing column(s) ['t'] (time is always required)")
        arrs: dict[str, np.ndarray] = {}
        for k, v in cols.items():
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise LogError(f"{where}column {k} is not numeric") from None
            if k == "t":
                a = a.reshape(-1) if a.ndim == 2 and 1 in a.shape else a
                if a.ndim != 1:
                    raise LogError(f"{where}column t must be 1-D, got shape {a.shape}")
            else:
                if a.ndim == 1:
                    a = a[:, None]
                if a.ndim != 2:
                    raise LogError(f"{where}column {k} must be (N,) or (N, n), got shape {a.shape}")
            bad = ~np.isfinite(a)
            if bad.any():
                idx = int(np.argwhere(bad)[0][0])
                kind = "NaN" if np.isnan(a).any() else "inf"
                raise LogError(
                    f"{where}column {k} has {int(bad.sum())} non-finite value(s) ({kind}), "
                    f"first at sample {idx}"
                )
            arrs[k] = a
        lengths = {k: a.shape[0] for k, a in arrs.items()}
        if len(set(lengths.values())) > 1:
            raise LogError(f"{where}columns have mismatched lengths {lengths}")
        widths = {k: a.shape[1] for k, a in arrs.items() if k != "t"}
        if len(set(widths.values())) > 1:
            raise LogError(f"{where}columns have mismatched joint counts {widths}")
        t = arrs["t"]
        if t.shape[0] < 2:
            raise LogError(f"{where}a log needs at least 2 samples, got {t.shape[0]}")
        d = np.diff(t)
        if np.any(d <= 0):
            i = int(np.argmax(d <= 0))
            raise LogError(
                f"{where}time is not strictly increasing: t[{i}] = {float(t[i])!r} s, "
                f"t[{i + 1}] = {float(t[i + 1])!r} s"
            )
        dt = (t[-1] - t[0]) / (t.shape[0] - 1)
        dev = np.abs(d - dt)
        if np.any(dev > time_rtol * dt):
            i = int(np.argmax(dev))
            raise LogError(
                f"{where}time is not uniformly sampled: step {i} is {float(d[i])!r} s but the "
                f"mean period is {float(dt)!r} s (tolerance {time_rtol:g} relative)"
            )
        return cls(source=source, **arrs)


def _csv_header(log: Log) -> tuple[list[str], np.ndarray]:
    names, blocks = ["t"], [log.t[:, None]]
    for c in LOG_COLUMNS[1:]:
        a = getattr(log, c)
        if a is None:
            continue
        names += [c] if a.shape[1] == 1 else [f"{c}[{i}]" for i in range(a.shape[1])]
        blocks.append(a)
    return names, np.hstack(blocks)


_INDEXED = re.compile(r"^([A-Za-z0-9_]+)\[(\d+)\]$")


def _gather_indexed(table: Mapping[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
    """Join ``c[0]``, ``c[1]``, ... columns into one (N, n) array per name."""
    out: dict[str, Any] = {}
    parts: dict[str, dict[int, np.ndarray]] = {}
    for name, col in table.items():
        m = _INDEXED.match(name)
        if m:
            parts.setdefault(m.group(1), {})[int(m.group(2))] = col
        else:
            out[name] = col
    for name, p in parts.items():
        idx = sorted(p)
        if idx != list(range(len(idx))):
            raise LogError(f"{where}column {name}: joint indices must be 0..n-1, got {idx}")
        if name in out:
            raise LogError(f"{where}column {name} given both bare and indexed")
        out[name] = np.stack([np.asarray(p[i], dtype=float).reshape(-1) for i in idx], axis=1)
    return out


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as f:
        header = f.readline().strip()
    if not header:
        raise LogError(f"{path}: empty file")
    if "," not in header:
        for sep, word in ((";", "semicolons"), ("\t", "tabs")):
            if sep in header:
                raise LogError(
                    f"{path}: the columns are separated by {word} ({sep!r}); jaxflex reads "
                    "comma-separated CSV with '.' as the decimal point: save the file with ',' "
                    "between columns (or as .npz)")
    names = [h.strip() for h in header.split(",")]
    if any(re.fullmatch(r"[-+0-9.eE]+", n) for n in names):
        raise LogError(f"{path}: the first row must be a header of column names, got {header!r}")
    if len(set(names)) != len(names):
        raise LogError(f"{path}: duplicate column names in header {names}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy's "Empty input file"
            data = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float,
                                 invalid_raise=True, ndmin=2)
    except ValueError as e:
        raise LogError(f"{path}: rows of unequal length or bad values ({e})") from None
    if data.size == 0:
        raise LogError(f"{path}: no data rows (the file has only a header, with columns "
                       f"{names})")
    if data.shape[1] != len(names):
        raise LogError(f"{path}: header has {len(names)} columns, rows have {data.shape[1]}")
    return {n: data[:, i] for i, n in enumerate(names)}


def _struct_to_dict(v: Any) -> Any:
    """A MATLAB struct (scipy ``mat_struct``) as a nested dict; arrays unchanged."""
    if hasattr(v, "_fieldnames"):
        return {f: _struct_to_dict(getattr(v, f)) for f in v._fieldnames}
    return v


def _read_mat(path: Path) -> dict[str, Any]:
    import scipy.io

    try:
        # squeeze_me: row vectors (1, N) (what MATLAB and scipy save for 1-D arrays) and
        # column vectors (N, 1) both become (N,); (1, 1) scalars become 0-d
        d = scipy.io.loadmat(path, squeeze_me=True, struct_as_record=False)
    except NotImplementedError:
        raise LogError(
            f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7 or export CSV"
        ) from None
    except Exception as e:  # noqa: BLE001 - scipy raises many types for a bad file
        raise LogError(f"{path}: not a readable MATLAB file ({e})") from None
    return {k: _struct_to_dict(v) for k, v in d.items() if not k.startswith("__")}


def read_variables(path: str | os.PathLike) -> dict[str, Any]:
    """The variables of a CSV, ``.npz`` or ``.mat`` file as stored: name -> numpy array, or
    a nested dict for a MATLAB struct (field -> array or dict). Raises ``LogError`` for an
    unreadable file or unknown format and ``FileNotFoundError`` for a missing one."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"log file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return _read_csv(path)
    if suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except (ValueError, OSError) as e:
            raise LogError(f"{path}: not a readable .npz file ({e})") from None
    if suffix == ".mat":
        return _read_mat(path)
    raise LogError(f"{path}: unknown log format '{suffix}' (use .csv, .npz or .mat)")


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
    if leaf in _UNITS:
        return _UNITS[leaf]
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


def _describe(raw: Mapping[str, Any], limit: int = 40) -> str:
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


def _split_unit(expr: str) -> tuple[str, str | None]:
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
                      f"(variables: {_describe(raw)})")
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
    body, unit = _split_unit(expr.strip())
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
        units = {c: _SI_OF_SUFFIX.get(_split_unit(mapping[c])[1] or "", "")
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


def load_log(
    path: str | os.PathLike, mapping: Mapping[str, str] | None = None, *,
    required: Sequence[str] = REQUIRED_COLUMNS, time_rtol: float = 1e-3,
) -> Log:
    """Read and validate a log from CSV (header row), ``.npz`` or ``.mat``.

    ``mapping`` maps a log column (``t``, ``tau``, ``q1``, ...) to an expression on the
    file's variables (docs/spec.md section 6.4: struct paths, selections, products, unit
    suffixes, e.g. ``"para.u[0]*rec.act_torque_abs_nm[0]"``, ``"rec.act_pos_se_deg[0]:deg"``);
    unmapped columns are looked up by their own name. Only log columns are kept. An (n, N)
    array (one row per joint, as lab recorders store signals) is transposed to (N, n) when
    N is the length of ``t``. ``required`` lists the columns that must be present (static-map
    logs need only ``t``, ``v``, ``F``). A time column advancing by ``MS_SUSPECT_PERIOD``
    (0.5) or more per sample is refused as probably milliseconds unless its mapping carries a
    unit (``t=time:ms`` or ``t=time:s``). Raises ``LogError`` with a clear message for a
    missing column (listing what the file has) or variable, a struct without a field path,
    NaN, a bad time axis or mismatched lengths; ``FileNotFoundError`` for a missing file.
    """
    path = Path(path)
    where = f"{path}: "
    raw = read_variables(path)
    arrays = {k: v for k, v in raw.items() if not isinstance(v, dict)}
    # joined c[0], c[1], ... columns, and the originals so that 'tau[0]' still names one
    raw = {**{k: v for k, v in raw.items() if isinstance(v, dict)}, **arrays,
           **_gather_indexed(arrays, where)}
    mapping = dict(mapping or {})
    bad = sorted(set(mapping) - set(LOG_COLUMNS))
    if bad:
        raise LogError(f"{where}mapping names unknown log column(s) {bad}")
    cols: dict[str, Any] = {}
    for c in LOG_COLUMNS:
        if c in mapping:
            cols[c] = evaluate(mapping[c], raw, where)
        elif c in raw:
            if isinstance(raw[c], dict):
                field = sorted(raw[c])[0] if raw[c] else "field"
                raise LogError(f"{where}variable '{c}' is a struct with fields "
                               f"{sorted(raw[c])}; map the column to one, e.g. "
                               f"{map_option(mapping, **{c: f'{c}.{field}'})}")
            cols[c] = raw[c]
    missing = [c for c in required if c not in cols]
    if missing:
        raise LogError(
            f"{where}missing column(s) {missing} (required: {list(required)}); the file has "
            f"variables: {_describe(raw)}. Map them with --map, e.g. "
            f"--map '{missing[0]}=<variable>' (docs/spec.md section 6.4)")
    if cols.get("t") is not None:
        t = np.asarray(cols["t"], dtype=float)
        cols["t"] = t.reshape(-1) if t.ndim == 2 and 1 in t.shape else t
        t = cols["t"]
        if t.ndim == 1 and t.shape[0] > 1:
            N = t.shape[0]
            for c, a in cols.items():
                a = np.asarray(a)
                if c != "t" and a.ndim == 2 and a.shape[1] == N and a.shape[0] != N:
                    cols[c] = a.T
            period = (t[-1] - t[0]) / (N - 1)
            unit = _split_unit(mapping["t"])[1] if "t" in mapping else None
            if unit is None and period >= MS_SUSPECT_PERIOD:
                expr = mapping.get("t", "t")
                raise LogError(
                    f"{where}time column t advances by {period:g} per sample: this looks like "
                    f"milliseconds (or another unit), not seconds. Map it with a unit: "
                    f"{map_option(mapping, t=f'{expr}:ms')} (or ':s' in place of ':ms' if it "
                    "really is in seconds)")
    for c, a in list(cols.items()):
        if np.ndim(a) == 0:
            raise LogError(f"{where}column {c} is a single number, expected one value per sample")
    return Log.from_arrays(required=required, time_rtol=time_rtol, source=str(path), **cols)


def inspect_file(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The variables of a log file (struct fields as dotted paths), for ``jaxflex inspect``:
    a list of {"name", "shape", "dtype", "unit" (guessed from a log-column name or a name
    suffix such as ``_deg``; "" when unknown), "value" (for a single number)}."""
    rows = []
    for name, v in flatten_variables(read_variables(path)).items():
        a = np.asarray(v)
        row: dict[str, Any] = {"name": name, "shape": tuple(a.shape), "dtype": str(a.dtype),
                               "unit": name_unit(name)}
        if a.size == 1 and a.dtype.kind in "biuf":
            row["value"] = float(a.reshape(()))
        rows.append(row)
    return rows


def save_log(log: Log, path: str | os.PathLike) -> None:
    """Write a log as CSV (header ``t,tau,q1,...``; ``c[i]`` for joint i when n > 1) or
    ``.npz`` (one (N, n) array per column). Written atomically; floats with full precision."""
    path = Path(path)
    suffix = path.suffix.lower()
    tmp = path.with_name(path.name + ".tmp" + suffix)
    if suffix == ".csv":
        names, table = _csv_header(log)
        np.savetxt(tmp, table, delimiter=",", header=",".join(names), comments="", fmt="%.17g")
    elif suffix == ".npz":
        np.savez(tmp, **{c: getattr(log, c) for c in log.columns()})
    else:
        raise LogError(f"{path}: save_log writes .csv or .npz, got '{suffix}'")
    os.replace(tmp, path)
