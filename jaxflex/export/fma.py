"""The fused multiply-add on Python floats, as XLA's CPU dot products compute it.

``exact_fma`` is written once and serves twice: the translator folds constants with it, and
the Python export carries its source (``inspect.getsource``) into the generated module, which
imports nothing from jaxflex. It therefore reads only the standard library's ``math`` and
``fractions``.
"""

from __future__ import annotations

import math


def exact_fma(a: float, b: float, c: float) -> float:
    """a * b + c rounded once to float64 (IEEE 754 fusedMultiplyAdd) on Python floats: the
    product split exactly into p + e (Dekker's two-product) and the three summed with one
    rounding (``math.fsum``); outside the range where the split is exact, by rationals.

    **Arguments:**

    - ``a``, ``b``: the factors (any units).
    - ``c``: the addend (the unit of ``a * b``).

    **Returns:**

    a * b + c with one rounding (the unit of ``a * b``); inf or nan as IEEE arithmetic gives
    them where a factor, the product or ``c`` is not finite.
    """
    p = a * b
    if a == 0 or b == 0 or not (math.isfinite(p) and math.isfinite(c)):
        return p + c
    if 1e-140 < abs(a) < 1e140 and 1e-140 < abs(b) < 1e140:
        t = 134217729.0 * a
        ah = t - (t - a)
        al = a - ah
        t = 134217729.0 * b
        bh = t - (t - b)
        bl = b - bh
        e = ((ah * bh - p) + ah * bl + al * bh) + al * bl
        return math.fsum((p, e, c))
    from fractions import Fraction

    r = Fraction(a) * Fraction(b) + Fraction(c)
    return float(r) if r != 0 else p + c
