"""How each back end spells the translator's operations: the ``Dialect`` and its two
instances, ``PYTHON`` (floats and ``math``) and ``C99`` (doubles and libm).

One traced jaxpr translated in both dialects gives the same operations in the same order, so
the two exports round alike; a dialect changes only the spelling.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable

import numpy as np

from jaxflex.export.atoms import Atom, Opaque, Sym, UnsupportedPrimitive


def _spell_literal(c: Any, *, true: str, false: str, nan: str, inf: str) -> str:
    """A constant's source, negative numbers parenthesised (``-x ** 2`` must not parse as
    ``-(x ** 2)``)."""
    if isinstance(c, (bool, np.bool_)):
        return true if c else false
    if isinstance(c, (int, np.integer)):
        v = int(c)
        return f"({v})" if v < 0 else str(v)
    v = float(c)
    if math.isnan(v):
        return nan
    if math.isinf(v):
        return inf if v > 0 else f"(-{inf})"
    r = repr(v)
    return f"({r})" if v < 0 or r.startswith("-") else r


_PY_LITERAL = partial(_spell_literal, true="True", false="False", nan="_NAN", inf="_INF")
_C_LITERAL = partial(_spell_literal, true="1", false="0", nan="NAN", inf="INFINITY")

# Python/math spellings of unary elementwise primitives; {0} is the operand.
_UNARY: dict[str, str] = {
    "neg": "-{0}", "sin": "_m.sin({0})", "cos": "_m.cos({0})", "tan": "_m.tan({0})",
    "asin": "_m.asin({0})", "acos": "_m.acos({0})", "atan": "_m.atan({0})",
    "sinh": "_m.sinh({0})", "cosh": "_m.cosh({0})", "tanh": "_m.tanh({0})",
    "asinh": "_m.asinh({0})", "acosh": "_m.acosh({0})", "atanh": "_m.atanh({0})",
    "exp": "_m.exp({0})", "exp2": "2.0 ** {0}", "log": "_m.log({0})", "expm1": "_m.expm1({0})",
    "log1p": "_m.log1p({0})", "sqrt": "_m.sqrt({0})", "rsqrt": "1.0 / _m.sqrt({0})",
    "cbrt": "_m.copysign(abs({0}) ** (1.0 / 3.0), {0})", "abs": "abs({0})",
    "sign": "_sign({0})", "floor": "float(_m.floor({0}))", "ceil": "float(_m.ceil({0}))",
    "is_finite": "_m.isfinite({0})", "not": "not {0}", "square": "{0} * {0}",
    "logistic": "1.0 / (1.0 + _m.exp(-{0}))", "erf": "_m.erf({0})", "erfc": "_m.erfc({0})",
    "lgamma": "_m.lgamma({0})",
}
# the arithmetic operators, spelt alike in Python and C
_ARITHMETIC: dict[str, str] = {
    "add": "{0} + {1}", "add_any": "{0} + {1}", "sub": "{0} - {1}", "mul": "{0} * {1}",
    "div": "{0} / {1}",
}
_BINARY: dict[str, str] = {
    **_ARITHMETIC, "pow": "{0} ** {1}", "atan2": "_m.atan2({0}, {1})",
    "rem": "_m.fmod({0}, {1})", "nextafter": "_m.nextafter({0}, {1})",
    "max": "({0} if {0} >= {1} or {0} != {0} else {1})",
    "min": "({0} if {0} <= {1} or {0} != {0} else {1})",
    "eq": "{0} == {1}", "ne": "{0} != {1}", "lt": "{0} < {1}", "le": "{0} <= {1}",
    "gt": "{0} > {1}", "ge": "{0} >= {1}", "and": "{0} and {1}", "or": "{0} or {1}",
}


@dataclass(frozen=True)
class Dialect:
    """How a back end spells the translator's operations (one traced jaxpr, several back ends).

    ``unary``/``binary``: templates of elementwise primitives ({0}, {1}: operands);
    ``literal``: a constant's source; ``select2``/``select_n``: two-way and n-way selects
    ({0}: predicate; ``select_n`` takes the case index); ``to_bool``/``to_int``/``to_float``:
    conversions (``to_float`` None: no code, the value is already a float); ``int_div``:
    integer division; ``round_even``/``round_away``: the two rounding methods; ``fma``: a fused
    multiply-add.
    """

    name: str
    unary: dict[str, str]
    binary: dict[str, str]
    literal: Callable[[Any], str]
    select2: str
    select_n: str
    to_bool: str
    to_int: str
    to_float: str | None
    int_div: str
    round_even: str
    round_away: str
    fma: str


PYTHON = Dialect(
    name="python", unary=_UNARY, binary=_BINARY, literal=_PY_LITERAL,
    select2="({2} if {0} else {1})", select_n="({{1}} if {{0}} == {i} else {{2}})",
    to_bool="bool({0})", to_int="int({0})", to_float="float({0})", int_div="int({0} / {1})",
    round_even="float(round({0}))", round_away="_round_away({0})",
    fma="exact_fma({0}, {1}, {2})",
)
"""Python on floats with ``math`` (``_m``); the generated module defines ``_sign``,
``_round_away`` and ``exact_fma`` (the source of ``jaxflex.export.fma.exact_fma``)."""

_C_UNARY: dict[str, str] = {
    **{k: f"{k}({{0}})" for k in ("sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh",
                                  "tanh", "asinh", "acosh", "atanh", "exp", "exp2", "log",
                                  "expm1", "log1p", "sqrt", "floor", "ceil", "erf", "erfc",
                                  "lgamma")},
    "neg": "-{0}", "rsqrt": "1.0 / sqrt({0})",
    "cbrt": "copysign(pow(fabs({0}), 1.0 / 3.0), {0})", "abs": "fabs({0})",
    "sign": "jf_sign({0})", "is_finite": "(isfinite({0}) != 0)", "not": "(!{0})",
    "square": "{0} * {0}", "logistic": "1.0 / (1.0 + exp(-{0}))",
}
_C_BINARY: dict[str, str] = {
    **_ARITHMETIC, "pow": "pow({0}, {1})", "atan2": "atan2({0}, {1})",
    "rem": "fmod({0}, {1})", "nextafter": "nextafter({0}, {1})",
    "max": "(({0} >= {1} || {0} != {0}) ? {0} : {1})",
    "min": "(({0} <= {1} || {0} != {0}) ? {0} : {1})",
    "eq": "({0} == {1})", "ne": "({0} != {1})", "lt": "({0} < {1})", "le": "({0} <= {1})",
    "gt": "({0} > {1})", "ge": "({0} >= {1})", "and": "({0} && {1})", "or": "({0} || {1})",
}

C99 = Dialect(
    name="c99", unary=_C_UNARY, binary=_C_BINARY, literal=_C_LITERAL,
    select2="({0} ? {2} : {1})", select_n="({{0}} == {i} ? {{1}} : {{2}})",
    to_bool="({0} != 0)", to_int="trunc({0})", to_float=None, int_div="trunc({0} / {1})",
    round_even="nearbyint({0})", round_away="round({0})",
    fma="fma({0}, {1}, {2})",
)
"""C99 on doubles with libm (every value, booleans and integers included, is a double);
the generated file defines ``jf_sign``."""


def format_atom(a: Atom, dialect: Dialect = PYTHON) -> str:
    """Source of an atom in ``dialect`` (default Python)."""
    if isinstance(a, Opaque):
        raise UnsupportedPrimitive(f"the exporter cannot output the {a.what} directly")
    return a.name if isinstance(a, Sym) else dialect.literal(a)
