"""Residual analysis of a fitted model, as MATLAB's ``resid`` gives it: the residual's
autocorrelation and its cross-correlation with the input, each with a confidence band, and a
whiteness test (Ljung-Box).

A model that explains a log leaves residuals that are white (no autocorrelation beyond lag 0)
and independent of past inputs. A model-limited fit leaves coloured residuals, and where they
correlate with the input it says which dynamics are missing. Host-side numpy: the residuals
are few thousand samples, and the statistics run once per fit.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

#: Default number of lags (MATLAB's ``resid`` uses 25).
LAGS: int = 25
#: Default confidence of the bands (MATLAB's ``resid``: 99%).
CONFIDENCE: float = 0.99


@dataclasses.dataclass(frozen=True)
class ResidualAnalysis:
    """Autocorrelation and input cross-correlation of one residual channel.

    Attributes:
        lags: lags 0..M of the autocorrelation [samples].
        autocorrelation: normalised autocorrelation r_ee(k) / r_ee(0), lags 0..M.
        band: half-width of the confidence band of the autocorrelation at lags >= 1 under
            whiteness (z / sqrt(N)).
        cross_lags: lags -M..M of the cross-correlation [samples]; positive: input leads.
        cross_correlation: normalised cross-correlation of residual and input, or None.
        cross_band: half-width of its confidence band under independence, or None.
        ljung_box_q: Ljung-Box statistic over lags 1..M.
        p_white: its p-value (chi-square, M degrees of freedom): small means coloured.
        correlation_time: integrated autocorrelation time [samples], 1 + 2 sum rho(k) over
            the lags before rho first falls below the band (1 for white residuals).
        outside: lags 1..M whose autocorrelation lies outside the band.
        cross_outside: lags whose cross-correlation lies outside its band.
        n: samples used.
    """

    lags: np.ndarray
    autocorrelation: np.ndarray
    band: float
    cross_lags: np.ndarray
    cross_correlation: np.ndarray | None
    cross_band: float | None
    ljung_box_q: float
    p_white: float
    correlation_time: float
    outside: int
    cross_outside: int
    n: int

    @property
    def white(self) -> bool:
        """Whether the residual passes the whiteness test at the band's confidence."""
        return self.p_white >= 1.0 - CONFIDENCE

    def summary(self) -> dict[str, Any]:
        """The numbers as plain JSON types (the curves included)."""
        return {
            "n": self.n, "lags": int(self.lags[-1]), "band": self.band,
            "autocorrelation": [float(x) for x in self.autocorrelation],
            "ljung_box_q": self.ljung_box_q, "p_white": self.p_white, "white": self.white,
            "correlation_time": self.correlation_time, "outside_band": self.outside,
            "cross_correlation": (None if self.cross_correlation is None
                                  else [float(x) for x in self.cross_correlation]),
            "cross_band": self.cross_band, "cross_outside_band": self.cross_outside,
        }


def _band_z_and_p(confidence: float, q: float, lags: int) -> tuple[float, float]:
    """The two-sided normal quantile of ``confidence`` and the chi-square survival of the
    Ljung-Box ``q`` with ``lags`` degrees of freedom. scipy is imported here, not with the
    module: a command's start would pay 0.2-0.55 s for it (tests/test_app_layer.py)."""
    from scipy import special

    return float(special.ndtri(0.5 + confidence / 2)), float(special.chdtrc(lags, q))


def _autocorrelation(x: np.ndarray, lags: int) -> np.ndarray:
    """Biased normalised autocorrelation of ``x`` (mean removed) at lags 0..``lags``."""
    x = x - x.mean()
    n = x.size
    f = np.fft.rfft(x, 2 * n)
    r = np.fft.irfft(f * np.conj(f))[: lags + 1]
    return r / r[0] if r[0] > 0 else np.zeros(lags + 1)


def _cross_correlation(e: np.ndarray, u: np.ndarray, lags: int) -> np.ndarray:
    """Normalised cross-correlation sum_t e(t) u(t - k) / (N sd_e sd_u) at k = -lags..lags."""
    e, u = e - e.mean(), u - u.mean()
    n = e.size
    fe, fu = np.fft.rfft(e, 2 * n), np.fft.rfft(u, 2 * n)
    r = np.fft.irfft(fe * np.conj(fu))
    out = np.concatenate([r[-lags:], r[: lags + 1]]) if lags else r[:1]
    scale = math.sqrt(float(e @ e) * float(u @ u))
    return out / scale if scale > 0 else np.zeros(2 * lags + 1)


def analyse_residual(residual: Any, input: Any = None, *, lags: int = LAGS,
                     confidence: float = CONFIDENCE) -> ResidualAnalysis:
    """Autocorrelation, input cross-correlation and whiteness of one residual channel.

    Arguments:
        residual: the residual sequence, shape (N,) (any unit; e.g. rad of output error).
        input: the input sequence of the same length (e.g. the applied torque [N m]), or None.
        lags: the largest lag M [samples].
        confidence: confidence of the bands (two-sided).

    Returns:
        A ``ResidualAnalysis``.

    Raises:
        ValueError: when the residual is not one-dimensional, has fewer than 2 (M + 1)
            samples, holds a non-finite value, or the input's length differs.
    """
    e = np.asarray(residual, float)
    if e.ndim != 1:
        raise ValueError(f"analyse_residual: the residual must be 1-D, got shape {e.shape}")
    u = None
    if input is not None:
        u = np.asarray(input, float).reshape(-1)
        if u.size != e.size:
            raise ValueError(f"analyse_residual: input has {u.size} samples, residual {e.size}")
        u = u[None, :]
    # one segment: the pooled statistics of ``analyse_segments`` are the plain ones
    return analyse_segments(e[None, :], u, lags=lags, confidence=confidence)


def _pooled_correlation(a: np.ndarray, b: np.ndarray, lags: int) -> np.ndarray:
    """sum over segments s and samples t of a[s, t] b[s, t - k] at k = -lags..lags: the lagged
    products within each segment (rows), never across two."""
    L = a.shape[1]
    fa, fb = np.fft.rfft(a, 2 * L, axis=1), np.fft.rfft(b, 2 * L, axis=1)
    r = np.fft.irfft(fa * np.conj(fb), 2 * L, axis=1).sum(axis=0)
    return np.concatenate([r[2 * L - lags:], r[: lags + 1]]) if lags else r[:1]


def analyse_segments(residual: Any, input: Any = None, *, lags: int = LAGS,
                     confidence: float = CONFIDENCE) -> ResidualAnalysis:
    """``analyse_residual`` of a residual recorded in segments (e.g. the open-loop replays
    of a log's segments, each from its own start): the lagged products are pooled within the
    segments, never across the join of two, and the statistics are those of one sequence of
    all the samples (Bartlett's bands and Ljung-Box with N = S x L).

    Arguments:
        residual: the residual, shape (S, L): S segments of L samples (any unit).
        input: the input of the same shape (e.g. the applied torque [N m]), or None.
        lags: the largest lag M [samples].
        confidence: confidence of the bands (two-sided).

    Returns:
        A ``ResidualAnalysis`` (one segment: the same as ``analyse_residual``).

    Raises:
        ValueError: when the residual is not two-dimensional, its segments have fewer than
            2 (M + 1) samples, it holds a non-finite value, or the input's shape differs.
    """
    e = np.asarray(residual, float)
    if e.ndim != 2:
        raise ValueError(f"analyse_segments: the residual must be (S, L), got shape {e.shape}")
    S, L = e.shape
    if not 1 <= lags or L < 2 * (lags + 1):
        raise ValueError(f"analyse_segments: segments of {L} samples are too few for {lags} "
                         "lags")
    if not np.all(np.isfinite(e)):
        raise ValueError("analyse_segments: the residual holds NaN or inf")
    n = e.size
    e = e - e.mean()
    r = _pooled_correlation(e, e, lags)[lags:]
    rho = r / r[0] if r[0] > 0 else np.zeros(lags + 1)
    k = np.arange(1, lags + 1)
    q = float(n * (n + 2) * np.sum(rho[1:] ** 2 / (n - k)))
    z, p = _band_z_and_p(confidence, q, lags)
    band = z / math.sqrt(n)
    first_in = next((i for i in range(1, lags + 1) if abs(rho[i]) < band), lags + 1)
    tau = float(1.0 + 2.0 * np.sum(rho[1:first_in]))
    xc, xband, xout = None, None, 0
    if input is not None:
        u = np.asarray(input, float)
        if u.shape != e.shape:
            raise ValueError(f"analyse_segments: input has shape {u.shape}, residual {e.shape}")
        u = u - u.mean()
        scale = math.sqrt(float(np.sum(e * e)) * float(np.sum(u * u)))
        xc = (_pooled_correlation(e, u, lags) / scale if scale > 0
              else np.zeros(2 * lags + 1))
        ru = _pooled_correlation(u, u, lags)[lags:]
        rho_u = ru / ru[0] if ru[0] > 0 else np.zeros(lags + 1)
        s = float(rho[0] * rho_u[0] + 2 * np.sum(rho[1:] * rho_u[1:]))
        xband = z * math.sqrt(max(s, 1.0 / n) / n)
        xout = int(np.sum(np.abs(xc) > xband))
    return ResidualAnalysis(
        lags=np.arange(lags + 1), autocorrelation=rho, band=band,
        cross_lags=np.arange(-lags, lags + 1), cross_correlation=xc, cross_band=xband,
        ljung_box_q=q, p_white=p, correlation_time=max(tau, 1.0),
        outside=int(np.sum(np.abs(rho[1:]) > band)), cross_outside=xout, n=n,
    )
