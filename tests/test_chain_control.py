"""The paper's cascade law (eq. 9-16) with friction observers on a coupled three-axis flexible
arm built from its kinematics (jaxflex.core.chain), closed loop, and its N2 certificate for n
joints (eq. 29-31)."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.certificate import certify, lambda_min
from jaxflex.core.chain import SerialChain
from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.core.friction import LuGre
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.sim.simulate import simulate_sampled
from jaxflex.core.trajectory import RestToRest


def three_axis_arm() -> FlexibleJointPlant:
    """An anthropomorphic arm (vertical base axis, shoulder, elbow), elastic joints, LuGre."""
    Ic = np.stack([np.diag([2e-3, 2e-3, 1e-3]), np.diag([1e-3, 6e-3, 6e-3]),
                   np.diag([5e-4, 3e-3, 3e-3])])
    links = SerialChain.from_dh(
        a=[0.0, 0.3, 0.25], d=[0.2, 0.0, 0.0], alpha=[np.pi / 2, 0.0, 0.0],
        mass=[0.8, 0.6, 0.35], com=[[0.0, -0.05, 0.0], [-0.15, 0.0, 0.0], [-0.12, 0.0, 0.0]],
        inertia=Ic, gravity=(0.0, 0.0, -9.81))
    lugre = LuGre(Fc=[0.1, 0.11, 0.06], Fs=[0.14, 0.15, 0.08], vs=[0.05] * 3,
                  sigma0=[100.0, 100.0, 80.0], sigma1=[0.1, 0.1, 0.08], sigma2=[0.2, 0.2, 0.1])
    return FlexibleJointPlant(links=links, J=[0.005, 0.005, 0.003], K=[8.0, 8.0, 5.0],
                              friction=lugre)


GAINS = CascadeGains(Ke=[1e-3] * 3, KD1=[1.0] * 3, KD2=[1.0] * 3, kv=[2.0] * 3,
                     L1=[50.0] * 3, L2=[6.0] * 3)


@pytest.mark.slow
def test_cascade_tracks_on_a_coupled_three_axis_arm():
    p = three_axis_arm()
    q_start = jnp.array([0.0, 0.3, -0.6])
    traj = RestToRest(waypoints=[q_start, q_start + jnp.array([0.5, 0.3, -0.4]), q_start],
                      durations=[1.5, 1.5], t0=0.2)
    # start at rest with the springs holding the arm's weight (q2 = q1 + K^-1 G)
    x0 = p.init_state(q1=q_start, q2=q_start + p.links.gravity(q_start) / p.K)
    sim = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 3.5, x0=x0))
    on = sim(p, CascadeController(model=p, gains=GAINS, trajectory=traj, compensation=True))
    assert not bool(on.metrics.diverged)
    # a 0.5 rad move in 1.5 s: the link error stays within 0.05 rad (LuGre stiction holds a
    # few hundredths of a rad at the rests) and far below the motion
    e = np.abs(np.asarray(on.e1))
    print("max |e1| per joint [rad]", e.max(0), "rms", np.asarray(on.metrics.rms_error))
    assert e.max() < 0.05, e.max(0)
    assert float(jnp.max(on.metrics.rms_error)) < 0.03
    # the coupling is real: the base axis feels the moving shoulder and elbow
    M0 = p.links.mass_matrix(q_start)
    assert abs(float(M0[1, 2])) > 0.05 * float(M0[2, 2])


def test_n2_certificate_on_the_three_axis_arm():
    p = three_axis_arm()
    cert = certify(p, GAINS, vmax=2.0, num=41)
    assert cert.certified_up_to > 0.1
    # N2 is block-diagonal per joint: the 3-joint lambda_min is the worst single joint's (to
    # the rounding of an eigensolver on a matrix whose entry sigma0 / (eps Ke) is 1e8)
    for v in (0.0, 0.5, 1.5):
        singles = [float(lambda_min(_joint(p, i), _joint_gains(i), v)) for i in range(3)]
        np.testing.assert_allclose(float(lambda_min(p, GAINS, v)), min(singles), rtol=1e-6)


def _joint(p: FlexibleJointPlant, i: int) -> FlexibleJointPlant:
    from jaxflex.core.plant import DiagonalInertia
    fr = p.friction
    one = LuGre(**{k: getattr(fr, k)[i:i + 1] for k in ("Fc", "Fs", "vs", "sigma0", "sigma1",
                                                        "sigma2")})
    return FlexibleJointPlant(links=DiagonalInertia(I=[1.0]), J=p.J[i:i + 1], K=p.K[i:i + 1],
                              friction=one)


def _joint_gains(i: int) -> CascadeGains:
    return CascadeGains(**{k: getattr(GAINS, k)[i:i + 1] for k in
                           ("Ke", "KD1", "KD2", "kv", "L1", "L2")})
