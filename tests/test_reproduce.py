"""``jaxflex reproduce`` writes results.json with the contract's keys and its figures."""

import json

import numpy as np

from jaxflex.app.cli import main
from jaxflex.io.params import load_params, save_params
from jaxflex.io.presets import paper_params, paper_sensing


def test_reproduce_cli_writes_results(tmp_path):
    out = tmp_path / "rep"
    # one experiment keeps the default suite fast; the slow study test runs them all
    assert main(["reproduce", "--out", str(out), "--duration", "1.0", "--no-q2d-comparison",
                 "--tasks", "sinusoid"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert set(res["experiments"]) == {"sinusoid"}
    # the paper's own sensing, with the estimator the estimator study selects
    assert (res["config"]["sensing"], res["config"]["estimator"]) == ("paper", "kalman")
    # the default observer has leakage; the loop at rest is then stable with compensation
    assert res["config"]["observer_leak"][0] > 0
    rest = res["rest"]
    assert rest["with_compensation"]["spectral_radius"] < 1.0
    assert rest["without_compensation"]["spectral_radius"] < 1.0
    # the paper's own observer (no leakage) is shown beside it: a growing rest mode and a
    # limit cycle (a property of the design, explained by the linearised loop), larger than
    # anything the leaky observer leaves at rest
    paper = res["paper_observer"]["rest"]["with_compensation"]
    assert paper["spectral_radius"] > 1.0
    assert paper["peak_amplitude"] > 5 * rest["with_compensation"]["peak_amplitude"]
    assert set(res["paper_observer"]["experiments"]) == {"sinusoid"}
    for e in res["experiments"].values():
        for metric in ("rms_error", "max_error"):
            for key in ("with_compensation", "without_compensation"):
                v = e[metric][key]
                assert isinstance(v, float) and 0 < v < 1.0
        # the paper's claim (Fig. 9-10): friction compensation reduces the tracking error
        assert e["rms_error"]["with_compensation"] < 0.7 * e["rms_error"]["without_compensation"]
        # the friction estimate beats no estimate (F_hat = 0) with compensation
        fe = e["friction_error_rms"]
        assert fe["with_compensation"] < fe["without_compensation"]
        for f in e["figures"]:
            assert (out / f).stat().st_size > 1000
    assert (out / "sinusoid_torque_friction.png").stat().st_size > 1000
    # every title names the estimator and the observer shown
    title = res["experiments"]["sinusoid"]["title"]
    assert "Kalman-filter velocities" in title and "leak 0.2 rad/s" in title
    # the paper's own controller (no leak, dirty derivative) has its figure too
    own = res["paper_own_observer"]
    assert own["velocity"] == "filtered" and own["observer_leak"] == [0.0]
    assert "dirty-derivative" in own["label"] and "no leak" in own["label"]
    fig = own["experiments"]["sinusoid"]["figures"]
    assert fig == ["sinusoid_paper_own_observer.png"]
    assert (out / fig[0]).stat().st_size > 1000
    # the configuration run is written as a parameter file that export follows
    from jaxflex.export import describe, rig_controller

    assert res["params_file"] == "params.json"
    sc = rig_controller(out / "params.json")
    assert sc.sensing.velocity == "kalman" and sc.estimator is not None
    assert describe(sc).startswith("Kalman-filter velocities") and "leak 0.2" in describe(sc)
    assert np.all(np.asarray(sc.sensing.q1_resolution) == np.asarray(paper_sensing().q1_resolution))


def test_reproduce_cli_bad_params_file_is_a_clear_error(tmp_path, capsys):
    p = paper_params()
    p.plant["I"] = [-0.07]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(p.to_dict()))
    assert main(["reproduce", "--out", str(tmp_path / "o"), "--params", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "parameter I" in err and "bad.json" in err
    assert not (tmp_path / "o").exists()  # refused before anything was written
    # what save_params writes reads back as the same floats
    good = tmp_path / "good.json"
    save_params(paper_params(), good)
    assert load_params(good).to_dict() == paper_params().to_dict()
