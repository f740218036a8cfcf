"""Logs of measured (or simulated) runs (docs/spec.md section 6): load, validate, save.

A log is a table sampled at a fixed period with columns (SI units, link-referred)

    t [s], tau [N m] applied motor torque, q1 [rad] link angle, q2 [rad] rotor angle,
    optional q1d [rad] reference, F [N m] measured friction, v [rad/s] velocity.

For n joints a column ``c`` is stored as ``c[0]``, ..., ``c[n-1]`` in a CSV header (a single
joint may use the bare name). Formats: CSV with a header row, ``.npz`` and MATLAB ``.mat``
(v5/v7, read with scipy). A ``mapping`` renames the file's variables to the log columns; a
mapping value may be a product such as ``"gtau*vir"`` (variables or numbers joined by ``*``),
which is how the EMPS benchmark stores its force.

Everything here is host-side numpy; a bad log raises ``LogError`` (a ``ValueError``) naming
the problem before any JAX code runs.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

LOG_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2", "q1d", "F", "v")
REQUIRED_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2")
_UNITS = {"t": "s", "tau": "N m", "q1": "rad", "q2": "rad", "q1d": "rad", "F": "N m",
          "v": "rad/s"}


class LogError(ValueError):
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
                f"{where}time is not strictly increasing: t[{i}] = {t[i]!r}, t[{i + 1}] = "
                f"{t[i + 1]!r}"
            )
        dt = (t[-1] - t[0]) / (t.shape[0] - 1)
        dev = np.abs(d - dt)
        if np.any(dev > time_rtol * dt):
            i = int(np.argmax(dev))
            raise LogError(
                f"{where}time is not uniformly sampled: step {i} is {d[i]!r} s but the mean "
                f"period is {dt!r} s (tolerance {time_rtol:g} relative)"
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
    names = [h.strip() for h in header.split(",")]
    if any(re.fullmatch(r"[-+0-9.eE]+", n) for n in names):
        raise LogError(f"{path}: the first row must be a header of column names, got {header!r}")
    if len(set(names)) != len(names):
        raise LogError(f"{path}: duplicate column names in header {names}")
    try:
        data = np.genfromtxt(path, delimiter=",", skip_header=1, dtype=float,
                             invalid_raise=True, ndmin=2)
    except ValueError as e:
        raise LogError(f"{path}: rows of unequal length or bad values ({e})") from None
    if data.size == 0:
        raise LogError(f"{path}: no data rows")
    if data.shape[1] != len(names):
        raise LogError(f"{path}: header has {len(names)} columns, rows have {data.shape[1]}")
    return {n: data[:, i] for i, n in enumerate(names)}


def _read_mat(path: Path) -> dict[str, np.ndarray]:
    import scipy.io

    try:
        d = scipy.io.loadmat(path)
    except NotImplementedError:
        raise LogError(
            f"{path}: MATLAB v7.3 (HDF5) files are not supported; save with -v7 or export CSV"
        ) from None
    except Exception as e:  # noqa: BLE001 - scipy raises many types for a bad file
        raise LogError(f"{path}: not a readable MATLAB file ({e})") from None
    return {k: np.asarray(v) for k, v in d.items() if not k.startswith("__")}


def _evaluate(expr: str, raw: Mapping[str, np.ndarray], where: str) -> np.ndarray:
    """A variable name or a product of names and numbers, e.g. ``"gtau*vir"``."""
    out: Any = 1.0
    for term in (s.strip() for s in expr.split("*")):
        if term in raw:
            val = np.asarray(raw[term], dtype=float)
            out = out * (val.reshape(-1) if val.size == 1 else val)
        else:
            try:
                out = out * float(term)
            except ValueError:
                raise LogError(
                    f"{where}mapping refers to variable '{term}' which is not in the file "
                    f"(variables: {sorted(raw)})"
                ) from None
    a = np.asarray(out, dtype=float)
    return a.reshape(()) if a.size == 1 else a


def parse_mapping(text: str | None) -> dict[str, str] | None:
    """Parse ``"tau=gtau*vir,q1=qm,q2=qm"`` (a CLI mapping) into a dict; None stays None."""
    if text is None or not text.strip():
        return None
    out = {}
    for item in text.split(","):
        if "=" not in item:
            raise LogError(f"mapping item {item!r} must look like column=variable")
        k, v = (s.strip() for s in item.split("=", 1))
        if k not in LOG_COLUMNS:
            raise LogError(f"mapping: unknown log column '{k}'; known columns: {list(LOG_COLUMNS)}")
        out[k] = v
    return out


def load_log(
    path: str | os.PathLike, mapping: Mapping[str, str] | None = None, *,
    required: Sequence[str] = REQUIRED_COLUMNS, time_rtol: float = 1e-3,
) -> Log:
    """Read and validate a log from CSV (header row), ``.npz`` or ``.mat``.

    ``mapping`` maps a log column (``t``, ``tau``, ``q1``, ...) to a variable of the file or a
    product like ``"gtau*vir"``; unmapped columns are looked up by their own name. Only log
    columns are kept; other variables are ignored. ``required`` lists the columns that must be
    present (static-map logs need only ``t``, ``v``, ``F``). Raises ``LogError`` with a clear
    message for a missing file, column or variable, NaN, bad time axis or mismatched lengths.
    """
    path = Path(path)
    where = f"{path}: "
    if not path.exists():
        raise FileNotFoundError(f"log file not found: {path}")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        raw = _read_csv(path)
    elif suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            raw = {k: z[k] for k in z.files}
    elif suffix == ".mat":
        raw = _read_mat(path)
    else:
        raise LogError(f"{path}: unknown log format '{suffix}' (use .csv, .npz or .mat)")
    raw = _gather_indexed(raw, where)
    mapping = dict(mapping or {})
    bad = sorted(set(mapping) - set(LOG_COLUMNS))
    if bad:
        raise LogError(f"{where}mapping names unknown log column(s) {bad}")
    cols: dict[str, Any] = {}
    for c in LOG_COLUMNS:
        if c in mapping:
            cols[c] = _evaluate(mapping[c], raw, where)
        elif c in raw:
            cols[c] = raw[c]
    if cols.get("t") is not None and np.asarray(cols["t"]).ndim == 2:
        cols["t"] = np.asarray(cols["t"]).reshape(-1)
    for c, a in list(cols.items()):
        if np.ndim(a) == 0:
            raise LogError(f"{where}column {c} is a single number, expected one value per sample")
    return Log.from_arrays(required=required, time_rtol=time_rtol, source=str(path), **cols)


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
