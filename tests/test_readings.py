"""The readings' model of an identification: an encoder's count and the white noise before its
rounding, and the exact likelihood of a rounded reading (``jaxflex.fit.readings.quantised_residual``,
``jaxflex.identify.problem``'s ``reading_model``, ``exact_reading``, ``reading_statistics``)."""

from __future__ import annotations

import warnings

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from jaxflex.fit.readings import quantised_residual, quantised_slope
from jaxflex.identify import IdentificationWarning, identify
from jaxflex.identify.problem import (
    READ_NOISE_FLOOR,
    exact_reading,
    make_problem,
    reading_model,
    reading_statistics,
)
from jaxflex.io.logs import Log
from jaxflex.io.params import Params

jax.config.update("jax_enable_x64", True)

E = jnp.asarray(np.concatenate([-np.logspace(12, -8, 400), [0.0], np.logspace(-8, 12, 400)]))


@pytest.mark.parametrize("quantum", [0.0, 1e-4, 0.5, 3.0, 16.0, 64.0])
def test_the_rounded_reading_s_residual_is_finite_odd_and_rises(quantum):
    q = jnp.asarray(quantum)
    r, s = quantised_residual(E, q), quantised_slope(E, q)
    assert bool(jnp.all(jnp.isfinite(r)) and jnp.all(jnp.isfinite(s)))
    np.testing.assert_allclose(r, -quantised_residual(-E, q), atol=1e-12)
    assert bool(jnp.all(jnp.diff(r) >= -1e-12))  # monotone in the model's error
    assert bool(jnp.all(s >= 0.0)) and float(jnp.max(s)) <= 1.0 + 1e-6
    far = jnp.abs(E) > quantum / 2 + 100  # far from the cell: slope 1, shifted by half a count
    np.testing.assert_allclose(s[far], 1.0, atol=1e-3)


def test_without_a_grid_the_residual_is_gaussian():
    np.testing.assert_allclose(quantised_residual(E, jnp.asarray(0.0)), E, rtol=0, atol=0)
    e = jnp.linspace(-5, 5, 101)
    np.testing.assert_allclose(quantised_residual(e, jnp.asarray(1e-2)), e, atol=1e-4)


def test_half_its_square_is_the_reading_s_negative_log_likelihood():
    e = np.linspace(-30, 30, 601)
    for quantum in (0.3, 2.0, 8.0, 20.0):
        h = quantum / 2
        a = np.abs(e)  # the small tail is the accurate one
        nll = -np.log(norm.cdf(h - a) - norm.cdf(-h - a))
        nll0 = -np.log(norm.cdf(h) - norm.cdf(-h))
        got = 0.5 * np.asarray(quantised_residual(jnp.asarray(e), jnp.asarray(quantum)))**2
        np.testing.assert_allclose(got, nll - nll0, rtol=1e-6, atol=1e-9)


def test_a_reading_s_likelihood_and_slope_take_two_error_functions_per_reading():
    """The solver's compiled program evaluates the residual and its slope at every step of
    every segment: each error function there is a long polynomial expansion that XLA
    compiles, so the readings' likelihood spends two per reading (the constant at e = 0 and
    the curvature are per count, not per reading)."""
    e, t = jnp.ones((40, 500, 2)), jnp.ones((40, 500, 2))
    quantum = jnp.asarray([0.5, 3.0])
    jaxpr = jax.make_jaxpr(lambda e, t: jax.jvp(lambda x: quantised_residual(x, quantum),
                                                (e,), (t,)))(e, t)

    def per_reading(jx):
        n = 0
        for eqn in jx.eqns:
            if eqn.primitive.name in ("erf", "erfc") and eqn.outvars[0].aval.shape == e.shape:
                n += 1
            for sub in jax.extend.core.jaxprs_in_params(eqn.params):
                n += per_reading(sub)
        return n

    assert per_reading(jaxpr.jaxpr) == 2


def test_a_model_inside_a_coarse_count_is_not_pulled_to_its_centre():
    """A count 32 noise deviations wide: anywhere in the middle half of the cell costs next
    to nothing, a Gaussian residual would pay (e / c)^2 / 2 there."""
    e = jnp.linspace(-8.0, 8.0, 33)
    assert float(jnp.max(jnp.abs(quantised_residual(e, jnp.asarray(32.0))))) < 1e-6


def test_the_expected_cost_is_half_a_unit_per_gaussian_reading_and_less_when_rounded():
    from types import SimpleNamespace as NS

    def stats(quantum):
        return reading_statistics(NS(quantum=np.array([quantum]), read_noise=np.array([1.0]),
                                     segs=NS(y_meas=np.zeros((4, 250, 1)))))

    cost, spread = stats(0.0)
    assert cost == pytest.approx(500.0, rel=1e-6)
    assert spread == pytest.approx(np.sqrt(2 / 1000), rel=1e-3)
    # Monte Carlo of the rounded reading at a count of 8 noise deviations
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 8, 200_000)
    y = np.round((x + rng.normal(size=x.size)) / 8) * 8
    mc = 0.5 * np.mean(np.asarray(quantised_residual(jnp.asarray(x - y), jnp.asarray(8.0)))**2)
    assert stats(8.0)[0] / 1000 == pytest.approx(mc, rel=0.02)


def _quantised_log(noise_counts: float) -> tuple[Log, Params]:
    t = np.arange(3000) * 1e-3
    q = 0.5 * np.sin(2 * np.pi * 0.7 * t)
    step = 2 * np.pi / 2**16
    rng = np.random.default_rng(1)
    read = np.round((q + noise_counts * step * rng.normal(size=q.size)) / step) * step
    log = Log.from_arrays(t=t, tau=0.1 * np.cos(t), q1=read, q2=read + 1e-3)
    init = Params.from_dict({"plant": {"I": 0.07, "J": 0.005, "K": 6.77}, "friction": {
        "Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1, "sigma2": 0.2}})
    return log, init


def test_the_readings_are_read_off_the_log():
    log, init = _quantised_log(0.0)
    prob, _ = make_problem(log, init, segment_length=500)
    count, noise = reading_model(log, prob)
    w = np.asarray(prob.w_y)
    step = 2 * np.pi / 2**16
    np.testing.assert_allclose(count / w, step, rtol=1e-9)
    np.testing.assert_allclose(noise / w, READ_NOISE_FLOOR * step, rtol=1e-9)
    assert exact_reading(log, prob) is not None
    # a count of noise before the rounding: the Gaussian's variance holds it
    log, init = _quantised_log(1.0)
    prob, _ = make_problem(log, init, segment_length=500)
    assert exact_reading(log, prob) is None


@pytest.mark.slow
def test_a_quantised_closed_loop_log_is_not_biased_by_its_counts():
    """``studies.ident_independent``'s 20 s log (18-bit encoders, the readings the true
    angles rounded), started 40-70% off: under the readings' exact likelihood every LuGre
    parameter is within 2% (least squares on the counts: Fs 2.9% low, vs 5.5% high, 4
    standard errors) and within 2 of its standard errors."""
    from studies import ident_independent as study

    log, init = study.log_and_start(20.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        r = identify(log, init, list(study.TRUTH), reading="exact")
    assert r.converged and r.model["verdict"] == "adequate"
    assert r.params.extra["identification"]["reading"]["likelihood"] == "rounded"
    for k, true in study.TRUTH.items():
        value, se = float(np.ravel(r.params.friction[k])[0]), r.stderr[k][0]
        assert abs(value / true - 1) < 0.02 and abs(value - true) < 2 * se, (k, value, se)


@pytest.mark.slow
def test_both_likelihoods_run_one_compiled_solver(lowerings):
    """By default a fit the noise explains on a rounded log (``studies.ident_independent``'s
    closed loop, 3 s, 18-bit encoders) ends under the readings' exact likelihood, and the
    least-squares search and the exact phase share one compiled solver per parameter space
    (``gaussian_reading``)."""
    from studies import ident_independent as study

    log, init = study.log_and_start(3.0)
    with lowerings(by_name=True) as lowered, warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        r = identify(log, init, list(study.TRUTH), max_steps=60, static_start=False)
    assert r.params.extra["identification"]["reading"]["likelihood"] == "rounded"
    assert any("reading" in a for a in r.attempts)
    spaces = 1 + len({tuple(a["refit_without"]) for a in r.attempts if "refit_without" in a})
    assert 1 <= lowered.count("jit(_steps_loop)") <= spaces, (lowered, spaces)


def test_a_float_log_has_no_count():
    t = np.arange(2000) * 1e-3
    q = 0.5 * np.sin(2 * np.pi * 0.7 * t)
    log = Log.from_arrays(t=t, tau=0.1 * np.cos(t), q1=q, q2=q + 1e-3)
    _, init = _quantised_log(0.0)
    prob, _ = make_problem(log, init, segment_length=500)
    count, _ = reading_model(log, prob)
    assert np.all(count == 0.0) and exact_reading(log, prob) is None


def test_an_unknown_reading_is_refused_by_name():
    log, init = _quantised_log(0.0)
    with pytest.raises(ValueError, match="reading must be one of"):
        identify(log, init, reading="auto")
