"""Signal helpers for logged angles, in numpy: Savitzky-Golay smoothing and differentiation
(``savgol``, ``savgol_coeffs``) and the measurement noise of a channel (``white_noise_std``,
``noise_level``). They give the first guesses of segment start states and the noise units of
a fit's residuals.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def savgol_coeffs(window: int, order: int, deriv: int = 0, delta: float = 1.0) -> np.ndarray:
    """Savitzky-Golay weights (window,) that give the ``deriv``-th derivative [units / s^deriv
    for ``delta`` in s] at the centre of ``window`` (odd) samples of period ``delta``, from
    the least-squares polynomial of degree ``order`` through them, applied as a dot product
    with the window's samples in time order (scipy's ``savgol_coeffs(..., use="dot")``; a test
    checks equality with scipy).

    Written here, not imported: importing ``scipy.signal`` imports ``scipy.stats`` and all
    its submodules, a large share of every command's start."""
    if window % 2 != 1 or not 0 <= deriv <= order < window:
        raise ValueError(f"savgol: need an odd window > order >= deriv >= 0, got window "
                         f"{window}, order {order}, deriv {deriv}")
    half = window // 2
    vander = np.arange(-half, half + 1, dtype=float)[None, :] ** np.arange(order + 1)[:, None]
    unit = np.zeros(order + 1)
    unit[deriv] = math.factorial(deriv) / delta**deriv
    return np.linalg.lstsq(vander, unit, rcond=None)[0]


def savgol_window(window: int, n: int) -> int:
    """The window [samples] ``savgol`` uses on ``n`` samples: ``window``, at most the log's
    length and made odd (a shorter log takes its longest odd stretch)."""
    return min(window, n - (1 - n % 2))


def savgol(x: np.ndarray, dt: float, deriv: int = 0, window: int = 31, order: int = 3) -> np.ndarray:
    """Savitzky-Golay smoothing (``deriv`` = 0) or derivative of order ``deriv`` of samples
    ``x`` (along axis 0) with period ``dt`` [s]: the one numerical differentiation of logs.
    ``window`` samples (made odd and at most the log's length), polynomials of degree
    ``order``; the first and last half windows take the derivative of the polynomial fitted to
    the first and last whole window (scipy's ``savgol_filter(..., mode="interp")``, to which a
    test holds it; ``savgol_coeffs`` says why it is not imported)."""
    x = np.asarray(x, float)
    N = x.shape[0]
    window = savgol_window(window, N)
    flat = x.reshape(N, -1)
    out = np.empty_like(flat)
    half = window // 2
    # inside: one weighted sum per sample over its centred window
    views = np.lib.stride_tricks.sliding_window_view(flat, window, axis=0)  # (N-w+1, m, w)
    out[half:N - half] = views @ savgol_coeffs(window, order, deriv, dt)
    # the edges: the polynomial through the first (last) whole window and its derivative
    t = np.arange(window, dtype=float)
    for rows, at in ((slice(0, window), slice(0, half)), (slice(N - window, N), slice(N - half, N))):
        poly = np.polynomial.polynomial.polyfit(t, flat[rows], order)  # (order + 1, m)
        for _ in range(deriv):
            poly = np.polynomial.polynomial.polyder(poly)
        edge = t[:half] if at.start == 0 else t[window - half:]
        out[at] = np.polynomial.polynomial.polyval(edge, poly).T / dt**deriv
    return out.reshape(x.shape)


def white_noise_std(q: np.ndarray, orders: Sequence[int] = (2, 3, 4, 5, 6)) -> float:
    """White measurement noise [rad] of a sampled angle by differencing: the k-th difference
    of white noise has variance C(2k, k) sigma^2, a smooth motion's is attenuated by
    (2 sin(w dt / 2))^k; the smallest estimate over ``orders`` bounds sigma from above with
    the least motion left in it (quantisation included, where the motion makes it white)."""
    q = np.asarray(q, float).reshape(len(q), -1)[:, 0]
    est = [math.sqrt(np.var(np.diff(q, k)) / math.comb(2 * k, k)) for k in orders]
    return float(min(est))


def noise_level(q: np.ndarray) -> dict[str, float]:
    """Angle measurement noise of a logged channel [rad]: the quantisation step (the smallest
    increment above floating-point rounding: one count, which a quantised channel shows
    wherever it moves slowly or its noise toggles a count; a percentile of the increments
    reads several counts on a channel that moves fast), its step^2/12 standard deviation, and
    the total standard deviation: the white noise by differencing (``white_noise_std``,
    quantisation included), at least the quantisation's (a channel that stands still leaves
    no white quantisation error to difference). Not a smoothing residual, which keeps part of
    the motion and overstates the noise."""
    q = np.asarray(q, float).reshape(q.shape[0], -1)[:, 0]
    d = np.abs(np.diff(q))
    d = d[d > 1e-12 * max(1.0, float(np.max(np.abs(q))))]
    step = float(np.min(d)) if d.size else 0.0
    return {"step": step, "quantisation_std": step / math.sqrt(12.0),
            "total_std": max(white_noise_std(q), step / math.sqrt(12.0))}
