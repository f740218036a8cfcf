"""Closed-loop simulation: tracking, convergence of the integrators, vmap and grad."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.core.friction import LuGre
from jaxflex.io.presets import paper_gains, paper_plant, paper_sinusoid, two_link_plant
from jaxflex.sim.simulate import REFERENCE_ORDER, simulate_continuous, simulate_sampled
from jaxflex.core.trajectory import Multisine, RestToRest, Sinusoid, Taylor


def _ctrl(plant=None, comp=True, method="model", dt=1e-3, traj=None, gains=None):
    plant = paper_plant() if plant is None else plant
    return CascadeController(
        model=plant, gains=paper_gains() if gains is None else gains,
        trajectory=paper_sinusoid() if traj is None else traj, compensation=comp,
        q2d_method=method, dt=dt,
    )


def test_frictionless_nominal_plant_tracks_to_near_zero():
    p = paper_plant(friction=False)
    r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 4.0))(p, _ctrl(p, comp=False))
    e = np.abs(np.asarray(r.e1[:, 0]))
    t = np.asarray(r.t)
    assert e[t < 0.5].max() > 1e-3  # starts off the reference (rest vs moving reference)
    assert e[t > 2.0].max() < 1e-5


def test_two_link_arm_with_gravity_tracks():
    p = two_link_plant(gravity=9.81, friction=False)
    traj = RestToRest(waypoints=[[0.0, 0.0], [0.4, -0.3], [0.0, 0.0]], durations=[1.5, 1.5], t0=0.2)
    gains = CascadeGains(Ke=[1e-3] * 2, KD1=[1.0] * 2, KD2=[1.0] * 2, kv=[2.0] * 2,
                         L1=[50.0] * 2, L2=[6.0] * 2)
    c = _ctrl(p, comp=False, traj=traj, gains=gains)
    x0 = p.init_state(q1=0.0, q2=jnp.linalg.solve(jnp.diag(p.K), p.links.gravity(jnp.zeros(2))))
    r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 3.5, x0=x0))(p, c)
    assert not bool(r.metrics.diverged)
    assert float(jnp.max(jnp.abs(r.e1))) < 2e-3


def test_compensation_reduces_rms_error_on_lugre_plant():
    p = paper_plant()
    sim = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 6.0, save=False))
    off = sim(p, _ctrl(p, comp=False)).metrics.rms_error[0]
    on = sim(p, _ctrl(p, comp=True)).metrics.rms_error[0]
    assert on < 0.7 * off, (on, off)


@pytest.mark.slow
def test_split_integrator_converges_to_diffrax_sampled_loop():
    """Same sampled-data loop; plant integrated by the Strang-split RK4 with 1, 2, 4, 8
    substeps against Kvaerno5 at rtol 1e-10 per sample interval. The error falls with h
    at (at least) second order."""
    p = paper_plant()
    c = _ctrl(p)
    T = 0.4
    ref = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, T, integrator="diffrax"))(p, c)
    errs = []
    for m in (1, 2, 4, 8):
        r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, T, substeps=m))(p, c)
        errs.append(float(jnp.max(jnp.abs(r.q1 - ref.q1))))
    errs = np.array(errs)
    assert np.all(np.diff(errs) < 0), errs
    assert errs[-1] < 1e-8, errs
    # 1 -> 2 -> 4 substeps: at least second order; at 8 the reference's own error (~3e-9) shows
    assert errs[0] / errs[1] > 3.0 and errs[1] / errs[2] > 3.0, errs


@pytest.mark.parametrize("substeps", [1, 3])
def test_rolled_rk4_stages_replay_the_same_motion(substeps):
    """``rolled`` (the RK4 stages as a loop: the fitting engine's Jacobian blocks) replays
    the same motion as the unrolled stages, to rounding, with a stateful input-path effect
    (actuator lag) and a spring effect in the plant; and it is a loop: one copy of the vector
    field in the program, not four."""
    from jaxflex.core.effects import EFFECTS
    from jaxflex.core.state import PlantState
    from jaxflex.sim.step import replay

    plant = paper_plant().with_effects(EFFECTS["actuator_lag"].typical(1),
                                       EFFECTS["joint_damping"].typical(1))
    aux = tuple(e.aux_init(1) for e in plant.effects)
    zero = jnp.zeros(1)
    x0 = PlantState(q1=zero, dq1=zero, q2=zero, dq2=zero, z=zero, aux=aux)
    tau = 1.5 * jnp.sin(jnp.linspace(0.0, 20.0, 2000))[:, None]
    run = {r: eqx.filter_jit(lambda t, r=r: replay("flexible", plant, x0, t, 1e-3, substeps,
                                                   rolled=r)[0]) for r in (False, True)}
    a, b = (jax.tree_util.tree_leaves(run[r](tau)) for r in (False, True))
    for u, v in zip(a, b):
        assert float(jnp.max(jnp.abs(u - v))) <= 1e-12 * max(float(jnp.max(jnp.abs(u))), 1e-3)
    # the Jacobian's program as the engine builds it (forward mode, substeps unrolled): four
    # copies of the vector field and its tangent per substep against one
    jvp = {r: eqx.filter_jit(lambda t, r=r: jax.jvp(
        lambda u: replay("flexible", plant, x0, u, 1e-3, substeps, unroll=True,
                         rolled=r)[0].dq2,
        (t,), (jnp.ones_like(t),))) for r in (False, True)}
    size = {r: jvp[r].lower(tau).compile().compiled.as_text().count(" = ") for r in jvp}
    assert size[True] < 0.6 * size[False], size


@pytest.mark.slow
def test_sampled_loop_converges_to_continuous_loop_as_period_shrinks():
    p = paper_plant()
    T = 0.3
    cont = simulate_continuous(p, _ctrl(p), T, save_dt=1e-3)
    errs = []
    for dt in (1e-3, 5e-4, 2.5e-4):
        c = _ctrl(p, dt=dt)
        r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, T, substeps=4))(p, c)
        every = int(round(1e-3 / dt))
        q1 = np.asarray(r.q1[::every, 0])
        errs.append(np.max(np.abs(q1 - np.asarray(cont.q1[: len(q1), 0]))))
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < 0.35 * errs[0], errs


def _cost(theta, plant, traj):
    """RMS tracking error [rad] as a function of (Fc, sigma2) of the true plant and (KD1, L2)."""
    fr = plant.friction
    fr2 = LuGre(Fc=theta[0], Fs=fr.Fs, vs=fr.vs, sigma0=fr.sigma0, sigma1=fr.sigma1, sigma2=theta[1])
    p = eqx.tree_at(lambda q: q.friction, plant, fr2)
    g = paper_gains()
    g = CascadeGains(Ke=g.Ke, KD1=theta[2:3], KD2=g.KD2, kv=g.kv, L1=g.L1, L2=theta[3:4])
    c = CascadeController(model=plant, gains=g, trajectory=traj)
    return simulate_sampled(p, c, 0.6, substeps=4, save=False).metrics.rms_error[0]


def test_vmap_equals_python_loop():
    p = paper_plant()
    traj = paper_sinusoid()
    thetas = jnp.array([[0.11, 0.2, 1.0, 6.0], [0.08, 0.25, 1.5, 5.0], [0.14, 0.1, 0.7, 8.0]])
    f = jax.jit(lambda th: _cost(th, p, traj))
    batched = jax.jit(jax.vmap(lambda th: _cost(th, p, traj)))(thetas)
    looped = jnp.stack([f(th) for th in thetas])
    np.testing.assert_allclose(batched, looped, rtol=1e-12, atol=1e-15)


@pytest.mark.slow
def test_grad_matches_finite_differences():
    p = paper_plant()
    traj = Sinusoid(amplitude=0.05, frequency=1.0)
    theta = jnp.array([0.11, 0.2, 1.0, 6.0])
    f = jax.jit(lambda th: _cost(th, p, traj))
    g = jax.jit(jax.grad(lambda th: _cost(th, p, traj)))(theta)
    assert np.all(np.isfinite(g))
    fd = []
    for i in range(4):
        h = 1e-6 * max(1.0, abs(float(theta[i])))
        e = jnp.zeros(4).at[i].set(h)
        fd.append((f(theta + e) - f(theta - e)) / (2 * h))
    np.testing.assert_allclose(g, np.array(fd), rtol=2e-4, atol=1e-9)


def test_divergence_is_flagged_not_raised():
    """A controller with the reference-only q2d derivatives and a fast task blows up; the run
    reports it instead of returning NaNs."""
    p = paper_plant()
    r = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 3.0))(p, _ctrl(p, method="reference"))
    assert bool(r.metrics.diverged)
    assert np.all(np.isfinite(np.asarray(r.q1)))


@pytest.mark.parametrize("layout", [dict(unroll=4), pytest.param(
    dict(unroll=3, unroll_substeps=True), marks=pytest.mark.slow, id="layout1")])
def test_samples_per_trip_of_the_time_loop_change_no_number(layout):
    """``unroll`` (samples per trip of the time loop; the sweep engine's GPU layout) runs the
    same loop: the trajectory and metrics equal the default layout's to rounding, including a
    remainder of samples (1001 samples, 3 or 4 per trip)."""
    p, c = paper_plant(), _ctrl()
    run = lambda **kw: eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 1.001, substeps=3, **kw))(p, c)
    a, b = run(), run(**layout)
    np.testing.assert_allclose(np.asarray(b.q1), np.asarray(a.q1), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(b.tau), np.asarray(a.tau), rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(float(b.metrics.rms_error[0]), float(a.metrics.rms_error[0]), rtol=1e-12)


@pytest.mark.parametrize("bad", [dict(substeps=0), dict(t_final=-1.0), dict(unroll=0)])
def test_simulate_bad_arguments(bad):
    kw = dict(t_final=1.0) | bad
    with pytest.raises(ValueError):
        simulate_sampled(paper_plant(), _ctrl(), kw.pop("t_final"), **kw)


@pytest.mark.parametrize("traj", [
    paper_sinusoid(),
    RestToRest(waypoints=jnp.array([0.0, 0.8, -0.3]), durations=jnp.array([0.7, 1.1])),
    Multisine.schroeder(0.1, 0.5, 4.0, 5),
])
@pytest.mark.parametrize("method", ["model", "reference"])
def test_taylor_reference_hands_the_controller_the_same_law(traj, method):
    """The sampled loop hands the controller the reference through ``Taylor`` at each sample
    time (derivatives evaluated once per sample): the derivatives and the law's
    torque must be those of the trajectory itself, to rounding."""
    t = jnp.asarray(1.2345)
    d = traj.derivatives(t, order=REFERENCE_ORDER)
    tay = Taylor(d, t)
    np.testing.assert_allclose(tay.derivatives(t, order=REFERENCE_ORDER), d, rtol=1e-14, atol=0)
    c = _ctrl(traj=traj, method=method)
    c_tay = eqx.tree_at(lambda k: k.trajectory, c, tay)
    q1, q2 = jnp.array([0.3]), jnp.array([0.31])
    st = c.init(0.0, q1, q2, jnp.array([0.2]), jnp.array([0.25]))
    st = eqx.tree_at(lambda s: s.z_hat, st, jnp.array([1e-3]))
    args = (st, t, q1 + 0.01, q2 + 0.02, jnp.array([0.4]), jnp.array([0.5]))
    (s_a, out_a), (s_b, out_b) = c.step(*args), c_tay.step(*args)
    for a, b in zip(jax.tree_util.tree_leaves((s_a, out_a)), jax.tree_util.tree_leaves((s_b, out_b))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
