"""Every command keeps its promises: outputs checked before work, failures told apart (bad
input, not converged, a bug), global options anywhere, suggested commands that run as
printed, statistics that stay honest under correlated draws or noise, units and labels.

Commands run in-process through ``jaxflex.app.cli.main`` on tiny logs and parameter files.
"""

from __future__ import annotations

import json
import re
import shlex
import signal
from pathlib import Path

import numpy as np
import pytest

from jaxflex.app.cli import build_parser, main

GOOD = {"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
        "friction": {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1,
                     "sigma2": 0.2},
        "gains": {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0}}
SENTINEL = "an earlier result\n"


def _run(capsys, argv: list[str]) -> tuple[int, str, str]:
    """``main(["--no-cache", *argv])``; returns (exit code, stdout, stderr)."""
    capsys.readouterr()
    rc = main(["--no-cache", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


def _params(tmp_path: Path, doc: dict | None = None, name: str = "p.json") -> Path:
    f = tmp_path / name
    f.write_text(json.dumps(GOOD if doc is None else doc))
    return f


def _log(tmp_path: Path, name: str = "log.csv", N: int = 400, noise: float = 0.0,
         header: str = "t,tau,q1,q2", sep: str = ",") -> Path:
    """A small smooth two-angle log (1 ms samples), optionally with white torque noise."""
    t = np.arange(N) * 1e-3
    q1 = 0.2 * np.sin(6.0 * t)
    q2 = q1 + 1e-3 * np.sin(9.0 * t)
    tau = 0.05 * np.cos(6.0 * t) + noise * np.random.default_rng(0).standard_normal(N)
    f = tmp_path / name
    rows = "\n".join(sep.join(f"{v:.17g}" for v in r) for r in zip(t, tau, q1, q2))
    f.write_text(header.replace(",", sep) + "\n" + rows + "\n")
    return f


# ----- outputs: checked before any work, for every command -------------------------------------


def test_validate_refuses_a_folder_holding_another_commands_result(tmp_path, capsys):
    """A discover output folder (report.json, params.json) is not overwritten by validate."""
    out = tmp_path / "discover_out"
    out.mkdir()
    for f in ("report.json", "params.json"):
        (out / f).write_text(SENTINEL)
    rc, _, err = _run(capsys, ["validate", str(_log(tmp_path)), "--params",
                               str(_params(tmp_path)), "--out", str(out)])
    assert rc == 2 and "already holds a result" in err and "report.json" in err
    assert "--force" in err and "Traceback" not in err
    assert (out / "report.json").read_text() == SENTINEL
    assert sorted(p.name for p in out.iterdir()) == ["params.json", "report.json"]


@pytest.mark.parametrize("command,existing", [
    ("validate", "log_params.png"), ("validate", "table.md"), ("discover", "params.json"),
    ("discover", "replay.png"), ("sweep", "samples.csv"), ("sweep", "sensitivity.png"),
    ("reproduce", "q2d_comparison.png"), ("reproduce", "sinusoid_tracking.png"),
])
def test_any_file_a_command_would_write_needs_force(tmp_path, capsys, command, existing):
    out = tmp_path / "o"
    out.mkdir()
    (out / existing).write_text(SENTINEL)
    spread = tmp_path / "s.json"
    spread.write_text(json.dumps({"t_final": 0.05, "samples": 4}))
    argv = {"validate": ["validate", str(_log(tmp_path)), "--params", str(_params(tmp_path))],
            "discover": ["discover", str(_log(tmp_path))],
            "sweep": ["sweep", str(spread), "--no-progress"],
            "reproduce": ["reproduce", "--duration", "0.05"]}[command]
    rc, _, err = _run(capsys, [*argv, "--out", str(out)])
    assert rc == 2 and "already holds a result" in err and existing in err
    assert (out / existing).read_text() == SENTINEL


def test_every_command_with_outputs_refuses_an_existing_one(tmp_path, capsys):
    """One existing output per command that writes files; nothing is overwritten."""
    p = _params(tmp_path)
    log = _log(tmp_path)
    spread = tmp_path / "s.json"
    spread.write_text(json.dumps({"t_final": 0.05, "samples": 4}))
    cases = {
        "identify": (["identify", str(log), "--params", str(p), "--out"], "r.json", None),
        "export": (["export", "--out"], "c.py", None),
        "tune": (["tune", "--params", str(p), "--out"], "g.json", None),
        "run-loop": (["run-loop", "--lockstep", "--log"], "run.csv", None),
        "validate": (["validate", str(log), "--params", str(p), "--out"], "v", "report.json"),
        "discover": (["discover", str(log), "--out"], "d", "report.json"),
        "sweep": (["sweep", str(spread), "--out"], "w", "summary.json"),
        "reproduce": (["reproduce", "--out"], "r", "results.json"),
    }
    registered = set(build_parser()._subparsers._group_actions[0].choices)
    with_outputs = {c for c in registered
                    if {"--out", "--log"} & set(build_parser()._subparsers._group_actions[0]
                                                .choices[c]._option_string_actions)}
    assert with_outputs == set(cases)
    for command, (argv, name, inner) in cases.items():
        target = tmp_path / command / name
        target.parent.mkdir()
        if inner is None:
            target.write_text(SENTINEL)
            check = target
        else:
            target.mkdir()
            check = target / inner
            check.write_text(SENTINEL)
        rc, _, err = _run(capsys, [*argv, str(target)])
        assert rc == 2 and "--force" in err, (command, err)
        assert check.read_text() == SENTINEL


def test_tune_report_figure_needs_force(tmp_path, capsys):
    rep = tmp_path / "g_report"
    rep.mkdir()
    (rep / "tracking.png").write_text(SENTINEL)
    rc, _, err = _run(capsys, ["tune", "--params", str(_params(tmp_path)), "--out",
                               str(tmp_path / "g.json")])
    assert rc == 2 and "--report" in err and "tracking.png" in err
    assert not (tmp_path / "g.json").exists()


def test_validate_writes_with_force_and_reports_the_noise_floor(tmp_path, capsys):
    out = tmp_path / "v"
    out.mkdir()
    (out / "report.json").write_text(SENTINEL)
    rc, stdout, err = _run(capsys, ["validate", str(_log(tmp_path, noise=0.01)), "--params",
                                    str(_params(tmp_path)), "--out", str(out), "--force"])
    assert rc == 0, err
    rep = json.loads((out / "report.json").read_text())
    row = rep["logs"]["log"]["params"]
    assert 0 < row["torque_noise_pct"] < row["torque_pct"]
    assert row["noise_std"]["tau"][0] == pytest.approx(0.01, rel=0.2)
    assert "noise floor" in stdout and rep["units"] == {"position": "rad", "torque": "N m"}


# ----- interrupts leave nothing, or a result marked partial ------------------------------------


@pytest.mark.parametrize("command", ["discover", "validate"])
def test_interrupted_command_leaves_no_empty_folder(tmp_path, capsys, monkeypatch, command):
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    if command == "discover":
        monkeypatch.setattr("jaxflex.discover.discover", interrupted)
        argv = ["discover", str(_log(tmp_path)), "--no-plots"]
    else:
        monkeypatch.setattr("jaxflex.validate.validate", interrupted)
        argv = ["validate", str(_log(tmp_path)), "--params", str(_params(tmp_path))]
    out = tmp_path / "new" / "out"
    rc, _, err = _run(capsys, [*argv, "--out", str(out)])
    assert rc == 130 and "interrupted" in err and "Traceback" not in err
    assert not out.exists() and not out.parent.exists()


def test_ctrl_c_stops_discover_even_where_a_fit_swallows_it(tmp_path, capsys, monkeypatch):
    """A fit's solve ends on Ctrl-C and returns its last point (``least_squares``); the
    workflow would carry on for minutes and write a result as if nothing happened. The
    command stops within a second, exits 130 and writes nothing."""
    import time

    def swallowing_workflow(log, nominal, cfg, progress=None):
        try:
            signal.raise_signal(signal.SIGINT)  # Ctrl-C during a solve ...
        except KeyboardInterrupt:
            pass  # ... which ends on it and returns
        t0 = time.time()
        while time.time() - t0 < 20.0:  # the rest of the workflow, no progress calls
            sum(range(1000))
        return None

    monkeypatch.setattr("jaxflex.discover.discover", swallowing_workflow)
    out = tmp_path / "out"
    t0 = time.time()
    rc, _, err = _run(capsys, ["discover", str(_log(tmp_path)), "--out", str(out), "--no-plots"])
    assert rc == 130 and "interrupted" in err and "Traceback" not in err
    assert time.time() - t0 < 10.0 and not out.exists()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # handlers restored


def test_ctrl_c_while_writing_leaves_the_whole_result(tmp_path, capsys, monkeypatch):
    """Ctrl-C as the first figure is written: the command finishes writing, then exits 130."""
    import jaxflex.app.plots.validate as plots

    real = plots.plot_validation_log

    def ctrl_c_then_plot(*a, **k):
        signal.raise_signal(signal.SIGINT)
        return real(*a, **k)

    monkeypatch.setattr(plots, "plot_validation_log", ctrl_c_then_plot)
    out = tmp_path / "v"
    rc, _, err = _run(capsys, ["validate", str(_log(tmp_path)), "--params",
                               str(_params(tmp_path)), "--out", str(out)])
    assert rc == 130 and "interrupted" in err
    assert json.loads((out / "report.json").read_text())["logs"]["log"]["params"]["figure"]
    assert (out / "table.md").exists() and (out / "torque_errors.png").exists()


def test_interrupted_command_keeps_a_folder_that_existed(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("jaxflex.discover.discover",
                        lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
    out = tmp_path / "out"
    out.mkdir()
    rc, _, _ = _run(capsys, ["discover", str(_log(tmp_path)), "--out", str(out), "--no-plots"])
    assert rc == 130 and out.is_dir()


# ----- three kinds of failure ------------------------------------------------------------------


def _numpy_value_error():
    np.reshape(np.zeros(3), (2, 2))


def _jaxflex_refusal():
    from jaxflex.fit.inverse import measured_motion

    measured_motion(None, kind="bogus")  # a plain ValueError raised by the library's own check


def test_classify_tells_input_from_bugs():
    from jaxflex.io.errors import InputError, NotConverged, classify
    from jaxflex.io.logs import LogError
    from jaxflex.io.params import ParamsError

    def caught(f):
        try:
            f()
        except Exception as e:  # noqa: BLE001
            return e

    assert classify(LogError("x")) == classify(ParamsError("x")) == "input"
    assert classify(InputError("x")) == "input"
    assert classify(NotConverged("x")) == "unconverged"
    assert classify(caught(_jaxflex_refusal)) == "input"
    assert classify(caught(_numpy_value_error)) == "bug"
    assert classify(caught(lambda: np.linalg.inv(np.zeros((2, 2))))) == "bug"
    assert classify(np.linalg.LinAlgError("Singular matrix")) == "bug"
    assert classify(KeyError("K")) == classify(RuntimeError("x")) == "bug"
    assert classify(caught(lambda: open("/nonexistent/jaxflex/file"))) == "input"


@pytest.mark.parametrize("exc", [np.linalg.LinAlgError("Singular matrix"), KeyError("lam"),
                                 RuntimeError("XLA failed"), TypeError("bad operand")],
                         ids=["LinAlgError", "KeyError", "RuntimeError", "TypeError"])
def test_a_failure_inside_a_computation_is_reported_as_a_bug(tmp_path, capsys, monkeypatch, exc):
    def broken(*a, **k):
        raise exc

    monkeypatch.setattr("jaxflex.core.certificate.certify", broken)
    rc, _, err = _run(capsys, ["certify", "--params", str(_params(tmp_path))])
    assert rc == 70, err
    assert "a bug in jaxflex" in err and "please report it" in err and "Traceback" not in err
    path = Path(re.search(r"the full traceback is in (\S+);", err).group(1))
    text = path.read_text()
    assert "Traceback" in text and type(exc).__name__ in text and "certify" in text
    path.unlink()


def test_a_numpy_value_error_inside_a_computation_is_a_bug(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("jaxflex.core.certificate.certify", lambda *a, **k: _numpy_value_error())
    rc, _, err = _run(capsys, ["certify", "--params", str(_params(tmp_path))])
    assert rc == 70 and "cannot reshape" in err
    Path(re.search(r"the full traceback is in (\S+);", err).group(1)).unlink()


def test_a_result_that_did_not_converge_exits_3(tmp_path, capsys, monkeypatch):
    from jaxflex.io.errors import NotConverged

    def unconverged(*a, **k):
        raise NotConverged("the tuner's search stopped at its step limit")

    monkeypatch.setattr("jaxflex.core.certificate.certify", unconverged)
    rc, _, err = _run(capsys, ["certify", "--params", str(_params(tmp_path))])
    assert rc == 3 and "not converged" in err and "step limit" in err


# ----- global options before or after the command; suggested commands run as printed -----------


def _unconverged(tmp_path: Path) -> Path:
    doc = json.loads(json.dumps(GOOD))
    doc["identification"] = {"converged": False, "reason": "step limit"}
    return _params(tmp_path, doc, "unconverged.json")


def test_accept_unconverged_works_after_the_command_as_the_refusal_suggests(tmp_path, capsys):
    p = _unconverged(tmp_path)
    argv = ["certify", "--params", str(p)]
    rc, _, err = _run(capsys, argv)
    assert rc == 2 and "--accept-unconverged" in err
    for where in (argv + ["--accept-unconverged"], ["--accept-unconverged"] + argv):
        rc, _, err = _run(capsys, where)
        assert rc == 0, err
    assert _run(capsys, argv)[0] == 2  # the option does not outlive its command


@pytest.mark.parametrize("option", [["--no-cache"], ["--no-trace-cache"], ["--no-lean-xla"],
                                    ["--host-devices", "1"], ["--accept-unconverged"]])
def test_every_global_option_is_accepted_after_the_command(tmp_path, capsys, option):
    rc, _, err = _run(capsys, ["certify", "--params", str(_params(tmp_path)), "--num", "5",
                               *option])
    assert rc == 0, err


def test_global_option_after_the_command_is_not_reset_and_identify_keeps_its_own():
    args = build_parser().parse_args(["--host-devices", "3", "certify", "--params", "p.json"])
    assert args.host_devices == 3 and not args.accept_unconverged
    args = build_parser().parse_args(["certify", "--params", "p.json", "--host-devices", "2"])
    assert args.host_devices == 2
    args = build_parser().parse_args(["identify", "log.csv", "--params", "p.json", "--out",
                                      "r.json", "--accept-unconverged"])
    assert args.accept_result and not args.accept_unconverged


@pytest.mark.slow
def test_sweep_resume_hint_runs_as_printed(tmp_path, capsys, monkeypatch):
    """The interrupted sweep's hint keeps --samples (and every other option) and runs."""
    import jaxflex.sweep

    spread = tmp_path / "spread.json"
    spread.write_text(json.dumps({"t_final": 0.05, "samples": 100,
                                  "uncertain": {"friction.Fc": {"dist": "uniform", "rel": 0.1}}}))
    out = tmp_path / "o"
    real = jaxflex.sweep.run_sweep

    def ctrl_c_after_two_chunks(spec, on_chunk=None, **kw):
        def checkpoint(ck):
            on_chunk(ck)
            if len(ck.done) == 2:  # as a terminal's Ctrl-C: the sweep stops after this chunk
                signal.raise_signal(signal.SIGINT)
        return real(spec, on_chunk=checkpoint, **kw)

    monkeypatch.setattr(jaxflex.sweep, "run_sweep", ctrl_c_after_two_chunks)
    argv = ["sweep", str(spread), "--out", str(out), "--samples", "12", "--chunk-size", "4",
            "--no-progress", "--seed", "3"]
    rc, _, err = _run(capsys, argv)
    assert rc == 130 and json.loads((out / "summary.json").read_text())["partial"]
    monkeypatch.setattr(jaxflex.sweep, "run_sweep", real)
    hint = re.search(r"continue with: (.*)$", err.strip()).group(1)
    cmd = shlex.split(hint)
    assert cmd[0] == "jaxflex" and "--resume" in cmd and "--samples" in cmd
    # run again as at first, without the options: refused, with the command that continues
    rc, _, err = _run(capsys, ["sweep", str(spread), "--out", str(out), "--no-progress"])
    assert rc == 2 and "interrupted sweep" in err
    assert re.search(r"continue it with: (.*?); or pass --force", err).group(1) == hint
    capsys.readouterr()
    assert main(cmd[1:]) == 0, capsys.readouterr().err
    doc = json.loads((out / "summary.json").read_text())
    assert not doc["partial"] and doc["samples"] == 12


def test_milliseconds_hint_runs_as_printed(tmp_path, capsys):
    """A log timed in ms: the message's --map option, added as printed, makes the command
    run."""
    f = _log(tmp_path, "ms.csv")
    rows = f.read_text().splitlines()
    f.write_text("\n".join([rows[0]] + [",".join([f"{1000 * float(r.split(',')[0]):.6g}",
                                                   *r.split(",")[1:]]) for r in rows[1:]]) + "\n")
    argv = ["validate", str(f), "--params", str(_params(tmp_path)), "--out", str(tmp_path / "v")]
    rc, _, err = _run(capsys, argv + ["--map", "q2=q1"])
    assert rc == 2 and "milliseconds" in err
    hint = re.search(r"Map it with a unit: (--map \S+)", err).group(1)
    assert "q2=q1" in hint  # the items given are kept
    rc, _, err = _run(capsys, argv + shlex.split(hint))
    assert rc == 0, err


def test_struct_column_hint_runs_as_printed(tmp_path, capsys):
    """A .mat whose torque is a struct: the message's --map (keeping the items given) runs."""
    from scipy.io import savemat

    t = np.arange(400) * 1e-3
    q = 0.2 * np.sin(6.0 * t)
    f = tmp_path / "rig.mat"
    savemat(f, {"t": t, "tau": {"cmd": 0.05 * np.cos(6.0 * t)}, "pos": q})
    argv = ["validate", str(f), "--params", str(_params(tmp_path)), "--out", str(tmp_path / "v"),
            "--model", "rigid"]
    rc, _, err = _run(capsys, argv + ["--map", "q1=pos"])
    assert rc == 2 and "struct" in err
    hint = re.search(r"e\.g\. (--map \S+)", err).group(1)
    assert "q1=pos" in hint and "tau=tau.cmd" in hint
    rc, _, err = _run(capsys, argv + shlex.split(hint))
    assert rc == 0, err


def test_missing_folder_hint_runs_as_printed(tmp_path, capsys):
    import subprocess

    folder = tmp_path / "a folder" / "deeper"
    rc, _, err = _run(capsys, ["export", "--out", str(folder / "c.py")])
    assert rc == 2
    cmd = re.search(r"\((mkdir -p .*?)\)", err).group(1)
    subprocess.run(cmd, shell=True, check=True)
    assert folder.is_dir()
    assert _run(capsys, ["export", "--out", str(folder / "c.py")])[0] == 0


# ----- sensitivities under correlated draws ----------------------------------------------------


def test_sensitivity_ranks_the_real_driver_under_correlated_draws():
    """Draws as from an identification's posterior: Fc and sigma2 correlated at -0.9997 and
    barely moving the error, the inertia driving it. The ranking names the inertia, and the
    pair is flagged as not separable."""
    from jaxflex.sweep.spec import parse_spread
    from jaxflex.sweep.summary import Accumulator

    spec = parse_spread({"uncertain": {"friction.Fc": {"dist": "uniform", "rel": 1e-4},
                                       "friction.sigma2": {"dist": "uniform", "rel": 3e-3},
                                       "plant.I": {"dist": "uniform", "rel": 0.15}}})
    rng = np.random.default_rng(4)
    S = 400
    z = rng.standard_normal((S, 3))
    c = -0.9997
    theta = np.column_stack([0.11 * (1 + 3e-5 * z[:, 0]),
                             0.2 * (1 + 1e-3 * (c * z[:, 0] + np.sqrt(1 - c * c) * z[:, 1])),
                             0.07 * (1 + 0.05 * z[:, 2])])
    y = 1e-3 * (1.0 + 0.02 * z[:, 2] + 0.02 * rng.standard_normal(S))
    acc = Accumulator(spec)
    acc.add(np.arange(S), {"theta": theta, "rms_error": y, "max_error": 2 * y, "tau_rms": y,
                           "saturation_fraction": np.zeros(S), "diverged": np.zeros(S, bool),
                           "fs_raised": np.zeros(S, bool),
                           "band_hist": np.zeros((1, acc.T, 400), np.int64)})
    sens = acc.result().summary["sensitivity"]
    assert sens[0]["parameter"] == "plant.I"
    by = {s["parameter"]: s for s in sens}
    assert by["plant.I"]["shapley"] > 10 * (by["friction.Fc"]["shapley"]
                                            + by["friction.sigma2"]["shapley"])
    total = sum(s["shapley"] for s in sens)
    assert total == pytest.approx(sens[0]["r2_linear"], rel=1e-9)
    from jaxflex.sweep.summary import collinear_groups

    assert collinear_groups(sens) == [["friction.Fc", "friction.sigma2"]]
    assert acc.result().summary["sensitivity_warnings"][0].startswith(
        "friction.Fc, friction.sigma2 are drawn so correlated")
    assert "collinear_with" not in by["plant.I"]


def test_sweep_over_a_posterior_names_the_driver_and_warns_of_collinear_draws(tmp_path, capsys):
    """A sweep drawing from an identification's posterior with Fc and sigma2 correlated at
    -0.9997: the summary names the inertia, and says the pair cannot be separated."""
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit.space import ParamSpace
    from jaxflex.io.presets import paper_params

    p = paper_params()
    names = ("Fc", "sigma2", "I")
    theta0 = ParamSpace.build(p.to_plant(), names).theta0()
    labels = [f"{k}[0]" for k in sorted(theta0)]
    sd = np.array([{"Fc[0]": 3e-5, "I[0]": 0.05, "sigma2[0]": 1e-3}[k] for k in labels])
    corr = np.eye(3)
    i, j = labels.index("Fc[0]"), labels.index("sigma2[0]")
    corr[i, j] = corr[j, i] = -0.9997
    doc = p.to_dict()
    doc["identification"] = {"converged": True, "covariance": {
        "parameters": list(names), "labels": labels,
        "theta": np.asarray(ravel_pytree(theta0)[0]).tolist(),
        "matrix": (corr * np.outer(sd, sd)).tolist()}}
    (tmp_path / "ident.json").write_text(json.dumps(doc))
    spread = tmp_path / "spread.json"
    spread.write_text(json.dumps({"identified": "ident.json", "samples": 64, "t_final": 0.5}))
    rc, out, err = _run(capsys, ["sweep", str(spread), "--out", str(tmp_path / "w"),
                                 "--no-progress"])
    assert rc == 0, err
    assert "top driver: plant.I" in out
    assert "friction.Fc, friction.sigma2 are drawn so correlated" in err
    sens = json.loads((tmp_path / "w" / "summary.json").read_text())["sensitivity"]
    assert sens[0]["parameter"] == "plant.I" and sens[0]["shapley"] > 0.8


def test_shapley_shares_of_independent_inputs_are_squared_correlations():
    from jaxflex.sweep.summary import shapley_r2

    r = np.array([0.6, -0.3, 0.1])
    np.testing.assert_allclose(shapley_r2(np.eye(3), r), r**2, atol=1e-12)
    # above the exact limit: sampled orders, same answer for independent inputs
    r14 = np.linspace(-0.2, 0.2, 14)
    np.testing.assert_allclose(shapley_r2(np.eye(14), r14, permutations=50), r14**2, atol=1e-12)


# ----- validate: each error beside what the noise alone gives ----------------------------------


def test_torque_noise_floor_matches_the_error_of_the_true_model():
    from jaxflex.io.logs import Log
    from jaxflex.io.params import Params
    from jaxflex.validate import rel_error_pct, torque_noise_floor, torque_prediction

    p = Params.from_dict({"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
                          "friction": {"Fc": 1e-9, "Fs": 1e-9, "vs": 0.05, "sigma0": 100.0,
                                       "sigma1": 0.0, "sigma2": 0.2}})
    N, dt = 3000, 1e-3
    t = np.arange(N) * dt
    q = 0.3 * np.sin(2.0 * t) + 0.1 * np.sin(5.3 * t)
    v = 0.6 * np.cos(2.0 * t) + 0.53 * np.cos(5.3 * t)
    a = -1.2 * np.sin(2.0 * t) - 2.809 * np.sin(5.3 * t)
    rng = np.random.default_rng(0)
    tau = 0.075 * a + 0.2 * v + 0.1 * rng.standard_normal(N)  # rigid: (I + J) q'' + sigma2 q'
    q1 = q + 1e-6 * rng.standard_normal(N)
    log = Log.from_arrays(t=t, tau=tau, q1=q1, q2=q1)
    true = torque_prediction(p, log, kind="rigid")
    floor = torque_noise_floor(p, log, kind="rigid")["pct"]
    err = rel_error_pct(log.tau, true)
    assert err == pytest.approx(floor, rel=0.1)  # the true model is at the floor
    wrong = Params.from_dict({**p.to_dict(), "plant": {"I": 0.3, "J": 0.005, "K": 6.77}})
    assert rel_error_pct(log.tau, torque_prediction(wrong, log, kind="rigid")) > 1.3 * floor


# ----- units and labels ------------------------------------------------------------------------


def test_inspect_gives_speeds_their_unit(tmp_path, capsys):
    f = tmp_path / "lab.csv"
    f.write_text("time_s,act_vel_deg_per_s,pos_deg,speed_rpm,acc_rad_per_s2\n0,1,2,3,4\n")
    rc, out, err = _run(capsys, ["inspect", str(f), "--json"])
    assert rc == 0, err
    units = {r["name"]: r["unit"] for r in json.loads(out)}
    assert units == {"time_s": "s", "act_vel_deg_per_s": "deg/s", "pos_deg": "deg",
                     "speed_rpm": "rpm", "acc_rad_per_s2": "rad/s^2"}


def test_time_errors_print_plain_numbers(tmp_path, capsys):
    f = tmp_path / "back.csv"
    f.write_text("t,tau,q1,q2\n0,0,0,0\n0.001,0,0,0\n0.0005,0,0,0\n0.003,0,0,0\n")
    rc, _, err = _run(capsys, ["discover", str(f), "--out", str(tmp_path / "o")])
    assert rc == 2 and "not strictly increasing" in err and "np.float64" not in err
    assert "t[1] = 0.001 s" in err


def test_semicolon_csv_names_the_delimiter(tmp_path, capsys):
    f = _log(tmp_path, "semi.csv", sep=";")
    rc, _, err = _run(capsys, ["discover", str(f), "--out", str(tmp_path / "o")])
    assert rc == 2 and "semicolons" in err and "','" in err


def test_a_prismatic_axis_is_labelled_in_metres(tmp_path, capsys):
    from jaxflex.io.logs import axis_units

    assert axis_units({"q1": "x:mm", "q2": "x:mm"}) == ("m", "N")
    assert axis_units({"q1": "enc:deg"}) == ("rad", "N m")
    assert axis_units(None, linear=True) == ("m", "N")
    out = tmp_path / "v"
    rc, stdout, err = _run(capsys, ["validate", str(_log(tmp_path)), "--params",
                                    str(_params(tmp_path)), "--out", str(out), "--map",
                                    "t=t,tau=tau:N,q1=q1:m,q2=q2:m"])
    assert rc == 0, err
    assert json.loads((out / "report.json").read_text())["units"] == {"position": "m",
                                                                      "torque": "N"}
    assert "of q1 and q2 in m" in stdout


# ----- the README says what the commands print -------------------------------------------------


def test_readme_does_not_claim_compensation_worsens_the_filtered_estimator():
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert "compensation makes the error worse" not in text
    assert "--estimator filtered" in text


@pytest.mark.slow
def test_readme_filtered_estimator_sentence_matches_reproduce(tmp_path, capsys):
    """What README says of ``reproduce --estimator filtered``: compensation lowers every
    experiment's RMS error, raises the sinusoid's maximum error and the error at rest."""
    out = tmp_path / "rep"
    rc, _, err = _run(capsys, ["reproduce", "--out", str(out), "--estimator", "filtered",
                               "--no-q2d-comparison"])
    assert rc == 0, err
    doc = json.loads((out / "results.json").read_text())
    for e in doc["experiments"].values():
        assert e["rms_error"]["with_compensation"] < e["rms_error"]["without_compensation"]
    sin = doc["experiments"]["sinusoid"]["max_error"]
    assert sin["with_compensation"] > sin["without_compensation"]
    rest = doc["rest"]
    assert (rest["with_compensation"]["rms_error_tail"]
            > rest["without_compensation"]["rms_error_tail"])


# ----- bad and odd inputs through the command line ---------------------------------------------

def _bad_cases(tmp: Path) -> list[tuple[list[str], list[str]]]:
    """(argv, names expected on stderr) for bad or odd inputs; every one must exit 2 with a
    one-line message and no traceback."""
    p = _params(tmp)
    log = _log(tmp)
    empty = tmp / "empty.csv"
    empty.write_text("")
    one_row = tmp / "one.csv"
    one_row.write_text("t,tau,q1,q2\n0,0,0,0\n")
    text_cell = tmp / "text.csv"
    text_cell.write_text("t,tau,q1,q2\n0,0,0,0\n0.001,abc,0,0\n0.002,0,0,0\n")
    tabs = _log(tmp, "tabs.csv", sep="\t")
    no_header = tmp / "nohead.csv"
    no_header.write_text("0,0,0,0\n0.001,0,0,0\n")
    npz = tmp / "bad.npz"
    npz.write_bytes(b"not a zip")
    mat = tmp / "bad.mat"
    mat.write_bytes(b"not a mat file")
    spread = tmp / "s.json"
    spread.write_text(json.dumps({"t_final": 0.05, "samples": 4}))
    params_list = _params(tmp, [1, 2], "list.json")
    params_neg = _params(tmp, {**GOOD, "plant": {"I": 0.07, "J": 0.005, "K": -1.0}}, "neg.json")
    return [
        (["validate", str(tmp / "absent.csv"), "--params", str(p), "--out", str(tmp / "v1")],
         ["absent.csv", "not found"]),
        (["validate", str(empty), "--params", str(p), "--out", str(tmp / "v2")],
         ["empty.csv", "empty file"]),
        (["validate", str(one_row), "--params", str(p), "--out", str(tmp / "v3")],
         ["at least 2 samples"]),
        (["validate", str(text_cell), "--params", str(p), "--out", str(tmp / "v4")],
         ["text.csv"]),
        (["validate", str(tabs), "--params", str(p), "--out", str(tmp / "v5")],
         ["tabs", "comma-separated"]),
        (["validate", str(no_header), "--params", str(p), "--out", str(tmp / "v6")],
         ["header"]),
        (["validate", str(npz), "--params", str(p), "--out", str(tmp / "v7")],
         ["bad.npz", "not a readable .npz"]),
        (["validate", str(mat), "--params", str(p), "--out", str(tmp / "v8")],
         ["bad.mat", "not a readable MATLAB file"]),
        (["validate", str(log), str(tmp / "sub" / "log.csv"), "--params", str(p), "--out",
          str(tmp / "v9")], ["share the name 'log'"]),
        (["validate", str(log), "--params", str(params_list), "--out", str(tmp / "v10")],
         ["JSON object"]),
        (["validate", str(log), "--params", str(params_neg), "--out", str(tmp / "v11")],
         ["neg.json", "K must be > 0"]),
        (["validate", str(log), "--params", str(p), "--against", str(tmp / "nope.json"),
          "--out", str(tmp / "v12")], ["nope.json", "not found"]),
        (["validate", str(log), "--params", str(p), "--map", "tau=torque", "--out",
          str(tmp / "v13")], ["torque"]),
        (["validate", str(log), "--params", str(p), "--map", "q1=q1:furlong", "--out",
          str(tmp / "v14")], ["furlong", "unknown unit"]),
        (["validate", str(log), "--params", str(p), "--map", "x=q1", "--out", str(tmp / "v15")],
         ["unknown log column 'x'"]),
        (["validate", str(log), "--params", str(p), "--map", "@" + str(tmp / "nomap.txt"),
          "--out", str(tmp / "v16")], ["map file not found"]),
        (["validate", str(log), "--params", str(p), "--out", str(log)],
         ["is a file", "folder is expected"]),
        (["discover", str(log), "--train-frac", "0.99", "--out", str(tmp / "d1")],
         ["--train-frac"]),
        (["discover", str(log), "--segment", "-1", "--out", str(tmp / "d2")], ["--segment"]),
        (["discover", str(log), "--params", str(params_list), "--out", str(tmp / "d3")],
         ["JSON object"]),
        (["inspect", str(tmp / "absent.mat")], ["absent.mat", "not found"]),
        (["inspect", str(mat)], ["bad.mat"]),
        (["certify", "--params", str(p), "--accept-unconverged", "--host-devices", "0"],
         ["--host-devices must be >= 1"]),
        (["reproduce", "--out", str(tmp / "r1"), "--leak", "-1"], ["--leak", ">= 0"]),
        (["sweep", str(spread), "--out", str(tmp / "w1"), "--t-final", "1e-6"],
         ["--t-final"]),
        (["sweep", str(tmp / "absent_spread.json"), "--out", str(tmp / "w2")],
         ["absent_spread.json"]),
        (["export", "--params", str(params_neg), "--out", str(tmp / "c.py")],
         ["neg.json", "K must be > 0"]),
        (["tune", "--params", str(p), "--out", str(tmp / "g.json"), "--margin", "-1"],
         ["--margin"]),
        (["validate", str(log), "--params", str(p), "--segment", "0", "--out", str(tmp / "v17")],
         ["--segment", "at least 2 samples"]),
        (["validate", str(log), "--params", str(p), "--substeps", "0", "--out",
          str(tmp / "v18")], ["--substeps", ">= 1"]),
        (["sweep", str(spread), "--samples", "0", "--out", str(tmp / "w3")], ["--samples"]),
        (["sweep", str(spread), "--chunk-size", "0", "--out", str(tmp / "w4")],
         ["--chunk-size"]),
        (["sweep", str(spread), "--worst", "-1", "--out", str(tmp / "w5")], ["--worst"]),
        (["reproduce", "--duration", "0", "--out", str(tmp / "r2")], ["--duration", "> 0 s"]),
        (["analyse", "--modes", "0"], ["--modes", ">= 1"]),
        (["certify", "--params", str(p), "--vmax", "-1"], ["vmax", "> 0"]),
        (["export", "--dt", "-1", "--out", str(tmp / "c2.py")], ["dt must be > 0"]),
        (["run-loop", "--duration", "-1", "--lockstep", "--log", str(tmp / "rl.csv")],
         ["duration must be > 0"]),
    ]


N_BAD_CASES = 38


def test_there_are_enough_bad_cases(tmp_path):
    assert len(_bad_cases(tmp_path)) == N_BAD_CASES >= 20


@pytest.mark.parametrize("case", range(N_BAD_CASES))
def test_bad_or_odd_input_is_refused_by_name(tmp_path, capsys, case):
    (tmp_path / "sub").mkdir()
    _log(tmp_path / "sub")
    argv, names = _bad_cases(tmp_path)[case]
    rc, _, err = _run(capsys, argv)
    assert rc == 2, (argv, err)
    assert "Traceback" not in err and "bug" not in err
    for n in names:
        assert n in err, (n, err)
    assert not any(p.is_dir() and not any(p.iterdir()) for p in tmp_path.glob("[vdrwg]*"))


def test_torque_noise_floor_counts_fast_torque_the_motion_cannot_resolve():
    """Chatter at 200 Hz on the torque (a controller on quantised angles): not white, so the
    white-noise estimate alone would miss most of it; the true model is still at the floor."""
    from jaxflex.io.logs import Log
    from jaxflex.io.params import Params
    from jaxflex.validate import rel_error_pct, torque_noise_floor, torque_prediction

    p = Params.from_dict({"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
                          "friction": {"Fc": 1e-9, "Fs": 1e-9, "vs": 0.05, "sigma0": 100.0,
                                       "sigma1": 0.0, "sigma2": 0.2}})
    N, dt = 3000, 1e-3
    t = np.arange(N) * dt
    q = 0.3 * np.sin(2.0 * t)
    tau = 0.075 * (-1.2 * np.sin(2.0 * t)) + 0.2 * 0.6 * np.cos(2.0 * t)
    tau = tau + 0.3 * np.sin(2 * np.pi * 200.0 * t + 0.3)
    log = Log.from_arrays(t=t, tau=tau, q1=q, q2=q)
    err = rel_error_pct(log.tau, torque_prediction(p, log, kind="rigid"))
    assert torque_noise_floor(p, log, kind="rigid")["pct"] == pytest.approx(err, rel=0.05)


def test_fast_energy_is_the_energy_above_the_derivatives_band():
    from jaxflex.validate import fast_energy

    dt, N = 1e-3, 4000
    t = np.arange(N) * dt
    slow = 0.5 * np.sin(2.0 * t) + 0.2 * t
    for hz in (120.0, 200.0, 400.0):
        tone = 0.3 * np.sin(2 * np.pi * hz * t + 0.4)
        assert fast_energy(slow + tone, dt) == pytest.approx(np.sum(tone**2), rel=0.02)
    assert fast_energy(slow, dt) < 1e-6 * np.sum(slow**2)


def test_validate_reports_every_error_beside_its_noise_floor(tmp_path, capsys):
    """A closed-loop log (the EMPS P/P cascade simulated from known parameters, with encoder
    and torque noise): the replay gap, the torque error and the three closed-loop errors each
    come with their noise floor, and the true model's closed-loop position error sits near
    its floor."""
    from jaxflex.data import load_emps
    from jaxflex.io.logs import Log, save_log
    from jaxflex.io.params import Params, save_params
    from jaxflex.validate import PPCascade, simulate_pp_cascade

    truth = Params.from_dict({
        "plant": {"I": 95.0 - 1e-3, "J": 1e-3, "K": 1e6},
        "friction": {"Fc": 20.0, "Fs": 26.0, "vs": 0.01, "sigma0": 1e6, "sigma1": 0.0,
                     "sigma2": 200.0},
        "loop_controller": {"type": "pp_cascade", "kp": 160.18, "kv": 243.44, "gtau": 35.15}})
    dt, N = 1e-3, 2000
    ref = load_emps("DATA_EMPS").q1d[:N, 0]
    q, tau = simulate_pp_cascade(truth, PPCascade.from_dict(truth.extra["loop_controller"]),
                                 ref, dt)
    rng = np.random.default_rng(1)
    q = np.asarray(q) + 2e-6 * rng.standard_normal(N)
    tau = np.asarray(tau) + 0.5 * rng.standard_normal(N)
    save_log(Log.from_arrays(t=np.arange(N) * dt, tau=tau, q1=q, q2=q, q1d=ref),
             tmp_path / "emps.csv")
    save_params(truth, tmp_path / "truth.json")
    out = tmp_path / "v"
    rc, stdout, err = _run(capsys, ["validate", str(tmp_path / "emps.csv"), "--params",
                                    str(tmp_path / "truth.json"), "--model", "rigid",
                                    "--linear", "--out", str(out)])
    assert rc == 0, err
    row = json.loads((out / "report.json").read_text())["logs"]["emps"]["params"]
    assert row["gap_noise"] > 0 and row["torque_noise_pct"] > 0
    cl = row["closed_loop"]
    assert set(cl["noise_floor"]) == {"position_pct", "velocity_pct", "torque_pct"}
    for k in ("position_pct", "velocity_pct", "torque_pct"):  # the true model: at its floors
        assert cl[k] < 1.5 * cl["noise_floor"][k], k
    assert row["gap"] < 1.5 * row["gap_noise"]
    assert f"({cl['noise_floor']['position_pct']:.2g})" in stdout


@pytest.mark.slow
def test_ctrl_c_stops_a_real_discover_run(tmp_path):
    """A terminal's Ctrl-C (SIGINT to the process group) during discover's fits: exit 130 in
    seconds, no output folder."""
    import os
    import subprocess
    import sys
    import time

    from jaxflex.identify.datagen import generate_log
    from jaxflex.io.logs import save_log

    save_log(generate_log((), seed=1, t_final=4.0).log, tmp_path / "log.csv")
    out = tmp_path / "new" / "out"
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.Popen([sys.executable, "-m", "jaxflex", "--no-cache", "discover",
                          str(tmp_path / "log.csv"), "--out", str(out)], cwd=root, env=env,
                         start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    try:
        time.sleep(8.0)  # compiling and fitting the nominal model
        t0 = time.time()
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert time.time() - t0 < 10.0 and "Traceback" not in err
    assert not (tmp_path / "new").exists()


def test_a_ctrl_c_that_a_callback_swallows_still_stops_the_command():
    """A KeyboardInterrupt raised inside a finaliser (as in JAX's garbage-collection callback)
    is printed as "Exception ignored" and lost; inside ``interrupts_stop`` (identify's and
    discover's computations) the signal is recorded, so the block still ends in
    KeyboardInterrupt. Without it the block would run to its end."""
    import os
    import time

    from jaxflex.app.cli.outputs import interrupts_stop

    class Swallows:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # the handler runs here; its exception is ignored

    ran_on = False
    with pytest.raises(KeyboardInterrupt):
        with interrupts_stop():
            Swallows()
            ran_on = True
    assert ran_on  # the interrupt was swallowed where it landed and raised at the block's end
