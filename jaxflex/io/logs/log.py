"""The one log type (``Log``): columns, joints, sample time, checks, slices."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxflex.io.errors import InputError

LOG_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2", "q1d", "F", "v")
REQUIRED_COLUMNS: tuple[str, ...] = ("t", "tau", "q1", "q2")
#: The SI unit of each log column.
COLUMN_UNITS: dict[str, str] = {"t": "s", "tau": "N m", "q1": "rad", "q2": "rad", "q1d": "rad", "F": "N m",
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
