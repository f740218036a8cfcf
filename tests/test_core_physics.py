"""Core physics: LuGre static map, energy balance, n-link dynamics, bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.controller import CascadeController, CascadeGains
from jaxflex.core.friction import LuGre
from jaxflex.core.plant import DiagonalInertia, FlexibleJointPlant
from jaxflex.io.presets import paper_gains, paper_lugre, paper_plant, paper_sinusoid, two_link_plant
from jaxflex.sim.step import plant_step, rk4


@pytest.mark.parametrize("v", [-3.0, -0.3, -0.04, -0.005, 0.002, 0.03, 0.2, 1.0, 4.0])
def test_lugre_constant_velocity_converges_to_static_map(v):
    """At constant v the LuGre force tends to F_ss(v) = sign(v) g(v) + sigma2 v (eq. 35).

    z is integrated with plain RK4 on z' (eq. 5), independently of the exact update used by
    the simulator, long enough for the slowest rate sigma0 |v| / Fs to settle.
    """
    fr = paper_lugre()
    vv = jnp.array([v])
    rate = float(fr.z_rate(vv)[0])
    T = 12.0 / rate
    h = min(0.5 / rate, T / 2000)
    steps = int(T / h)
    z = jax.lax.fori_loop(0, steps, lambda i, z: rk4(lambda zz: fr.z_dot(vv, zz), z, h),
                          jnp.zeros(1))
    np.testing.assert_allclose(fr.force(vv, z), fr.steady_state(vv), rtol=1e-5, atol=1e-9)
    # the exact update reaches the same point
    np.testing.assert_allclose(fr.step_z(vv, jnp.zeros(1), T), z, rtol=1e-5, atol=1e-12)


def test_exact_z_update_is_stable_for_stiff_rates():
    """A tiny Fc and a large step: explicit RK4 would blow up (docs/spec.md section 9), the exact
    update relaxes monotonically to the steady deflection."""
    fr = LuGre(Fc=1e-4, Fs=1e-4, vs=0.05, sigma0=1e5, sigma1=0.1, sigma2=0.0)
    v = jnp.array([2.0])
    z = fr.step_z(v, jnp.zeros(1), 1e-3)
    np.testing.assert_allclose(z, fr.z_steady(v), rtol=1e-9)
    assert float(fr.stiff_step_bound(v, 0.005)[0]) < 1e-6


@pytest.mark.parametrize("plant", [
    pytest.param(paper_plant(friction=False), id="one-link"),
    pytest.param(two_link_plant(friction=False), id="two-link-gravity", marks=pytest.mark.slow),
])
def test_energy_conserved_without_friction_and_input(plant):
    n = plant.n
    x = plant.init_state(q1=jnp.full(n, 0.3), q2=jnp.full(n, 0.5), dq1=0.4)
    E0 = float(plant.energy(x))
    step = jax.jit(lambda x: plant_step(plant, x, jnp.zeros(n), 1e-3, 10))
    Es = []
    for _ in range(2000):
        x = step(x)
        Es.append(float(plant.energy(x)))
    drift = np.max(np.abs(np.array(Es) - E0)) / abs(E0)
    assert drift < 1e-8, drift


def test_lugre_plant_is_dissipative():
    """With LuGre and no input, mechanical energy plus the bristle storage sigma0 z^2/2 never
    increases (holds while |q1'| < 4 g(v)/sigma1 = 4.4 rad/s, which this motion respects)."""
    plant = paper_plant()
    x = plant.init_state(q1=0.0, q2=0.6)
    V = lambda x: float(plant.energy(x) + plant.bristle_energy(x))
    step = jax.jit(lambda x: plant_step(plant, x, jnp.zeros(1), 1e-3, 20))
    Vs, vmax = [V(x)], 0.0
    for _ in range(3000):
        x = step(x)
        Vs.append(V(x))
        vmax = max(vmax, abs(float(x.dq1[0])))
    dV = np.diff(Vs)
    assert vmax < 4.4
    assert Vs[-1] < 0.6 * Vs[0]  # it really dissipates (stiction then holds part of the spring energy)
    assert np.all(dV <= 1e-9 * Vs[0]), dV.max()


def test_two_link_christoffel_skew_symmetry():
    """C from the Christoffel symbols of M: x^T (M' - 2C) x = 0 for any x."""
    links = two_link_plant().links
    q, dq, x = jnp.array([0.3, -0.7]), jnp.array([1.1, 0.4]), jnp.array([0.5, -2.0])
    Mdot = jax.jvp(links.mass_matrix, (q,), (dq,))[1]
    C = jax.jacfwd(lambda v: links.coriolis(q, dq, v))(x)
    np.testing.assert_allclose(x @ (Mdot - 2 * C) @ x, 0.0, atol=1e-12)


def test_bad_input_errors_name_the_problem():
    with pytest.raises(ValueError, match="parameter I"):
        DiagonalInertia(I=-0.07)
    with pytest.raises(ValueError, match="parameter J"):
        FlexibleJointPlant(links=DiagonalInertia(I=0.07), J=-1.0, K=6.77)
    with pytest.raises(ValueError, match="Fs"):
        LuGre(Fc=0.2, Fs=0.1, vs=0.05, sigma0=100, sigma1=0.1, sigma2=0.2)
    with pytest.raises(ValueError, match="sigma1"):
        LuGre(Fc=0.1, Fs=0.2, vs=0.05, sigma0=100, sigma1=-0.1, sigma2=0.2)
    with pytest.raises(ValueError, match="6n gains"):
        CascadeGains.from_vector(jnp.ones(5))
    with pytest.raises(ValueError, match="same shape"):
        CascadeGains(Ke=[0.001, 0.001], KD1=1.0, KD2=1.0, kv=2.0, L1=200.0, L2=6.0)
    with pytest.raises(ValueError, match="KD1"):
        CascadeGains(Ke=0.001, KD1=0.0, KD2=1.0, kv=2.0, L1=200.0, L2=6.0)
    with pytest.raises(ValueError, match="gains are for 1 joint"):
        CascadeController(model=two_link_plant(), gains=paper_gains(), trajectory=paper_sinusoid())
    with pytest.raises(ValueError, match="q2d_method"):
        CascadeController(model=paper_plant(), gains=paper_gains(), trajectory=paper_sinusoid(),
                          q2d_method="magic")
