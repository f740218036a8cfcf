"""A log from a file and back: ``load_log`` (with a mapping), ``inspect_file``, ``save_log``."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.io.logs.log import LOG_COLUMNS, REQUIRED_COLUMNS, Log, LogError
from jaxflex.io.logs.mapping import (
    MS_SUSPECT_PERIOD,
    describe_variables,
    evaluate,
    flatten_variables,
    map_option,
    name_unit,
    split_unit,
)
from jaxflex.io.logs.readers import csv_header, gather_indexed, read_variables


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
           **gather_indexed(arrays, where)}
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
            f"variables: {describe_variables(raw)}. Map them with --map, e.g. "
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
            unit = split_unit(mapping["t"])[1] if "t" in mapping else None
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
        names, table = csv_header(log)
        np.savetxt(tmp, table, delimiter=",", header=",".join(names), comments="", fmt="%.17g")
    elif suffix == ".npz":
        np.savez(tmp, **{c: getattr(log, c) for c in log.columns()})
    else:
        raise LogError(f"{path}: save_log writes .csv or .npz, got '{suffix}'")
    os.replace(tmp, path)
