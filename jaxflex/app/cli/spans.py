"""Lengths of log as the commands take them: a number of samples (``250``) or a duration in
seconds (``0.3s``), one argument type for every ``--segment``."""

from __future__ import annotations

import argparse
import dataclasses
import math
from typing import Literal


@dataclasses.dataclass(frozen=True)
class Span:
    """A length of log: ``value`` samples (``unit`` "samples") or seconds (``unit`` "s")."""

    value: float
    unit: Literal["samples", "s"]

    def samples(self, dt: float) -> int:
        """The length in samples of period ``dt`` [s] (seconds rounded to the nearest)."""
        return int(self.value) if self.unit == "samples" else int(round(self.value / dt))

    def seconds(self, dt: float) -> float:
        """The length [s] at sample period ``dt`` [s]."""
        return self.value * dt if self.unit == "samples" else self.value

    def __str__(self) -> str:
        return f"{int(self.value)}" if self.unit == "samples" else f"{self.value:g}s"


def span(text: str) -> Span:
    """An argparse type: ``N`` (an integer number of samples >= 0) or ``Xs`` (seconds >= 0).

    **Raises:**

    ``argparse.ArgumentTypeError`` naming what was expected.
    """
    what = "a number of samples (e.g. 250) or seconds (e.g. 0.3s)"
    try:
        if text.endswith("s"):
            value, unit = float(text[:-1]), "s"
        else:
            value, unit = int(text), "samples"
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected {what} >= 0, got {text!r}")
    return Span(value, unit)


def span_or_auto(text: str) -> Span | str:
    """An argparse type: ``auto`` or a ``span``."""
    return text if text == "auto" else span(text)
