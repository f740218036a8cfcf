"""Effect families with an order (``jaxflex.core.effects.orders``, docs/spec.md section 8): each
order is registered and chained to the next, an order with its new parameters at zero is the
order below, and each order's first guess (``from_lower``) reads its new parameters off a
residual that holds them."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.discover.localisation import _ResidualStart
from jaxflex.core.effects import EFFECTS, family_orders
from jaxflex.io.params import Params
from jaxflex.io.presets import paper_params, paper_plant

FAMILIES = {"cogging": 3, "motor_cogging": 3, "motor_friction": 2, "actuator_lag": 2,
            "asymmetric_friction": 2, "hardening_spring": 2}


def test_each_family_is_a_chain_of_registered_orders():
    for family, top in FAMILIES.items():
        names = family_orders(family)
        assert len(names) == top
        for k, name in enumerate(names, start=1):
            cls = EFFECTS[name]
            assert cls.family_name() == family and cls.order == k
            assert cls.candidate == (k == 1)  # a higher order is reached from the one below
            assert cls.label() == (family if k == 1 else f"{family} order {k}")
        assert family_orders(family, 1) == [family]
    assert family_orders("gravity") == ["gravity"] and EFFECTS["gravity"].label() == "gravity"


@pytest.mark.parametrize("name", [n for f in FAMILIES for n in family_orders(f)[1:]])
def test_a_higher_order_is_rebuilt_from_its_params_entry(name):
    e = EFFECTS[name].typical(1)
    d = paper_params().to_dict()
    d["effects"] = {name: e.params()}
    plant = Params.from_dict(d).to_plant()
    ref = paper_plant().with_effects(e)
    x = ref.init_state(q1=0.1, dq1=0.3, q2=0.13, dq2=0.5)
    tau = jnp.array([0.2])
    for u, v in zip(jax.tree_util.tree_leaves(plant.vector_field(x, tau)),
                    jax.tree_util.tree_leaves(ref.vector_field(x, tau))):
        np.testing.assert_allclose(u, v, rtol=1e-12)


def _hooks(e, q, v):
    x = paper_plant().init_state(q1=q, dq1=v, q2=q, dq2=v)
    return float(jnp.ravel(e.link_torque(x))[0]), float(jnp.ravel(e.rotor_torque(x))[0])


@pytest.mark.parametrize("q,v", [(0.3, 0.5), (-1.1, -0.02), (2.0, 0.004)])
def test_an_order_with_its_new_terms_at_zero_is_the_order_below(q, v):
    E = EFFECTS
    pairs = [
        (E["cogging"](A=0.03, N=8.0, phi=0.3),
         E["cogging_2"](A=0.03, N=8.0, phi=0.3, A2=0.0, phi2=1.0)),
        (E["cogging_2"](A=0.03, N=8.0, phi=0.3, A2=0.01, phi2=1.0),
         E["cogging_3"](A=0.03, N=8.0, phi=0.3, A2=0.01, phi2=1.0, A3=0.0, phi3=2.0)),
        (E["motor_cogging"](A=0.02, N=60.0, phi=0.1),
         E["motor_cogging_2"](A=0.02, N=60.0, phi=0.1, A2=0.0, phi2=0.5)),
        (E["motor_friction"](Fm=0.03, bm=0.01),
         E["motor_friction_2"](Fm=0.03, bm=0.01, Fsm=0.0, vsm=0.1)),
    ]
    for lower, higher in pairs:
        assert _hooks(higher, q, v) == pytest.approx(_hooks(lower, q, v), abs=1e-15)
    # and the new term is the harmonic / the Stribeck excess
    c2 = E["cogging_2"](A=0.0, N=8.0, phi=0.0, A2=0.01, phi2=0.4)
    assert _hooks(c2, q, v)[0] == pytest.approx(0.01 * math.sin(16.0 * q + 0.4))
    m2 = E["motor_friction_2"](Fm=0.0, bm=0.0, Fsm=0.02, vsm=0.1)
    assert _hooks(m2, q, v)[1] == pytest.approx(
        -0.02 * math.exp(-((v / 0.1) ** 2)) * math.tanh(v / 0.01))
    # the friction level's orders: order 2 with dS = dF is order 1; its static shift decays
    # with the plant's own Stribeck velocity
    fr, vv = paper_plant().friction, jnp.array([v])
    a1 = E["asymmetric_friction"](dF=0.02)
    assert float(E["asymmetric_friction_2"](dF=0.02, dS=0.02).friction_level(vv, fr)[0]) == \
        pytest.approx(float(a1.friction_level(vv, fr)[0]), abs=1e-15)
    a2 = E["asymmetric_friction_2"](dF=0.0, dS=0.03)
    assert float(a2.friction_level(vv, fr)[0]) == pytest.approx(
        0.03 * math.exp(-((v / float(fr.vs[0])) ** 2)))
    # the spring's orders, on the deflection q (d' = v)
    d, dd = jnp.array([q]), jnp.array([v])
    s1, s2 = E["hardening_spring"](K3=40.0), E["hardening_spring_2"](K3=40.0, K5=0.0)
    assert float(s2.spring_torque(d, dd)[0]) == pytest.approx(float(s1.spring_torque(d, dd)[0]))
    s5 = E["hardening_spring_2"](K3=0.0, K5=500.0)
    assert float(s5.spring_torque(d, dd)[0]) == pytest.approx(500.0 * q**5)


def _transfer(e, w):
    """The applied torque's response to the commanded one at w [rad/s], from the hooks."""
    z = e.aux_init(1)
    A = np.asarray(jax.jacobian(lambda a: e.aux_rhs(a, jnp.zeros(1), None).ravel())(z)
                   ).reshape(z.size, z.size)
    B = np.asarray(jax.jacobian(lambda u: e.aux_rhs(z, u, None).ravel())(jnp.zeros(1))
                   ).reshape(z.size, 1)
    C = np.asarray(jax.jacobian(lambda a: e.applied_torque(jnp.zeros(1), a))(z)).reshape(1, z.size)
    D = float(jax.grad(lambda u: e.applied_torque(u, z)[0])(jnp.zeros(1))[0])
    return (C @ np.linalg.solve(1j * w * np.eye(z.size) - A, B))[0, 0] + D


def test_second_order_lag_is_a_current_loop_with_the_mean_delay_of_its_start():
    T1 = 0.008
    lower = EFFECTS["actuator_lag"](T=T1)
    data = _ResidualStart({}, None, h=1e-3)
    e = EFFECTS["actuator_lag_2"].from_lower(lower, data)
    T, zeta = float(e.T[0]), float(e.zeta[0])
    assert 2 * zeta * T == pytest.approx(T1) and zeta == pytest.approx(1.0)
    tau = jnp.array([0.7])
    aux = e.aux_steady(tau)
    assert float(e.applied_torque(tau, aux)[0]) == pytest.approx(0.7)
    np.testing.assert_allclose(e.aux_rhs(aux, tau, None), 0.0, atol=1e-12)
    # 1 / (T^2 s^2 + 2 zeta T s + 1); its phase at low frequency is the first-order lag's
    for w in (5.0, 60.0, 300.0):
        H = _transfer(e, w)
        assert H == pytest.approx(1.0 / (1.0 - (w * T) ** 2 + 2j * zeta * T * w), rel=1e-9)
    assert np.angle(_transfer(e, 5.0)) == pytest.approx(np.angle(_transfer(lower, 5.0)),
                                                        rel=1e-3)
    # a short fitted lag starts above the step's bound, as underdamped as the mean asks
    short = EFFECTS["actuator_lag_2"].from_lower(EFFECTS["actuator_lag"](T=0.0035), data)
    assert float(short.T[0]) == pytest.approx(3e-3) and float(short.zeta[0]) < 1.0


def _series(q1, r_link, q2=None, r_rotor=None, v2=None, d=None):
    t = np.arange(q1.size) * 1e-3
    v1 = np.gradient(q1, t)
    q2 = q1 if q2 is None else q2
    v2 = np.gradient(q2, t) if v2 is None else v2
    d = np.zeros_like(q1) if d is None else d
    return {"t": t, "q1": q1, "v1": v1, "r_link": r_link, "q2": q2, "v2": v2,
            "r_rotor": np.zeros_like(q1) if r_rotor is None else r_rotor,
            "d": d, "dd": np.gradient(d, t)}


def test_the_next_harmonic_starts_from_the_residual_at_its_frequency():
    t = np.arange(8000) * 1e-3
    q = 1.2 * np.sin(2 * np.pi * 0.125 * t) + 0.05 * np.sin(2 * np.pi * 1.3 * t)
    rng = np.random.default_rng(0)
    r = (0.03 * np.sin(8 * q + 0.3) + 0.015 * np.sin(16 * q + 1.1)
         + 0.006 * np.sin(24 * q - 0.7) + 0.002 * rng.standard_normal(q.size))
    data = _ResidualStart(_series(q, r), vs=0.05, h=1e-3)
    lower = EFFECTS["cogging"](A=0.029, N=8.0, phi=0.31)
    e2 = EFFECTS["cogging_2"].from_lower(lower, data)
    assert float(e2.A[0]) == 0.029 and float(e2.N[0]) == 8.0  # the fit is kept
    assert float(e2.A2[0]) == pytest.approx(0.015, rel=0.1)
    assert float(e2.phi2[0]) == pytest.approx(1.1, abs=0.1)
    e3 = EFFECTS["cogging_3"].from_lower(e2, data)
    assert float(e3.A3[0]) == pytest.approx(0.006, rel=0.1)
    assert float(e3.phi3[0]) == pytest.approx(-0.7, abs=0.1)
    # the rotor's ripple reads the rotor residual against q2
    rot = _ResidualStart(_series(q, np.zeros_like(q), q2=q, r_rotor=r), vs=0.05, h=1e-3)
    m2 = EFFECTS["motor_cogging_2"].from_lower(EFFECTS["motor_cogging"](A=0.03, N=8.0, phi=0.3),
                                               rot)
    assert float(m2.A2[0]) == pytest.approx(0.015, rel=0.1)


def test_the_stribeck_order_starts_from_the_rotor_residual():
    t = np.arange(8000) * 1e-3
    q = 1.2 * np.sin(2 * np.pi * 0.125 * t) + 0.05 * np.sin(2 * np.pi * 1.3 * t)
    v = np.gradient(q, t)
    rng = np.random.default_rng(1)
    friction = -((0.02 + 0.03 * np.exp(-((v / 0.1) ** 2))) * np.tanh(v / 0.01) + 0.01 * v)
    r = friction + 0.002 * rng.standard_normal(q.size)
    data = _ResidualStart(_series(q, np.zeros_like(q), q2=q, r_rotor=r, v2=v), vs=0.05,
                          params=paper_params(), h=1e-3)
    e = EFFECTS["motor_friction_2"].from_lower(EFFECTS["motor_friction"](Fm=0.035, bm=0.012),
                                               data)
    assert float(e.Fm[0]) == pytest.approx(0.02, rel=0.15)
    assert float(e.Fsm[0]) == pytest.approx(0.03, rel=0.2)
    assert float(e.bm[0]) == pytest.approx(0.01, rel=0.2)
    assert 0.06 <= float(e.vsm[0]) <= 0.16


def test_the_static_asymmetry_starts_as_its_order_below():
    """Order 2 of the friction level's asymmetry starts with the static shift at the fitted
    Coulomb shift: its friction is order 1's."""
    lower = EFFECTS["asymmetric_friction"](dF=0.03)
    e = EFFECTS["asymmetric_friction_2"].from_lower(lower, _ResidualStart({}, vs=0.05, h=1e-3))
    assert float(e.dF[0]) == float(e.dS[0]) == 0.03
    plant = paper_plant()
    for v in (0.5, -0.02, 0.004):
        x = plant.init_state(dq1=v, z=1e-3)
        assert float(plant.with_effects(e).friction_torque(x)[0]) == pytest.approx(
            float(plant.with_effects(lower).friction_torque(x)[0]), abs=1e-15)


def test_the_fifth_power_starts_from_the_link_residual_against_the_deflection():
    """A link residual 70 d^3 + 7000 d^5 [N m] on a deflection of up to 0.1 rad (beside a
    nominal spring's error in K d, which the fit clears): order 2 reads K3 and K5 off it;
    a residual that asks for a negative term leaves K3 as fitted and K5 at a tenth of the
    cubic term at the 95th-percentile deflection."""
    t = np.arange(8000) * 1e-3
    q = 1.2 * np.sin(2 * np.pi * 0.125 * t) + 0.05 * np.sin(2 * np.pi * 1.3 * t)
    rng = np.random.default_rng(3)
    d = 0.1 * np.sin(2 * np.pi * 0.7 * t + 0.4)
    r = 70.0 * d**3 + 7000.0 * d**5 + 0.3 * d + 0.002 * rng.standard_normal(q.size)
    data = _ResidualStart(_series(q, r, d=d), vs=0.05, h=1e-3)
    e = EFFECTS["hardening_spring_2"].from_lower(EFFECTS["hardening_spring"](K3=150.0), data)
    assert float(e.K3[0]) == pytest.approx(70.0, rel=0.1)
    assert float(e.K5[0]) == pytest.approx(7000.0, rel=0.1)
    soft = _ResidualStart(_series(q, -70.0 * d**3, d=d), vs=0.05, h=1e-3)
    e = EFFECTS["hardening_spring_2"].from_lower(EFFECTS["hardening_spring"](K3=150.0), soft)
    d95 = np.percentile(np.abs(d), 95)
    assert float(e.K3[0]) == 150.0
    assert float(e.K5[0]) == pytest.approx(15.0 / d95**2)
