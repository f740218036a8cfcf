"""Closed-loop analysis: the autodiff Jacobian of the one-sample loop map against
finite differences, the rest modes of the paper's loop, the divergence flag, the bound in rad."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.loop.analyse import ClosedLoopMap, analyse_loop, jacobian_at, modes, state_names
from jaxflex.core.certificate import task_bound
from jaxflex.core.controller import CascadeController
from jaxflex.io.presets import paper_gains, paper_plant, paper_sinusoid, sensing_preset
from jaxflex.sim.simulate import lost_band, simulate_sampled
from jaxflex.core.trajectory import Sinusoid


def _map(method="model", comp=True, sensing="ideal", traj=None):
    p = paper_plant()
    c = CascadeController(model=p, gains=paper_gains(), compensation=comp, q2d_method=method,
                          trajectory=traj or Sinusoid(amplitude=0.0, frequency=1.0),
                          tau_max=2.0)
    return ClosedLoopMap(p, c, sensing_preset(sensing))


@pytest.mark.parametrize("sensing", ["ideal", "rig"])
def test_jacobian_and_eigenvalues_match_finite_differences(sensing):
    m = _map(sensing=sensing, traj=paper_sinusoid())
    xi, unravel = m.initial()
    # a point on the way (moving, z != 0) so that every coupling is active
    step = jax.jit(lambda t, v: m.step(t, v, unravel))
    for k in range(300):
        xi = step(k * 1e-3, xi)
    t = 0.3
    A = np.asarray(jacobian_at(m, t, xi, unravel))
    h = 1e-7
    E = np.eye(xi.shape[0])
    fd = np.stack([(np.asarray(step(t, xi + h * E[i])) - np.asarray(step(t, xi - h * E[i])))
                   / (2 * h) for i in range(xi.shape[0])], axis=1)
    np.testing.assert_allclose(A, fd, rtol=1e-5, atol=1e-6 * np.abs(A).max())
    ev = np.sort_complex(np.linalg.eigvals(A))
    ev_fd = np.sort_complex(np.linalg.eigvals(fd))
    np.testing.assert_allclose(np.abs(ev), np.abs(ev_fd), atol=1e-6)
    assert len(state_names(m.plant, m.controller)) == xi.shape[0]


def test_rest_modes_of_the_paper_loop():
    """Table 3 gains with model-based q2d derivatives: a growing ~4.5 Hz mode at rest with
    compensation (the limit cycle), none without; filtered q2d derivatives with
    exact velocities are stable with compensation."""
    on = analyse_loop(paper_plant(), paper_gains(), q2d_method="model")
    off = analyse_loop(paper_plant(), paper_gains(), q2d_method="model", compensation=False)
    filt = analyse_loop(paper_plant(), paper_gains(), q2d_method="filtered")
    assert not on.rest.stable and off.rest.stable and filt.rest.stable
    grow = on.rest.modes[0]
    assert grow["abs"] > 1.0 and 3.5 < grow["frequency_hz"] < 5.5 and grow["damping"] < 0
    assert "plant.z" in grow["states"] or "ctrl.z_hat" in grow["states"]


def test_modes_of_a_known_discrete_oscillator():
    dt, f, zeta = 1e-3, 3.0, 0.2
    w = 2 * np.pi * f
    s = -zeta * w + 1j * w * np.sqrt(1 - zeta**2)
    mu = np.exp(s * dt)
    A = np.array([[mu.real, -mu.imag], [mu.imag, mu.real]])
    m = modes(A, dt, ["a", "b"])
    assert m.frequency[0] == pytest.approx(f * np.sqrt(1 - zeta**2), rel=1e-9)
    assert m.damping[0] == pytest.approx(zeta, rel=1e-9)
    np.testing.assert_allclose(m.participation.sum(axis=0), 1.0)


def _run(method, comp, T):
    p = paper_plant()
    c = CascadeController(model=p, gains=paper_gains(), compensation=comp, q2d_method=method,
                          trajectory=paper_sinusoid(), tau_max=2.0)
    return eqx.filter_jit(lambda p, c: simulate_sampled(p, c, T, save=False))(p, c).metrics


def test_divergence_flag_trips_on_a_lost_run_not_on_a_tracking_one():
    ok = _run("model", False, 2.0)
    assert not bool(ok.diverged) and int(ok.diverged_at) == -1
    # the reference-only q2d derivatives lose the link: error far beyond the
    # 0.05 rad amplitude, but no state near the old 1e3 bound
    lost = _run("reference", False, 4.0)
    assert bool(lost.diverged) and int(lost.diverged_at) > 0
    band = float(lost_band(jax.vmap(paper_sinusoid().position)(jnp.arange(200) * 0.01))[0])
    assert band == pytest.approx(2 * (0.05 + 0.01), rel=1e-3)
    assert float(lost.max_error[0]) > band


@pytest.mark.slow
def test_ultimate_bound_in_rad_is_vacuous_for_the_paper_gains():
    b = task_bound(paper_plant(), paper_gains(), paper_sinusoid(), 2.0)
    assert b["vacuous"] and b["e1_bound_rad"] > 1e3 * b["reference_half_range_rad"]
    assert b["reference_half_range_rad"] == pytest.approx(0.05, rel=1e-3)
    assert b["task_speed"] == pytest.approx(1.2 * 0.05 * 2 * np.pi * 0.5, rel=1e-3)
    assert "half-range" in b["reason"]
