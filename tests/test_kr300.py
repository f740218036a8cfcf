"""The shipped KUKA KR300 model (jaxflex.data.kr300): gravity's structure, agreement with the
authors' generated rigid-body model, the held wrist, and the model against measured torque."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.chain import SerialChain
from jaxflex.data import load_kuka
from jaxflex.data.kr300 import (
    hydraulic_counterbalance,
    kuka_kr300_arm,
    kuka_kr300_chain,
    kuka_kr300_plant,
    load_kuka_wrist,
)

# G(q) [N m] and the axes 1-3 block of M(q) [kg m^2] (rotor inertias u^2 J_m removed) of the
# authors' generated model (symbolic_code/gravload_200.m, inertia_200.m, 200 kg payload) at
# two poses in the recorded convention
POSES = [
    ([0.3, 0.2, -0.5, 0.4, -0.3, 0.6],
     [0.0, -4458.8119302458, -3295.9410835041, -99.3224844629, -529.5615409759, 0.0],
     [[1030.6349489027, -1.7463040934, 4.1731250565],
      [-1.7463040934, 1509.5645648984, 639.7374932664],
      [4.1731250565, 639.7374932664, 440.6425434744]]),
    ([-1.0, 0.5, 0.1, -0.8, 0.9, 0.0],
     [0.0, -5191.3791218244, -2380.2098954437, -340.4325970878, 59.6588009403, 0.0],
     [[1142.2907122217, -9.6937017812, -36.1671570101],
      [-9.6937017812, 867.9324233767, 293.7844081663],
      [-36.1671570101, 293.7844081663, 390.3685147959]]),
]


@pytest.mark.parametrize("q, G_ref, M_ref", POSES)
def test_kr300_matches_the_authors_model(q, G_ref, M_ref):
    ch = kuka_kr300_chain()
    q = jnp.asarray(q)
    np.testing.assert_allclose(ch.gravity(q), G_ref, atol=1e-8)
    np.testing.assert_allclose(ch.mass_matrix(q)[:3, :3], M_ref, rtol=1e-10)


def test_kr300_gravity_acts_on_axes_2_and_3_not_on_axis_1():
    arm = kuka_kr300_arm(q_wrist=(0.2, -0.4, 0.1))
    qs = jax.random.uniform(jax.random.PRNGKey(0), (40, 3), minval=-1.0, maxval=1.0)
    G = jax.jit(jax.vmap(arm.gravity))(qs)
    assert float(jnp.max(jnp.abs(G[:, 0]))) < 1e-9          # axis 1 is vertical
    assert float(jnp.max(jnp.abs(G[:, 1]))) > 500.0          # the arm's weight on axis 2
    assert float(jnp.max(jnp.abs(G[:, 2]))) > 500.0
    # the held wrist: M and G of axes 1-3 are those of the six-axis chain at that wrist pose
    q = jnp.array([0.3, 0.2, -0.5])
    full = jnp.concatenate([q, jnp.array([0.2, -0.4, 0.1])])
    ch = kuka_kr300_chain()
    np.testing.assert_allclose(arm.mass_matrix(q), ch.mass_matrix(full)[:3, :3], rtol=1e-12)
    np.testing.assert_allclose(arm.gravity(q), ch.gravity(full)[:3], rtol=1e-12)


def test_axis_kinds_follow_the_kinematics():
    """Axis 1 of the KR300 is parallel to gravity at any pose (no gravity moment: "vertical"),
    axes 2-6 are not; a prismatic joint is "prismatic"; tilting a base axis away from gravity
    makes it "horizontal"."""
    chain = kuka_kr300_chain()
    rng = np.random.default_rng(0)
    for q in (np.zeros(6), rng.uniform(-1.0, 1.0, 6)):
        assert chain.axis_kinds(q) == ["vertical"] + ["horizontal"] * 5
    lift = SerialChain.from_dh(a=[0.0], d=[0.0], alpha=[0.0], mass=[1.0], com=[[0, 0, 0]],
                               inertia=[np.eye(3) * 0.01], joints="P")
    assert lift.axis_kinds([0.1]) == ["prismatic"]
    tilted = SerialChain.from_dh(a=[0.5], d=[0.0], alpha=[0.0], mass=[1.0], com=[[0.2, 0, 0]],
                                 inertia=[np.eye(3) * 0.01], gravity=(0.0, -9.81, 0.0))
    assert tilted.axis_kinds([0.0]) == ["horizontal"]


def test_kr300_model_explains_the_measured_gravity_load():
    # measured motor torque (link-referred) against G + counterbalance at the measured pose,
    # the six axes at their measured motion: the static load must match in sign and size
    # (friction and acceleration are left over, so only the means are compared)
    ch = kuka_kr300_chain()
    for traj in ("A", "B"):
        wrist = load_kuka_wrist(traj)
        logs = [load_kuka(traj, axis) for axis in (1, 2, 3)]
        q = np.concatenate([np.stack([lg.q2.ravel() for lg in logs], 1), wrist["q"]], 1)
        tau = np.stack([lg.tau.ravel() for lg in logs], 1)
        G = np.array(jax.jit(jax.vmap(ch.gravity))(jnp.asarray(q[::10])))
        G[:, 1] += hydraulic_counterbalance(q[::10, 1])
        mean_tau, mean_G = tau[::10].mean(0), G.mean(0)
        assert abs(mean_G[0]) < 1e-6
        for i in (1, 2):
            assert np.sign(mean_G[i]) == np.sign(mean_tau[i])
            assert 0.5 < mean_G[i] / mean_tau[i] < 2.0, (traj, i, mean_G, mean_tau)


def test_kr300_plant_builds_and_moves():
    plant = kuka_kr300_plant()
    assert plant.n == 3
    np.testing.assert_allclose(plant.J, [609.0, 843.9, 751.3], rtol=1e-3)
    x = plant.init_state(q1=jnp.array([0.1, 0.2, -0.3]))
    xd = jax.jit(lambda p, s, u: p.vector_field(s, u))(plant, x, jnp.zeros(3))
    # without torque and spring deflection the links fall under gravity on axes 2-3 only
    assert abs(float(xd.dq1[0])) < abs(float(xd.dq1[1]))
    assert bool(jnp.all(jnp.isfinite(xd.dq1)))
