"""One control-law interface and one inverse dynamics: a law a user writes runs in every
sampled-data loop of jaxflex, and the workflows that read a model's torque off a log agree."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxflex.core.controller import (
    AbstractControlLaw,
    AbstractTrackingLaw,
    CascadeController,
    ControllerState,
    LawOutput,
)
from jaxflex.core.plant import FlexibleJointPlant
from jaxflex.core.trajectory import Sinusoid, Trajectory
from jaxflex.fit.inverse import measured_motion, model_residuals, torque_residuals
from jaxflex.identify.datagen import RotorPD
from jaxflex.identify.experiments import synthetic_log
from jaxflex.io.presets import paper_params
from jaxflex.sim.simulate import simulate_sampled
from jaxflex.validate import PDLaw, PPLaw, predicted_torque
from jaxflex.validate.loops import CascadeLaw, loop_start, sampled_loop

jax.config.update("jax_enable_x64", True)


class LinkPD(AbstractTrackingLaw):
    """A law as a user writes it: PD on the link angle, velocity by a first difference."""

    model: FlexibleJointPlant
    trajectory: Trajectory
    dt: float = eqx.field(static=True, default=1e-3)
    tau_max: Array = eqx.field(default_factory=lambda: jnp.asarray(2.0))

    def init(self, t0, q1, q2, dq1=None, dq2=None):
        return ControllerState.at_rest(q1, q2)

    def step(self, state, t, q1, q2, dq1=None, dq2=None):
        ref = self.trajectory.position(jnp.asarray(t, float))
        tau = jnp.clip(6.0 * (ref - q1) - 0.3 * (q1 - state.q1_prev) / self.dt,
                       -self.tau_max, self.tau_max)
        return ControllerState.at_rest(q1, q2), LawOutput.of_torque(tau, e1=q1 - ref)


def test_every_sampled_law_is_one_interface():
    for law in (CascadeController, RotorPD, PPLaw, PDLaw, CascadeLaw, LinkPD):
        assert issubclass(law, AbstractControlLaw), law


def test_a_user_law_runs_in_both_sampled_loops_alike():
    """The closed loop of ``simulate_sampled`` and the declared-loop scan of ``validate`` run
    the same user law around the same plant to the same motion."""
    plant = paper_params().to_plant()
    law = LinkPD(model=plant, trajectory=Sinusoid(amplitude=0.5, frequency=0.5))
    res = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 2.0, substeps=4))(plant, law)
    x0 = loop_start(plant, jnp.zeros(1))
    q, tau = eqx.filter_jit(sampled_loop)(plant, "flexible", law, x0, 1e-3, 4, res.t.shape[0])
    assert np.max(np.abs(np.asarray(q)[:, 0] - np.asarray(res.q1)[:, 0])) < 1e-6
    assert float(np.max(np.abs(np.asarray(tau)))) > 0.1  # the law did act


def test_the_one_inverse_dynamics_holds_on_a_replayed_log():
    """On a smooth log replayed through the true plant the model's residuals are a small
    share of the torque; a wrong stiffness leaves a large one; the validation's torque
    prediction is the logged torque plus the rotor residual."""
    p = paper_params()
    plant = p.to_plant()
    t = np.arange(4000) * 1e-3
    tau = (0.6 * np.sin(2 * np.pi * 0.7 * t) + 0.3 * np.sin(2 * np.pi * 2.3 * t))[:, None]
    log, _ = synthetic_log(plant, tau, dt=1e-3)
    motion = measured_motion(log, 41, smooth=True)
    link, rotor = torque_residuals(plant, motion)
    inner = slice(100, -100)
    scale = float(np.std(log.tau))
    assert float(np.sqrt(np.mean(rotor[inner] ** 2))) < 0.02 * scale
    wrong = eqx.tree_at(lambda q: q.K, plant, 2.0 * plant.K)
    _, rotor_w = torque_residuals(wrong, motion)
    assert float(np.sqrt(np.mean(rotor_w[inner] ** 2))) > 0.1 * scale
    _, r = model_residuals(plant, "flexible", motion)
    np.testing.assert_allclose(np.asarray(predicted_torque(plant, "flexible", motion)),
                               np.asarray(motion.tau) + np.asarray(r), rtol=0, atol=1e-12)


def test_controller_state_is_what_the_tracking_laws_share():
    law = RotorPD(model=paper_params().to_plant(), trajectory=Sinusoid(amplitude=0.5, frequency=0.5))
    st = law.init(0.0, jnp.zeros(1), jnp.zeros(1))
    assert isinstance(st, ControllerState)
