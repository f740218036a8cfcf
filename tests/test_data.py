"""The shipped data sets (jaxflex.data): shapes, sample periods, units, fidelity to the originals."""

from pathlib import Path

import numpy as np
import pytest

from jaxflex import data
from jaxflex.io.logs import Log

# CI clones have the shared folder beside the repository (../shared/data); a user's clone may not.
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KUKA_SRC = SHARED / "kuka_kr300_flexible_joint"
EMPS_SRC = SHARED / "emps"


@pytest.mark.parametrize("name", data.EMPS_NAMES)
def test_emps_log_shape_period_units(name):
    log = data.load_emps(name)
    assert isinstance(log, Log)
    assert (log.N, log.n) == (24841, 1)
    assert log.columns() == ("t", "tau", "q1", "q2", "q1d")
    assert log.dt == pytest.approx(1e-3, rel=1e-9)
    # Prismatic axis in metres: the load travels about 0.25 m (SOURCE.md: reference 0 ... 0.2464 m).
    assert log.q1.min() > -1e-3 and 0.24 < log.q1.max() < 0.25
    assert log.q1d.max() == pytest.approx(0.2463566056, abs=1e-9)
    np.testing.assert_array_equal(log.q1, log.q2)  # rigid, one encoder
    # Tracking of the reference within a few mm (closed loop), i.e. same units and sign.
    assert np.max(np.abs(log.q1 - log.q1d)) < 5e-3
    # Force = gtau * vir in N: |vir| < 10 V (saturation), gtau = 35.15 N/V.
    rec = data.emps_record(name)
    np.testing.assert_allclose(log.tau[:, 0], 35.15065188248547 * rec.vir, rtol=1e-15)
    assert 100.0 < np.abs(log.tau).max() < 10 * rec.gtau


def test_emps_record_extras():
    est, val = data.emps_record("DATA_EMPS"), data.emps_record("DATA_EMPS_PULSES")
    assert est.pulses is None
    assert (est.kp, est.kv) == (160.18, 243.45)
    assert est.dt == pytest.approx(1e-3)
    assert set(np.unique(val.pulses)) == {0.0, 5.0}
    # The pulses act on vir in volts: the force jumps by about 5 V * gtau at each edge.
    edges = np.flatnonzero(np.diff(val.pulses) != 0)
    assert len(edges) > 10
    jump = np.median(np.abs(np.diff(val.force)[edges]))
    assert jump == pytest.approx(5 * val.gtau, rel=0.1)


@pytest.mark.skipif(not EMPS_SRC.exists(), reason=f"original EMPS files not found at {EMPS_SRC}")
@pytest.mark.parametrize("name", data.EMPS_NAMES)
def test_emps_shipped_byte_identical(name):
    shipped = (data.DATA_DIR / f"{name}.mat").read_bytes()
    assert shipped == (EMPS_SRC / f"{name}.mat").read_bytes()


@pytest.mark.parametrize("trajectory", data.KUKA_TRAJECTORIES)
@pytest.mark.parametrize("axis", data.KUKA_AXES)
def test_kuka_log_shape_period_units(trajectory, axis):
    log = data.load_kuka(trajectory, axis)
    assert isinstance(log, Log)
    assert (log.N, log.n) == (2501, 1)
    assert log.columns() == ("t", "tau", "q1", "q2", "q1d")
    assert log.dt == pytest.approx(4e-3, rel=1e-6)
    assert log.t[0] == 0.0 and log.t[-1] == pytest.approx(10.0, rel=1e-6)
    q1, q2, tau = log.q1[:, 0], log.q2[:, 0], log.tau[:, 0]
    amp = np.ptp(q1)
    # Radians (not degrees): each axis moves a few tenths of a radian.
    assert 0.3 < amp < 1.0
    # Motor side link-referred with the right gear and sign: the two encoders differ only by
    # the joint deflection (a few mrad), two orders of magnitude below the motion. A missing
    # or extra gear factor (~250) or a sign flip would give |q2 - q1| of the order of amp.
    dev = np.max(np.abs(q2 - q1))
    assert dev < 5e-3 and dev < 0.02 * amp
    # Reference in the same units.
    assert np.max(np.abs(log.q1d[:, 0] - q1)) < 1e-2
    # Link-side torque: the gear ratio (~250) times a motor torque of ~5-20 N m.
    assert 1e3 < np.abs(tau).max() < 1e4
    # Deflection grows with the transmitted torque (positive stiffness in this sign convention).
    assert np.corrcoef(q2 - q1, tau)[0, 1] > 0.5


def test_kuka_rigid_fit_signs():
    # tau ~ Jt q2'' + Fv q2' + Fc sign(q2') + c: a sign error in tau or q2 makes Jt or Fv < 0.
    from jaxflex.validate import rigid_torque_fit

    for axis in data.KUKA_AXES:
        c = rigid_torque_fit(data.load_kuka("A", axis))
        assert c["Jt"] > 100 and c["Fv"] > 100 and c["Fc"] > 0, (axis, c)


def test_kuka_multi_axis_and_conversion():
    rec = data.kuka_record("B")
    log = data.load_kuka("B", (3, 1))
    assert log.n == 2
    np.testing.assert_array_equal(log.q1[:, 0], np.deg2rad(rec.act_pos_se_deg[2]))
    np.testing.assert_array_equal(log.q2[:, 1], np.deg2rad(rec.act_pos_mot_deg[0]))
    np.testing.assert_allclose(log.tau[:, 0], rec.u[2] * rec.act_torque_abs_nm[2], rtol=1e-15)
    np.testing.assert_allclose(rec.u, [1798 / 7, 1872 / 7, 757 / 3], rtol=1e-12)
    assert rec.dt == pytest.approx(4e-3, rel=1e-6)


@pytest.mark.skipif(not KUKA_SRC.exists(), reason=f"original KUKA files not found at {KUKA_SRC}")
@pytest.mark.parametrize("trajectory", data.KUKA_TRAJECTORIES)
def test_kuka_shipped_equal_original(trajectory):
    import hashlib

    import scipy.io

    src = KUKA_SRC / data.KUKA_SOURCE_FILES[trajectory]
    d = scipy.io.loadmat(src, squeeze_me=True, struct_as_record=False)
    rec = data.kuka_record(trajectory)
    t = d["rec"].time_cont
    assert rec.time_cont.dtype == t.dtype and np.array_equal(rec.time_cont, t)
    for k in data.KUKA_SIGNALS:
        orig = getattr(d["rec"], k)[:3]
        got = getattr(rec, k)
        assert got.dtype == orig.dtype and got.shape == (3, 2501)
        assert np.array_equal(got, orig), k
    for k in data.KUKA_PARA:
        orig = np.asarray(getattr(d["para"], k))[:3]
        got = getattr(rec, k)
        assert got.dtype == orig.dtype and np.array_equal(got, orig), k
    assert rec.traj_name == d["traj_name"]
    assert rec.source_sha256 == hashlib.sha256(src.read_bytes()).hexdigest()


@pytest.mark.skipif(not KUKA_SRC.exists(), reason=f"original KUKA files not found at {KUKA_SRC}")
def test_reduce_kuka_reproduces_shipped(tmp_path):
    out = data.reduce_kuka(KUKA_SRC, tmp_path)
    assert sorted(out) == list(data.KUKA_TRAJECTORIES)
    with np.load(out["C"]) as new, np.load(data.DATA_DIR / "kuka_kr300_traj_C.npz") as old:
        assert sorted(new.files) == sorted(old.files)
        for k in new.files:
            assert np.array_equal(new[k], old[k]), k


def test_available_lists_the_shipped_files():
    av = data.available()
    assert set(av) == {"emps", "kuka_kr300"}
    assert av["emps"]["names"] == ("DATA_EMPS", "DATA_EMPS_PULSES")
    assert av["kuka_kr300"]["trajectories"] == ("A", "B", "C")
    for entry in av.values():
        for f in entry["files"]:
            assert Path(f).is_file(), f


@pytest.mark.parametrize(
    "call, words",
    [
        (lambda: data.load_emps("EMPS"), ["EMPS", "DATA_EMPS_PULSES"]),
        (lambda: data.emps_record("data_emps"), ["DATA_EMPS"]),
        (lambda: data.load_kuka("D"), ["trajectory", "'A', 'B', 'C'"]),
        (lambda: data.load_kuka("A", 4), ["axis", "[1, 2, 3]"]),
        (lambda: data.load_kuka("A", 0), ["axis", "[1, 2, 3]"]),
        (lambda: data.load_kuka("A", (1, 5)), ["axis 5"]),
        (lambda: data.load_kuka("A", ()), ["axis", "[1, 2, 3]"]),
        (lambda: data.kuka_record("a"), ["trajectory", "'A'"]),
    ],
)
def test_unknown_names_raise_valueerror_with_choices(call, words):
    with pytest.raises(ValueError) as e:
        call()
    for w in words:
        assert w in str(e.value)
