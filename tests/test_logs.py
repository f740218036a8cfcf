"""Logs (docs/spec.md section 6): round trips and a clear error for every malformed case."""

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from jaxflex.io.logs import Log, LogError, load_log, parse_mapping, save_log

EMPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps" / "DATA_EMPS.mat"


def _arrays(N=50, n=1, seed=0):
    rng = np.random.default_rng(seed)
    return {"t": np.arange(N) * 1e-3, "tau": rng.normal(size=(N, n)), "q1": rng.normal(size=(N, n)),
                "q2": rng.normal(size=(N, n)), "q1d": rng.normal(size=(N, n))}


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
@pytest.mark.parametrize("n", [1, 2])
def test_round_trip_exact(tmp_path, suffix, n):
    log = Log.from_arrays(**_arrays(n=n))
    p = tmp_path / f"log{suffix}"
    save_log(log, p)
    back = load_log(p)
    assert back.columns() == log.columns()
    for c in log.columns():
        np.testing.assert_array_equal(getattr(back, c), getattr(log, c))
    assert back.n == n and back.N == 50
    assert back.dt == pytest.approx(1e-3)


def test_mat_with_mapping_product(tmp_path):
    a = _arrays()
    p = tmp_path / "run.mat"
    scipy.io.savemat(p, {"time": a["t"][:, None], "u": a["tau"], "gain": np.array([[2.5]]),
                         "enc": a["q1"], "ref": a["q1d"]})
    log = load_log(p, {"t": "time", "tau": "gain*u", "q1": "enc", "q2": "enc", "q1d": "ref"})
    np.testing.assert_allclose(log.tau, 2.5 * a["tau"])
    np.testing.assert_array_equal(log.q2, a["q1"])


def test_parse_mapping():
    assert parse_mapping("tau=gtau*vir, q1=qm") == {"tau": "gtau*vir", "q1": "qm"}
    assert parse_mapping(None) is None
    with pytest.raises(LogError, match="unknown log column 'x'"):
        parse_mapping("x=qm")
    with pytest.raises(LogError, match="column=variable"):
        parse_mapping("tau")


def _csv(tmp_path, header, rows):
    p = tmp_path / "bad.csv"
    p.write_text(header + "\n" + "\n".join(",".join(str(v) for v in r) for r in rows) + "\n")
    return p


GOOD = [[i * 1e-3, 0.1, 0.01 * i, 0.01 * i] for i in range(10)]


def test_missing_column(tmp_path):
    p = _csv(tmp_path, "t,tau,q1", [r[:3] for r in GOOD])
    with pytest.raises(LogError, match=r"missing column\(s\) \['q2'\]"):
        load_log(p)


def test_nan(tmp_path):
    rows = [list(r) for r in GOOD]
    rows[4][2] = "nan"
    with pytest.raises(LogError, match="column q1 has 1 non-finite value.*NaN.*sample 4"):
        load_log(_csv(tmp_path, "t,tau,q1,q2", rows))


def test_non_increasing_time(tmp_path):
    rows = [list(r) for r in GOOD]
    rows[5][0] = rows[4][0]
    with pytest.raises(LogError, match="not strictly increasing: t\\[4\\]"):
        load_log(_csv(tmp_path, "t,tau,q1,q2", rows))


def test_non_uniform_time(tmp_path):
    rows = [list(r) for r in GOOD]
    for r in rows[6:]:
        r[0] += 0.5e-3
    with pytest.raises(LogError, match="not uniformly sampled"):
        load_log(_csv(tmp_path, "t,tau,q1,q2", rows))


def test_mismatched_lengths(tmp_path):
    a = _arrays()
    a["q2"] = a["q2"][:-3]
    p = tmp_path / "bad.npz"
    np.savez(p, **a)
    with pytest.raises(LogError, match="mismatched lengths.*'q2': 47"):
        load_log(p)


def test_ragged_csv_rows(tmp_path):
    rows = [list(r) for r in GOOD]
    rows[3] = rows[3][:3]
    with pytest.raises(LogError, match="bad.csv"):
        load_log(_csv(tmp_path, "t,tau,q1,q2", rows))


def test_other_bad_inputs(tmp_path):
    with pytest.raises(FileNotFoundError, match="log file not found"):
        load_log(tmp_path / "nope.csv")
    p = tmp_path / "x.txt"
    p.write_text("t\n0\n")
    with pytest.raises(LogError, match="unknown log format"):
        load_log(p)
    p = _csv(tmp_path, "0,1,2,3", GOOD)
    with pytest.raises(LogError, match="header"):
        load_log(p)
    p = tmp_path / "m.mat"
    scipy.io.savemat(p, {"t": np.arange(5.0)})
    with pytest.raises(LogError, match="variable 'gtau' which is not in the file"):
        load_log(p, {"tau": "gtau*vir"})
    with pytest.raises(LogError, match="unknown column"):
        Log.from_arrays(t=np.arange(3.0), tau=np.zeros(3), q1=np.zeros(3), q2=np.zeros(3),
                        speed=np.zeros(3))


def test_static_map_log_needs_only_v_and_F():
    log = Log.from_arrays(required=("t", "v", "F"), t=np.arange(4.0), v=np.ones(4), F=np.ones(4))
    assert log.columns() == ("t", "F", "v")


@pytest.mark.skipif(not EMPS.exists(), reason="EMPS data not present")
def test_emps_mat_loads():
    log = load_log(EMPS, {"tau": "gtau*vir", "q1": "qm", "q2": "qm", "q1d": "qg"})
    assert log.N == 24841 and log.n == 1
    assert log.dt == pytest.approx(1e-3, rel=1e-4)
