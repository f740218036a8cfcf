"""What a long workflow reports while it runs: one protocol for every workflow (identify,
discover, tune, sweep), and the three reporters a caller usually wants: nothing, printed
lines, a tqdm bar (the command line's).

A workflow calls ``progress(done, total, message)`` on the host between compiled steps:
``done`` of ``total`` units of its work (``total`` None where it is not known ahead) and a
line of text ("" where there is none).
"""

from __future__ import annotations

import sys
from typing import Any, Protocol, TextIO


class Progress(Protocol):
    """A workflow's progress reporter (module docstring): ``done`` units of ``total`` (None:
    not known ahead) and a line of text ("" for none). It returns nothing; a reporter may
    raise ``KeyboardInterrupt`` to stop the workflow."""

    def __call__(self, done: int, total: int | None, message: str) -> None:
        """Report ``done`` of ``total`` with ``message``."""


def silent(done: int, total: int | None, message: str) -> None:
    """The reporter that reports nothing (every workflow's default)."""


class Printer:
    """Prints each message as a line, the numbered steps every ``every``-th only.

    **Arguments:**

    - ``every``: of the reports with a known ``total`` (numbered steps), print those whose
      ``done`` is a multiple of it; reports without a total are always printed.
    - ``prefix``: put before every line (e.g. ``"  [identify] "``).
    - ``stream``: where to print (standard output by default).
    """

    def __init__(self, every: int = 1, prefix: str = "", stream: TextIO | None = None):
        if every < 1:
            raise ValueError(f"Printer: every must be >= 1, got {every}")
        self.every, self.prefix, self.stream = every, prefix, stream

    def __call__(self, done: int, total: int | None, message: str) -> None:
        if message and (total is None or done % self.every == 0):
            print(f"{self.prefix}{message}", file=self.stream or sys.stdout, flush=True)


class Bar:
    """A tqdm progress bar as a reporter: its length is the latest ``total``, its position
    ``done``, the message its postfix. Use it as a context manager, or ``close()`` it.

    **Arguments:**

    - ``desc``: the bar's label.
    - ``unit``: what one unit of work is (``"step"``, ``"chunk"``, ...).
    - ``initial``: the position the bar starts at (units already done).
    """

    def __init__(self, desc: str, unit: str = "step", initial: int = 0):
        from tqdm.auto import tqdm

        self._bar = tqdm(desc=desc, unit=unit, initial=initial, total=None)

    def __call__(self, done: int, total: int | None, message: str) -> None:
        if total is not None and self._bar.total != total:
            self._bar.total = total
        self._bar.n = done
        if message:
            self._bar.set_postfix_str(message, refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        """Close the bar (its last state stays on the terminal)."""
        self._bar.close()

    def __enter__(self) -> Bar:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
