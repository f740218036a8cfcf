"""Bad inputs through the public command line: parameter files, spread files,
output paths, controller files, log files and interrupts.

Every case asserts a non-zero exit, a message on stderr that names the problem, no traceback,
and that an output file written before (a sentinel) is unchanged. Cases run in-process through
``jaxflex.app.cli.main`` (fast); only the interrupts use subprocesses, with real signals sent to the
process group as a terminal does.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from jaxflex.app.cli import main

ROOT = Path(__file__).resolve().parents[1]
GOOD = {"plant": {"I": 0.07, "J": 0.005, "K": 6.77},
        "friction": {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0, "sigma1": 0.1,
                     "sigma2": 0.2},
        "gains": {"Ke": 0.001, "KD1": 1.0, "KD2": 1.0, "kv": 2.0, "L1": 200.0, "L2": 6.0}}
SENTINEL = "an earlier result\n"


def _with(path: str, value, base=GOOD) -> dict:
    """A copy of ``base`` with the dotted ``path`` set (``...`` removes it)."""
    d = json.loads(json.dumps(base))
    *head, last = path.split(".")
    cur = d
    for k in head:
        cur = cur[k]
    if value is ...:
        del cur[last]
    else:
        cur[last] = value
    return d


def _refused(capsys, argv: list[str], *names: str, sentinel: Path | None = None) -> str:
    """Run the command; assert exit != 0, each of ``names`` in stderr, no traceback, the
    sentinel file unchanged. Returns stderr."""
    capsys.readouterr()
    rc = main(["--no-cache", *argv])
    err = capsys.readouterr().err
    assert rc != 0, f"accepted: {argv}"
    assert "Traceback" not in err
    for n in names:
        assert n in err, f"{n!r} not in {err!r}"
    if sentinel is not None:
        assert sentinel.read_text() == SENTINEL
    return err


@pytest.fixture
def sentinel(tmp_path: Path) -> Path:
    p = tmp_path / "earlier.txt"
    p.write_text(SENTINEL)
    return p


# ----- parameter files (through certify, export and tune) --------------------------------------

PARAM_CASES = [
    ("plant.K", "6.77", ["plant.K", "without quotes"]),
    ("plant.K", True, ["plant.K", "True"]),
    ("friction.sigma_0", 100.0, ["sigma_0", "did you mean 'sigma0'"]),
    ("gain", {"Ke": 0.001}, ["'gain'", "did you mean 'gains'"]),
    ("friction", ..., ["missing section 'friction'"]),
    ("plant.I", ..., ["plant.I is missing"]),
    ("friction.Fs", 0.05, ["Fs"]),
    ("plant.J", -0.005, ["J", "> 0"]),
    ("plant.K", [6.77, 7.0], ["plant.K", "one per joint"]),
    ("gains.KD2", ..., ["gains.KD2 is missing"]),
    ("gains.Ke", "0.001", ["gains.Ke"]),
    ("gains.KD1", [], ["gains.KD1", "empty"]),
    ("gains.kV", 2.0, ["'kV'", "did you mean 'kv'"]),
    ("effects", {"gravty": {"mgl": 0.5}}, ["gravty", "did you mean 'gravity'"]),
    ("effects", {"gravity": {"mgL": 0.5}}, ["mgL", "did you mean 'mgl'"]),
    ("controller", {"q2d": "model"}, ["'q2d'", "did you mean 'q2d_method'"]),
    ("friction", 0.11, ["section 'friction' must be an object"]),
    ("plant.K", float("nan"), ["plant.K", "finite"]),
]


@pytest.mark.parametrize("path,value,names", PARAM_CASES,
                         ids=[f"{p}={v!r}" for p, v, _ in PARAM_CASES])
def test_parameter_file_refused(tmp_path, capsys, sentinel, path, value, names):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(_with(path, value)))
    _refused(capsys, ["certify", "--params", str(f)], str(f), *names)
    # the same file given to a command with an output leaves that output alone
    _refused(capsys, ["export", "--params", str(f), "--out", str(sentinel), "--force"], *names,
             sentinel=sentinel)


def test_parameter_file_not_json_missing_or_not_an_object(tmp_path, capsys):
    f = tmp_path / "p.json"
    f.write_text("{nope")
    _refused(capsys, ["certify", "--params", str(f)], "not valid JSON")
    _refused(capsys, ["certify", "--params", str(tmp_path / "absent.json")], "not found",
             "absent.json")
    f.write_text("[1, 2]")
    _refused(capsys, ["certify", "--params", str(f)], "JSON object")


def test_own_top_level_keys_need_a_prefix(tmp_path, capsys):
    f = tmp_path / "p.json"
    f.write_text(json.dumps({**GOOD, "x_lab": "rig 2"}))
    capsys.readouterr()
    assert main(["--no-cache", "certify", "--params", str(f)]) == 0
    f.write_text(json.dumps({**GOOD, "lab": "rig 2"}))
    _refused(capsys, ["certify", "--params", str(f)], "'lab'", "x_")


# ----- spread files (through sweep) ------------------------------------------------------------

SPREAD_CASES = [
    ({"sampels": 10}, ["'sampels'", "did you mean 'samples'"]),
    ({"uncertain": {"friction.sigma_0": {"dist": "uniform", "rel": 0.1}}},
     ["sigma_0", "did you mean 'sigma0'"]),
    ({"uncertain": {"frction.Fc": {"dist": "uniform", "rel": 0.1}}},
     ["frction.Fc", "did you mean 'friction'"]),
    ({"uncertain": {"plant.K": {"dist": "unifrom", "rel": 0.1}}}, ["plant.K", "'dist' must be"]),
    ({"uncertain": {"plant.K": {"dist": "uniform", "rel": "0.1"}}}, ["plant.K", "'rel'"]),
    ({"uncertain": {"plant.I": {"dist": "normal", "std": 0.1}}}, ["plant.I must stay > 0"]),
    ({"uncertain": {"friction.Fs": {"dist": "uniform", "low": 0.01, "high": 0.1}}},
     ["friction.Fs is always drawn below friction.Fc"]),
    ({"samples": 0}, ["samples must be a positive integer"]),
    ({"samples": True}, ["samples must be a positive integer"]),
    ({"controller": {"tau_max": -1}}, ["controller.tau_max"]),
    ({"controller": {"compensaton": True}}, ["'compensaton'", "did you mean 'compensation'"]),
    ({"trajectory": "sinus"}, ["trajectory must be one of"]),
    ({"t_final": 1e-4}, ["t_final", "controller period"]),
    ({"nominal": _with("plant.K", "6.77")}, ["plant.K"]),
    ({"nominal": _with("gain", {})}, ["'gain'"]),
    ({"sensing": {"q1_nois": 0.0}}, ["sensing", "q1_nois"]),
    ({"uncertain": {"effects.gravty.mgl": {"dist": "uniform", "low": 0.1, "high": 0.2}}},
     ["gravty", "did you mean 'gravity'"]),
]


@pytest.mark.parametrize("doc,names", SPREAD_CASES, ids=[str(i) for i in range(len(SPREAD_CASES))])
def test_spread_file_refused(tmp_path, capsys, doc, names):
    f = tmp_path / "spread.json"
    f.write_text(json.dumps(doc))
    out = tmp_path / "o"
    out.mkdir()
    (out / "summary.json").write_text(SENTINEL)
    _refused(capsys, ["sweep", str(f), "--out", str(out), "--force", "--no-progress"],
             *names, sentinel=out / "summary.json")


# ----- output paths ----------------------------------------------------------------------------


def _good_params(tmp_path: Path) -> Path:
    f = tmp_path / "good.json"
    f.write_text(json.dumps(GOOD))
    return f


def test_output_file_in_a_missing_folder(tmp_path, capsys):
    p = _good_params(tmp_path)
    for argv in (["identify", "log.csv", "--params", str(p), "--out", str(tmp_path / "nope" / "r.json")],
                 ["export", "--out", str(tmp_path / "nope" / "c.py")],
                 ["tune", "--params", str(p), "--out", str(tmp_path / "nope" / "g.json")]):
        _refused(capsys, argv, "does not exist", "mkdir -p", str(tmp_path / "nope"))


def test_existing_output_file_needs_force(tmp_path, capsys, sentinel):
    p = _good_params(tmp_path)
    for argv in (["identify", "log.csv", "--params", str(p), "--out", str(sentinel)],
                 ["export", "--out", str(sentinel)],
                 ["tune", "--params", str(p), "--out", str(sentinel)],
                 ["run-loop", "--log", str(sentinel)]):
        _refused(capsys, argv, "exists", "--force", str(sentinel), sentinel=sentinel)


def test_output_figure_of_identify_is_checked_too(tmp_path, capsys, sentinel):
    p = _good_params(tmp_path)
    _refused(capsys, ["identify", "log.csv", "--params", str(p), "--out", str(tmp_path / "r.json"),
                      "--figure", str(sentinel)], "exists", str(sentinel), sentinel=sentinel)
    assert not (tmp_path / "r.json").exists()


def test_folder_where_a_file_is_expected_and_the_reverse(tmp_path, capsys, sentinel):
    p = _good_params(tmp_path)
    _refused(capsys, ["identify", "log.csv", "--params", str(p), "--out", str(tmp_path)],
             "is a folder", "file is expected")
    _refused(capsys, ["export", "--out", str(sentinel / "c.py")], "is a file, not a folder",
             sentinel=sentinel)
    spread = tmp_path / "s.json"
    spread.write_text("{}")
    _refused(capsys, ["sweep", str(spread), "--out", str(sentinel)], "is a file",
             "folder is expected", sentinel=sentinel)
    _refused(capsys, ["reproduce", "--out", str(sentinel)], "is a file", sentinel=sentinel)
    _refused(capsys, ["discover", "log.csv", "--out", str(sentinel)], "is a file",
             sentinel=sentinel)


def test_output_folder_holding_a_result_needs_force(tmp_path, capsys):
    for cmd, marker in (("reproduce", "results.json"), ("discover", "report.json"),
                        ("sweep", "summary.json")):
        out = tmp_path / cmd
        out.mkdir()
        (out / marker).write_text(SENTINEL)
        argv = {"reproduce": ["reproduce", "--out", str(out)],
                "discover": ["discover", "log.csv", "--out", str(out)],
                "sweep": ["sweep", str(_spread(tmp_path)), "--out", str(out)]}[cmd]
        _refused(capsys, argv, "already holds a result", marker, "--force")
        assert (out / marker).read_text() == SENTINEL


def test_tune_report_folder_holding_a_report_needs_force(tmp_path, capsys):
    p = _good_params(tmp_path)
    rep = tmp_path / "g_report"
    rep.mkdir()
    (rep / "report.json").write_text(SENTINEL)
    _refused(capsys, ["tune", "--params", str(p), "--out", str(tmp_path / "g.json")],
             "--report", "already holds a result", sentinel=rep / "report.json")
    assert not (tmp_path / "g.json").exists()


def _spread(tmp_path: Path) -> Path:
    f = tmp_path / "spread.json"
    f.write_text(json.dumps({"t_final": 0.05, "samples": 8,
                             "uncertain": {"friction.sigma0": {"dist": "uniform", "rel": 0.1}}}))
    return f


def test_sweep_resume_and_checkpoint_messages(tmp_path, capsys):
    out = tmp_path / "o"
    _refused(capsys, ["sweep", str(_spread(tmp_path)), "--out", str(out), "--resume"],
             "no checkpoint", "without --resume")
    out.mkdir()
    (out / "checkpoint.pkl").write_bytes(b"not a checkpoint")
    _refused(capsys, ["sweep", str(_spread(tmp_path)), "--out", str(out)],
             "interrupted sweep", "--resume", "--force")
    _refused(capsys, ["sweep", str(_spread(tmp_path)), "--out", str(out), "--resume"],
             "not a readable checkpoint")


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output_folder(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        _refused(capsys, ["export", "--out", str(ro / "c.py")], "not writable")
    finally:
        ro.chmod(0o700)


# ----- controller files (run-loop --controller) ------------------------------------------------

CONTROLLER_CASES = [
    ("def broken(:\n", ["syntax error at line 1", "jaxflex export"]),
    ("class Controller:\n    pass\nQ2D_METHOD = 'model'\nSPEC_MAP = {}\nDEFAULT_PARAMS = {}\n",
     ["no DT", "jaxflex export"]),
    ("class Controller:\n    pass\nDT = -1.0\nQ2D_METHOD = 'model'\nSPEC_MAP = {}\n"
     "DEFAULT_PARAMS = {}\n", ["DT must be a number > 0"]),
    ("raise RuntimeError('needs the lab network')\n",
     ["importing it raised RuntimeError", "needs the lab network"]),
    ("DT = 0.001\n", ["no Controller, Q2D_METHOD, SPEC_MAP, DEFAULT_PARAMS"]),
]


@pytest.mark.parametrize("source,names", CONTROLLER_CASES,
                         ids=["syntax", "no_dt", "bad_dt", "raises", "empty"])
def test_controller_file_refused(tmp_path, capsys, source, names):
    c = tmp_path / "controller.py"
    c.write_text(source)
    log = tmp_path / "log.csv"
    _refused(capsys, ["run-loop", "--controller", str(c), "--log", str(log), "--lockstep"],
             str(c), *names)
    assert not log.exists()


def test_controller_file_missing(tmp_path, capsys):
    _refused(capsys, ["run-loop", "--controller", str(tmp_path / "absent.py"), "--log",
                      str(tmp_path / "log.csv")], "not found", "absent.py")


# ----- interrupts: real signals to the process group -------------------------------------------


def _spawn(argv: list[str]) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.Popen([sys.executable, "-m", "jaxflex", "--no-cache", *argv], cwd=ROOT,
                            env=env, start_new_session=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("sig", [
    pytest.param(signal.SIGINT, id="SIGINT"),
    pytest.param(signal.SIGTERM, id="SIGTERM", marks=pytest.mark.slow),
])
def test_run_loop_interrupted_writes_log_and_summary(tmp_path, sig):
    ctrl = tmp_path / "c.py"
    assert main(["--no-cache", "export", "--out", str(ctrl)]) == 0
    log = tmp_path / "run.csv"
    p = _spawn(["run-loop", "--controller", str(ctrl), "--duration", "120", "--lockstep",
                "--log", str(log)])
    try:
        line = p.stderr.readline()  # the loop announces itself once the rig is ready
        assert "rig ready" in line, line
        time.sleep(0.5)
        os.killpg(p.pid, sig)  # as a terminal's Ctrl-C: the loop and the rig process
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "stopped early" in err
    summary = json.loads(log.with_suffix(".summary.json").read_text())
    assert summary["stop_reason"] == f"signal {sig.name}" and not summary["completed"]
    rows = log.read_text().splitlines()
    assert rows[0] == "t,tau,q1,q2,q1d" and len(rows) - 1 == summary["samples"] >= 2


@pytest.mark.slow
def test_sweep_interrupted_keeps_chunks_and_resumes(tmp_path):
    spread = tmp_path / "spread.json"
    spread.write_text(json.dumps({"t_final": 0.2, "samples": 800,
                                  "uncertain": {"friction.*": {"dist": "uniform", "rel": 0.2}}}))
    out = tmp_path / "o"
    argv = ["sweep", str(spread), "--out", str(out), "--chunk-size", "4", "--no-progress"]
    p = _spawn(argv)
    try:
        t0 = time.time()
        while not (out / "checkpoint.pkl").exists() and time.time() - t0 < 120:
            time.sleep(0.05)
        time.sleep(0.3)
        os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "--resume" in err
    doc = json.loads((out / "summary.json").read_text())
    assert doc["partial"] and 0 < doc["samples"] < 800
    assert doc["samples"] == 4 * doc["chunks_done"]
    # a resume with other options is another sweep, and is refused
    r = subprocess.run([sys.executable, "-m", "jaxflex", "--no-cache", *argv, "--samples", "16",
                        "--resume"], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 2 and "another sweep" in r.stderr and "Traceback" not in r.stderr
    assert json.loads((out / "summary.json").read_text())["samples"] == doc["samples"]
    r = subprocess.run([sys.executable, "-m", "jaxflex", "--no-cache", *argv, "--resume"],
                       cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    full = json.loads((out / "summary.json").read_text())
    assert not full["partial"] and full["samples"] == 800 and full["chunks_done"] == 200
    assert not (out / "checkpoint.pkl").exists()


# ----- log files (through identify, discover and validate) -------------------------------------

def _write_csv(path: Path, header: str, rows: list[list[float]]) -> Path:
    path.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return path


LOG_CASES = [
    # (file maker, names expected in stderr)
    (lambda p: _write_csv(p / "h.csv", "t,tau,q1,q2", []), ["no data rows"]),
    (lambda p: _write_csv(p / "c.csv", "time,torque,q1,q2",
                          [[i * 1e-3, 0.0, 0.0, 0.0] for i in range(50)]),
     ["missing column", "time", "torque"]),
    (lambda p: _write_csv(p / "n.csv", "t,tau,q1,q2",
                          [[i * 1e-3, float("nan") if i == 7 else 0.0, 0.0, 0.0]
                           for i in range(50)]), ["NaN", "tau"]),
    (lambda p: _write_csv(p / "u.csv", "t,tau,q1,q2",
                          [[(i * 1e-3) ** 2, 0.0, 0.0, 0.0] for i in range(50)]),
     ["uniformly sampled"]),
    (lambda p: _write_csv(p / "ms.csv", "t,tau,q1,q2",
                          [[float(i), 0.0, 0.0, 0.0] for i in range(50)]), ["milliseconds", "t:ms"]),
    (lambda p: _write_csv(p / "d.csv", "t,tau,q1,q1",
                          [[i * 1e-3, 0.0, 0.0, 0.0] for i in range(50)]), ["duplicate"]),
    (lambda p: (p / "x.txt").write_text("1,2\n") and p / "x.txt", ["unknown log format"]),
    (lambda p: p / "missing.csv", ["not found"]),
]


@pytest.mark.parametrize("case", range(len(LOG_CASES)))
@pytest.mark.parametrize("command", ["identify", "discover"])
def test_bad_logs_are_refused(capsys, tmp_path, sentinel, case, command):
    make, names = LOG_CASES[case]
    log = make(tmp_path)
    params = tmp_path / "p.json"
    params.write_text(json.dumps(GOOD))
    out = sentinel if command == "identify" else tmp_path / "o"
    argv = [command, str(log), "--params", str(params), "--out", str(out)]
    if command == "identify":
        argv.append("--force")  # the sentinel may be replaced only by a finished result
    _refused(capsys, argv, *names, sentinel=sentinel)


@pytest.mark.parametrize("value", ["0", "-2", "many", "2.5"])
def test_identify_substeps_must_be_a_positive_integer_or_auto(tmp_path, capsys, value):
    p = _good_params(tmp_path)
    rc = main(["--no-cache", "identify", "log.csv", "--params", str(p), "--out",
               str(tmp_path / "r.json"), "--substeps", value])
    err = capsys.readouterr().err
    assert rc == 2 and "--substeps" in err and "positive integer or 'auto'" in err
    assert not (tmp_path / "r.json").exists()


def test_discover_substeps_out_of_range_is_refused_before_reading(tmp_path, capsys):
    """``jaxflex discover --substeps 0`` (or 100) names the option and its range before the
    log is read (log.csv does not exist)."""
    for bad in ("0", "100"):
        _refused(capsys, ["discover", "log.csv", "--out", str(tmp_path / "o"), "--substeps", bad],
                 "--substeps", "[1, 16]")
