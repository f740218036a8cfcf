"""The values the exporter's translator works on: atoms, statements and programs.

An array value of a jaxpr is held as a numpy object array of *atoms*, one per element: a
Python constant (folded at generation time), a ``Sym`` (a variable of the generated code) or
an ``Opaque`` placeholder that must not be used. A ``Program`` is the translation of one
traced function: its hoisted (parameter-only) and per-sample ``Stmt`` lists and its outputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np


class UnsupportedPrimitive(ValueError):
    """A jaxpr primitive the exporter cannot translate (the message names it)."""


class Sym:
    """A variable of the generated code; ``static`` if it depends only on parameters."""

    __slots__ = ("name", "static")

    def __init__(self, name: str, static: bool):
        self.name = name
        self.static = static

    def __repr__(self) -> str:
        return self.name


class Opaque:
    """Placeholder for outputs that must not be used (e.g. the LU factors behind a solve)."""

    def __init__(self, what: str):
        self.what = what


Atom = Any  # float | int | bool | Sym | Opaque


def is_const(a: Atom) -> bool:
    """Whether ``a`` is a constant known at generation time (not a variable of the code)."""
    return not isinstance(a, (Sym, Opaque))


@dataclass
class Stmt:
    """One generated statement: ``targets = code``; ``uses`` the names it reads."""

    targets: tuple[str, ...]
    code: str
    uses: tuple[str, ...]
    static: bool


@dataclass
class Program:
    """Generated code of one traced function: hoisted and per-sample statements."""

    params: list[str]
    signals: list[str]
    outputs: list[Atom]
    static_stmts: list[Stmt] = field(default_factory=list)
    dyn_stmts: list[Stmt] = field(default_factory=list)


def const_array(v: Any) -> np.ndarray:
    """An object array of the constants (or atoms) of ``v``, as the translator holds values."""
    arr = np.asarray(v)
    out = np.empty(arr.shape, dtype=object)
    for idx in np.ndindex(arr.shape):
        x = arr[idx]
        if isinstance(x, Sym):
            out[idx] = x
        elif arr.dtype == np.bool_:
            out[idx] = bool(x)
        elif np.issubdtype(arr.dtype, np.integer):
            out[idx] = int(x)
        elif arr.dtype == object:
            out[idx] = x
        else:
            out[idx] = float(x)
    return out


def map_atoms(f: Callable[[Atom], Atom], x: np.ndarray) -> np.ndarray:
    """``f`` applied to every atom of the object array ``x``."""
    out = np.empty(x.shape, dtype=object)
    for idx in np.ndindex(x.shape):
        out[idx] = f(x[idx])
    return out


def sym_array(prefix: str, shape: tuple[int, ...], static: bool) -> np.ndarray:
    """An object array of fresh input symbols ``prefix_i`` (row-major)."""
    out = np.empty(shape, dtype=object)
    for k, idx in enumerate(np.ndindex(shape)):
        out[idx] = Sym(f"{prefix}_{k}", static)
    return out


def eliminate_dead(stmts: list[Stmt], live: set[str]) -> list[Stmt]:
    """Statements needed for the ``live`` names, in order (``live`` is updated in place)."""
    keep = []
    for st in reversed(stmts):
        if any(t in live for t in st.targets):
            keep.append(st)
            live.update(st.uses)
    keep.reverse()
    return keep
