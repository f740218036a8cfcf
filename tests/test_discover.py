"""Discrepancy discovery (issue 7): a hidden effect is named and the held-out gap shrinks; a
clean log gives ``none``; the log reader and CLI refuse bad input. The accuracy over many
cases is ``studies/discover_accuracy.py`` (slow test below runs it small)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from jaxflex.datagen import generate_log
from jaxflex.discover import DiscoverConfig, LogData, discover, gap_metric, make_segments, read_log

# a small candidate set keeps the default tests short (one compile shared by both logs)
CANDS = ("backlash", "hardening_spring", "torque_offset")
CFG = DiscoverConfig(candidates=CANDS, max_effects=2)


def _log(g):
    return LogData(g.t, g.tau, g.q1, g.q2, g.q1d)


def test_hidden_backlash_is_named_and_gap_halved():
    g = generate_log(("backlash",), seed=3, t_final=8.0)
    rep = discover(_log(g), config=CFG)
    assert rep["effect"] == "backlash"
    assert rep["effects"][0] == "backlash"
    assert rep["gap_after"] <= 0.5 * rep["gap_before"]
    b = rep["effect_params"]["backlash"]["b"]
    assert b["value"] == pytest.approx(g.truth["effects"]["backlash"]["b"], rel=0.2)
    assert b["stderr"] is not None and 0 < b["stderr"] < 0.2 * b["value"]
    assert set(rep["candidate_scores"]) == set(CANDS)
    assert rep["candidate_scores"]["backlash"]["significant"]


def test_clean_log_gives_none():
    g = generate_log((), seed=4, t_final=8.0)
    rep = discover(_log(g), config=CFG)
    assert rep["effect"] == "none" and rep["effects"] == []
    assert rep["gap_after"] == rep["gap_before"]
    assert not any(s["significant"] for s in rep["candidate_scores"].values())


def test_gap_metric_zero_for_exact_replay_and_one_for_standing_still():
    t = np.arange(2000) * 1e-3
    q = 0.1 * np.sin(2 * np.pi * t)
    log = LogData(t, np.zeros_like(t), q, q)
    segs = make_segments(log, 0, 2000, 250)
    assert float(gap_metric((segs.q1, segs.q2), segs)) == 0.0
    still = (np.broadcast_to(segs.q1[:, :1], segs.q1.shape), np.broadcast_to(segs.q2[:, :1], segs.q2.shape))
    assert float(gap_metric(still, segs)) == pytest.approx(1.0)


def test_bad_logs_are_refused(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t,tau,q1\n0,0,0\n0.001,0,0\n")
    with pytest.raises(ValueError, match="missing column"):
        read_log(p)
    t = np.arange(200) * 1e-3
    with pytest.raises(ValueError, match="NaN"):
        LogData(t, np.full(200, np.nan), t, t)
    with pytest.raises(ValueError, match="uniform"):
        LogData(t**2, t, t, t)
    with pytest.raises(FileNotFoundError):
        read_log(tmp_path / "missing.csv")


def test_cli_reports_bad_log(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("t,tau,q1\n0,0,0\n")
    r = subprocess.run([sys.executable, "-m", "jaxflex", "discover", str(p), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2 and "missing column" in r.stderr and "q2" in r.stderr


@pytest.mark.slow
def test_cli_end_to_end(tmp_path):
    g = generate_log(("hardening_spring",), seed=5, t_final=8.0)
    g.write_csv(tmp_path / "log.csv")
    r = subprocess.run([sys.executable, "-m", "jaxflex", "discover", str(tmp_path / "log.csv"),
                        "--out", str(tmp_path / "o"), "--candidates", ",".join(CANDS)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    for k in ("effect", "effects", "gap_before", "gap_after", "effect_params", "candidate_scores"):
        assert k in rep
    assert rep["effect"] == "hardening_spring"
    params = json.loads((tmp_path / "o" / "params.json").read_text())
    assert "hardening_spring" in params["effects"]
    for f in ("signature.png", "replay.png", "scores.png"):
        assert (tmp_path / "o" / f).exists()


@pytest.mark.slow
def test_accuracy_study_small(tmp_path):
    r = subprocess.run([sys.executable, "studies/discover_accuracy.py", "--small", "--out",
                        str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["summary"]["cases"] == 2
