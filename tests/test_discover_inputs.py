"""Discovery on real logs as a new user runs it: the parameter file's model (rigid, flexible,
rotor) and its identification's verdict decide how the file is taken; a model the replay
cannot integrate is refused with its remedy; a numerical failure of a fit is a solver failure,
not a bad input."""

import json

import numpy as np
import pytest

from jaxflex.discover import (
    DiscoverConfig,
    SolverFailure,
    discover,
    model_kind_of,
    nominal_for_model,
    spring_mode,
)
from jaxflex.data import EMPS_IDIM_LS
from jaxflex.io.errors import InputError
from jaxflex.io.logs import save_log
from jaxflex.io.params import Params, ParamsError

#: The EMPS benchmark's published rigid model as a rigid identification would write it (the
#: moving mass as I plus a tiny J, a large K), with a Stribeck hump and no force offset.
EMPS_RIGID = EMPS_IDIM_LS.params_dict(Fs=22.0, sigma1=100.0, offset=False)


@pytest.fixture(scope="module")
def emps_log():
    """The first 8 s of the shipped EMPS log (one encoder: q2 = q1)."""
    from jaxflex.data import load_emps

    return load_emps("DATA_EMPS").slice(0, 8000)


def _rigid(**ident) -> Params:
    return Params.from_dict({**EMPS_RIGID, "identification": {"model": "rigid", **ident}})


def test_a_rigid_model_too_stiff_for_the_replay_is_refused_with_its_remedy(emps_log):
    """Replayed as a flexible joint, the rigid file's spring mode (sqrt(K (1/I + 1/J)), 31.6
    rad/s per ms) is past RK4's limit: the replay overflowed and the nominal refit's
    covariance died in numpy ("Eigenvalues did not converge"). It is refused before any fit,
    naming the mode and the remedy."""
    p = _rigid()
    I, J = EMPS_RIGID["plant"]["I"], EMPS_RIGID["plant"]["J"]
    assert spring_mode(p) == pytest.approx(np.sqrt(1e6 * (1 / I + 1 / J)))
    with pytest.raises(ValueError, match=r"spring mode.*--model rigid.*substeps"):
        discover(emps_log, p, DiscoverConfig(candidates=("torque_offset",), model="flexible"))


def test_a_rigid_model_is_replayed_as_two_stiff_halves(emps_log):
    """model 'rigid': two halves of I + J joined by the spring of a 600 rad/s mode at 1 ms
    (as ``studies/discover_emps.py``), friction unchanged; a one-encoder log reads q2 = q1."""
    p, log, note = nominal_for_model(_rigid(), "rigid", emps_log, 1e-3)
    half = EMPS_IDIM_LS.M / 2
    assert p.plant["I"] == pytest.approx([half]) and p.plant["J"] == pytest.approx([half])
    assert spring_mode(p) == pytest.approx(600.0)
    assert p.friction == _rigid().friction
    assert "rigid" in note and log is emps_log
    one = emps_log.__class__.from_arrays(t=emps_log.t, tau=emps_log.tau, q1=emps_log.q1,
                                         required=("t", "tau", "q1"))
    assert np.array_equal(nominal_for_model(_rigid(), "rigid", one, 1e-3)[1].q2, one.q1)


@pytest.mark.slow
def test_a_rigid_identification_runs_from_the_command_line(tmp_path, capsys):
    """The rigid EMPS file, its model read from the file: discover runs (it used to exit 2
    with "Eigenvalues did not converge" and leave an empty folder), reports the model and
    the final model's residual analysis with its figure."""
    from jaxflex.app.cli import main
    from jaxflex.data import load_emps

    log = load_emps("DATA_EMPS").slice(0, 8000)
    save_log(log, tmp_path / "emps.csv")
    (tmp_path / "rigid.json").write_text(json.dumps(_rigid(converged=True).to_dict()))
    code = main(["discover", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "rigid.json"),
                 "--out", str(tmp_path / "o"), "--candidates", "torque_offset",
                 "--max-effects", "1"])
    out = capsys.readouterr().out
    assert code == 0, out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["config"]["model"] == "rigid" and rep["log"]["model"] == "rigid"
    assert rep["log"]["model_note"].startswith("rigid model: inertia 95.1")
    assert rep["answer"].startswith(rep["effect"]) and len(rep["effects_tied"]) <= 1
    assert np.isfinite(rep["gap_before"]) and rep["gap_before"] < 0.05
    assert "rigid model" in out
    # the final model's residual analysis (MATLAB's resid) on its one encoder (the log's q2
    # is q1: compared once), and its figure
    ra = rep["residual_analysis"]
    assert set(ra["channels"]) == {"q1"} and ra["lags"] == 25
    for c in ra["channels"].values():
        assert len(c["autocorrelation"]) == 26 and len(c["cross_correlation"]) == 51
        assert 0 <= c["p_white"] <= 1 and c["band"] > 0 and c["cross_band"] > 0
    assert "residuals.png" in rep["figures"] and (tmp_path / "o" / "residuals.png").exists()


@pytest.mark.slow
def test_a_solver_crash_is_a_solver_failure_naming_the_fit(emps_log, tmp_path, capsys,
                                                             monkeypatch):
    """A numpy LinAlgError inside a fit is a ``SolverFailure`` naming the fit (the nominal
    model's refit here), not a bad input: the command exits 1 (not 2) and report.json records
    the failure."""
    import jaxflex.discover.fitting as fitting
    from jaxflex.app.cli import main

    def broken(*a, **k):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")

    monkeypatch.setattr(fitting, "covariance", broken)
    with pytest.raises(SolverFailure, match="nominal model's refit.*Eigenvalues") as e:
        discover(emps_log, _rigid(), DiscoverConfig(candidates=("torque_offset",),
                                                    model="rigid"))
    assert not isinstance(e.value, ValueError)
    save_log(emps_log, tmp_path / "emps.csv")
    (tmp_path / "rigid.json").write_text(json.dumps(_rigid().to_dict()))
    code = main(["discover", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "rigid.json"),
                 "--out", str(tmp_path / "o"), "--candidates", "torque_offset", "--no-plots"])
    assert code == 3
    assert "solver failure in the nominal model's refit" in capsys.readouterr().err
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["failed"]["kind"] == "solver failure" and rep["effect"] is None


def test_a_fit_that_runs_a_parameter_out_of_range_is_a_solver_failure_naming_it(
        emps_log, monkeypatch):
    """A solve that runs a fitted parameter to a non-finite value (an inertia grown until the
    replay no longer feels it: the residual stays finite there, its Jacobian does not) is a
    ``SolverFailure`` that names the parameter, not a linear-algebra error of its
    covariance."""
    import jax.numpy as jnp

    import jaxflex.discover.fitting as fitting
    from jaxflex.fit import Solution

    def runaway(prob, y0, **kw):  # the solve's end point, without the solve
        theta, starts = y0
        theta = dict(theta) | {"I": jnp.full_like(theta["I"], 1e4)}  # I = exp(1e4) = inf
        return Solution(y=(theta, starts), steps=1, converged=False, cost=1.0, reason="",
                        seconds=0.0)

    monkeypatch.setattr(fitting, "least_squares", runaway)
    with pytest.raises(SolverFailure, match="nominal model's refit.*ran I to inf"):
        discover(emps_log, _rigid(), DiscoverConfig(candidates=("torque_offset",),
                                                    model="rigid", max_steps=3))


def test_the_model_kind_is_read_from_the_identification():
    """From ``identification.start.kind`` beside the model's verdict, or from
    ``identification.model`` where that is the kind's name (files without a verdict)."""
    assert model_kind_of(_rigid()) == "rigid"
    assert model_kind_of(_rigid(model={"verdict": "adequate"}, start={"kind": "rotor"})) \
        == "rotor"
    assert model_kind_of(_rigid(model={"verdict": "adequate"})) is None
    assert model_kind_of(Params.from_dict(EMPS_RIGID)) is None


def test_a_model_limited_file_runs_from_the_command_line_with_its_kind(tmp_path, capsys,
                                                                      monkeypatch):
    """The command takes a converged, model-limited file without --accept-unconverged, says
    so in one line, and takes the file's model kind ('rigid': the input check passes and the
    refusal of a too-stiff flexible replay does not come)."""
    from jaxflex.app.cli import main

    import jaxflex.discover as d

    seen = {}

    def fake(log, nominal, cfg, progress=None):
        seen["model"], seen["samples"] = cfg.model, log.N
        raise InputError("stop here")

    monkeypatch.setattr(d, "discover", fake)
    from jaxflex.data import load_emps

    save_log(load_emps("DATA_EMPS").slice(0, 3000), tmp_path / "emps.csv")
    p = _rigid(converged=True, model={"verdict": "model-limited", "cost_over_noise": 40.0},
               start={"kind": "rigid"})
    (tmp_path / "p.json").write_text(json.dumps(p.to_dict()))
    code = main(["discover", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "p.json"),
                 "--out", str(tmp_path / "o"), "--no-plots"])
    io = capsys.readouterr()
    assert code == 2 and "stop here" in io.err
    assert seen["model"] == "rigid"
    notes = [ln for ln in (io.out + io.err).splitlines() if "model-limited" in ln]
    assert len(notes) == 1, notes
    assert not (tmp_path / "o").exists()  # a refused run leaves no empty folder
    main(["discover", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "p.json"),
          "--out", str(tmp_path / "o"), "--no-plots", "--model", "flexible"])
    assert seen["model"] == "flexible"
    # a shipped data set by name, as identify takes it
    main(["discover", "jaxflex:emps/DATA_EMPS", "--params", str(tmp_path / "p.json"),
          "--out", str(tmp_path / "o"), "--no-plots"])
    assert seen["samples"] == 24841


def test_a_rotor_identification_gets_the_link_side_from_the_logs_rigid_fit():
    """model 'rotor': J and K from the file, the link inertia and friction from the rigid fit
    of the log, as the KUKA study builds its nominal (``studies/discover_kuka.py``)."""
    from jaxflex.data import load_kuka
    from jaxflex.validate import rigid_torque_fit

    log = load_kuka("A", 1)
    p0 = Params.from_dict({"plant": {"I": 1.0, "J": 5.0, "K": 2e6},
                           "friction": {"Fc": 1.0, "Fs": 1.0, "vs": 0.1, "sigma0": 1e3,
                                        "sigma1": 0.0, "sigma2": 1.0}})
    p, _, note = nominal_for_model(p0, "rotor", log, log.dt)
    rigid = rigid_torque_fit(log)
    assert p.plant["J"] == [5.0] and p.plant["K"] == [2e6]
    assert p.plant["I"][0] == pytest.approx(max(rigid["Jt"] - 5.0, 0.1 * rigid["Jt"]))
    assert p.friction["Fc"][0] == pytest.approx(abs(rigid["Fc"]))
    assert p.friction["sigma2"][0] == pytest.approx(abs(rigid["Fv"]))
    assert "rotor" in note


def test_every_rounds_tie_is_in_the_answer():
    """A tie left by a later round reaches the answer: with gravity decided in round 1 and
    time_delay tied with actuator_lag in round 2, the answer names both rivals of the second
    effect (it used to read "gravity" with effects [gravity, time_delay] only); a round whose
    winner was dropped adds nothing."""
    from jaxflex.discover import DiscoverResult, effect_ties

    rounds = [{"winner": "gravity", "tied": ["gravity"]},
              {"winner": "time_delay", "tied": ["time_delay", "actuator_lag"]},
              {"winner": "none", "tied": ["cogging", "backlash"]}]
    assert effect_ties(rounds) == [["gravity"], ["time_delay", "actuator_lag"]]
    fields = {f: None for f in DiscoverResult.__dataclass_fields__}
    res = DiscoverResult(**(fields | dict(effect="gravity", effects=["gravity", "time_delay"],
                                          rounds=rounds, tied=["gravity"])))
    assert res.effects_tied == [["gravity"], ["time_delay", "actuator_lag"]]
    assert res.answer() == "gravity: gravity, then time_delay | actuator_lag"
    first = [{"winner": "cogging", "tied": ["motor_cogging", "cogging"]}]
    res = DiscoverResult(**(fields | dict(effect="indistinguishable", effects=["cogging"],
                                          rounds=first)))
    assert res.answer() == "indistinguishable: cogging | motor_cogging"
    assert DiscoverResult(**(fields | dict(effect="none", rounds=[]))).answer() == "none"


def test_a_declared_vertical_axis_leaves_gravity_untried(monkeypatch):
    """A parameter file that declares its axis vertical (top-level ``axis``, as KUKA's axis
    1) or prismatic: gravity cannot act there and is not tried; asked for by name it is
    refused, naming the declaration; a bad declaration is refused naming its values."""
    import jaxflex.discover.workflow as dm
    from jaxflex.identify.datagen import generate_log
    from jaxflex.discover import cannot_act, declared_axes
    from jaxflex.core.effects import candidate_effects
    from jaxflex.io.presets import paper_params

    d = paper_params().to_dict()
    vertical = Params.from_dict(d | {"axis": "vertical"})
    assert declared_axes(vertical) == ["vertical"] and "gravity" in cannot_act(vertical)
    assert "gravity" in cannot_act(Params.from_dict(d | {"axis": "prismatic"}))
    assert cannot_act(Params.from_dict(d | {"axis": "horizontal"})) == {}
    assert cannot_act(paper_params()) == {}
    with pytest.raises(ParamsError, match="axis: expected one of"):
        declared_axes(Params.from_dict(d | {"axis": "sideways"}))
    log = generate_log((), seed=4, t_final=3.0).log
    with pytest.raises(ValueError, match="'gravity'.*declares the axis 'vertical'"):
        discover(log, vertical, DiscoverConfig(candidates=("gravity", "torque_offset")))

    class Tried(Exception):
        pass

    def tried(log, nominal, universe, **kw):
        raise Tried(list(universe))

    import jaxflex.discover.candidates as dc

    monkeypatch.setattr(dc, "workspace", tried)
    seen = []
    with pytest.raises(Tried) as e:
        discover(log, vertical, progress=lambda d, t, m: seen.append(m))
    assert "gravity" not in e.value.args[0]
    # the first workspace holds the candidates alone: a family's higher order only once its
    # order below is in a model (``Workspaces``)
    assert sorted(e.value.args[0]) == sorted(c for c in candidate_effects() if c != "gravity")
    assert any(s.startswith("not tried: gravity") for s in seen), seen
    with pytest.raises(Tried) as e:
        discover(log, paper_params())
    assert "gravity" in e.value.args[0]
    # an n-joint file declares per joint
    two = Params.from_dict({"plant": {k: [v[0]] * 2 for k, v in d["plant"].items()},
                            "friction": {k: [v[0]] * 2 for k, v in d["friction"].items()},
                            "axis": ["vertical", "horizontal"]})
    assert declared_axes(two) == ["vertical", "horizontal"]
    from jaxflex.io.logs import Log

    got = []
    monkeypatch.setattr(dm, "discover", lambda lg, nom, cfg, progress: got.append(cannot_act(nom)))
    both = Log.from_arrays(t=log.t, **{k: np.hstack([getattr(log, k)] * 2)
                                       for k in ("tau", "q1", "q2")})
    dm.discover_joints(both, two)
    assert "gravity" in got[0] and got[1] == {}


@pytest.mark.slow
def test_a_model_limited_rotor_identification_of_kuka_axis_1_runs(tmp_path, capsys):
    """KUKA KR300 axis 1, recording C, from a converged, model-limited rotor identification
    (datasheet J and K) of a vertical axis, as a new user runs it: the note, the rotor
    model's link side from the log, gravity not tried; an answer with the residual analysis
    (measured: encoder_skew, 1.8 +- 0.16 ms, held-out gap 0.0131 -> 0.0033, 69 s)."""
    from jaxflex.app.cli import main
    from jaxflex.data import kuka_record, load_kuka

    save_log(load_kuka("C", 1), tmp_path / "k.csv")
    rec = kuka_record("A")
    p = {"plant": {"I": 1.0, "J": float(rec.J_mr[0] * rec.u[0] ** 2),
                   "K": float(rec.c_rad_ff[0])},
         "friction": {"Fc": 1.0, "Fs": 1.2, "vs": 0.05, "sigma0": 1e4, "sigma1": 0.0,
                      "sigma2": 1.0},
         "identification": {"model": {"verdict": "model-limited"}, "start": {"kind": "rotor"},
                            "converged": True},
         "axis": "vertical"}
    (tmp_path / "p.json").write_text(json.dumps(p))
    code = main(["discover", str(tmp_path / "k.csv"), "--params", str(tmp_path / "p.json"),
                 "--out", str(tmp_path / "o"), "--no-plots"])
    io = capsys.readouterr()
    out = io.out
    assert code == 0, out
    assert "model-limited" in io.err and "rotor model" in out and "not tried: gravity" in out
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["config"]["model"] == "rotor" and "gravity" in rep["not_tried"]
    assert "gravity" not in rep["config"]["candidates"]
    assert rep["gap_after"] <= rep["gap_before"] and np.isfinite(rep["gap_after"])
    assert set(rep["residual_analysis"]["channels"]) == {"q1", "q2"}


def test_an_unconverged_identification_is_refused_unless_accepted(tmp_path, capsys,
                                                                    monkeypatch):
    """A file whose solver did not reach a stationary point is refused by the command (exit
    2, naming the file) and taken with --accept-unconverged."""
    import jaxflex.discover as d
    from jaxflex.app.cli import main

    monkeypatch.setattr(d, "discover", lambda *a, **k: (_ for _ in ()).throw(InputError("ran")))
    from jaxflex.data import load_emps

    save_log(load_emps("DATA_EMPS").slice(0, 3000), tmp_path / "emps.csv")
    p = _rigid(converged=False, reason="max steps")
    (tmp_path / "p.json").write_text(json.dumps(p.to_dict()))
    argv = ["discover", str(tmp_path / "emps.csv"), "--params", str(tmp_path / "p.json"),
            "--out", str(tmp_path / "o"), "--no-plots"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "p.json: refused: the identification did not converge" in err and "ran" not in err
    assert main(["--accept-unconverged"] + argv) == 2
    assert "ran" in capsys.readouterr().err


def test_a_one_encoder_log_is_compared_once():
    """A log whose q2 column is its q1 (one encoder) is replayed and compared on q1 alone, so
    no sample counts twice in the evidence; a two-encoder log on both."""
    from jaxflex.discover.candidates import replayed_outputs, workspace
    from jaxflex.identify.datagen import generate_log
    from jaxflex.io.logs import Log
    from jaxflex.io.presets import paper_params

    two = generate_log((), seed=1, t_final=3.0).log
    one = Log.from_arrays(t=two.t, tau=two.tau, q1=two.q1, q2=two.q1)
    assert replayed_outputs(two) == ("q1", "q2") and replayed_outputs(one) == ("q1",)
    kw = dict(segment=0.3, train_frac=0.5, substeps=1, max_effects=1)
    ws1, ws2 = (workspace(g, paper_params(), ("torque_offset",), **kw) for g in (one, two))
    assert ws1.train.outputs == ws1.test.outputs == ("q1",)
    assert ws2.train.outputs == ("q1", "q2")
    assert np.asarray(ws2.train.segs.y_meas).shape[-1] == 2
    assert np.asarray(ws1.train.segs.y_meas).shape[-1] == 1
