"""Loaders for lab files as they are (docs/spec.md section 6.4): struct paths,
selections, unit suffixes, products with factors from the file, row vectors, map files, and
the common log traps (row vectors, milliseconds, header-only files, structs)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from jaxflex.io.logs import LogError, evaluate, inspect_file, load_log, parse_mapping

ROOT = Path(__file__).resolve().parents[1]
N = 200


def _kuka_like(tmp_path) -> tuple[Path, dict]:
    """A .mat shaped like the KUKA recordings: (axis, time) arrays inside structs, degrees."""
    rng = np.random.default_rng(0)
    rec = {"time_cont": np.arange(N) * 4e-3,  # a 1-D array: saved as a (1, N) row vector
           "act_pos_se_deg": rng.normal(size=(3, N)),
           "act_pos_mot_deg": rng.normal(size=(3, N)),
           "act_torque_abs_nm": rng.normal(size=(3, N))}
    para = {"u": np.array([256.9, 267.4, 252.3])}
    p = tmp_path / "rec.mat"
    scipy.io.savemat(p, {"rec": rec, "para": para, "traj_name": "A"})
    return p, {**rec, **para}


KUKA_MAP = ("t=rec.time_cont, q1=rec.act_pos_se_deg[1]:deg, q2=rec.act_pos_mot_deg[1]:deg, "
            "tau=para.u[1]*rec.act_torque_abs_nm[1]")


def test_struct_paths_selection_units_and_factors(tmp_path):
    p, d = _kuka_like(tmp_path)
    log = load_log(p, parse_mapping(KUKA_MAP))
    assert log.N == N and log.n == 1
    np.testing.assert_allclose(log.q1[:, 0], np.deg2rad(d["act_pos_se_deg"][1]), rtol=1e-15)
    np.testing.assert_allclose(log.q2[:, 0], np.deg2rad(d["act_pos_mot_deg"][1]), rtol=1e-15)
    np.testing.assert_allclose(log.tau[:, 0], d["u"][1] * d["act_torque_abs_nm"][1], rtol=1e-15)
    assert log.dt == pytest.approx(4e-3)


def test_rows_of_axis_time_array_become_joints(tmp_path):
    p, d = _kuka_like(tmp_path)
    m = parse_mapping("t=rec.time_cont,q1=rec.act_pos_se_deg[0:3]:deg,"
                      "q2=rec.act_pos_mot_deg[0:3]:deg,tau=rec.act_torque_abs_nm")
    log = load_log(p, m)
    assert log.n == 3 and log.q1.shape == (N, 3)
    np.testing.assert_allclose(log.q1[:, 2], np.deg2rad(d["act_pos_se_deg"][2]))
    np.testing.assert_array_equal(log.tau, d["act_torque_abs_nm"].T)


def test_column_selection_and_division(tmp_path):
    t = np.arange(N) * 1e-3
    table = np.stack([t, np.sin(t), np.cos(t), 2 * t], axis=1)
    p = tmp_path / "m.npz"
    np.savez(p, data=table, gain=np.array(4.0))
    log = load_log(p, {"t": "data[:,0]", "q1": "data[:,1]", "q2": "data[:,2]",
                       "tau": "data[:,3]/gain"})
    np.testing.assert_allclose(log.tau[:, 0], 0.5 * t)
    np.testing.assert_array_equal(log.q2[:, 0], np.cos(t))


def test_map_file(tmp_path):
    p, d = _kuka_like(tmp_path)
    mf = tmp_path / "kuka.map"
    mf.write_text("# KUKA KR300, axis 2\n" + KUKA_MAP.replace(", ", "\n") + "  # torque\n")
    assert parse_mapping(f"@{mf}") == parse_mapping(KUKA_MAP)
    log = load_log(p, parse_mapping(f"@{mf}"))
    assert log.n == 1
    with pytest.raises(LogError, match="map file not found"):
        parse_mapping(f"@{tmp_path / 'none.map'}")
    with pytest.raises(LogError, match="mapped twice"):
        parse_mapping("q1=a,q1=b")


def test_row_vector_mat_is_accepted(tmp_path):
    """A .mat saved from 1-D numpy arrays holds (1, N) rows."""
    t = np.arange(N) * 1e-3
    p = tmp_path / "rows.mat"
    scipy.io.savemat(p, {"t": t, "tau": np.sin(t), "q1": t, "q2": t})
    assert scipy.io.loadmat(p)["tau"].shape == (1, N)
    log = load_log(p)
    assert log.N == N and log.n == 1
    np.testing.assert_array_equal(log.tau[:, 0], np.sin(t))


def test_time_in_milliseconds_refused_with_hint_or_converted(tmp_path):
    t_ms = np.arange(N) * 1.0
    p = tmp_path / "ms.npz"
    np.savez(p, time=t_ms, tau=np.zeros(N), q1=np.zeros(N), q2=np.zeros(N))
    with pytest.raises(LogError, match=r"milliseconds.*--map 't=time:ms'"):
        load_log(p, {"t": "time"})
    log = load_log(p, {"t": "time:ms"})
    assert log.dt == pytest.approx(1e-3)
    log = load_log(p, {"t": "time:s"})  # an explicit unit confirms seconds
    assert log.dt == pytest.approx(1.0)


def test_header_only_and_wrong_names_list_the_file_columns(tmp_path):
    p = tmp_path / "h.csv"
    p.write_text("time,torque,enc1,enc2\n")
    with pytest.raises(LogError, match=r"no data rows.*\['time', 'torque', 'enc1', 'enc2'\]"):
        load_log(p)
    p = tmp_path / "w.csv"
    p.write_text("time,torque,enc1,enc2\n" + "\n".join(f"{i},0,0,0" for i in range(5)) + "\n")
    with pytest.raises(LogError, match=r"missing column.*the file has variables: time \(5,\), "
                                       r"torque \(5,\), enc1"):
        load_log(p)


def test_struct_errors_name_the_fields(tmp_path):
    p, _ = _kuka_like(tmp_path)
    with pytest.raises(LogError, match=r"'rec' is a struct with fields \['act_pos_mot_deg'.*"
                                       r"e.g. 'rec.act_pos_mot_deg'"):
        load_log(p, {"t": "rec"})
    with pytest.raises(LogError, match=r"struct 'rec' has no field 'pos'"):
        load_log(p, {"t": "rec.pos"})
    with pytest.raises(LogError, match=r"out of range for shape \(3, 200\)"):
        load_log(p, {"t": "rec.time_cont", "q1": "rec.act_pos_se_deg[5]"})
    with pytest.raises(LogError, match="unknown unit suffix ':furlong'"):
        evaluate("x:furlong", {"x": np.ones(3)})
    with pytest.raises(LogError, match="not numeric"):
        load_log(p, {"t": "traj_name"})


def test_inspect_lists_struct_fields(tmp_path):
    p, _ = _kuka_like(tmp_path)
    rows = {r["name"]: r for r in inspect_file(p)}
    assert rows["rec.act_pos_se_deg"]["shape"] == (3, N)
    assert rows["rec.act_pos_se_deg"]["unit"] == "deg"
    assert rows["rec.act_torque_abs_nm"]["unit"] == "N m"
    assert rows["rec.time_cont"]["shape"] == (N,)
    out = subprocess.run([sys.executable, "-m", "jaxflex", "inspect", str(p), "--json"],
                         capture_output=True, text=True, cwd=ROOT,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    names = [r["name"] for r in json.loads(out.stdout)]
    assert "para.u" in names and "rec.time_cont" in names
