"""The fitting engine (``jaxflex.fit``): constraint vocabulary, the multiple-shooting problem
with measured starts and gated effects, the host-stepped solver (one compilation for problems
that differ only in data), covariance through the reparametrisation."""

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.effects import EFFECTS, Gated
from jaxflex.fit import (
    CostBound,
    Padding,
    ParamSpace,
    Problem,
    covariance,
    induced_point,
    least_squares,
    make_segments,
    noise_level,
)
from jaxflex.fit.space import _parse
from jaxflex.identify import excitation_torque, synthetic_log
from jaxflex.io.logs import Log
from jaxflex.io.presets import paper_params


def _gated_plant(active: tuple[str, ...] = ()):
    p = paper_params().to_plant(with_effects=False)
    effs = [Gated(EFFECTS[n].typical(1), jnp.asarray(1.0 if n in active else 0.0))
            for n in ("actuator_lag", "backlash", "torque_offset")]
    return p.with_effects(*effs)


def _fixed_start_problem(plant, log, free, length=150):
    space = ParamSpace.build(plant, free)
    segs = make_segments(log, kind="flexible", outputs=("q1", "q2"), length=length)
    return Problem(space=space, segs=segs, w_y=jnp.asarray(100.0), w_def=jnp.zeros(5),
                   dt=log.dt, kind="flexible", substeps=1, outputs=("q1", "q2"),
                   free_starts=False)


def test_constraint_vocabulary():
    assert _parse("positive>=1.5e-3") == ("lower", 1.5e-3, 0.0)
    assert _parse("bounded:0.1,2") == ("bounded", 0.1, 2.0)
    with pytest.raises(ValueError, match="unknown constraint"):
        _parse("bounded:2,1")
    with pytest.raises(ValueError, match="unknown constraint"):
        _parse("sometimes")
    plant = _gated_plant(("actuator_lag", "backlash"))
    space = ParamSpace.build(plant, ("Fc", "Fs", "actuator_lag.T", "backlash.b", "K"))
    rng = np.random.default_rng(1)
    for _ in range(10):
        th = {k: jnp.asarray(rng.normal(scale=4.0, size=1)) for k in space.names}
        ph = space.physical(th)
        assert float(ph["Fs"][0]) >= float(ph["Fc"][0]) > 0
        assert float(ph["actuator_lag.T"][0]) >= 1.5e-3
        p = space.plant(th)
        # backlash's K is "tied:K": it follows the plant's (fitted) K
        assert float(p.effects[1].inner.K[0]) == pytest.approx(float(p.K[0]))
    with pytest.raises(ValueError, match="not fitted"):
        ParamSpace.build(plant, ("backlash.w",))
    with pytest.raises(ValueError, match="not in the initial parameters"):
        ParamSpace.build(plant, ("gravity.mgl",))
    # round trip through theta
    th0 = space.theta0()
    ph0 = space.physical(th0)
    assert float(ph0["K"][0]) == pytest.approx(6.77, rel=1e-12)


def test_a_capped_stribeck_excess_stays_below_its_cap_and_the_default_is_exp():
    """``ParamSpace.friction_cap`` bounds Fs - Fc (discover sets it to the largest logged
    torque); left infinite it is exactly the "ordered" map Fs = Fc + exp(u), so no other fit
    changes; values round-trip through theta either way, a value past the cap is moved
    inside, and the map stays finite and differentiable far past it."""
    space = ParamSpace.build(paper_params().to_plant(), ("Fc", "Fs"))
    th = {"Fc": jnp.asarray([np.log(0.1)]), "Fs": jnp.asarray([np.log(0.05)])}
    assert float(space.physical(th)["Fs"][0]) == 0.1 + 0.05  # exp, bit for bit
    capped = eqx.tree_at(lambda s: s.friction_cap, space, jnp.asarray(2.0))
    for u in (-3.0, 0.0, 3.0, 50.0, 800.0):
        ph = capped.physical({"Fc": th["Fc"], "Fs": jnp.asarray([u])})
        assert 0.1 < float(ph["Fs"][0]) <= (0.1 + 2.0) * (1 + 1e-12)
        g = jax.grad(lambda v: capped.physical({"Fc": th["Fc"], "Fs": v})["Fs"][0])(
            jnp.asarray([u]))
        assert np.isfinite(float(g[0]))
    for sp in (space, capped):
        back = sp.physical(sp.theta_of({"Fc": 0.1, "Fs": 1.3}))
        assert float(back["Fs"][0]) == pytest.approx(1.3, rel=1e-12)
    past = capped.physical(capped.theta_of({"Fc": 0.1, "Fs": 40.0}))
    assert float(past["Fs"][0]) < 0.1 + 2.0


def test_a_capped_coulomb_level_stays_below_its_cap():
    """The cap bounds Fc as well (a level the actuator never breaks turns the bristles into a
    spring to ground): Fc stays below it however far its coordinate runs, round-trips
    below it, and is exp(u) bit for bit while the cap is infinite."""
    space = ParamSpace.build(paper_params().to_plant(), ("Fc", "Fs", "sigma0"))
    th = {"Fc": jnp.asarray([np.log(0.1)]), "Fs": jnp.asarray([np.log(0.05)]),
          "sigma0": jnp.asarray([0.0])}
    assert float(space.physical(th)["Fc"][0]) == np.exp(np.log(0.1))
    capped = eqx.tree_at(lambda s: s.friction_cap, space, jnp.asarray(2.0))
    for u in (0.0, 5.0, 300.0, 800.0):
        ph = capped.physical({**th, "Fc": jnp.asarray([u])})
        assert 0.0 < float(ph["Fc"][0]) <= 2.0 * (1 + 1e-12)
        assert float(ph["Fs"][0]) <= 4.0 * (1 + 1e-12)
    back = capped.physical(capped.theta_of({"Fc": 1.5, "Fs": 1.7}))
    assert float(back["Fc"][0]) == pytest.approx(1.5, rel=1e-12)
    assert float(back["Fs"][0]) == pytest.approx(1.7, rel=1e-12)


def test_a_positive_parameter_driven_far_down_stays_positive():
    """A coordinate u of a positive parameter far below any data's reach (a flat direction
    the solver ran along: KUKA axis 2 B drove Fc to exactly 0 and discover stopped on
    "Fc must be > 0") maps to exp(LOG_TINY) > 0, not to an underflowed 0, and the parameter
    file of that point builds a plant; above LOG_TINY the map is exp, bit for bit."""
    from jaxflex.fit import params_of_plant
    from jaxflex.fit.space import LOG_TINY

    space = ParamSpace.build(paper_params().to_plant(), ("Fc", "Fs", "K"))
    th = {"Fc": jnp.asarray([-800.0]), "Fs": jnp.asarray([-2.0]), "K": jnp.asarray([-5000.0])}
    ph = space.physical(th)
    assert float(ph["Fc"][0]) == float(np.exp(LOG_TINY)) > 0.0
    assert float(ph["K"][0]) == float(np.exp(LOG_TINY))
    params_of_plant(space.plant(th), paper_params()).to_plant()  # no "must be > 0"
    assert float(space.physical(th | {"Fc": jnp.asarray([-3.0])})["Fc"][0]) == float(np.exp(-3.0))
    # Fc free under a fixed Fs (Fc = Fs sigmoid(u)) stays positive too
    frac = ParamSpace.build(paper_params().to_plant(), ("Fc",))
    assert float(frac.physical({"Fc": jnp.asarray([-800.0])})["Fc"][0]) > 0.0


def test_a_lower_bound_can_be_raised_for_a_coarser_step():
    """``ParamSpace.with_lower_bound``: a "positive>=m" time constant's bound is set (raised
    for a coarser step, lowered for a finer one), values above it round-trip, the map stays
    above it for any coordinate; a parameter without a lower bound, or not in the space, is
    refused by name."""
    plant = paper_params().to_plant().with_effects(
        EFFECTS["actuator_lag"](T=np.array([0.012])))
    space = ParamSpace.build(plant, ("K", "actuator_lag.T"))
    raised = space.with_lower_bound("actuator_lag.T", 6e-3)
    assert raised.with_lower_bound("actuator_lag.T", 7.5e-4).transforms[1][1] == 7.5e-4
    th = raised.theta_of({"actuator_lag.T": 0.012})
    assert float(raised.physical(th)["actuator_lag.T"][0]) == pytest.approx(0.012, rel=1e-12)
    low = raised.physical(th | {"actuator_lag.T": jnp.asarray([-50.0])})
    assert 6e-3 <= float(low["actuator_lag.T"][0]) < 6e-3 * (1 + 1e-12)
    with pytest.raises(ValueError, match="no lower bound"):
        space.with_lower_bound("K", 1.0)
    with pytest.raises(ValueError, match="not a parameter"):
        space.with_lower_bound("time_delay.T", 1.0)


def test_gap_is_zero_for_exact_replay_and_one_for_standing_still():
    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.6), substeps=2)
    prob = _fixed_start_problem(p.to_plant(), log, ("Fc", "Fs"))
    m = prob.segs.y_meas
    num = lambda ys: float(jnp.sqrt(jnp.sum((ys - m) ** 2) / jnp.sum((m - m[:, :1]) ** 2)))
    assert num(m) == 0.0
    assert num(jnp.broadcast_to(m[:, :1], m.shape)) == pytest.approx(1.0)
    # the model that made the log replays it from measured starts better than a wrong one
    # (the starts come from differentiated angles and a steady-state z, so not exactly)
    true_gap = float(prob.gap(prob.y0()))
    wrong = prob.space.theta_of({"Fc": 0.2, "Fs": 0.25})
    assert true_gap < 0.15 and true_gap < 0.5 * float(prob.gap(wrong))


def test_structured_jacobian_with_gated_effects_and_measured_starts():
    """The custom JVP equals plain autodiff for a fixed-start problem whose plant holds gated
    effects with internal states (warm-up over the torque before each segment)."""
    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.6), substeps=1)
    plant = _gated_plant(("actuator_lag",))
    prob = _fixed_start_problem(plant, log, ("Fc", "Fs", "K", "actuator_lag.T",
                                             "torque_offset.offset"))
    plain = dataclasses.replace(prob, structured=False)
    from jax.flatten_util import ravel_pytree

    flat, unravel = ravel_pytree(prob.y0())
    f_s = lambda x: prob.residuals(unravel(x))
    f_p = lambda x: plain.residuals(unravel(x))
    r_s, r_p = (np.asarray(jax.jit(f)(flat)) for f in (f_s, f_p))
    np.testing.assert_array_equal(r_s, r_p)
    J_s, J_p = (np.asarray(jax.jit(jax.jacfwd(f))(flat)) for f in (f_s, f_p))
    assert np.max(np.abs(J_s - J_p)) <= 1e-12 * np.max(np.abs(J_p))
    assert np.max(np.abs(J_p)) > 0


def test_masked_parameters_stay_fixed_and_share_one_compilation():
    """Two problems that differ in which parameters are fitted (mask, gates: data) reuse the
    solver's compiled step; masked parameters do not move and get no standard error."""
    truth = paper_params()
    log, _ = synthetic_log(truth.to_plant(), excitation_torque(t_final=0.9), substeps=1)
    start = paper_params()
    start.friction["Fc"] = [0.15]
    start.friction["Fs"] = [0.2]
    plant = start.to_plant(with_effects=False).with_effects(
        Gated(EFFECTS["torque_offset"].typical(1), jnp.asarray(0.0)))
    prob = _fixed_start_problem(plant, log, ("Fc", "Fs", "sigma2", "torque_offset.offset"))
    th0 = prob.space.theta0()
    a = eqx.tree_at(lambda q: q.space, prob, prob.space.with_mask(("Fc", "Fs"), th0))
    b = eqx.tree_at(lambda q: q.space, prob, prob.space.with_mask(("Fc", "Fs", "sigma2"), th0))
    traces = []

    def counted(y, prob):  # runs in Python only while JAX traces (compiles)
        traces.append(1)
        return prob.residuals(y)

    sa = least_squares(a, th0, fn=counted, max_steps=30)
    after_first = len(traces)
    sb = least_squares(b, th0, fn=counted, max_steps=30)
    assert after_first > 0 and len(traces) == after_first  # b reused a's compilations
    assert float(sa.y["sigma2"][0]) == float(th0["sigma2"][0])
    assert float(sb.y["sigma2"][0]) != float(th0["sigma2"][0])
    assert sb.cost <= sa.cost * (1 + 1e-9)
    phys = b.space.physical(sb.y)
    assert float(phys["Fc"][0]) == pytest.approx(0.11, rel=0.1)  # from 0.15; starts are estimates
    cov = covariance(a, sa.y)
    assert np.isnan(cov["stderr"]["sigma2"][0]) and cov["stderr"]["Fc"][0] > 0
    assert cov["n_free"] == 2


def test_solver_reports_a_capped_run_as_unconverged():
    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.6), substeps=1)
    start = paper_params()
    start.friction["Fc"] = [0.2]
    start.friction["Fs"] = [0.3]
    prob = _fixed_start_problem(start.to_plant(), log, ("Fc", "Fs"))
    sol = least_squares(prob, prob.y0(), max_steps=1)
    assert not sol.converged and "max_steps" in sol.reason and sol.steps == 1
    with pytest.raises(ValueError, match="max_steps"):
        least_squares(prob, prob.y0(), max_steps=0)


@pytest.mark.parametrize("shape", [(1000,), (400, 2), (37, 3)])
def test_savgol_equals_scipy(shape):
    """jaxflex's Savitzky-Golay (written out to keep scipy.signal's 0.55 s import out of every
    command) gives scipy's ``savgol_filter(mode="interp")`` and ``savgol_coeffs`` to 1e-9,
    inside and on both edges, for smoothing and both derivatives, and a window longer than
    the samples is cut to their count as before."""
    import scipy.signal

    from jaxflex.fit import savgol, savgol_coeffs

    rng = np.random.default_rng(0)
    t = np.arange(shape[0]) * 1e-3
    x = np.cumsum(rng.normal(size=shape), axis=0) + np.sin(40 * t).reshape(-1, *[1] * (len(shape) - 1))
    for deriv in (0, 1, 2):
        for window in (5, 31, 41):
            w = min(window, shape[0] - (1 - shape[0] % 2))
            ref = scipy.signal.savgol_filter(x, w, 3, deriv=deriv, delta=1e-3, axis=0,
                                             mode="interp")
            assert np.max(np.abs(savgol(x, 1e-3, deriv, window) - ref)) <= 1e-9 * np.max(np.abs(ref))
        np.testing.assert_allclose(savgol_coeffs(31, 3, deriv, 1e-3),
                                   scipy.signal.savgol_coeffs(31, 3, deriv, 1e-3, use="dot"),
                                   rtol=1e-9, atol=1e-12 * 1e3**deriv)
    with pytest.raises(ValueError, match="odd window"):
        savgol_coeffs(30, 3)


def test_noise_level_finds_quantisation_step():
    t = np.arange(5000) * 1e-3
    step = 2 * np.pi / 2**14
    q = np.round(0.3 * np.sin(2 * np.pi * 0.7 * t) / step) * step
    nl = noise_level(q)
    assert nl["step"] == pytest.approx(step, rel=1e-6)
    assert nl["total_std"] == pytest.approx(step / np.sqrt(12), rel=0.3)


def test_noise_level_of_a_moving_fine_encoder():
    """A 20-bit encoder with half a count of white noise on a multisine at 1 kHz: one count
    as the step and the total noise, sqrt(step^2 / 12 + (step / 2)^2), within 10% (a
    smoothing-residual estimate read 2x too high here, a percentile of the increments several
    counts)."""
    rng = np.random.default_rng(1)
    t = np.arange(10000) * 1e-3
    step = 2 * np.pi / 2**20
    x = sum(a * np.sin(2 * np.pi * f * t + ph) for a, f, ph in
            ((0.3, 0.4, 0.0), (0.05, 3.1, 1.0), (0.01, 11.0, 2.0)))
    q = np.round((x + 0.5 * step * rng.normal(size=t.size)) / step) * step
    nl = noise_level(q)
    assert nl["step"] == pytest.approx(step, rel=1e-6)
    assert nl["total_std"] == pytest.approx(np.sqrt(step**2 / 12 + (0.5 * step) ** 2), rel=0.1)


def test_segments_refuse_bad_lengths():
    t = np.arange(100) * 1e-3
    log = Log.from_arrays(t=t, tau=t, q1=t, q2=t)
    with pytest.raises(ValueError, match="segment length"):
        make_segments(log, length=1)
    with pytest.raises(ValueError, match="segment length"):
        make_segments(log, length=101)


@pytest.mark.slow
@pytest.mark.parametrize("scaling", ["identity", "marquardt"])
def test_shooting_solve_equals_dense_solve(scaling):
    """The block-tridiagonal/Schur solve of the multiple-shooting normal equations gives the
    same damped Gauss-Newton step as the dense solve, to 1e-10."""
    import lineax as lx
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit.normal import dense_newton_step, shooting_newton_step
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    init = perturb(p, DEFAULT_FREE, (1.5, 1.5, 0.5, 1.5, 0.5, 1.5))
    prob, y0 = make_problem(log, init, DEFAULT_FREE + ("K",), segment_length=100, substeps=1)
    assert prob.segs.count == 5
    r, lin = jax.linearize(prob.residuals, y0)
    jac = lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: y0))
    for lam in (1e-6, 1.0, 1e4):
        a = ravel_pytree(dense_newton_step(jac, r, jnp.asarray(lam), scaling))[0]
        b = ravel_pytree(shooting_newton_step(jac, r, jnp.asarray(lam), scaling))[0]
        assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(a)), lam


def test_segment_slots_hold_every_count_with_little_padding():
    from jaxflex.fit.segments import segment_slots

    slots = [segment_slots(c) for c in range(1, 3000)]
    assert slots[:2] == [1, 2]  # the smallest logs are not padded
    assert all(s >= c for c, s in zip(range(1, 3000), slots))
    assert max(s / c for c, s in zip(range(9, 3000), slots[8:])) <= 1.25
    assert len(set(slots)) < 40  # few shapes for 3,000 lengths


@pytest.mark.slow
def test_logs_of_other_lengths_share_the_compiled_solver(lowerings):
    """A multiple-shooting problem is solved in its bucket of segment slots (inert padding
    segments): the same steps, cost, residual and normal equations as in its own shape (to
    1e-10), and a log with another segment count in the same bucket lowers no new solver,
    residual, replay or covariance program."""
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit import discretisation_bias, residuals, simulated_outputs
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))

    def problem(t_final):
        log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=t_final), substeps=1)
        return make_problem(log, init, DEFAULT_FREE, segment_length=50, substeps=1)

    prob, y0 = problem(0.45)  # 9 segments in 10 slots
    assert prob.segs.count == 9
    a = least_squares(prob, y0, max_steps=3)
    b = least_squares(prob, y0, max_steps=3, bucket=False)
    fa, fb = (np.asarray(ravel_pytree(s.y)[0]) for s in (a, b))
    assert a.steps == b.steps and a.y[1].shape == y0[1].shape
    assert np.max(np.abs(fa - fb)) <= 1e-10 * np.max(np.abs(fb))
    assert a.cost == pytest.approx(b.cost, rel=1e-10)
    np.testing.assert_allclose(a.residual, b.residual, rtol=0, atol=1e-10 * np.max(np.abs(b.residual)))
    for k, v in b.normal.items():
        if hasattr(v, "shape"):
            assert a.normal[k].shape == v.shape, k
            assert np.max(np.abs(a.normal[k] - v)) <= 1e-10 * max(np.max(np.abs(v)), 1e-300), k
    np.testing.assert_allclose(residuals(prob, a.y), prob.residuals(a.y), rtol=0,
                               atol=1e-10 * np.max(np.abs(b.residual)))
    np.testing.assert_allclose(simulated_outputs(prob, a.y), prob.simulate(a.y)[0], rtol=1e-12)
    covariance(prob, a.y, solution=a), discretisation_bias(prob, a)

    other, y1 = problem(0.5)  # 10 segments: the same bucket
    assert other.segs.count == 10
    with lowerings() as lowered:
        sol = least_squares(other, y1, max_steps=3)
        simulated_outputs(other, sol.y), residuals(other, sol.y)
        covariance(other, sol.y, solution=sol), discretisation_bias(other, sol)
        # the stops are data of the compiled loop: other bounds and windows lower nothing
        least_squares(other, y1, max_steps=4, decrement_tol=CostBound(1e-3, 1e-9),
                      stall=(3, CostBound(0.0, 1e-12)))
    assert lowered == [], lowered
    assert sol.y[1].shape == y1[1].shape and sol.residual.shape == other.residuals(sol.y).shape


@pytest.mark.slow
def test_traced_substeps_equal_compiled_ones_and_share_every_program(lowerings):
    """A problem whose substeps are a traced count (``dynamic_substeps``, identify's automatic
    choice) gives the compiled-in count's numbers (solve, replay, covariance), and a problem
    with other substeps (the coarse-to-fine refinement) lowers no program at all."""
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit import discretisation_bias, dynamic_substeps, refined, simulated_outputs
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.3), substeps=4)
    fixed, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=50, substeps=2)
    traced, _ = make_problem(log, init, DEFAULT_FREE, segment_length=50,
                             substeps=dynamic_substeps(2))
    assert traced.n_substeps == fixed.n_substeps == 2
    a = least_squares(fixed, y0, max_steps=3)
    b = least_squares(traced, y0, max_steps=3)
    fa, fb = (np.asarray(ravel_pytree(s.y)[0]) for s in (a, b))
    assert a.steps == b.steps
    assert np.max(np.abs(fa - fb)) <= 1e-10 * np.max(np.abs(fa))
    assert b.cost == pytest.approx(a.cost, rel=1e-10)
    covariance(traced, b.y, solution=b), discretisation_bias(traced, b)
    np.testing.assert_allclose(simulated_outputs(traced, b.y), simulated_outputs(fixed, b.y),
                               rtol=1e-12, atol=0)

    finer = refined(traced, 4)
    assert finer.n_substeps == 8 and not isinstance(finer.substeps, int)
    with lowerings() as lowered:
        sol = least_squares(finer, b.y, max_steps=2)
        simulated_outputs(finer, sol.y)
        covariance(finer, sol.y, solution=sol), discretisation_bias(finer, sol)
    assert lowered == [], lowered
    np.testing.assert_allclose(simulated_outputs(finer, sol.y),
                               simulated_outputs(refined(fixed, 4), sol.y), rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="substeps"):
        dynamic_substeps(0)


@pytest.mark.slow
def test_a_check_given_a_coarser_checks_order_replays_once_and_keeps_to_the_safe_side(
        monkeypatch):
    """``replay_error(..., order=p)`` (``refine_fit``'s checks after the first) makes one
    finer replay instead of two and uses p no higher than the scheme's own order: given a
    higher p it reckons with ``SCHEME_ORDER``, the shift ``discretisation_bias`` reads from
    it the measured one's rescaled by (1 - 2^-p_measured) / (1 - 2^-2) (the shift is linear
    in the extrapolated error). ``induced_point`` moves the fitted entries by that shift."""
    import jaxflex.fit.discretisation as disc
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.3), substeps=4)
    prob, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=50, substeps=1)
    sol = least_squares(prob, y0, max_steps=3)
    measured = disc.discretisation_bias(prob, sol)
    replays = []
    real = disc.residuals
    monkeypatch.setattr(disc, "residuals", lambda q, y: replays.append(q.n_substeps) or real(q, y))
    error = disc.replay_error(prob, sol, order=5.0)
    given = disc.discretisation_bias(prob, sol, error=error)
    assert replays == [2] and given["order"] == disc.SCHEME_ORDER
    scale = (1.0 - 2.0 ** -measured["order"]) / (1.0 - 2.0 ** -disc.SCHEME_ORDER)
    for k, v in measured["shift_theta"].items():
        assert given["shift_theta"][k] == pytest.approx(v * scale, rel=1e-8, abs=1e-300), k
    moved = induced_point(prob, sol, error.e, 0.5)
    for k, v in given["shift_theta"].items():
        name, j = k.split("[")[0], int(k.split("[")[1].rstrip("]"))
        step = np.ravel(moved[0][name])[j] - np.ravel(sol.y[0][name])[j]
        assert step == pytest.approx(0.5 * v, rel=1e-8, abs=1e-300), k
    assert moved[1].shape == sol.y[1].shape


def _plain_residuals(y, prob):  # the same residuals by another function: the dense route
    return prob.residuals(y)


@pytest.mark.slow
def test_structured_covariance_equals_dense_covariance():
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))
    prob, y0 = make_problem(log, init, DEFAULT_FREE + ("K",), segment_length=100, substeps=1)
    fast = covariance(prob, y0)
    dense = covariance(prob, y0, fn=_plain_residuals)
    assert fast["rank"] == dense["rank"] and fast["n_free"] == dense["n_free"]
    for k in prob.space.names:
        # the Schur route squares the conditioning the dense SVD sees: agree to 1e-4
        np.testing.assert_allclose(fast["stderr"][k], dense["stderr"][k], rtol=1e-4)
    np.testing.assert_allclose(fast["rss"], dense["rss"], rtol=1e-12)


@pytest.mark.slow
def test_covariance_from_the_solvers_normal_equations_equals_a_fresh_one(monkeypatch):
    """``covariance(..., solution=sol)`` reuses the solver's normal equations at its final
    point (no second linearisation): the same standard errors, rank, rss and final cost as
    linearising again at that point."""
    from jaxflex.fit import cost
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))
    prob, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=100, substeps=1)
    sol = least_squares(prob, y0, max_steps=4)
    assert sol.normal is not None and "Ntt" in sol.normal
    reused = covariance(prob, sol.y, solution=sol)
    fresh = covariance(prob, sol.y)
    assert reused["rank"] == fresh["rank"] and reused["n_free"] == fresh["n_free"]
    for k in prob.space.names:
        np.testing.assert_allclose(reused["stderr"][k], fresh["stderr"][k], rtol=1e-8)
    np.testing.assert_allclose(reused["rss"], fresh["rss"], rtol=1e-10)
    np.testing.assert_allclose(sol.cost, cost(prob, sol.y), rtol=1e-10)
    # a dense fit reuses the Jacobian its solver kept: the same standard errors without
    # linearising again
    dsol = least_squares(prob, y0, fn=_plain_residuals, structure="dense", max_steps=3)
    assert "J" in dsol.normal
    reused = covariance(prob, dsol.y, fn=_plain_residuals, solution=dsol)
    fresh = covariance(prob, dsol.y, fn=_plain_residuals)
    assert reused["rank"] == fresh["rank"]
    for k in prob.space.names:
        np.testing.assert_allclose(reused["stderr"][k], fresh["stderr"][k], rtol=1e-10)
    # the static map's fit takes that route (no second linearisation)
    import jaxflex.fit.uncertainty as uncertainty_module
    from jaxflex.identify.static import STATIC_NAMES, StaticMap, fit_static_map

    v = np.concatenate([-np.geomspace(2.0, 0.01, 20), np.geomspace(0.01, 2.0, 20)])
    lug = p.to_plant().friction
    F = np.asarray(jax.vmap(lambda vi: lug.steady_state(vi[None])[0])(jnp.asarray(v))).ravel()
    F = F + 1e-3 * np.random.default_rng(0).standard_normal(v.size)
    start = {k: 1.2 * float(p.friction[k][0]) for k in STATIC_NAMES}
    fresh_route = uncertainty_module._jacobian
    reused = []

    def linearised_again(*a, **k):
        reused.append(False)
        return fresh_route(*a, **k)

    monkeypatch.setattr(uncertainty_module, "_jacobian", linearised_again)
    fit = fit_static_map(StaticMap(v=v, F=F), start)
    assert reused == [] and all(np.isfinite(se) and se > 0 for _, se in fit.values()), fit


@pytest.mark.slow
def test_zero_residual_optimum_is_reported_converged():
    """A noise-free log replayed by its own model: the optimum has a residual at rounding
    level, where every trial step is rejected (the cost cannot fall) and optimistix's test,
    which needs an accepted step, never fires. The trust region then shrinks below the
    tolerance on the unknowns, which ends the run as converged (MINPACK's xtol test), at the
    true values, instead of running to max_steps."""
    from jax.flatten_util import ravel_pytree

    from jaxflex.identify import make_problem, perturb

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.6), substeps=1)
    init = perturb(p, ("Fc", "sigma2"), (1.05, 0.95))
    prob, y0 = make_problem(log, init, ("Fc", "sigma2"), segment_length=200, substeps=1)
    sol = least_squares(prob, y0, max_steps=200)
    assert sol.converged and sol.steps < 200, (sol.reason, sol.steps, sol.cost)
    phys = prob.space.physical(sol.y[0])
    assert abs(float(phys["Fc"][0]) / 0.11 - 1) < 1e-6
    assert abs(float(phys["sigma2"][0]) / 0.2 - 1) < 1e-6
    assert np.all(np.isfinite(ravel_pytree(sol.y)[0]))


@pytest.mark.slow
def test_shooting_solve_equals_dense_solve_for_two_joints():
    """The block-arrow solve with (n_state, n) segment starts, n = 2 (two independent joints
    with their own parameters): the same damped step as the dense solve, to 1e-10."""
    import lineax as lx
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit.normal import dense_newton_step, shooting_newton_step
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb
    from jaxflex.io.params import Params

    p = Params.from_dict({
        "plant": {"I": [0.07, 0.05], "J": [0.005, 0.004], "K": [6.77, 5.0]},
        "friction": {"Fc": [0.11, 0.08], "Fs": [0.15, 0.11], "vs": [0.05, 0.04],
                     "sigma0": [100.0, 80.0], "sigma1": [0.1, 0.08], "sigma2": [0.2, 0.15]}})
    tau = excitation_torque(t_final=0.5, n=2) * np.array([1.0, 0.8])
    log, _ = synthetic_log(p.to_plant(), tau, substeps=1)
    init = perturb(p, DEFAULT_FREE, (1.5, 1.5, 0.5, 1.5, 0.5, 1.5))
    prob, y0 = make_problem(log, init, DEFAULT_FREE + ("K",), segment_length=100, substeps=1)
    assert prob.segs.count == 5 and prob.segs.x0.shape == (5, 5, 2)
    r, lin = jax.linearize(prob.residuals, y0)
    jac = lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: y0))
    for scaling in ("identity", "marquardt"):
        for lam in (1e-6, 1.0, 1e4):
            a = ravel_pytree(dense_newton_step(jac, r, jnp.asarray(lam), scaling))[0]
            b = ravel_pytree(shooting_newton_step(jac, r, jnp.asarray(lam), scaling))[0]
            assert np.max(np.abs(a - b)) <= 1e-10 * np.max(np.abs(a)), (scaling, lam)


def _rosenbrock(y, k):  # a curved narrow valley, y* = (1, 1)
    return jnp.stack([k * (y[1] - y[0] ** 2), 1.0 - y[0]])


def test_geodesic_acceleration_takes_a_curved_valley_in_fewer_steps():
    """Rosenbrock's valley (width 1/1000): plain Levenberg-Marquardt creeps along it with a
    small trust region; with geodesic acceleration the solver reaches the same minimum in
    at most a third of the steps."""
    y0 = jnp.array([-1.2, 1.0])
    plain = least_squares(jnp.asarray(1e3), y0, fn=_rosenbrock, max_steps=2000)
    geo = least_squares(jnp.asarray(1e3), y0, fn=_rosenbrock, max_steps=2000, geodesic=0.75)
    for s in (plain, geo):
        assert s.converged, s.reason
        np.testing.assert_allclose(np.asarray(s.y), [1.0, 1.0], atol=1e-8)
    assert 3 * geo.steps <= plain.steps, (geo.steps, plain.steps)


def test_a_stalled_run_ends_early_and_says_it_did_not_converge():
    """The progress stop (``stall``): on Rosenbrock's valley, where plain Levenberg-Marquardt
    creeps, the run ends once ||r||^2 fell by less than the bound over the window, reported
    not converged with the reason, and the costs it saw confirm the rule; a bound of 0 changes
    nothing."""
    y0 = jnp.array([-1.2, 1.0])
    k = jnp.asarray(1e3)
    plain = least_squares(k, y0, fn=_rosenbrock, max_steps=2000)
    costs = []
    stalled = least_squares(k, y0, fn=_rosenbrock, max_steps=2000, stall=(5, 1e-2),
                            progress=lambda i, t, m: costs.append(float(m.split()[-1])))
    assert not stalled.converged and stalled.reason.startswith("stalled"), stalled.reason
    assert 5 < stalled.steps < plain.steps, (stalled.steps, plain.steps)
    assert 2 * (costs[-6] - costs[-1]) < 1e-2
    assert all(2 * (costs[i - 5] - costs[i]) >= 1e-2 for i in range(5, len(costs) - 1))
    # a bound of two pieces is the larger: either piece alone gives the same run
    for two in (CostBound(0.0, 1e-2, other=(0.0, 5e-3)), CostBound(0.0, -1.0, other=(0.0, 1e-2))):
        assert two(3.0) == 1e-2
        again = least_squares(k, y0, fn=_rosenbrock, max_steps=2000, stall=(5, two))
        assert again.steps == stalled.steps and again.reason == stalled.reason
    same = least_squares(k, y0, fn=_rosenbrock, max_steps=2000, stall=(5, 0.0))
    assert same.steps == plain.steps and same.converged
    np.testing.assert_array_equal(np.asarray(same.y), np.asarray(plain.y))
    with pytest.raises(ValueError, match="stall window"):
        least_squares(k, y0, fn=_rosenbrock, stall=(0, 1.0))
    with pytest.raises(ValueError, match="stall window"):
        least_squares(k, y0, fn=_rosenbrock, stall=(65, 1.0))


def test_an_interrupt_returns_the_point_reached_marked_unconverged():
    """Ctrl-C (here raised from the progress callback at step 3) ends the run between calls
    of the compiled loop: not converged, the reason says so, and the steps reported are those
    the returned point has taken (the call's steps, at least the 3 reported)."""
    from jaxflex.fit import cost

    seen = []

    def interrupt(i, t, m):
        seen.append((i, m))
        if i == 3:
            raise KeyboardInterrupt

    k = jnp.asarray(1e3)
    sol = least_squares(k, jnp.array([-1.2, 1.0]), fn=_rosenbrock, max_steps=2000,
                        progress=interrupt)
    assert not sol.converged and sol.reason == f"interrupted after {sol.steps} steps"
    assert sol.steps >= 3 and [i for i, _ in seen] == [1, 2, 3]
    assert sol.cost == pytest.approx(cost(k, sol.y, _rosenbrock), rel=1e-12)


def test_work_made_ahead_runs_in_order_and_a_failure_stops_nothing():
    """``Ahead`` runs its callables in a background thread under the caller's float64 mode;
    one that raises is passed over (the real call meets it again), the next still runs, and
    no thread is left once joined."""
    import threading

    from jaxflex.runtime.ahead import THREAD_NAME, Ahead

    ran = []

    def fails():
        ran.append("fails")
        raise FloatingPointError("made ahead")

    def works():
        ran.append(jnp.asarray(1.0).dtype)

    ahead = Ahead([fails, works])
    ahead.wait(1)
    ahead.join()
    assert ran == ["fails", jnp.dtype("float64")]
    assert not any(t.name == THREAD_NAME and t.is_alive() for t in threading.enumerate())


def test_side_by_side_keeps_order_float64_and_failures():
    """``side_by_side`` runs calls in worker threads under the caller's float64 mode: results
    in the items' order, the same with one worker as with two, a raised exception handed
    back beside the others' results, and no worker left once it returns; ``all_side_by_side``
    raises it."""
    import threading

    from jaxflex.runtime.ahead import POOL_NAME, all_side_by_side, side_by_side

    def work(k):
        if k == 2:
            raise FloatingPointError("item 2")
        x = jnp.arange(4.0) * k
        return float(jnp.sum(jnp.sin(x))), x.dtype

    items = [0, 1, 2, 3, 4]
    two = side_by_side(work, items, workers=2)
    one = side_by_side(work, items, workers=1)
    assert [r for r, _ in two] == [r for r, _ in one]
    assert isinstance(two[2][1], FloatingPointError) and two[2][0] is None
    assert all(e is None and r[1] == jnp.dtype("float64") for i, (r, e) in enumerate(two)
               if i != 2)
    assert two[3][0][0] == pytest.approx(float(np.sum(np.sin(np.arange(4.0) * 3))), rel=1e-15)
    assert not any(t.name.startswith(POOL_NAME) and t.is_alive()
                   for t in threading.enumerate())
    assert all_side_by_side(work, [0, 1]) == [r for r, _ in one[:2]]
    with pytest.raises(FloatingPointError, match="item 2"):
        all_side_by_side(work, items)


def _decay(y, data):  # residuals in units of the noise (sigma = 1)
    t, z = data
    return y[0] * jnp.exp(-y[1] * t) + y[2] - z


def test_statistical_stop_ends_within_a_small_fraction_of_a_standard_error():
    """With residuals in noise units, the statistical stop (Gauss-Newton decrement below
    1e-2) ends the run earlier than the tolerances, with the unknowns within 0.1 standard
    errors of the fully converged ones."""
    rng = np.random.default_rng(3)
    t = jnp.linspace(0.0, 5.0, 400)
    z = 30.0 * jnp.exp(-0.7 * t) + 2.0 + jnp.asarray(rng.normal(size=t.shape))
    y0 = jnp.array([5.0, 3.0, -4.0])
    full = least_squares((t, z), y0, fn=_decay, max_steps=500)
    stat = least_squares((t, z), y0, fn=_decay, max_steps=500, decrement_tol=1e-2)
    assert full.converged and stat.converged
    assert stat.reason.startswith("statistical stop"), stat.reason
    assert stat.steps < full.steps, (stat.steps, full.steps)
    J = np.asarray(jax.jacfwd(_decay)(full.y, (t, z)))
    se = np.sqrt(np.diag(np.linalg.inv(J.T @ J)))
    assert np.all(np.abs(np.asarray(stat.y) - np.asarray(full.y)) < 0.1 * se)
    # residuals 7x their noise units: the stop measured against the fit's own residual
    # variance (a callable bound, discover's ``relative_stop``) ends at the same point
    from jaxflex.discover import relative_stop

    rel = least_squares((t, z * 7.0), y0 * jnp.array([7.0, 1.0, 7.0]),
                        fn=_decay, max_steps=500, decrement_tol=relative_stop(t.size - 3))
    assert rel.reason.startswith("statistical stop"), rel.reason
    assert np.all(np.abs(np.asarray(rel.y) / np.array([7.0, 1.0, 7.0]) - np.asarray(full.y))
                  < 0.1 * se)
    # any other callable is judged on the host, one step a call: the same run
    bound = relative_stop(t.size - 3)
    host = least_squares((t, z * 7.0), y0 * jnp.array([7.0, 1.0, 7.0]), fn=_decay,
                         max_steps=500, decrement_tol=lambda c: bound(c))
    assert host.steps == rel.steps and host.reason == rel.reason
    np.testing.assert_allclose(np.asarray(host.y), np.asarray(rel.y), rtol=1e-12)
    with pytest.raises(ValueError, match="decrement_tol"):
        least_squares((t, z), y0, fn=_decay, decrement_tol=-1.0)


@pytest.mark.slow
def test_shooting_jacobian_blocks_give_J_and_J_transpose():
    """The Jacobian blocks the shooting descent keeps (for geodesic acceleration) give J v and
    J^T w equal to the materialised Jacobian's, to 1e-12."""
    import lineax as lx
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit.normal import shooting_blocks, shooting_mv, shooting_tmv
    from jaxflex.identify import DEFAULT_FREE, make_problem

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    prob, y0 = make_problem(log, p, DEFAULT_FREE, segment_length=100, substeps=1)
    r, lin = jax.linearize(prob.residuals, y0)
    jac = lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: y0))
    J = np.asarray(jac.as_matrix())
    blk = shooting_blocks(jac, r)
    rng = np.random.default_rng(0)
    v = rng.normal(size=J.shape[1])
    w = rng.normal(size=J.shape[0])
    v_theta, v_x = ravel_pytree(y0)[1](jnp.asarray(v))
    Jv = shooting_mv(blk, ravel_pytree(v_theta)[0], v_x.reshape(v_x.shape[0], -1))
    np.testing.assert_allclose(Jv, J @ v, atol=1e-12 * np.max(np.abs(J @ v)))
    gt, gx = shooting_tmv(blk, jnp.asarray(w))
    JTw = J.T @ w
    np.testing.assert_allclose(np.concatenate([gt, np.ravel(gx)]), JTw,
                               atol=1e-12 * np.max(np.abs(JTw)))


@pytest.mark.slow
def test_problem_residual_blocks_equal_the_probed_linearisation():
    """``Problem.residual_blocks`` (the solver's Jacobian, straight from the segment
    replays) gives the residual and the Jacobian blocks that probing the linearised residual
    gives (``shooting_blocks``), to 1e-12: with a parameter mask (``jac_columns``), in padding
    slots, and with a non-uniform continuity weight. Fails if a row weight, a mask or the
    coupling to the next start is wrong."""
    import lineax as lx

    from jaxflex.fit.normal import shooting_blocks
    from jaxflex.identify import DEFAULT_FREE, make_problem

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    prob, y0 = make_problem(log, p, DEFAULT_FREE, segment_length=100, substeps=1)
    prob = eqx.tree_at(lambda q: q.w_def, prob, prob.w_def * jnp.arange(1.0, 6.0).reshape(
        (-1,) + (1,) * (prob.w_def.ndim - 1)))
    fitted = [k for k in prob.space.names if k != "vs"]
    masked = eqx.tree_at(lambda q: q.space, prob, prob.space.with_mask(fitted, y0[0]))
    masked = dataclasses.replace(masked, jac_columns=len(fitted))
    pad = Padding.of(prob, y0)
    cases = [(prob, y0), (masked, y0), (prob.padded(pad.slots), pad.unknowns(y0))]
    for q, y in cases:
        r, lin = jax.linearize(q.residuals, y)
        want = shooting_blocks(lx.FunctionLinearOperator(lin, jax.eval_shape(lambda: y)), r)
        r_own, got = q.residual_blocks(y)
        np.testing.assert_allclose(r_own, r, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(r))))
        for k in ("Jt", "Jx", "Jn"):
            scale = float(jnp.max(jnp.abs(want[k])))
            np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-12 * scale, err_msg=k)
    with pytest.raises(ValueError, match="free segment starts"):
        dataclasses.replace(prob, free_starts=False).residual_blocks(y0[0])


def test_host_side_conversions_compile_no_programs(lowerings):
    """Building segments, parameters and starts from host data, and reading physical values
    back, lowers no per-shape program (``jnp.asarray`` of a numpy array compiles a copy in
    JAX 0.10, and every new process paid those compilations again: 66 programs on a second
    ``discover`` run, 25 after). Fails if one of these paths goes back to eager jnp."""
    from jaxflex.core.validation import as_param

    t = np.arange(437) * 1e-3  # shapes no other test uses
    log = Log.from_arrays(t=t, tau=np.sin(t), q1=np.cos(t), q2=np.cos(t) + 1e-3)
    plant = paper_params().to_plant(with_effects=False)
    space = ParamSpace.build(plant, ("Fc", "Fs", "sigma0"))
    theta = space.theta0()
    space.physical_values(theta)  # its one program, compiled (and kept) before counting
    with lowerings() as lowered:
        as_param(np.full(3, 0.25)), as_param(7.5), as_param([1.0, 2.0, 4.0])
        make_segments(log, kind="flexible", outputs=("q1", "q2"), length=109)
        space.theta_of({"Fc": 0.3})
        values = space.physical_values(space.theta_of({"Fc": 0.3}))
        space.plant(theta)
    assert lowered == [], lowered
    assert values["Fc"][0] == pytest.approx(0.3, rel=1e-12)
    assert isinstance(as_param(7.5), jax.Array) and as_param(7.5).shape == (1,)


@pytest.mark.parametrize("free", [True, False])
def test_encoder_skew_maps_the_replayed_link_output(free):
    """``encoder_skew`` acts on a replay's link output (``link_measured``): the q1 column is
    the link angle minus skew q1' minus offset, q2 and the motion are untouched; gated off it
    changes nothing. From measured starts (``free_starts=False``) the start is the link angle
    that *reads* as measured, so a log whose link channel carries the map is replayed from
    the right state (its error is the replay's own, measured 0.97e-3 rad against 0.99e-3 for
    the plain model on the unskewed log; the plain model on the skewed log: 1.25e-3)."""
    p = paper_params()
    skew, off = 3e-3, 4e-4
    log, xs = synthetic_log(p.to_plant(), excitation_torque(t_final=0.6), substeps=2)
    read = np.asarray(xs.q1) - skew * np.asarray(xs.dq1) - off
    skewed = dataclasses.replace(log, q1=read)
    plain = p.to_plant(with_effects=False)
    sk = EFFECTS["encoder_skew"](skew=[skew], offset=[off])

    def problem(plant, lg):
        prob = _fixed_start_problem(plant, lg, ("Fc",))
        return dataclasses.replace(prob, free_starts=free) if free else prob

    def outputs(plant, lg=skewed):
        prob = problem(plant, lg)
        return np.asarray(prob.simulate(prob.y0())[0])

    base, with_skew = outputs(plain), outputs(plain.with_effects(sk))
    gated_off = outputs(plain.with_effects(Gated(sk, jnp.asarray(0.0))))
    gated_on = outputs(plain.with_effects(Gated(sk, jnp.asarray(1.0))))
    np.testing.assert_array_equal(gated_off, base)
    np.testing.assert_allclose(gated_on, with_skew, rtol=0, atol=1e-15)
    if free:  # the same start state: only the link column moves, by the map
        np.testing.assert_array_equal(with_skew[..., 1], base[..., 1])
        dq1 = np.gradient(base[..., 0], log.dt, axis=1)  # the replay's own link velocity
        np.testing.assert_allclose((with_skew - base)[..., 0], -(skew * dq1 + off), rtol=0,
                                   atol=0.02 * skew * float(np.max(np.abs(dq1))))
    else:  # measured starts: the skewed model replays the skewed log; the plain one does not
        def err(plant, lg):  # RMS replay error from measured starts [rad]
            prob = problem(plant, lg)
            return float(np.sqrt(np.mean((prob.simulate(prob.y0())[0] - prob.segs.y_meas) ** 2)))

        own = err(plain, log)  # the replay's own error (estimated start velocities and z)
        assert err(plain.with_effects(sk), skewed) == pytest.approx(own, rel=0.05)
        assert err(plain, skewed) > 1.2 * own


def test_a_step_that_cannot_be_judged_is_not_a_stop():
    """Normal equations with non-finite entries (a solve that ran into a blown replay): the
    remaining Gauss-Newton step cannot be judged, so it is infinite (no statistical stop),
    not a crash of the identification it is part of."""
    import dataclasses

    from jaxflex.fit import least_squares, remaining_step
    from jaxflex.identify import DEFAULT_FREE, make_problem, perturb

    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.5), substeps=1)
    init = perturb(p, DEFAULT_FREE, (1.5, 1.5, 0.5, 1.5, 0.5, 1.5))
    prob, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=100, substeps=1)
    sol = least_squares(prob, y0, max_steps=2)
    assert math.isfinite(remaining_step(prob, sol))
    blown = jax.tree_util.tree_map(lambda a: np.full(np.shape(a), np.nan), sol.normal)
    assert remaining_step(prob, dataclasses.replace(sol, normal=blown)) == math.inf
