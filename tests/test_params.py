"""Parameter files (SPEC section 7): save/load round trip is exact; bad files give clear errors."""

import json

import numpy as np
import pytest

from jaxflex.params import Params, ParamsError, load_params, paper_params, save_params


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
