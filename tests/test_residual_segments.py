"""Residual analysis of a residual recorded in segments (``analyse_segments``): the lagged
products are pooled within segments, never across a join."""

import numpy as np
import pytest

from jaxflex.fit.residual_analysis import analyse_residual, analyse_segments


def test_one_segment_is_analyse_residual():
    rng = np.random.default_rng(0)
    e, u = rng.normal(size=3000), rng.normal(size=3000)
    a, b = analyse_residual(e, u), analyse_segments(e[None], u[None])
    np.testing.assert_allclose(b.autocorrelation, a.autocorrelation, atol=1e-12)
    np.testing.assert_allclose(b.cross_correlation, a.cross_correlation, atol=1e-12)
    assert b.ljung_box_q == pytest.approx(a.ljung_box_q)
    assert b.cross_band == pytest.approx(a.cross_band)


def test_lagged_products_are_pooled_within_segments():
    """The autocorrelation and cross-correlation equal the sums over segments of the
    products within each, written out."""
    rng = np.random.default_rng(1)
    S, L, M = 6, 80, 5
    e, u = rng.normal(size=(S, L)), rng.normal(size=(S, L))
    b = analyse_segments(e, u, lags=M)
    ec, uc = e - e.mean(), u - u.mean()
    r = np.array([sum(ec[s, k:] @ ec[s, :L - k] for s in range(S)) for k in range(M + 1)])
    np.testing.assert_allclose(b.autocorrelation, r / r[0], atol=1e-12)
    x = [sum(ec[s, k:] @ uc[s, :L - k] if k >= 0 else ec[s, :L + k] @ uc[s, -k:]
             for s in range(S)) for k in range(-M, M + 1)]
    scale = np.sqrt(np.sum(ec**2) * np.sum(uc**2))
    np.testing.assert_allclose(b.cross_correlation, np.array(x) / scale, atol=1e-12)
    assert b.n == S * L


def test_bad_segments_are_named():
    with pytest.raises(ValueError, match=r"\(S, L\)"):
        analyse_segments(np.zeros(100))
    with pytest.raises(ValueError, match="too few"):
        analyse_segments(np.zeros((3, 10)))
    with pytest.raises(ValueError, match="NaN"):
        analyse_segments(np.full((2, 100), np.nan))
    with pytest.raises(ValueError, match="input has shape"):
        analyse_segments(np.zeros((2, 100)), np.zeros((2, 99)))
