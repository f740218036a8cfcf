"""Inertial parameters (jaxflex.core.inertial): log-Cholesky consistency, the exact regressor, and
the base parameters of chains whose base set is known in closed form."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxflex.core.chain import SerialChain
from jaxflex.core.inertial import (
    base_parameters,
    is_physically_consistent,
    log_cholesky_from_phi,
    phi_from_log_cholesky,
    pseudo_inertia,
    random_states,
    regressor,
)


def planar(g: float) -> SerialChain:
    Ic = np.tile(np.diag([0.01, 0.02, 0.025]), (2, 1, 1))
    return SerialChain.from_dh(a=[0.3, 0.25], d=[0.0, 0.0], alpha=[0.0, 0.0], mass=[1.0, 2.0],
                               com=[[-0.1, 0.01, 0.0], [-0.1, 0.0, 0.02]], inertia=Ic,
                               gravity=(0.0, -g, 0.0))


def test_log_cholesky_is_physical_and_inverts():
    theta = jax.random.normal(jax.random.PRNGKey(0), (50, 10)) * 2.0
    phi = phi_from_log_cholesky(theta)
    assert is_physically_consistent(phi).all()
    assert float(jnp.min(phi[:, 0])) > 0                     # positive mass
    Ic = SerialChain(a=[0.0] * 50, d=[0.0] * 50, alpha=[0.0] * 50, offset=[0.0] * 50, phi=phi,
                     g=jnp.zeros(3), joints="R" * 50).inertia_com
    ev = jnp.linalg.eigvalsh(Ic)
    assert float(jnp.min(ev)) > 0                            # positive-definite inertia
    # triangle inequality of the principal moments (a real mass distribution)
    assert bool(jnp.all(ev[:, 0] + ev[:, 1] >= ev[:, 2] * (1 - 1e-9)))
    np.testing.assert_allclose(log_cholesky_from_phi(phi), theta, atol=1e-9)
    # a negative mass, or a violated triangle inequality, is not consistent
    bad = np.array(planar(9.81).phi)
    bad[0, 0] = -1.0
    assert not is_physically_consistent(bad)[0] and is_physically_consistent(bad)[1]
    rod = SerialChain.from_dh(a=[0.1], d=[0.0], alpha=[0.0], mass=[1.0], com=[[0, 0, 0]],
                              inertia=[np.diag([0.01, 0.01, 0.03])], gravity=(0, 0, 0))
    assert not is_physically_consistent(rod.phi)[0]          # Izz > Ixx + Iyy
    assert float(jnp.min(jnp.linalg.eigvalsh(pseudo_inertia(rod.phi)))) < 0


def test_regressor_reproduces_inverse_dynamics():
    ch = SerialChain.from_dh(a=[0.2, 0.5, 0.1], d=[0.3, 0.0, 0.1], alpha=[np.pi / 2, 0.0, -1.0],
                             mass=[4.0, 3.0, 1.0], com=np.full((3, 3), 0.05),
                             inertia=np.tile(np.diag([0.1, 0.12, 0.15]), (3, 1, 1)),
                             joints="RPR")
    s = jnp.asarray(random_states(3, 5, seed=1))
    Y = jax.jit(jax.vmap(lambda x: regressor(ch, *x)))(s)
    tau = jax.jit(jax.vmap(lambda x: ch.inverse_dynamics(*x)))(s)
    assert Y.shape == (5, 3, 30)
    np.testing.assert_allclose(Y @ ch.phi.ravel(), tau, rtol=1e-12, atol=1e-10)


def test_base_parameters_of_a_planar_arm():
    # horizontal 2R arm: 4 base parameters, link 1 only through its inertia about joint 1
    b = base_parameters(planar(0.0))
    assert b.rank == 4
    assert b.base == ["Izz1", "mx2", "my2", "Izz2"]
    zz1 = b.combinations[0]
    for term in ("+ 0.09 m1", "+ 0.09 m2", "+ 0.6 mx1"):   # Izz1 + a1^2 (m1 + m2) + 2 a1 mx1
        assert term in zz1, zz1
    assert "my1" in b.unidentifiable and "no joint torque" in b.reasons["my1"]
    assert "lumped" in b.reasons["m2"]
    # in a vertical plane gravity makes link 1's first moments visible: 6
    bg = base_parameters(planar(9.81))
    assert bg.rank == 6 and "my1" in bg.base
    # the base parameters explain the torques as the full set does
    ch = planar(9.81)
    beta = bg.values(ch.phi)
    q, dq, ddq = random_states(2, 1, seed=5)[0]
    Y = np.asarray(jax.jit(regressor)(ch, q, dq, ddq))
    Yb = Y[:, [bg.names.index(k) for k in bg.base]]
    np.testing.assert_allclose(Yb @ beta, Y @ np.asarray(ch.phi).ravel(), rtol=1e-10)
