"""Reading a lab file's variables (CSV with a header, ``.npz``, MATLAB ``.mat`` with its
structs as nested dicts: ``read_variables``) and the CSV header of a log (``csv_header``)."""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from jaxflex.io.logs.log import LOG_COLUMNS, Log, LogError


def csv_header(log: Log) -> tuple[list[str], np.ndarray]:
    """The CSV columns of ``log``: names (``c`` for one joint, else ``c[0]`` ...) and the
    (N, columns) table, absent columns left out."""
    names, blocks = ["t"], [log.t[:, None]]
    for c in LOG_COLUMNS[1:]:
        a = getattr(log, c)
        if a is None:
            continue
        names += [c] if a.shape[1] == 1 else [f"{c}[{i}]" for i in range(a.shape[1])]
        blocks.append(a)
    return names, np.hstack(blocks)


_INDEXED = re.compile(r"^([A-Za-z0-9_]+)\[(\d+)\]$")


def gather_indexed(table: Mapping[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
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
