"""SerialChain: M, C, G of a chain from DH parameters (jaxflex.core.chain) against closed forms,
energy conservation and the structure gravity must have."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.chain import SerialChain, standard_parameters
from jaxflex.core.plant import FlexibleJointPlant, PlanarTwoLink
from jaxflex.sim.step import rk4


def random_chain(seed: int, joints: str = "RRRRRR", g=(0.0, 0.0, -9.81)) -> SerialChain:
    """A chain with random DH parameters and physically consistent random links."""
    rng = np.random.default_rng(seed)
    n = len(joints)
    A = rng.normal(size=(n, 3, 3))
    Ic = np.einsum("nij,nkj->nik", A, A) * 0.05 + 0.01 * np.eye(3)
    return SerialChain.from_dh(
        a=rng.uniform(0.1, 0.6, n), d=rng.uniform(-0.3, 0.3, n),
        alpha=rng.uniform(-np.pi, np.pi, n), mass=rng.uniform(1.0, 10.0, n),
        com=rng.uniform(-0.2, 0.2, (n, 3)), inertia=Ic, gravity=g, joints=joints,
        offset=rng.uniform(-0.5, 0.5, n),
    )


def test_mass_matrix_symmetric_positive_definite():
    ch = random_chain(0, "RRPRRR")
    qs = jax.random.uniform(jax.random.PRNGKey(0), (20, 6), minval=-3.0, maxval=3.0)
    Ms = jax.jit(jax.vmap(ch.mass_matrix))(qs)
    np.testing.assert_allclose(Ms, jnp.swapaxes(Ms, 1, 2), atol=1e-12)
    assert float(jnp.min(jnp.linalg.eigvalsh(Ms))) > 1e-6


# the chain's terms, compiled once per chain structure: eager calls would compile every small op
_terms = eqx.filter_jit(lambda m, q, dq, v: (m.mass_matrix(q), m.gravity(q), m.coriolis(q, dq, v)))


def test_planar_two_link_matches_closed_form():
    m1, m2, l1, l2, lc1, lc2, I1, I2, g = 0.6, 0.35, 0.3, 0.25, 0.15, 0.12, 0.0045, 0.002, 9.81
    ref = PlanarTwoLink(m1=m1, m2=m2, l1=l1, lc1=lc1, lc2=lc2, I1=I1, I2=I2, g=g)
    # frame i sits at the distal end of link i, so the centre of mass is at lc - l along x
    Ic = np.zeros((2, 3, 3))
    Ic[0] = np.diag([1e-4, 3e-4, I1])
    Ic[1] = np.diag([2e-4, 1e-4, I2])
    ch = SerialChain.from_dh(a=[l1, l2], d=[0.0, 0.0], alpha=[0.0, 0.0], mass=[m1, m2],
                             com=[[lc1 - l1, 0, 0], [lc2 - l2, 0, 0]], inertia=Ic,
                             gravity=(0.0, -g, 0.0))
    for q, dq, v in [([0.3, -0.7], [1.0, -2.0], [0.5, 0.2]), ([1.2, 2.0], [-0.3, 0.8], [1, 1])]:
        q, dq, v = (jnp.asarray(x, float) for x in (q, dq, v))
        tols = (1e-14, 1e-13, 1e-13)  # M, G, C v
        for got, want, tol in zip(_terms(ch, q, dq, v), _terms(ref, q, dq, v), tols):
            np.testing.assert_allclose(got, want, atol=tol)


def test_rigid_chain_conserves_energy_without_torque():
    ch = random_chain(1, "RRR")

    def f(x):
        q, dq = x
        return dq, ch.solve_mass(q, -ch.coriolis(q, dq, dq) - ch.gravity(q))

    energy = lambda x: ch.kinetic_energy(*x) + ch.potential(x[0])

    @jax.jit
    def run(x):
        # the stages rolled: one copy of the chain in the program, a quarter of the compilation
        return jax.lax.scan(lambda s, _: (rk4(f, s, 2e-4, rolled=True), energy(s)), x, None,
                            length=5000)

    x0 = (jnp.array([0.3, -1.0, 0.5]), jnp.array([2.0, -1.0, 3.0]))
    x_end, E = run(x0)
    scale = float(jnp.max(jnp.abs(E)))
    drift = float(jnp.max(jnp.abs(E - E[0]))) / scale
    assert drift < 1e-9, drift
    assert float(jnp.max(jnp.abs(x_end[0] - x0[0]))) > 0.1  # the chain did move


def test_vertical_base_axis_has_no_gravity_torque():
    # joint 1 turns about z_0, which is parallel to gravity: G_1 = 0 at every pose
    ch = random_chain(2, "RRRRRR", g=(0.0, 0.0, -9.81))
    qs = jax.random.uniform(jax.random.PRNGKey(1), (50, 6), minval=-3.0, maxval=3.0)
    G = jax.vmap(ch.gravity)(qs)
    assert float(jnp.max(jnp.abs(G[:, 0]))) < 1e-10
    assert float(jnp.max(jnp.abs(G[:, 1]))) > 1.0  # gravity does act on the others
    # tilt gravity: now it acts on joint 1
    tilted = SerialChain(a=ch.a, d=ch.d, alpha=ch.alpha, offset=ch.offset, phi=ch.phi,
                         g=jnp.array([3.0, 0.0, -9.3]), joints=ch.joints)
    assert float(jnp.max(jnp.abs(jax.vmap(tilted.gravity)(qs)[:, 0]))) > 1.0


def test_prismatic_joint_closed_form():
    # a vertical prismatic joint (lift) carrying a revolute arm turning about a vertical axis:
    # M = [[m1 + m2, 0], [0, I2zz + m2 r^2]], G = ((m1 + m2) g, 0)
    m1, m2, r, Izz, g = 3.0, 2.0, 0.4, 0.05, 9.81
    Ic = np.zeros((2, 3, 3))
    Ic[0] = np.diag([0.1, 0.1, 0.1])
    Ic[1] = np.diag([0.01, 0.02, Izz])
    ch = SerialChain.from_dh(a=[0.0, 0.0], d=[0.0, 0.0], alpha=[0.0, 0.0], mass=[m1, m2],
                             com=[[0.0, 0.0, 0.0], [r, 0.0, 0.0]], inertia=Ic,
                             gravity=(0.0, 0.0, -g), joints="PR")
    for q in ([0.0, 0.0], [0.7, 1.3], [-0.2, -2.5]):
        M, G, _ = _terms(ch, jnp.asarray(q, float), jnp.zeros(2), jnp.zeros(2))
        np.testing.assert_allclose(M, np.diag([m1 + m2, Izz + m2 * r**2]), atol=1e-14)
        np.testing.assert_allclose(G, [(m1 + m2) * g, 0.0], atol=1e-12)
    # a horizontal prismatic joint after a revolute one (polar arm): Coriolis 2 m r r' th'
    ch = SerialChain.from_dh(a=[0.0, 0.0], d=[0.0, 0.0], alpha=[np.pi / 2, 0.0],
                             mass=[1.0, m2], com=[[0, 0, 0], [0, 0, 0]],
                             inertia=np.zeros((2, 3, 3)), gravity=(0.0, 0.0, 0.0),
                             joints="RP")
    q, dq = jnp.array([0.4, 0.8]), jnp.array([1.5, 0.3])
    M, _, C = _terms(ch, q, dq, dq)
    np.testing.assert_allclose(M, np.diag([m2 * 0.8**2, m2]), atol=1e-14)
    np.testing.assert_allclose(C,
                               [2 * m2 * 0.8 * 0.3 * 1.5, -m2 * 0.8 * 1.5**2], atol=1e-13)


def test_jit_grad_vmap_through_q_and_inertial_parameters():
    ch = random_chain(3, "RRPR")
    q, dq, ddq = jnp.array([0.1, -0.4, 0.2, 1.0]), jnp.array([0.5, 1, -1, 2.0]), jnp.ones(4)

    def loss(mass, com, q):
        c = ch.from_dh(a=ch.a, d=ch.d, alpha=ch.alpha, mass=mass, com=com,
                       inertia=ch.inertia_com, gravity=ch.g, joints=ch.joints, offset=ch.offset)
        return jnp.sum(c.inverse_dynamics(q, dq, ddq) ** 2)

    mass, com = ch.mass, ch.com
    gm, gc, gq = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(mass, com, q)
    loss = jax.jit(loss)
    eps, tol = 1e-6, 1e-6 * float(loss(mass, com, q))
    for i in range(4):
        e = jnp.zeros(4).at[i].set(eps)
        np.testing.assert_allclose(gm[i], (loss(mass + e, com, q) - loss(mass - e, com, q))
                                   / (2 * eps), rtol=1e-6, atol=tol)
        np.testing.assert_allclose(gq[i], (loss(mass, com, q + e) - loss(mass, com, q - e))
                                   / (2 * eps), rtol=1e-6, atol=tol)
    assert float(jnp.max(jnp.abs(gm))) > 100 * tol and float(jnp.max(jnp.abs(gq))) > 100 * tol
    e = jnp.zeros((4, 3)).at[2, 1].set(eps)
    np.testing.assert_allclose(gc[2, 1], (loss(mass, com + e, q) - loss(mass, com - e, q))
                               / (2 * eps), rtol=1e-6, atol=tol)
    # vmap over a batch of chains (their phi) equals a loop
    phis = ch.phi[None] * jnp.linspace(0.5, 2.0, 3)[:, None, None]
    mass_matrix = jax.jit(lambda p: ch.with_phi(p).mass_matrix(q))
    batched = jax.vmap(mass_matrix)(phis)
    for k in range(3):
        np.testing.assert_allclose(batched[k], mass_matrix(phis[k]), atol=1e-12)
    # the round trip mass, com, I_c -> phi -> mass, com, I_c
    np.testing.assert_allclose(standard_parameters(ch.mass, ch.com, ch.inertia_com), ch.phi,
                               atol=1e-12)


def test_flexible_plant_on_a_chain_is_passive():
    # the chain is a FlexibleJointPlant's links: energy balance E' = q2'^T tau without friction
    ch = random_chain(4, "RRR")
    plant = FlexibleJointPlant(links=ch, J=[0.5, 0.4, 0.3], K=[2e3, 1.5e3, 1e3])
    x = plant.init_state(q1=jnp.array([0.2, -0.5, 0.9]), dq1=jnp.array([1.0, -0.5, 0.3]),
                         q2=jnp.array([0.21, -0.49, 0.88]), dq2=jnp.array([0.9, -0.4, 0.2]))
    tau = jnp.array([3.0, -2.0, 1.0])
    dE = jax.jit(lambda x: jax.jvp(plant.energy, (x,), (plant.vector_field(x, tau),))[1])(x)
    np.testing.assert_allclose(dE, x.dq2 @ tau, rtol=1e-10)


@pytest.mark.parametrize("kw, match", [
    (dict(joints="RX"), "joints"),
    (dict(a=[0.1, 0.2, 0.3]), "a must have shape"),
    (dict(gravity=(0.0, 9.81)), "3-vector"),
])
def test_bad_chain_is_refused(kw, match):
    base = dict(a=[0.1, 0.2], d=[0.0, 0.0], alpha=[0.0, 0.0], joints="RR",
                offset=[0.0, 0.0], phi=np.tile([1.0, 0, 0, 0, 1, 0, 0, 1, 0, 1], (2, 1)),
                g=(0.0, 0.0, -9.81))
    if "gravity" in kw:
        base["g"] = kw.pop("gravity")
    base.update(kw)
    with pytest.raises(ValueError, match=match):
        SerialChain(**base)
