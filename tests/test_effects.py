"""Effects library (docs/spec.md section 8): names, construction from params, where each acts, the
physics of each hook, constraints, gradients."""

import dataclasses
import math

import jax
import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.core.effects import EFFECTS, link_input, link_measurement
from jaxflex.io.params import Params
from jaxflex.io.presets import paper_params
from jaxflex.io.presets import paper_plant

SPEC_NAMES = {
    "asymmetric_friction", "gravity", "cogging", "backlash", "hardening_spring",
    "joint_damping", "motor_friction", "actuator_lag", "torque_offset", "time_delay",
    "load_friction", "spring_hysteresis", "actuator_dead_zone",
}
#: Effects of real joints beyond the paper's model (``jaxflex.core.effects.extra``), opt-in
#: discovery candidates.
EXTRA_NAMES = ("load_friction", "spring_hysteresis", "actuator_dead_zone")


def test_all_spec_names_registered_with_metadata():
    assert SPEC_NAMES <= set(EFFECTS)
    for name in SPEC_NAMES:
        cls = EFFECTS[name]
        assert cls.name == name and cls.where and cls.constraints


@pytest.mark.parametrize("name", sorted(SPEC_NAMES))
def test_rebuilt_from_params_section(name):
    """Params.to_plant() rebuilds each effect from its 'effects' entry, same vector field."""
    e = EFFECTS[name].typical(1)
    p = paper_params()
    d = p.to_dict()
    d["effects"] = {name: e.params()}
    plant = Params.from_dict(d).to_plant()
    ref = paper_plant().with_effects(e)
    x = ref.init_state(q1=0.1, dq1=0.3, q2=0.13, dq2=0.5)
    tau = jnp.array([0.2])
    a, b = plant.vector_field(x, tau), ref.vector_field(x, tau)
    for u, v in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_allclose(u, v, rtol=1e-12)


def _acc(effect, **state):
    base = paper_plant()
    x = base.with_effects(effect).init_state(**state)
    x0 = base.init_state(**state)
    tau = jnp.array([0.3])
    a1, a2 = base.with_effects(effect).accelerations(x, tau)
    b1, b2 = base.accelerations(x0, tau)
    return float((a1 - b1)[0]) * 0.07, float((a2 - b2)[0]) * 0.005  # torque changes [N m]


def test_each_effect_acts_where_it_says():
    E = EFFECTS
    # link-side torques: only the link acceleration changes
    dl, dr = _acc(E["gravity"](mgl=0.4, q0=0.0), q1=0.3)
    assert dl == pytest.approx(-0.4 * math.sin(0.3)) and dr == 0.0
    dl, dr = _acc(E["cogging"](A=0.05, N=20.0, phi=0.3), q1=0.1)
    assert dl == pytest.approx(0.05 * math.sin(2.0 + 0.3)) and dr == 0.0
    # the friction's level by direction: the static map (eq. 35) is g + dF forward and
    # -(g - dF) backward, i.e. shifted by +dF both ways, and the bristle relaxes to it
    base, asym = paper_plant(), paper_plant().with_effects(E["asymmetric_friction"](dF=0.04))
    for v in (1.0, -1.0, 0.02, -0.02):
        vv = jnp.array([v])
        F0, F1 = base.friction.steady_state(vv), asym.lugre.steady_state(vv)
        assert float((F1 - F0)[0]) == pytest.approx(0.04, rel=1e-12)
        x = asym.init_state(dq1=v, z=asym.lugre.z_steady(vv))
        assert float(asym.friction_torque(x)[0]) == pytest.approx(float(F1[0]), rel=1e-12)
    assert base.lugre is base.friction  # no shift, no wrapper
    # rotor-side torque
    dl, dr = _acc(E["motor_friction"](Fm=0.03, bm=0.02), dq1=0.0, dq2=2.0)
    assert dl == 0.0 and dr == pytest.approx(-(0.03 + 0.04), rel=1e-6)
    # spring torques act on both sides with opposite signs
    dl, dr = _acc(E["hardening_spring"](K3=500.0), q1=0.0, q2=0.05)
    assert dl == pytest.approx(500.0 * 0.05**3) and dr == pytest.approx(-dl)
    dl, dr = _acc(E["joint_damping"](D=0.03), dq1=0.0, dq2=2.0)
    assert dl == pytest.approx(0.06) and dr == pytest.approx(-0.06)
    # input path
    dl, dr = _acc(E["torque_offset"](offset=0.05))
    assert dl == 0.0 and dr == pytest.approx(0.05)


def test_backlash_dead_zone():
    bl = EFFECTS["backlash"](b=0.01, K=6.77, w=1e-4)
    d = jnp.array([0.0, 0.005, -0.008, 0.05, -0.05])
    total = 6.77 * d + bl.spring_torque(d, 0 * d)
    expect = 6.77 * np.array([0.0, 0.0, 0.0, 0.04, -0.04])
    np.testing.assert_allclose(total, expect, atol=6.77 * 2e-4)


def test_actuator_lag_and_delay_steady_state_and_gain():
    for name in ("actuator_lag", "time_delay"):
        e = EFFECTS[name](T=0.004)
        tau = jnp.array([0.7])
        aux = e.aux_steady(tau)
        assert float(e.applied_torque(tau, aux)[0]) == pytest.approx(0.7)
        np.testing.assert_allclose(e.aux_rhs(aux, tau, None), 0.0, atol=1e-12)


def test_time_delay_pade_matches_exp():
    """Frequency response of the Pade state-space (from the hooks by autodiff) is
    exp(-j w T) to within the 2nd-order Pade error for w T <= 1, and lag is not a delay."""
    T = 0.004
    e = EFFECTS["time_delay"](T=T)
    z = jnp.zeros((2, 1))
    A = jax.jacobian(lambda a: e.aux_rhs(a, jnp.zeros(1), None).ravel())(z).reshape(2, 2)
    B = jax.jacobian(lambda u: e.aux_rhs(z, u, None).ravel())(jnp.zeros(1)).reshape(2, 1)
    C = jax.jacobian(lambda a: e.applied_torque(jnp.zeros(1), a))(z).reshape(1, 2)
    D = 1.0
    for w in (10.0, 100.0, 250.0):
        H = (C @ np.linalg.solve(1j * w * np.eye(2) - np.asarray(A), np.asarray(B)))[0, 0] + D
        assert abs(H) == pytest.approx(1.0, abs=1e-9)
        assert np.angle(H) == pytest.approx(-w * T, abs=2e-3)


@pytest.mark.parametrize(
    "name,kw,bad",
    [("hardening_spring", {"K3": -1.0}, "K3"), ("joint_damping", {"D": -0.1}, "D"),
     ("actuator_lag", {"T": 0.0}, "T"), ("time_delay", {"T": -1e-3}, "T"),
     ("backlash", {"b": -0.01, "K": 6.77}, "b"), ("cogging", {"A": 0.1, "N": 0.0}, "N"),
     ("motor_friction", {"Fm": -0.1}, "Fm")],
)
def test_constraints_refuse_bad_values(name, kw, bad):
    with pytest.raises(ValueError, match=bad):
        EFFECTS[name](**kw)


def test_gradient_reaches_effect_parameters():
    def f(K3):
        p = paper_plant().with_effects(EFFECTS["hardening_spring"](K3=K3))
        x = p.init_state(q1=0.0, q2=0.05)
        return p.accelerations(x, jnp.array([0.0]))[0][0]

    g = jax.grad(f)(300.0)
    assert float(g) == pytest.approx(0.05**3 / 0.07, rel=1e-9)


@pytest.mark.parametrize("name", sorted(n for n, e in EFFECTS.items() if e.candidate)
                         + list(EXTRA_NAMES))
def test_gated_effect_equals_the_effect_or_nothing(name):
    """A gated effect (``Gated``: the discrepancy workflow's switch, a run-time branch when the
    gate is not batched) gives the plant's accelerations and link reading with the effect
    (gate 1) or without it (gate 0), exactly; batched gates (vmap over models: both branches, then a select) give the
    same numbers."""
    from jaxflex.core.effects import Gated

    eff = EFFECTS[name].typical(1)
    # typical() of a signed effect is zero: give every parameter a size
    eff = jax.tree_util.tree_map(lambda a: a + 0.01 if a.shape == (1,) else a, eff)
    base = paper_plant()
    u = jnp.array([0.2])

    def acc(plant):
        x = plant.init_state(q1=0.3, dq1=0.4, q2=0.32, dq2=-0.7, z=1e-3)
        if x.aux is not None:  # an effect's internal state away from rest (lag, delay)
            x = dataclasses.replace(x, aux=tuple(
                None if a is None else jnp.asarray(a) + jnp.arange(1.0, 1.0 + jnp.size(a)).reshape(
                    jnp.shape(a)) for a in x.aux))
        # the accelerations and the link encoder's maps (``link_measured``, ``link_reading``)
        return jnp.concatenate([*plant.accelerations(x, u),
                                link_measurement(plant.effects, x.q1, x.dq1),
                                *link_input(plant.effects, x.q1, x.dq1, jnp.array([0.5]))])

    on, off = acc(base.with_effects(eff)), acc(base.with_effects(Gated(eff, jnp.asarray(0.0))))
    assert not np.allclose(np.asarray(on), np.asarray(acc(base)))  # the effect acts here
    np.testing.assert_array_equal(np.asarray(acc(base.with_effects(Gated(eff, jnp.asarray(1.0))))),
                                  np.asarray(on))
    np.testing.assert_allclose(np.asarray(off), np.asarray(acc(base)), rtol=1e-15, atol=0)
    batched = jax.vmap(lambda g: acc(base.with_effects(Gated(eff, g))))(jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(np.asarray(batched), np.stack([on, off]), rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("active", [(), ("cogging", "gravity", "joint_damping"),
                                    ("actuator_lag", "time_delay", "torque_offset"),
                                    ("backlash", "hardening_spring", "motor_cogging",
                                     "motor_friction", "asymmetric_friction")])
def test_gated_effects_taken_in_one_branch_per_hook_equal_the_active_effects(active):
    """Every candidate gated in (the discrepancy workflow's universal model), some on: the
    gated effects of each hook are taken in one run-time branch (``effect_torque``,
    ``applied_torque``), and the accelerations equal those of the plant holding only the
    active effects, in their order; an inactive effect's value never enters (one is given a
    parameter that makes its torque infinite); batched gates give the same numbers."""
    from jaxflex.core.effects import Gated

    names = sorted(n for n, e in EFFECTS.items() if e.candidate)
    effs = {n: jax.tree_util.tree_map(lambda a: a + 0.01 if a.shape == (1,) else a,
                                      EFFECTS[n].typical(1)) for n in names}
    idle = next(n for n in ("gravity", "torque_offset") if n not in active)
    effs[idle] = jax.tree_util.tree_map(lambda a: jnp.full_like(a, jnp.inf), effs[idle])
    base = paper_plant()
    u = jnp.array([0.2])

    def acc(plant, aux_of):
        x = plant.init_state(q1=0.3, dq1=0.4, q2=0.32, dq2=-0.7, z=1e-3)
        if x.aux is not None:  # internal states away from rest, the same per effect
            x = dataclasses.replace(x, aux=tuple(aux_of(e, a) for e, a in zip(plant.effects,
                                                                          x.aux)))
        return jnp.concatenate([*plant.accelerations(x, u),
                                link_measurement(plant.effects, x.q1, x.dq1),
                                *link_input(plant.effects, x.q1, x.dq1, jnp.array([0.5]))])

    def aux_of(e, a):
        if a is None:
            return None
        return jnp.asarray(a) + (1.0 + names.index(e.name)) * jnp.ones(jnp.shape(a))

    def gated(gates):
        return base.with_effects(*(Gated(effs[n], g) for n, g in zip(names, gates)))

    want = acc(base.with_effects(*(effs[n] for n in names if n in active)), aux_of)
    gates = jnp.asarray([1.0 if n in active else 0.0 for n in names])
    got = acc(gated(gates), aux_of)
    assert np.all(np.isfinite(np.asarray(got)))
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-14, atol=1e-14)
    batched = jax.vmap(lambda g: acc(gated(g), aux_of))(jnp.stack([gates, gates]))
    np.testing.assert_allclose(np.asarray(batched), np.stack([want, want]), rtol=1e-14,
                               atol=1e-14)


@pytest.mark.parametrize("on", [(), ("actuator_lag",), ("time_delay", "joint_damping")])
def test_gated_states_are_warmed_only_when_their_effect_is_on(on):
    """``warm_effects`` skips the warm-up of internal states whose effects are all gated off
    (they stay at equilibrium with the first torque: they cannot act); with one on, a replay
    of the gated universal plant equals that of the plant holding the active effects alone,
    warm-up included."""
    from jaxflex.core.effects import Gated
    from jaxflex.sim.step import replay, warm_effects

    names = ("actuator_lag", "joint_damping", "time_delay", "torque_offset")
    effs = {n: jax.tree_util.tree_map(lambda a: a + 0.01 if a.shape == (1,) else a,
                                      EFFECTS[n].typical(1)) for n in names}
    base = paper_plant()
    gated = base.with_effects(*(Gated(effs[n], jnp.asarray(1.0 if n in on else 0.0))
                                for n in names))
    plain = base.with_effects(*(effs[n] for n in names if n in on))
    tau_pre = jnp.linspace(0.1, 0.6, 30).reshape(30, 1)
    tau = jnp.sin(jnp.linspace(0.0, 6.0, 200)).reshape(200, 1)

    def run(plant):
        x0 = plant.init_state(q1=0.1, dq1=0.2, q2=0.11, dq2=0.1)
        x0 = warm_effects(plant, x0, tau_pre, 1e-3)
        return x0, replay("flexible", plant, x0, tau, 1e-3, 1)[0]

    xg, traj_g = run(gated)
    xp, traj_p = run(plain)
    if not on or on == ("joint_damping",):
        # nothing with a state is on: lag and delay left at equilibrium with tau_pre[0]
        np.testing.assert_array_equal(np.asarray(xg.aux[0]), np.asarray(tau_pre[0]))
    for k in ("q1", "q2", "dq1", "dq2"):
        np.testing.assert_allclose(np.asarray(getattr(traj_g, k)), np.asarray(getattr(traj_p, k)),
                                   rtol=1e-12, atol=1e-14)
    if "actuator_lag" in on:  # warmed: the lag state follows the torque history
        assert not np.allclose(np.asarray(xg.aux[0]), np.asarray(tau_pre[0]))
        np.testing.assert_allclose(np.asarray(xg.aux[0]), np.asarray(xp.aux[0]), rtol=1e-14)
    # a state whose effect is gated off stays where it started through the replay (its
    # derivative is not computed, ``Gated.aux_rhs``); one on moves
    for k, name in ((0, "actuator_lag"), (2, "time_delay")):
        moved = np.ptp(np.asarray(traj_g.aux[k]), axis=0)
        assert (np.all(moved == 0.0)) == (name not in on), (name, moved)


def test_encoder_scale_maps_invert_and_a_rotor_fit_recovers_it():
    """``encoder_scale``: its input map (kind "rotor") and output map (replays) are exact
    inverses; a value outside the calibration bound is refused by name; and the engine's
    torque-domain rotor fit recovers a planted scale (and K) from the motion a rotor with
    that link-encoder scale needs, where a fit without it cannot."""
    from jaxflex.fit import ParamSpace, least_squares
    from jaxflex.fit.inverse import Motion
    from jaxflex.validate import predicted_torque

    e = EFFECTS["encoder_scale"](scale=4e-4)
    assert not e.candidate and "encoder_scale" in EFFECTS
    q1, v1 = jnp.array([0.7]), jnp.array([0.3])
    qr, vr = link_input((e,), q1, v1, jnp.array([0.0]))
    np.testing.assert_allclose(np.asarray(link_measurement((e,), qr, vr)), np.asarray(q1),
                               rtol=1e-15)
    with pytest.raises(ValueError, match="encoder_scale: parameter scale"):
        EFFECTS["encoder_scale"](scale=0.05)

    t = np.arange(2000) * 4e-3
    q1 = 0.4 * np.sin(0.9 * t) + 0.2 * np.sin(2.3 * t)  # link angle [rad]
    d1, dd1 = np.gradient(q1, t), np.gradient(np.gradient(q1, t), t)
    defl = 1e-4 * np.sin(1.7 * t) + 5e-5 * np.cos(3.1 * t)  # spring deflection [rad]
    q2 = q1 + defl
    d2 = np.gradient(q2, t)
    dd2 = np.gradient(d2, t)
    fr = {"Fc": 1.0, "Fs": 1.0, "vs": 0.1, "sigma0": 1e5, "sigma1": 0.0, "sigma2": 0.0}
    truth = Params.from_dict({"plant": {"I": 1.0, "J": 600.0, "K": 4e6}, "friction": fr,
                              "effects": {"encoder_scale": {"scale": [5e-4]}}})
    cols = (q1 / (1 + 5e-4), d1 / (1 + 5e-4), dd1 / (1 + 5e-4), q2, d2, dd2, np.zeros_like(q1))
    motion = Motion(*(jnp.asarray(v).reshape(-1, 1) for v in cols))
    motion = eqx.tree_at(lambda m: m.tau, motion,
                         predicted_torque(truth.to_plant(), "rotor", motion))

    def fitted(free, scale0):
        start = Params.from_dict({"plant": {"I": 1.0, "J": 600.0, "K": 2e6}, "friction": fr,
                                  "effects": {"encoder_scale": {"scale": [scale0]}}})
        space = ParamSpace.build(start.to_plant(), free)
        res = lambda th, m: (predicted_torque(space.plant(th), "rotor", m) - m.tau).ravel()
        sol = least_squares(motion, space.theta0(), fn=res, max_steps=200)
        return sol, {k: float(np.asarray(v)[0]) for k, v in space.physical(sol.y).items()}

    sol, p = fitted(["K", "encoder_scale.scale"], 0.0)
    assert sol.converged
    assert p["K"] == pytest.approx(4e6, rel=1e-6) and p["encoder_scale.scale"] == pytest.approx(
        5e-4, rel=1e-6)
    sol0, p0 = fitted(["K"], 0.0)  # without the scale the same data give another K
    assert abs(p0["K"] / 4e6 - 1) > 0.05, p0


def test_extra_effects_carry_their_discovery_metadata_and_are_opt_in():
    """The three effects of real joints are registered with their fitting and discovery
    metadata on the class, and tried by discover only when named (not ``candidate``)."""
    from jaxflex.core.effects import acts_on_replay, candidate_effects
    from jaxflex.fit import is_fitted

    for name in EXTRA_NAMES:
        cls = EFFECTS[name]
        assert cls.name == name and cls.where and cls.telling
        assert name not in candidate_effects() and acts_on_replay(name)
        assert any(is_fitted(c) for c in cls.constraints.values())
        kw = cls.draw(np.random.default_rng(0))
        assert set(kw) <= set(cls.constraints) and set(cls.moderate) <= set(kw)
        e = cls.typical(2)
        assert all(np.shape(v) == (2,) for v in e.params().values())


def test_load_friction_is_a_share_of_the_transmitted_torque_against_the_rotor_motion():
    """rotor_torque = -mu |K (q2 - q1)| tanh(q2' / width): on the rotor only, proportional to
    the spring torque's magnitude whatever its sign, opposing the rotor's motion, zero with
    the spring unloaded."""
    e = EFFECTS["load_friction"](mu=0.08, K=6.77, width=0.01)
    for d, v in ((0.05, 2.0), (-0.05, 2.0), (0.02, -1.0), (0.0, 1.0)):
        dl, dr = _acc(e, q1=0.1, q2=0.1 + d, dq1=0.0, dq2=v)
        assert dl == 0.0
        assert dr == pytest.approx(-0.08 * abs(6.77 * d) * math.tanh(v / 0.01), rel=1e-9,
                                   abs=1e-15)
    assert _acc(e, q1=0.1, q2=0.15, dq2=2.0)[1] < 0 < _acc(e, q1=0.1, q2=0.15, dq2=-2.0)[1]
    with pytest.raises(ValueError, match="mu"):
        EFFECTS["load_friction"](mu=-0.1, K=6.77)


def _dahl_path(e, d):
    """The hysteresis state z [N m] along a deflection path ``d`` (T,) [rad] at 1 ms steps
    (RK4 of ``aux_rhs`` with the rate of the path's linear pieces)."""
    from jaxflex.core.state import PlantState

    h = 1e-3

    def step(z, seg):
        d0, d1 = seg
        rate = (d1 - d0) / h
        x = PlantState(q1=jnp.zeros(1), dq1=jnp.zeros(1), q2=d0 * jnp.ones(1),
                       dq2=rate * jnp.ones(1), z=jnp.zeros(1))
        f = lambda zz: e.aux_rhs(zz, jnp.zeros(1), x)
        k1 = f(z)
        k2 = f(z + 0.5 * h * k1)
        k3 = f(z + 0.5 * h * k2)
        k4 = f(z + h * k3)
        z = z + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return z, z[0]

    _, zs = jax.lax.scan(step, e.aux_init(1), (d[:-1], d[1:]))
    return np.concatenate([[0.0], np.asarray(zs)])


def test_spring_hysteresis_traces_a_dahl_loop_on_both_sides_of_the_spring():
    """Dahl's model on the deflection: z stays within +-Th, saturates at Th while the
    deflection grows, leaves a reversal from there with slope 2 Kh, and a deflection cycle dissipates
    (loop area > 0); the torque z acts in the spring (both sides, opposite signs)."""
    e = EFFECTS["spring_hysteresis"](Kh=3.0, Th=0.04)
    up = np.linspace(0.0, 0.1, 1001)
    d = np.concatenate([up, up[::-1][1:], -up[1:], -up[::-1][1:]])  # 0 -> 0.1 -> -0.1 -> 0
    z = _dahl_path(e, d)
    assert np.all(np.abs(z) <= 0.04 + 1e-12)
    assert z[1000] == pytest.approx(0.04, rel=1e-3)  # saturated at the top of the sweep
    # leaving the reversal from saturation at the slope Kh (1 + z / Th) = 2 Kh
    assert (z[1000] - z[1001]) / (d[1000] - d[1001]) == pytest.approx(6.0, rel=0.01)
    up_branch, down_branch = z[500], z[1500]  # the same deflection 0.05 rad, both ways
    assert up_branch > down_branch + 0.05  # a loop, not a curve
    area = float(np.sum(0.5 * (z[1:] + z[:-1]) * np.diff(d)))
    assert area > 0.0
    x = paper_plant().with_effects(e).init_state(q1=0.0, q2=0.01)
    x = dataclasses.replace(x, aux=(jnp.array([0.03]),))
    a1, a2 = paper_plant().with_effects(e).accelerations(x, jnp.zeros(1))
    b1, b2 = paper_plant().accelerations(paper_plant().init_state(q1=0.0, q2=0.01), jnp.zeros(1))
    assert float((a1 - b1)[0]) * 0.07 == pytest.approx(0.03)
    assert float((a2 - b2)[0]) * 0.005 == pytest.approx(-0.03)


def test_actuator_dead_zone_removes_a_band_of_the_commanded_torque():
    """tau_a ~ sign(u) max(|u| - b, 0), odd and monotone, within the corner width of it."""
    e = EFFECTS["actuator_dead_zone"](b=0.1, w=1e-3)
    u = jnp.array([-0.5, -0.2, -0.1, -0.05, 0.0, 0.05, 0.1, 0.2, 0.5])
    want = np.sign(np.asarray(u)) * np.maximum(np.abs(np.asarray(u)) - 0.1, 0.0)
    got = np.asarray(e.applied_torque(u, None))
    np.testing.assert_allclose(got, want, atol=1e-3)
    np.testing.assert_allclose(got, -got[::-1], atol=1e-15)
    assert np.all(np.diff(got) >= 0) and got[4] == 0.0
    assert got[-1] == pytest.approx(0.4, abs=1e-12)
    dl, dr = _acc(e)  # the default test torque 0.3 N m: 0.2 N m reaches the rotor
    assert dl == 0.0 and dr == pytest.approx(-0.1, rel=1e-6)


@pytest.mark.parametrize("name", EXTRA_NAMES)
def test_a_plant_with_an_extra_effect_simulates_and_its_gradient_is_finite(name):
    """A 1 s replay of the plant with the effect under a torque multisine (RK4, 1 ms, 4
    substeps) stays finite and differs from the plant without it, and the gradient of its
    link motion with respect to every fitted parameter is finite and not zero (also through
    the smoothed kinks: a reversal of the rotor, the deflection or the torque)."""
    from jaxflex.fit import is_fitted
    from jaxflex.sim.step import replay

    cls = EFFECTS[name]
    eff = cls(**{k: np.asarray(v, float) for k, v in cls.draw(np.random.default_rng(1)).items()
                 if v is not None} | ({"K": 6.77} if "K" in cls.constraints else {}))
    t = np.arange(1000) * 1e-3
    tau = jnp.asarray(0.4 * np.sin(2 * np.pi * 1.5 * t) + 0.2 * np.sin(2 * np.pi * 4.0 * t)
                      ).reshape(-1, 1)

    def motion(e):
        plant = paper_plant().with_effects(e) if e is not None else paper_plant()
        x0 = plant.init_state(q1=0.0, q2=0.0)
        xs, _ = replay("flexible", plant, x0, tau, 1e-3, 4)
        return xs.q1[:, 0]

    q_with, q_without = np.asarray(motion(eff)), np.asarray(motion(None))
    assert np.all(np.isfinite(q_with))
    assert np.max(np.abs(q_with - q_without)) > 1e-4
    fitted = [k for k, c in cls.constraints.items() if is_fitted(c)]
    for k in fitted:
        g = jax.grad(lambda v: jnp.sum(motion(dataclasses.replace(eff, **{k: v})) ** 2))(
            getattr(eff, k))
        assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).max()) > 0, (k, g)
