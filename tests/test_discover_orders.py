"""Discovery names an effect family and the order the log asks for (``jaxflex.discover.orders``,
docs/spec.md section 8.1), on logs of an independent simulator (``tests/independent_joint.py``:
numpy RK4, effects in forms of its own): a two-harmonic cogging is answered ``cogging`` order 2
and closes the gap, a one-harmonic cogging stays at order 1, a rotor friction with a
Stribeck term is answered ``motor_friction`` order 2, a spring with cubic and fifth-power
terms ``hardening_spring`` order 2 and one with the cubic term alone order 1, LuGre levels
that differ by direction in the static level beyond the Coulomb one ``asymmetric_friction``
order 2 and ones that differ alike order 1, a second-order current loop that a delay beats at
order 1 ``actuator_lag`` order 2."""

import pytest

from jaxflex.discover import DiscoverConfig, DiscoverResult, discover, effect_ties
from jaxflex.io.presets import paper_params

from independent_joint import harmonics, simulate

CANDS = ("cogging", "motor_cogging", "torque_offset", "hardening_spring")


def test_the_answer_names_the_family_and_its_order():
    """A round whose family grew records the order it added (``added``): the answer and the
    ties name it "cogging order 2"; an order 1 keeps the effect's name."""
    rounds = [{"winner": "cogging", "tied": ["cogging"], "added": "cogging_2"},
              {"winner": "time_delay", "tied": ["time_delay", "actuator_lag"],
               "added": "time_delay"}]
    assert effect_ties(rounds) == [["cogging order 2"], ["time_delay", "actuator_lag"]]
    fields = {f: None for f in DiscoverResult.__dataclass_fields__}
    res = DiscoverResult(**(fields | dict(effect="cogging", order=2,
                                          effects=["cogging_2", "time_delay"], rounds=rounds,
                                          tied=["cogging"])))
    assert res.families == ["cogging", "time_delay"] and res.orders == [2, 1]
    assert res.answer() == "cogging order 2: cogging order 2, then time_delay | actuator_lag"


def _run(candidates=CANDS, **effects):
    """Discovery (two effects at most) on a 10 s log of the independent joint with
    ``effects``, trying ``candidates``."""
    log = simulate(10.0, **effects)
    return discover(log, paper_params(), DiscoverConfig(candidates=candidates, max_effects=2))


@pytest.mark.slow
def test_a_two_harmonic_cogging_is_named_cogging_order_2():
    """A1 0.03 N m at N = 8 1/rad and A2 0.015 at 16: the fundamental alone closes about half
    of the gap's excess over the floor; its 2nd harmonic pays (the 3rd does not) and the
    answer is cogging order 2, closing at least 75% of the excess."""
    res = _run(link_ripple=harmonics([(0.03, 8.0, 0.3), (0.015, 16.0, 1.1)]))
    rep = res.to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("cogging", 2, ["cogging_2"])
    assert rep["explained_fraction"] >= 0.75
    p = rep["effect_params"]["cogging_2"]
    assert p["A"]["value"] == pytest.approx(0.03, rel=0.1)
    assert p["A2"]["value"] == pytest.approx(0.015, rel=0.15)
    assert p["N"]["value"] == pytest.approx(8.0, rel=0.02)
    tried = rep["rounds"][0]["orders"]
    assert [r["order"] for r in tried] == [2, 3] and tried[0]["kept"] and not tried[1]["kept"]


@pytest.mark.slow
def test_a_one_harmonic_cogging_stays_order_1():
    """The same joint with the fundamental only: order 2 does not pay, the answer is cogging
    order 1 (no harmonic fitted to the noise)."""
    rep = _run(link_ripple=harmonics([(0.03, 8.0, 0.3)])).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("cogging", 1, ["cogging"])
    assert not rep["rounds"][0]["orders"][0]["kept"]


@pytest.mark.slow
def test_a_rotor_friction_with_a_stribeck_term_is_named_motor_friction_order_2():
    """Coulomb 0.02, Stribeck excess 0.03 N m at 0.1 rad/s and viscous 0.01 N m s/rad on the
    rotor: Coulomb and viscous alone close part of the gap; the Stribeck order pays and closes
    it, with the levels recovered."""
    import math

    def rotor(v):
        return -((0.02 + 0.03 * math.exp(-((v / 0.1) ** 2))) * math.tanh(v / 0.01) + 0.01 * v)

    rep = _run(("motor_friction", "asymmetric_friction", "torque_offset", "joint_damping"),
               rotor_friction=rotor).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("motor_friction", 2,
                                                            ["motor_friction_2"])
    assert rep["explained_fraction"] >= 0.75
    p = rep["effect_params"]["motor_friction_2"]
    for k, v in (("Fm", 0.02), ("Fsm", 0.03), ("vsm", 0.1), ("bm", 0.01)):
        assert p[k]["value"] == pytest.approx(v, rel=0.15), k


SPRING_CANDS = ("hardening_spring", "backlash", "joint_damping", "torque_offset")


@pytest.mark.slow
def test_a_spring_with_a_fifth_power_is_named_hardening_spring_order_2():
    """K d + 70 d^3 + 7000 d^5 [N m] (deflections up to 0.13 rad): the cubic term alone
    leaves part of the gap; the fifth power pays, closes it, and both are recovered."""
    rep = _run(SPRING_CANDS, spring=lambda d: 70.0 * d**3 + 7000.0 * d**5).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("hardening_spring", 2,
                                                            ["hardening_spring_2"])
    assert rep["explained_fraction"] >= 0.75
    p = rep["effect_params"]["hardening_spring_2"]
    assert p["K3"]["value"] == pytest.approx(70.0, rel=0.05)
    assert p["K5"]["value"] == pytest.approx(7000.0, rel=0.05)


@pytest.mark.slow
def test_a_cubic_spring_stays_hardening_spring_order_1():
    """K d + 120 d^3: the fifth power does not pay; the answer is order 1 with K3 recovered."""
    rep = _run(SPRING_CANDS, spring=lambda d: 120.0 * d**3).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("hardening_spring", 1,
                                                            ["hardening_spring"])
    assert not rep["rounds"][0]["orders"][0]["kept"]
    assert rep["effect_params"]["hardening_spring"]["K3"]["value"] == pytest.approx(120.0,
                                                                                   rel=0.05)


ASYM_CANDS = ("asymmetric_friction", "torque_offset", "motor_friction", "cogging")


@pytest.mark.slow
def test_a_static_level_that_differs_by_direction_is_named_asymmetric_friction_order_2():
    """The simulator's LuGre levels per direction, inside its g(v): Coulomb 0.10 +- 0.02,
    static 0.16 +- 0.05 N m. The Coulomb shift alone leaves part of the gap; the static one
    pays, closes it, and both shifts are recovered."""
    rep = _run(ASYM_CANDS, asymmetry=(0.02, 0.05)).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("asymmetric_friction", 2,
                                                            ["asymmetric_friction_2"])
    assert rep["explained_fraction"] >= 0.75
    p = rep["effect_params"]["asymmetric_friction_2"]
    assert p["dF"]["value"] == pytest.approx(0.02, rel=0.05)
    assert abs(p["dS"]["value"] - 0.05) < 3.0 * p["dS"]["stderr"]


@pytest.mark.slow
def test_levels_that_differ_alike_by_direction_stay_asymmetric_friction_order_1():
    """Coulomb and static levels both 0.03 N m apart per direction: the static shift does not
    pay; the answer is order 1 with dF recovered."""
    rep = _run(ASYM_CANDS, asymmetry=(0.03, 0.03)).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("asymmetric_friction", 1,
                                                            ["asymmetric_friction"])
    assert not rep["rounds"][0]["orders"][0]["kept"]
    assert rep["effect_params"]["asymmetric_friction"]["dF"]["value"] == pytest.approx(
        0.03, rel=0.05)


@pytest.mark.slow
def test_a_current_loop_that_a_delay_beats_at_order_1_is_named_actuator_lag_order_2():
    """A second-order lag of 150 rad/s and damping 0.5 from command to applied torque: at
    order 1 the delay wins the round (its held-out gap a third of the first-order lag's);
    the lag, a rival of the contest, is grown, its order 2 pays over the delay, and the
    current loop is recovered."""
    rep = _run(("actuator_lag", "time_delay", "torque_offset", "motor_friction"),
               lag=(150.0, 0.5)).to_json()
    assert (rep["effect"], rep["order"], rep["effects"]) == ("actuator_lag", 2,
                                                            ["actuator_lag_2"])
    assert "contest_orders" in rep["rounds"][0]
    assert rep["explained_fraction"] >= 0.75
    p = rep["effect_params"]["actuator_lag_2"]
    assert p["T"]["value"] == pytest.approx(1.0 / 150.0, rel=0.05)
    assert p["zeta"]["value"] == pytest.approx(0.5, rel=0.05)


@pytest.mark.slow
def test_a_higher_order_is_built_only_once_its_order_below_is_in_a_model():
    """The run's workspaces (``Workspaces``): the first holds the candidates alone; one that
    holds a family's order 2 is built when asked for and kept; a fit made in the first
    replays the same (to rounding) read in the wider one (``Workspace.theta_of``), and a
    model with an effect outside a universe is refused."""
    import numpy as np

    from jaxflex.identify.datagen import generate_log
    from jaxflex.discover import Model, Workspaces, fit_model, output_residuals
    from jaxflex.core.effects import EFFECTS
    from jaxflex.io.params import Params

    g = generate_log(("torque_offset",), seed=4, t_final=3.0)
    true = Params.from_dict(g.truth["plant"])
    built = []
    wss = Workspaces(g.log, true, ("torque_offset", "motor_friction"), prepare=built.append,
                     segment=0.3, train_frac=0.5, substeps=1, max_effects=1)
    first = wss.holding()
    assert first.universe == ("motor_friction", "torque_offset") and built == [first]
    assert wss.holding(["torque_offset"]) is first
    fit = fit_model(first, Model(true, [EFFECTS["motor_friction"].typical(1)]), max_steps=3)
    wide = wss.holding(["motor_friction", "motor_friction_2"])
    assert "motor_friction_2" in wide.universe and built == [first, wide]
    assert wss.holding(["motor_friction_2"]) is wide
    assert set(fit.theta) != set(wide.space.names)
    np.testing.assert_allclose(output_residuals(wide, fit), output_residuals(first, fit),
                               rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="not in the workspace's universe"):
        first.for_model(Model(true, [EFFECTS["motor_friction_2"].typical(1)]))
