"""The model-based velocity estimator (coarse encoders): the steady-state Kalman
filter of ``jaxflex.core.estimator`` against the dirty derivative on quantised angles, its
convergence on exact measurements of a linear plant, its Riccati solution, its place in the
closed loop and the closed-loop Jacobian, and the errors for bad settings."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jaxflex.loop.analyse import ClosedLoopMap, jacobian_at, state_names
from jaxflex.core.controller import CascadeController
from jaxflex.core.estimator import (
    KalmanEstimator, KalmanTuning, joint_model, kalman_for, solve_filter_riccati,
)
from jaxflex.io.presets import paper_gains, paper_plant, paper_sensing, paper_sinusoid, sensing_of
from jaxflex.core.sensing import Sensing
from jaxflex.sim.simulate import simulate_sampled
from jaxflex.sim.step import plant_step


def _ctrl(plant=None, method="model", comp=True, traj=None):
    p = paper_plant() if plant is None else plant
    return CascadeController(model=p, gains=paper_gains(), trajectory=traj or paper_sinusoid(),
                             q2d_method=method, compensation=comp, tau_max=2.0)


def _dirty(x, tc, h):
    """The controller's filtered differentiation (``CascadeController.step``) of a sampled
    signal x (N, n), started at zero velocity."""
    def body(carry, xk):
        y, xp = carry
        y = (tc * y + xk - xp) / (tc + h)
        return (y, xk), y

    return jax.lax.scan(body, (jnp.zeros_like(x[0]), x[0]), x)[1]


def _rms(a, b, skip=200):
    return float(jnp.sqrt(jnp.mean((a - b)[skip:] ** 2)))


def test_kalman_beats_dirty_derivative_on_the_paper_encoders():
    """The paper's sinusoid run with exact sensing gives the true motion and torque; its
    angles quantised by the paper's 0.72 deg link encoder and its motor encoder (0.72/50 deg
    link-referred) and the torque by the 12-bit DAC, the Kalman filter's q1' and q2' are
    several times closer to the truth than the controller's dirty derivative."""
    p = paper_plant()
    c = _ctrl(p)
    r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 3.0))(p, c)
    s = paper_sensing()
    q1m = s.measure(r.q1, s.q1_resolution, 0.0)
    q2m = s.measure(r.q2, s.q2_resolution, 0.0)
    tau = s.dac(r.tau)
    d1 = _dirty(q1m, c.velocity_tc, c.dt)
    d2 = _dirty(q2m, c.velocity_tc, c.dt)
    est = kalman_for(dataclasses.replace(s, velocity="kalman"), c.model, c.dt)
    post = est.filter(q1m, q2m, tau)
    k1, k2 = _rms(post.dq1, r.dq1), _rms(post.dq2, r.dq2)
    f1, f2 = _rms(d1, r.dq1), _rms(d2, r.dq2)
    assert k1 < 0.3 * f1, (k1, f1)
    assert k2 < 0.3 * f2, (k2, f2)
    # one link count per sample is 12.6 rad/s; the filter is well below the motion's 0.16 rad/s
    assert k1 < 0.1
    # and its link angle is closer to the truth than the encoder's reading
    # (``KalmanTuning(angles=True)`` hands it to the controller)
    a_k, a_enc = _rms(post.q1, r.q1), _rms(q1m, r.q1)
    assert a_k < 0.7 * a_enc, (a_k, a_enc)


@pytest.mark.slow
def test_kalman_in_the_closed_loop_with_paper_sensing():
    """Same comparison inside the loop (the velocities the controller used): with the paper's
    sensing the Kalman loop's velocity error is far below the dirty derivative's, and with
    model-based q2d derivatives compensation lowers the tracking error, which it does not
    with the dirty derivative."""
    p = paper_plant()
    sim = eqx.filter_jit(lambda p, c, s: simulate_sampled(p, c, 3.0, sensing=s))
    out = {}
    for vel in ("filtered", "kalman"):
        s = dataclasses.replace(paper_sensing(), velocity=vel)
        for comp in (False, True):
            r = sim(p, _ctrl(p, comp=comp), s)
            out[vel, comp] = (_rms(r.dq1_hat, r.dq1), float(r.metrics.rms_error[0]))
    assert out["kalman", True][0] < 0.3 * out["filtered", True][0], out
    assert out["kalman", True][1] < 0.7 * out["kalman", False][1], out
    assert out["filtered", True][1] > out["filtered", False][1], out


def test_kalman_converges_to_true_velocities_on_exact_measurements_of_a_linear_plant():
    """Frictionless paper joint (linear), torque a sum of sines, exact angle measurements;
    the filter starts 1 rad/s off on both velocities and ends within 1e-6 rad/s."""
    p = paper_plant(friction=False)
    dt, N = 1e-3, 600
    t = jnp.arange(N) * dt
    tau = (0.3 * jnp.sin(2 * jnp.pi * 1.3 * t) + 0.1 * jnp.sin(2 * jnp.pi * 7.0 * t))[:, None]

    def body(x, u):
        return plant_step(p, x, u, dt, 10), x

    _, xs = jax.lax.scan(body, p.init_state(q1=0.1, dq1=0.2, dq2=0.2), tau)
    est = kalman_for(Sensing(velocity="kalman"), p, dt)
    post = est.filter(xs.q1, xs.q2, tau, dq1_0=xs.dq1[0] + 1.0, dq2_0=xs.dq2[0] - 1.0)
    err1 = np.abs(np.asarray(post.dq1 - xs.dq1)[:, 0])
    err2 = np.abs(np.asarray(post.dq2 - xs.dq2)[:, 0])
    assert err1[0] > 0.5 and err2[0] > 0.5
    assert err1[-100:].max() < 1e-6 and err2[-100:].max() < 1e-6, (err1[-1], err2[-1])
    assert np.abs(np.asarray(post.d[-100:])).max() < 1e-4  # no disturbance on this plant


def test_riccati_solution_matches_scipy():
    A, B = joint_model(jnp.array(0.07), jnp.array(0.005), jnp.array(6.77), 1e-3)
    B = np.asarray(B)
    C = np.zeros((2, 5))
    C[0, 0] = C[1, 2] = 1.0
    Q = 1e-4 * np.outer(B, B) + np.diag([0, 0, 0, 0, 1e-3])
    R = np.diag([0.0126**2 / 12, (0.0126 / 50) ** 2 / 12])
    P = np.asarray(solve_filter_riccati(A, jnp.asarray(C), jnp.asarray(Q), jnp.asarray(R)))
    P_ref = scipy.linalg.solve_discrete_are(np.asarray(A).T, C.T, Q, R)
    np.testing.assert_allclose(P, P_ref, rtol=1e-8, atol=1e-12 * np.abs(P_ref).max())


def test_estimator_gain_is_differentiable():
    """grad of the filter's gain through the doubling iteration equals finite differences
    (tuning and model parameters reach the estimator under ``grad``)."""
    p = paper_plant()

    def f(rate):
        s = Sensing(q1_resolution=0.01, q2_resolution=2e-4, velocity="kalman",
                    kalman=KalmanTuning(disturbance_rate=rate))
        return jnp.sum(kalman_for(s, p, 1e-3).L[0, 1])

    g = jax.grad(f)(1.0)
    h = 1e-5
    fd = (f(1.0 + h) - f(1.0 - h)) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=1e-5)


def test_closed_loop_with_kalman_is_vmap_and_grad_friendly():
    """A tuning parameter of the filter reaches the closed loop's metrics under vmap (equal to a
    loop) and grad (equal to finite differences). Exact angles, filter designed for noisy
    encoders, so the loss is smooth and the tuning matters."""
    p = paper_plant()
    c = _ctrl(p, method="filtered")  # the cheapest law to compile under grad

    def loss(rate):
        s = Sensing(velocity="kalman", q1_noise=1e-3, q2_noise=1e-4,
                    kalman=KalmanTuning(disturbance_rate=rate))
        return simulate_sampled(p, c, 0.3, sensing=s, substeps=4, save=False).metrics.sum_e2[0]

    rates = jnp.array([0.5, 1.0, 2.0])
    f = jax.jit(loss)
    np.testing.assert_allclose(jax.jit(jax.vmap(loss))(rates), [f(r) for r in rates],
                               rtol=1e-10)
    g = float(jax.jit(jax.grad(loss))(1.0))
    h = 1e-4
    fd = float((f(1.0 + h) - f(1.0 - h)) / (2 * h))
    assert g != 0.0 and g == pytest.approx(fd, rel=1e-4)


def test_closed_loop_jacobian_includes_the_estimator_state():
    p = paper_plant()
    s = dataclasses.replace(paper_sensing(), velocity="kalman")
    m = ClosedLoopMap(p, _ctrl(p), s)
    xi, unravel = m.initial()
    names = state_names(p, m.controller, s)
    assert len(names) == xi.shape[0]
    assert {"ctrl.estimator.dq1", "ctrl.estimator.d"} <= set(names)
    step = jax.jit(lambda t, v: m.step(t, v, unravel))
    for k in range(200):
        xi = step(k * 1e-3, xi)
    A = np.asarray(jacobian_at(m, 0.2, xi, unravel))
    hh = 1e-7
    E = np.eye(xi.shape[0])
    fd = np.stack([(np.asarray(step(0.2, xi + hh * E[i])) - np.asarray(step(0.2, xi - hh * E[i])))
                   / (2 * hh) for i in range(xi.shape[0])], axis=1)
    np.testing.assert_allclose(A, fd, rtol=1e-5, atol=1e-6 * np.abs(A).max())
    # the estimate depends on the estimator's own state (it is carried, not recomputed)
    i = names.index("ctrl.estimator.dq1")
    assert np.abs(A[:, i]).max() > 0


def test_bad_estimator_settings_raise_clear_errors():
    with pytest.raises(ValueError, match="velocity must be one of .*kalman.*'luenberger'"):
        Sensing(velocity="luenberger")
    with pytest.raises(ValueError, match="disturbance_rate must be >= 0"):
        Sensing(velocity="kalman", kalman=KalmanTuning(disturbance_rate=-1.0))
    with pytest.raises(ValueError, match="angle_floor must be finite"):
        KalmanTuning(angle_floor=float("nan"))
    with pytest.raises(ValueError, match="q1_noise must be >= 0"):
        Sensing(velocity="kalman", q1_noise=-1e-3)
    with pytest.raises(ValueError, match="kalman tuning given but velocity is 'filtered'"):
        Sensing(velocity="filtered", kalman=KalmanTuning())
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['rate'\]"):
        sensing_of({"velocity": "kalman", "kalman": {"rate": 1.0}})
    with pytest.raises(ValueError, match="q2_var must be >= 0"):
        KalmanEstimator.build(paper_plant(), 1e-3, q1_var=1e-6, q2_var=-1.0, tau_var=0.0)
    with pytest.raises(ValueError, match="dt must be > 0"):
        KalmanEstimator.build(paper_plant(), 0.0, q1_var=1e-6, q2_var=1e-6, tau_var=0.0)
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="needs a float64 model"):
            kalman_for(Sensing(velocity="kalman"), paper_plant(), 1e-3)
    # a parameter file's mapping builds the same tuning
    s = sensing_of({"velocity": "kalman", "kalman": {"disturbance_rate": 2.0}})
    assert float(s.kalman.disturbance_rate[0]) == 2.0
