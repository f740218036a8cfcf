"""The coupled arm's identification (jaxflex.identify.arm): exact recovery of base parameters,
rotor inertias, friction, offsets and a known torque's scale from a log made by the chain's
own inverse dynamics; the KUKA KR300's axes 1-3 fitted on A against the per-axis rigid
baseline on B."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.identify.arm import (
    ArmMotion,
    arm_base,
    identify_arm,
    kuka_arm_motion,
    kuka_counterbalance,
    torque_error_pct,
)
from jaxflex.core.chain import SerialChain

JA = np.array([0.8, 0.5, 0.3])       # rotor inertias [kg m^2]
FV = np.array([2.0, 1.5, 0.7])       # viscous [N m s/rad]
FC = np.array([3.0, 2.0, 1.0])       # Coulomb [N m]
C0 = np.array([0.4, -0.6, 0.2])      # offsets [N m]
KB = 1.3                             # the known torque's scale


def three_link() -> SerialChain:
    """An anthropomorphic arm (vertical axis 1, two parallel axes), gravity along -z."""
    rng = np.random.default_rng(3)
    Ic = np.stack([np.diag(d) for d in rng.uniform(0.1, 0.15, (3, 3))])
    return SerialChain.from_dh(a=[0.1, 0.6, 0.4], d=[0.5, 0.05, 0.0],
                               alpha=[np.pi / 2, 0.0, 0.0], mass=[8.0, 5.0, 3.0],
                               com=[[0.0, -0.1, 0.02], [-0.3, 0.01, 0.03], [-0.2, 0.0, 0.01]],
                               inertia=Ic)


def synthetic_motion(chain: SerialChain, N: int = 400) -> tuple[ArmMotion, np.ndarray]:
    """Sums of sines on the links, a different small deflection on the motors, exact
    derivatives, torques by the model of jaxflex.identify.arm's docstring (noise-free)."""
    t = np.arange(N) * 0.01
    w = np.array([[0.7, 1.9], [1.1, 2.3], [0.9, 3.1]])
    amp = np.array([[0.8, 0.3], [0.5, 0.2], [0.6, 0.25]])
    def sines(a, f, k):
        # k-th time derivative of sum_i a_i sin(f_i t + i)
        return sum(a[i] * f[i] ** k * np.sin(f[i] * t + i + k * np.pi / 2) for i in range(2))
    q, dq, ddq = (np.stack([sines(amp[j], w[j], k) for j in range(3)], 1) for k in (0, 1, 2))
    e, de, dde = (np.stack([sines(0.01 * amp[j], 2.5 * w[j], k) for j in range(3)], 1)
                  for k in (0, 1, 2))
    known = np.zeros((N, 3))
    known[:, 1] = 20.0 * q[:, 1] ** 2
    rb = jax.jit(jax.vmap(chain.inverse_dynamics))(jnp.asarray(q), jnp.asarray(dq), jnp.asarray(ddq))
    dqm = dq + de
    tau = (np.asarray(rb) + JA * (ddq + dde) + FV * dqm + FC * np.sign(dqm) + C0 + KB * known)
    return ArmMotion(t=t, q=q, dq=dq, ddq=ddq, qm=q + e, dqm=dqm, ddqm=ddq + dde, tau=tau,
                     joints=(0, 1, 2)), known


@pytest.mark.slow
def test_idim_recovers_base_parameters_friction_and_known_scale():
    chain = three_link()
    motion, known = synthetic_motion(chain)
    # the prior's inertias are wrong; with every base parameter free they do not matter
    prior = chain.with_phi(chain.phi * 1.7 + 0.05)
    base = arm_base(chain, (0, 1, 2))
    fit = identify_arm(prior, motion, known, fit_known=True, base=base)
    beta_true = base.values(chain.phi)
    np.testing.assert_allclose(fit.base_values(), beta_true, rtol=1e-6,
                               atol=1e-6 * np.abs(beta_true).max())
    for j in range(3):
        for name, true in (("Ja", JA), ("Fv", FV), ("Fc", FC), ("c", C0)):
            assert abs(fit.value(f"{name}{j + 1}") - true[j]) < 1e-6 * max(1.0, abs(true[j]))
    assert abs(fit.value("k_b") - KB) < 1e-6
    np.testing.assert_allclose(fit.predict(motion, known), motion.tau, atol=1e-6)


def test_kuka_coupled_fit_on_A_beats_the_per_axis_rigid_baseline_on_B():
    """Nominal inertias (the shipped model), the per-joint terms fitted on A, the wrist at its
    measured motion and the counterbalance known; validated on B against the rigid
    least-squares model of each axis alone (jaxflex.validate.rigid_torque_fit on A)."""
    from jaxflex.data import load_kuka
    from jaxflex.data.kr300 import kuka_kr300_chain
    from jaxflex.validate import rel_error_pct, rigid_torque, rigid_torque_fit

    chain = kuka_kr300_chain()
    mA, mB = kuka_arm_motion("A"), kuka_arm_motion("B")
    fit = identify_arm(chain, mA, kuka_counterbalance(mA), free=())
    err = torque_error_pct(mB.tau, fit.predict(mB, kuka_counterbalance(mB)))
    for ax in (2, 3):
        coef = rigid_torque_fit(load_kuka("A", ax))
        logB = load_kuka("B", ax)
        rigid = rel_error_pct(logB.tau[:, 0], rigid_torque(coef, logB))
        assert err[ax - 1] < rigid, (ax, err, rigid)
    # friction and rotor inertias come out positive
    assert all(fit.value(f"{k}{j}") > 0 for k in ("Ja", "Fv", "Fc") for j in (1, 2, 3))
