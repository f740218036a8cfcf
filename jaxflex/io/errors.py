"""The three ways a jaxflex run can fail, told apart by the kind of exception.

- **Bad input** (the user can fix it): an ``InputError`` (the base of the library's refusals:
  ``LogError``, ``SpreadError``, ``OutputError``), any other ``ValueError`` subclass that
  jaxflex defines (``ParamsError``, ...), a plain ``ValueError`` raised by a ``raise``
  statement in jaxflex's own code (the explicit checks of arguments and files, STYLE.md's
  "bad input is refused with ``ValueError``"), or an ``OSError`` about a path.
- **Not converged** (the input was fine, the result is not trustworthy): ``NotConverged``.
- **A bug**: everything else, in particular a ``ValueError`` raised inside numpy, scipy or
  JAX (``numpy.linalg.LinAlgError`` included), a ``KeyError``, ``TypeError`` or
  ``RuntimeError`` from inside a computation. A computation that fails on valid input is
  jaxflex's fault, not the user's.

``classify`` implements the rule; the command line maps the kinds to exit codes (2, 3, 70).
"""

from __future__ import annotations

import linecache
from types import TracebackType
from typing import Literal

Kind = Literal["input", "unconverged", "bug"]


class InputError(ValueError):
    """Bad input: a file, an argument or an option value the library refuses; the message
    names the input and says what is wrong with it."""


class ConfigError(InputError):
    """A setting of a configuration class outside its range; ``field`` names the setting
    (the command line names the option made of it: ``train_frac``, ``--train-frac``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field

    def option(self) -> str:
        """The message with the setting named as its command-line option."""
        return f"--{self.field.replace('_', '-')}: {str(self).partition(': ')[2]}"


class NotConverged(RuntimeError):
    """A computation on valid input that did not converge; its result must not be used as if
    it had (the message says what did not converge)."""


def _innermost(tb: TracebackType | None) -> TracebackType | None:
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb


def raised_by_jaxflex(exc: BaseException) -> bool:
    """Whether ``exc`` was raised by a ``raise`` statement in a jaxflex module (not by numpy,
    JAX or a builtin called from jaxflex code)."""
    tb = _innermost(exc.__traceback__)
    if tb is None:
        return False
    frame = tb.tb_frame
    if not str(frame.f_globals.get("__name__", "")).startswith("jaxflex"):
        return False
    line = linecache.getline(frame.f_code.co_filename, tb.tb_lineno).strip()
    return line.startswith("raise")


def classify(exc: BaseException) -> Kind:
    """Which of the three kinds (module docstring) ``exc`` is: ``"input"``,
    ``"unconverged"`` or ``"bug"``."""
    import numpy as np

    if isinstance(exc, NotConverged):
        return "unconverged"
    if isinstance(exc, np.linalg.LinAlgError):
        return "bug"
    if isinstance(exc, InputError):
        return "input"
    if isinstance(exc, ValueError):
        own_class = type(exc) is not ValueError and type(exc).__module__.startswith("jaxflex")
        return "input" if own_class or raised_by_jaxflex(exc) else "bug"
    if isinstance(exc, OSError):
        return "input" if exc.filename is not None or raised_by_jaxflex(exc) else "bug"
    return "bug"
