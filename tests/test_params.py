"""Parameter files (docs/spec.md section 7): save/load round trip is exact; bad files give clear errors."""

import json

import numpy as np
import pytest

from jaxflex.io.params import (
    ControllerConfig,
    Params,
    ParamsError,
    build_plant,
    load_params,
    save_params,
)
from jaxflex.io.presets import paper_params


def test_round_trip_exact(tmp_path):
    rng = np.random.default_rng(3)
    p = paper_params()
    d = p.to_dict()
    # Awkward floats (not short decimals) must survive exactly.
    d["plant"]["I"] = [float(0.07 * (1 + rng.normal() * 1e-3))]
    d["friction"]["sigma1"] = [float(rng.uniform(0.01, 1.0))]
    d["friction"]["Fs"] = [0.15000000000000002]
    d["effects"] = {"torque_offset": {"offset": [float(rng.normal())]}}
    d["stderr"] = {"friction": {"Fc": [1.2345678901234567e-05]}}
    p = Params.from_dict(d)
    path = tmp_path / "p.json"
    save_params(p, path)
    back = load_params(path)
    assert back.to_dict() == p.to_dict()
    save_params(back, tmp_path / "q.json")
    assert (tmp_path / "q.json").read_text() == path.read_text()


def test_two_joint_round_trip(tmp_path):
    d = {"plant": {"I": [0.07, 0.03], "J": [0.005, 0.003], "K": [6.77, 5.0]},
         "friction": {"Fc": [0.11, 0.06], "Fs": [0.15, 0.08], "vs": [0.05, 0.05],
                      "sigma0": [100.0, 80.0], "sigma1": [0.1, 0.08], "sigma2": [0.2, 0.1]}}
    p = Params.from_dict(d)
    save_params(p, tmp_path / "p.json")
    assert load_params(tmp_path / "p.json").to_dict() == p.to_dict()


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d.pop("friction"), "missing section 'friction'"),
        (lambda d: d["friction"].pop("vs"), "friction.vs is missing"),
        (lambda d: d["friction"].update(Fs=0.05), "Fs"),
        (lambda d: d["plant"].update(K=-1.0), "K"),
        (lambda d: d["friction"].update(sigma0="big"), "friction.sigma0"),
    ],
)
def test_bad_files(tmp_path, edit, match):
    d = paper_params().to_dict()
    edit(d)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ParamsError, match=match):
        load_params(path)


CONTROLLER = {"q2d_method": "filtered", "dt": 0.0005000000000000001, "tau_max": 1.7,
              "compensation": False, "sensing": {"q1_resolution": 1e-4, "velocity": "filtered",
                                                 "dac_bits": 12},
              "trajectory": ["polynomial", "sinusoid"]}


def test_controller_section_round_trip_exact(tmp_path):
    d = paper_params().to_dict()
    d["controller"] = CONTROLLER
    p = Params.from_dict(d)
    assert p.controller.dt == CONTROLLER["dt"] and p.controller.trajectory_name == "polynomial"
    assert "controller" not in p.extra
    save_params(p, tmp_path / "p.json")
    back = load_params(tmp_path / "p.json")
    assert back == p and back.to_dict() == d
    assert json.loads((tmp_path / "p.json").read_text())["controller"] == CONTROLLER
    one = Params.from_dict({**d, "controller": {"sensing": "rig", "trajectory": "fast"}})
    assert one.to_dict()["controller"] == {"sensing": "rig", "trajectory": "fast"}
    assert paper_params().controller is None and "controller" not in paper_params().to_dict()


@pytest.mark.parametrize(
    ("section", "match"),
    [
        ({"tau_mx": 2.0}, r"unknown key 'tau_mx' \(did you mean 'tau_max'\?\)"),
        ({"q2d": "model"}, r"unknown key 'q2d' \(did you mean 'q2d_method'\?\)"),
        ({"dt": "1ms"}, r"controller\.dt: expected a finite number > 0"),
        ({"dt": -1e-3}, r"controller\.dt"),
        ({"tau_max": True}, r"controller\.tau_max"),
        ({"compensation": "yes"}, r"controller\.compensation: expected true or false"),
        ({"q2d_method": "magic"}, r"controller\.q2d_method: expected one of"),
        ({"sensing": 16}, r"controller\.sensing: expected a sensing preset name"),
        ({"sensing": {"q1_resolutoin": 1e-4}},
         r"unknown field 'q1_resolutoin' \(did you mean 'q1_resolution'\?\)"),
        ({"sensing": {"velocity": "guessed"}}, r"controller\.sensing: .*velocity"),
        ({"trajectory": 3}, r"controller\.trajectory: expected a trajectory name"),
        ({"trajectory": []}, r"controller\.trajectory"),
        ([1, 2], r"controller: expected an object"),
    ],
)
def test_controller_section_refuses_unknown_keys_and_bad_types(tmp_path, section, match):
    d = paper_params().to_dict()
    d["controller"] = section
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(d))
    with pytest.raises(ParamsError, match=match):
        load_params(path)


def test_controller_config_resolution_refuses_contradictions():
    rec = ControllerConfig(q2d_method="model", dt=1e-3, trajectory=("sinusoid", "fast"))
    got = rec.resolve({"q2d_method": None, "dt": 1.0 / 1000.0, "tau_max": 1.5,
                       "trajectory": "fast"})
    assert got == ControllerConfig(q2d_method="model", dt=1e-3, tau_max=1.5, trajectory="fast")
    with pytest.raises(ParamsError, match=r"--q2d 'filtered' contradicts controller\.q2d_method"):
        rec.resolve({"q2d_method": "filtered"}, {"q2d_method": "--q2d"})
    with pytest.raises(ParamsError, match="controller.dt"):
        rec.resolve({"dt": 2e-3})
    with pytest.raises(ParamsError, match="controller.trajectory"):
        rec.resolve({"trajectory": "polynomial"})
    filled = ControllerConfig(dt=2e-3).with_defaults(ControllerConfig(dt=1e-3, tau_max=2.0))
    assert filled == ControllerConfig(dt=2e-3, tau_max=2.0)


def test_build_plant_is_the_params_builder_and_traces():
    import jax
    import jax.numpy as jnp

    p = paper_params()
    ref = p.to_plant()
    same = build_plant(p.plant, p.friction)
    assert jax.tree_util.tree_all(jax.tree_util.tree_map(jnp.array_equal, ref, same))
    assert build_plant(p.plant).friction is None

    def inertia_of(I):
        return build_plant({**p.plant, "I": I}, p.friction).links.I

    Is = jnp.array([[0.05], [0.07], [0.09]])
    np.testing.assert_array_equal(np.asarray(jax.vmap(inertia_of)(Is)), np.asarray(Is))
    with pytest.raises(ParamsError, match="unknown effect 'nope'"):
        build_plant(p.plant, p.friction, {"nope": {}})
