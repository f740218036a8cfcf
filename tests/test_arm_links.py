"""A coupled arm's link fields on the fitting engine: the ``links`` section of a parameter
file, the names ``"links.<field>"`` of ``jaxflex.fit.ParamSpace``, the base parameters of
``PlanarTwoLink`` and which fields the data can determine (``jaxflex.identify.links``); the
identification of a two-link arm from an independent simulator (``studies/arm_two_link.py``,
slow)."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.fit import ParamSpace, get_value, set_values
from jaxflex.fit.space import params_of_plant
from jaxflex.identify.links import base_record, structural_free
from jaxflex.io.params import Params, ParamsError
from jaxflex.core.plant import PlanarTwoLink


ARM = {"type": "planar_two_link", "m1": 0.6, "m2": 0.35, "l1": 0.3, "lc1": 0.15, "lc2": 0.12,
       "I1": 0.0045, "I2": 0.002, "g": 0.0}


def arm_params(**links) -> Params:
    return Params.from_dict({
        "links": {**ARM, **links}, "plant": {"J": [0.005, 0.003], "K": [6.77, 5.0]},
        "friction": {"Fc": [0.11, 0.06], "Fs": [0.15, 0.08], "vs": [0.05, 0.05],
                     "sigma0": [100.0, 80.0], "sigma1": [0.1, 0.08], "sigma2": [0.2, 0.1]}})


def test_links_section_round_trip_and_refusals():
    p = arm_params()
    assert p.n == 2 and isinstance(p.to_plant().links, PlanarTwoLink)
    assert Params.from_dict(json.loads(json.dumps(p.to_dict()))).to_dict() == p.to_dict()
    bad = [({"links": {**ARM, "type": "scara"}}, "links.type"),
           ({"links": {**ARM, "m3": 1.0}}, "unknown field 'm3'"),
           ({"links": {k: v for k, v in ARM.items() if k != "lc2"}}, "missing field"),
           ({"links": {**ARM, "m2": -1.0}}, "m2"),
           ({"plant": {"I": [1.0, 1.0], "J": [0.005, 0.003], "K": [6.77, 5.0]}}, "plant.I")]
    for change, words in bad:
        with pytest.raises(ParamsError, match=words.replace(".", r"\.")):
            Params.from_dict({**p.to_dict(), **change})
    with pytest.raises(ParamsError, match="not independent"):
        p.joint(0)


def test_link_names_map_onto_the_plant():
    p = arm_params()
    space = ParamSpace.build(p.to_plant(), ["links.I1", "links.m2", "K", "Fc", "Fs"])
    th = space.theta_of({"links.m2": 0.5, "K": [7.0, 4.0]})
    assert th["links.m2"].shape == (1,) and space.fitted_flat().size == 8
    plant = space.plant(th)
    assert plant.links.m2.shape == () and float(plant.links.m2) == pytest.approx(0.5)
    np.testing.assert_allclose(plant.K, [7.0, 4.0])
    back = params_of_plant(plant, p)
    assert back.links["m2"] == pytest.approx(0.5) and back.links["type"] == "planar_two_link"
    q = set_values(p, {"links.I2": [0.003]})
    assert get_value(q, "links.I2").tolist() == [0.003] and q.links["I1"] == ARM["I1"]
    for free, words in ((["I"], "not M = diag"), (["links.l1"], "geometry"),
                        (["links.mass"], "no fitted field 'mass'")):
        with pytest.raises(ValueError, match=words):
            ParamSpace.build(p.to_plant(), free)
    with pytest.raises(ValueError, match="'I'"):
        ParamSpace.build(Params.from_dict({"plant": {"I": 1.0, "J": 1.0, "K": 1.0},
                                           "friction": {k: v[0] for k, v in
                                                        p.friction.items()}}).to_plant(),
                         ["links.I"])


@pytest.mark.parametrize("g", [0.0, 9.81])
def test_base_parameters_determine_the_dynamics(g):
    """Two arms with the same base parameters and different fields have the same M, C, G;
    the base parameters match their definitions."""
    a = PlanarTwoLink(m1=0.6, m2=0.35, l1=0.3, lc1=0.15, lc2=0.12, I1=0.0045, I2=0.002, g=g)
    base = {k: float(v) for k, v in a.base_parameters().items()}
    assert base["a1"] == pytest.approx(0.0045 + 0.6 * 0.15**2 + 0.35 * 0.09)
    assert base["a3"] == pytest.approx(0.35 * 0.3 * 0.12)
    assert ("a4" in base) == (g != 0)
    # another split: m2 and m1 up, lc2 and lc1 down (a3 and a4 kept), I1, I2 absorbing a1, a2
    m2, lc2, m1, lc1 = 0.4, 0.105, 0.75, 0.1
    I2 = base["a2"] - m2 * lc2**2
    I1 = base["a1"] - m1 * lc1**2 - m2 * 0.09
    b = PlanarTwoLink(m1=m1, m2=m2, l1=0.3, lc1=lc1, lc2=lc2, I1=I1, I2=I2, g=g)
    for k, v in b.base_parameters().items():
        assert float(v) == pytest.approx(base[k], rel=1e-12)
    q, dq = jnp.array([0.3, -1.1]), jnp.array([0.7, 1.9])
    np.testing.assert_allclose(a.mass_matrix(q), b.mass_matrix(q), rtol=1e-12)
    np.testing.assert_allclose(a.coriolis(q, dq, dq), b.coriolis(q, dq, dq), rtol=1e-12)
    np.testing.assert_allclose(a.gravity(q), b.gravity(q), rtol=1e-12, atol=1e-14)
    # and a change of a base parameter does change them (the check can fail)
    c = PlanarTwoLink(m1=0.6, m2=0.35, l1=0.3, lc1=0.15, lc2=0.12, I1=0.0055, I2=0.002, g=g)
    assert not np.allclose(a.mass_matrix(q), c.mass_matrix(q))


def test_structural_free_keeps_a_minimal_set():
    p = arm_params()
    every = ["links.m1", "links.m2", "links.lc1", "links.lc2", "links.I1", "links.I2", "K"]
    free, fixed = structural_free(p, every)
    links = [k for k in free if k.startswith("links.")]
    assert len(links) == 3 and "K" in free  # a1, a2, a3 of the horizontal arm
    assert set(fixed) == set(every) - set(free)
    assert all("a1 = I1 + m1 lc1^2 + m2 l1^2" in why for why in fixed.values())
    free, fixed = structural_free(arm_params(g=9.81), every)
    assert len([k for k in free if k.startswith("links.")]) == 4 and len(fixed) == 2
    # a minimal set is kept whole; decoupled links are not touched
    assert structural_free(p, ["links.I1", "links.I2", "links.m2", "J"]) == (
        ["links.I1", "links.I2", "links.m2", "J"], {})
    # I1 and m1 enter a horizontal arm only through a1: the second adds nothing
    free, fixed = structural_free(p, ["links.I1", "links.m1"])
    assert free == ["links.I1"] and list(fixed) == ["links.m1"]


def test_base_record_propagates_the_covariance():
    links = PlanarTwoLink(m1=0.6, m2=0.35, l1=0.3, lc1=0.15, lc2=0.12, I1=0.0045, I2=0.002,
                          g=0.0)
    phys = {"K": np.array([6.77, 5.0]), "links.I1": np.array([0.0045]),
            "links.m2": np.array([0.35])}
    # sorted names: K[0], K[1], links.I1, links.m2
    cov = np.diag([1.0, 1.0, 1e-8, 4e-4])
    rec = base_record(links, phys, cov)["base_parameters"]
    # a1 = I1 + m1 lc1^2 + m2 l1^2: var = 1e-8 + l1^4 4e-4; a3 = m2 l1 lc2: (l1 lc2)^2 4e-4
    assert rec["a1"]["stderr"] == pytest.approx(np.sqrt(1e-8 + 0.3**4 * 4e-4))
    assert rec["a3"]["stderr"] == pytest.approx(0.3 * 0.12 * 2e-2)
    assert rec["a2"]["value"] == pytest.approx(0.002 + 0.35 * 0.12**2)


@pytest.mark.slow
def test_independent_simulator_agrees_with_the_plant_at_the_truth():
    """At the true parameters, with only the segment starts fitted, jaxflex's replay of the
    independent simulator's log (hand-written M, C, G, LuGre, DOP853) leaves what the
    encoders' quantisation explains: the two models are the same arm."""
    import equinox as eqx

    from jaxflex.fit import least_squares
    from jaxflex.identify.problem import make_problem, noise_cost
    from jaxflex.io.logs import Log

    from studies import arm_two_link

    log = Log.from_arrays(**arm_two_link.simulate(2.0))
    truth = Params.from_dict(arm_two_link.truth_params(0.0))
    prob, y0 = make_problem(log, truth, ["K"], segment_length=250, substeps=4)
    prob = eqx.tree_at(lambda p: p.space, prob, prob.space.with_mask([], y0[0]))
    sol = least_squares(prob, y0, max_steps=40)
    assert sol.cost < 1.3 * noise_cost(log, prob)
    # and a wrong arm does not: a1 10% high
    wrong = Params.from_dict({**truth.to_dict(), "links": {**truth.links, "I1": 0.0095}})
    prob_w, y0_w = make_problem(log, wrong, ["K"], segment_length=250, substeps=4)
    prob_w = eqx.tree_at(lambda p: p.space, prob_w, prob_w.space.with_mask([], y0_w[0]))
    assert least_squares(prob_w, y0_w, max_steps=40).cost > 10 * noise_cost(log, prob)


@pytest.mark.slow
def test_study_recovers_the_arm(tmp_path):
    """The study's check on the 8 s log of the independent simulator, from a start 20-40%
    off: converged with the cost at the noise (adequate), and every identifiable value (the
    base parameters, J, K and the six LuGre parameters of both joints) within 5% of its
    truth and within 3 of its standard errors."""
    from studies import arm_two_link

    res = arm_two_link.main(["--out", str(tmp_path), "--seconds", "8"])
    assert (tmp_path / "results.json").exists()
    assert res["converged"] and res["model"] == "adequate"
    for name, row in res["parameters"].items():
        assert abs(row["rel_error"]) < 0.05, (name, row)
        assert abs(row["in_stderr"]) < 3.0, (name, row)
