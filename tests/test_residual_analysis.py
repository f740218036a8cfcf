"""Residual analysis (MATLAB resid's statistics): white noise passes, coloured noise and an
input leaking into the residual are caught at the right lag."""

import numpy as np
import pytest

from jaxflex.fit.residual_analysis import analyse_residual


def test_white_noise_is_white_and_independent_of_the_input():
    rng = np.random.default_rng(0)
    a = analyse_residual(rng.normal(size=4000), rng.normal(size=4000))
    assert a.white and a.outside <= 2 and a.cross_outside <= 2
    assert a.correlation_time == pytest.approx(1.0)


def test_coloured_residual_fails_and_has_a_correlation_time():
    rng = np.random.default_rng(1)
    e = np.convolve(rng.normal(size=4000), np.ones(10) / 10, "same")
    a = analyse_residual(e)
    assert not a.white and a.outside > 5 and a.correlation_time > 5


def test_input_leak_is_found_at_its_lag():
    rng = np.random.default_rng(2)
    u, e = rng.normal(size=4000), rng.normal(size=4000)
    a = analyse_residual(e + 0.5 * np.roll(u, 3), u)
    assert a.cross_lags[np.argmax(a.cross_correlation)] == 3
    assert a.cross_outside >= 1


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="too few"):
        analyse_residual(np.zeros(10))
    with pytest.raises(ValueError, match="NaN"):
        analyse_residual(np.r_[np.zeros(100), np.nan])
    with pytest.raises(ValueError, match="input has"):
        analyse_residual(np.zeros(100), np.zeros(99))
