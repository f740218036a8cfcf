"""Hardware loop runner (jaxflex.app.hardware): the exported controller against the simulated rig
in lock-step equals the JAX closed loop; protections (torque limit, NaN/range guard,
watchdog, clean stop on exceptions and signals) always leave zero torque; docs/spec.md section 6 log."""

from __future__ import annotations

import math
import os
import signal
import time

import equinox as eqx
import numpy as np
import pytest

from jaxflex.export import build_controller, generate_source, load_module
from jaxflex.app.hardware import LoopConfig, RigIO, SimulatedRig, run_loop
from jaxflex.io.logs import Log, save_log
from jaxflex.io.presets import paper_params


class FakeIO(RigIO):
    """A rig that replays given angles and records every torque written."""

    def __init__(self, angles, n=1):
        self.n = n
        self.angles = angles
        self.k = -1  # run_loop reads once to warm the I/O before sample 0
        self.written: list[np.ndarray] = []
        self.closed = False

    def read(self):
        q = self.angles(self.k)
        self.k += 1
        return q

    def write(self, tau):
        self.written.append(np.array(tau, float))

    def close(self):
        self.closed = True


class ConstController:
    def __init__(self, tau, delay=0.0, on_step=None):
        self.tau, self.delay, self.on_step, self.calls = tau, delay, on_step, 0

    def reset(self):
        self.calls = 0

    def step(self, t, q1, q2):
        self.calls += 1
        if self.delay:
            time.sleep(self.delay)
        if self.on_step:
            self.on_step(self.calls)
        return self.tau


def _still(k):
    return np.zeros(1), np.zeros(1)


def test_torque_limit_and_final_zero():
    io = FakeIO(_still)
    res = run_loop(io, ConstController(5.0), LoopConfig(duration=0.05, tau_limit=1.5, realtime=False))
    assert res.stop_reason == "completed" and res.samples == 50
    assert np.all(res.tau == 1.5)
    assert np.all(io.written[-1] == 0.0) and io.closed
    assert len(io.written) == 51  # one per sample plus the final zero


@pytest.mark.parametrize("bad", [math.nan, 20.0])
def test_guard_commands_zero_and_stops(bad):
    io = FakeIO(lambda k: (np.array([bad if k == 7 else 0.0]), np.zeros(1)))
    res = run_loop(io, ConstController(1.0), LoopConfig(duration=0.1, q_limit=10.0, realtime=False))
    assert res.stop_reason.startswith("guard") and "sample 7" in res.stop_reason
    assert res.samples == 8 and res.tau[7, 0] == 0.0 and res.tau[6, 0] == 1.0
    assert np.all(io.written[-1] == 0.0) and np.all(io.written[-2] == 0.0)


def test_guard_on_nonfinite_torque_can_continue():
    io = FakeIO(_still)
    res = run_loop(io, ConstController(math.inf), LoopConfig(duration=0.01, realtime=False,
                                                           stop_on_fault=False))
    assert res.stop_reason == "completed" and len(res.faults) == 10
    assert np.all(res.tau == 0.0)


def test_watchdog_stops_after_consecutive_misses():
    io = FakeIO(_still)
    cfg = LoopConfig(rate=1000.0, duration=1.0, max_consecutive_misses=3)
    res = run_loop(io, ConstController(0.3, delay=3e-3), cfg)
    assert res.stop_reason.startswith("watchdog")
    assert res.misses >= 3 and res.samples < 20
    assert np.all(io.written[-1] == 0.0) and io.closed


def test_raising_controller_ends_at_zero_torque_and_writes_the_log(tmp_path):
    def boom(k):
        if k == 4:
            raise RuntimeError("controller crashed")

    io = FakeIO(_still)
    res = run_loop(io, ConstController(0.7, on_step=boom), LoopConfig(duration=0.1, realtime=False),
                   log_path=tmp_path / "log.csv")
    assert res.stop_reason.startswith("controller: step raised at sample 3")
    assert "RuntimeError: controller crashed" in res.stop_reason
    assert res.samples == 3 and np.all(res.tau == 0.7)
    # three torques, then the final zero; nothing is written for the failed sample
    assert [float(w[0]) for w in io.written] == [0.7, 0.7, 0.7, 0.0] and io.closed
    from jaxflex.io.logs import load_log

    log = load_log(tmp_path / "log.csv")
    assert log.N == 3 and res.log_path == str(tmp_path / "log.csv")


def test_dead_rig_stops_with_its_reason_and_keeps_the_log(tmp_path):
    class DyingIO(FakeIO):
        dead = False

        def read(self):
            if self.k >= 5:
                self.dead = True
                raise EOFError()
            return super().read()

        def write(self, tau):
            if self.dead:
                raise BrokenPipeError("rig process gone")
            super().write(tau)

    io = DyingIO(_still)
    res = run_loop(io, ConstController(0.2), LoopConfig(duration=0.1, realtime=False),
                   log_path=tmp_path / "log.csv")
    assert res.stop_reason == "rig: reading the encoders failed at sample 5: EOFError"
    assert res.samples == 5 and io.closed
    assert any("zero torque could not be written" in f and "rig process gone" in f
               for f in res.faults)
    assert (tmp_path / "log.csv").read_text().count("\n") == 6  # header and 5 samples


def test_nan_angle_stops_at_zero_and_writes_the_log(tmp_path):
    io = FakeIO(lambda k: (np.array([math.nan if k == 4 else 0.0]), np.zeros(1)))
    res = run_loop(io, ConstController(0.5), LoopConfig(duration=0.1, realtime=False),
                   log_path=tmp_path / "log.csv")
    assert res.stop_reason.startswith("guard: sample 4: non-finite angle")
    assert res.log_path is not None and np.all(io.written[-1] == 0.0)
    from jaxflex.io.logs import load_log

    assert load_log(tmp_path / "log.csv").N == 4  # the samples before the NaN


def test_signal_stops_cleanly():
    io = FakeIO(_still)
    ctrl = ConstController(0.7, on_step=lambda k: k == 5 and os.kill(os.getpid(), signal.SIGINT))
    old = signal.getsignal(signal.SIGINT)
    res = run_loop(io, ctrl, LoopConfig(duration=0.1, realtime=False))
    assert res.stop_reason == "signal SIGINT" and res.samples == 5
    assert np.all(io.written[-1] == 0.0)
    assert signal.getsignal(signal.SIGINT) is old


def test_realtime_timing_is_measured():
    """A controller step that sleeps 5 ms at sample 10 of a 500 Hz loop (2 ms period): its
    compute time is at least 5 ms, sample 11 starts at least 3 ms late (its slot began 2 ms
    after sample 10's, whose torque was written 5 ms after it), and that is a deadline miss.
    Lower bounds only, so a loaded machine cannot make it fail."""
    ctrl = ConstController(0.1)

    def step(t, q1, q2):
        ctrl.calls += 1
        if ctrl.calls == 11:
            time.sleep(5e-3)
        return 0.1

    ctrl.step = step
    io = FakeIO(_still)
    res = run_loop(io, ctrl, LoopConfig(rate=500.0, duration=0.1, max_consecutive_misses=50))
    s = res.timing_summary()
    assert res.samples == 50 and res.stop_reason == "completed"
    assert res.compute_time[10] >= 5e-3 and s["compute"]["max_us"] >= 5e3
    assert res.lateness[11] >= 3e-3 - 1e-4
    assert res.misses >= 1
    assert np.all(res.lateness >= 0.0) and np.all(np.diff(res.t) == pytest.approx(2e-3))


def test_config_validation():
    with pytest.raises(ValueError, match="rate"):
        LoopConfig(rate=0.0)
    with pytest.raises(ValueError, match="tau_limit"):
        LoopConfig(tau_limit=-1.0)


def test_log_csv_two_joints(tmp_path):
    t = np.arange(3) * 1e-3
    save_log(Log.from_arrays(t=t, tau=np.ones((3, 2)), q1=np.zeros((3, 2)),
                             q2=np.zeros((3, 2))), tmp_path / "l.csv")
    head = (tmp_path / "l.csv").read_text().splitlines()[0]
    assert head == "t,tau[0],tau[1],q1[0],q1[1],q2[0],q2[1]"


@pytest.mark.slow
def test_exported_controller_on_simulated_rig_matches_jax(tmp_path):
    """Lock-step: the loop (exported controller, plant in a separate process, 16-bit
    encoders) reproduces the JAX sampled-data simulation of the same run."""
    import jax

    from jaxflex.core.sensing import Sensing
    from jaxflex.sim.simulate import simulate_sampled

    jax.config.update("jax_enable_x64", True)
    p = paper_params()
    c = build_controller(p, "sinusoid")
    ctrl = load_module(generate_source(c)).Controller()
    res = 2 * math.pi / 2**16
    T = 1.5
    with SimulatedRig(p, c.dt, q1_0=ctrl.reference(0.0), resolution=(res, res / 50)) as rig:
        out = run_loop(rig, ctrl, LoopConfig(duration=T, realtime=False, tau_limit=2.0),
                       log_path=tmp_path / "run.csv")
    assert out.stop_reason == "completed" and out.samples == 1500
    s = Sensing(q1_resolution=res, q2_resolution=res / 50, velocity="filtered")
    r = eqx.filter_jit(lambda pl, cc, ss: simulate_sampled(pl, cc, T, sensing=ss))(p.to_plant(), c, s)
    np.testing.assert_allclose(out.q1, np.asarray(r.q1_meas), atol=1e-9)
    np.testing.assert_allclose(out.tau, np.asarray(r.tau), atol=1e-9)
    e_loop = out.q1 - out.q1d
    e_jax = np.asarray(r.q1_meas) - np.asarray(r.q1d)
    assert abs(np.sqrt(np.mean(e_loop**2)) - np.sqrt(np.mean(e_jax**2))) < 1e-9
    assert np.sqrt(np.mean(e_loop**2)) < 0.02  # it tracks (0.05 rad reference amplitude)
    text = (tmp_path / "run.csv").read_text().splitlines()
    assert text[0] == "t,tau,q1,q2,q1d" and len(text) == 1501
    from jaxflex.io.logs import load_log

    log = load_log(tmp_path / "run.csv")
    assert log.N == 1500 and abs(log.dt - 1e-3) < 1e-12


@pytest.mark.slow
def test_rig_reference_drives_the_exported_controller(tmp_path):
    """The rig gives the reference: a controller exported for the sinusoid, fed the
    polynomial task's derivatives by the loop at each sample, reproduces the JAX closed loop
    of the controller built for the polynomial task (lock-step, simulated rig)."""
    import jax

    from jaxflex.app.cli.run_loop import rig_reference
    from jaxflex.core.sensing import Sensing
    from jaxflex.sim.simulate import simulate_sampled

    jax.config.update("jax_enable_x64", True)
    p = paper_params()
    ctrl = load_module(generate_source(build_controller(p, "sinusoid"))).Controller()
    poly = build_controller(p, "polynomial")
    T = 1.0
    R = rig_reference("polynomial", 1, poly.dt, T)
    assert R.shape == (1001, 5, 1)
    res = 2 * math.pi / 2**16
    with SimulatedRig(p, poly.dt, q1_0=R[0, 0], resolution=(res, res / 50)) as rig:
        out = run_loop(rig, ctrl, LoopConfig(duration=T, realtime=False, tau_limit=2.0),
                       reference=R)
    assert out.stop_reason == "completed" and out.samples == 1000
    s = Sensing(q1_resolution=res, q2_resolution=res / 50, velocity="filtered")
    r = eqx.filter_jit(lambda pl, cc, ss: simulate_sampled(pl, cc, T, sensing=ss))(
        p.to_plant(), poly, s)
    np.testing.assert_allclose(out.q1d, np.asarray(r.q1d), atol=1e-12)
    np.testing.assert_allclose(out.tau, np.asarray(r.tau), atol=1e-9)
    with pytest.raises(ValueError, match="reference"):
        run_loop(FakeIO(_still), ctrl, LoopConfig(duration=T, realtime=False),
                 reference=R[:10])


@pytest.mark.slow
def test_cli_run_loop_lockstep(tmp_path, capsys):
    from jaxflex.app.cli import main

    log = tmp_path / "out.csv"
    ctrl = tmp_path / "controller.py"
    assert main(["export", "--out", str(ctrl)]) == 0
    rc = main(["run-loop", "--duration", "0.5", "--log", str(log), "--controller", str(ctrl),
               "--lockstep"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert '"stop_reason": "completed"' in text
    assert log.read_text().splitlines()[0] == "t,tau,q1,q2,q1d"
    assert len(log.read_text().splitlines()) == 501
    import json

    summary = json.loads((tmp_path / "out.summary.json").read_text())
    assert summary["completed"] and summary["samples"] == 500
    import argparse

    from jaxflex.app.cli.run_loop import run as run_loop_cmd

    ns = argparse.Namespace(
        params=None, rig_params=None, duration=0.1, rate=500.0, log=str(log),
        controller=str(ctrl), trajectory=None, q2d=None, tau_limit=None, q_limit=10.0,
        max_misses=10, lockstep=True, encoder_bits=16, force=True,
    )
    with pytest.raises(ValueError, match="dt"):
        run_loop_cmd(ns)


@pytest.mark.slow
def test_bench_export_study_small(tmp_path):
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).parents[1] / "studies" / "bench_export.py"
    spec = importlib.util.spec_from_file_location("bench_export", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--small", "--out", str(tmp_path)])
    assert (tmp_path / "results.json").exists()
    assert res["compute"]["sinusoid/model"]["export"]["median_us"] > 0
    assert res["loop"]["loopback_1000Hz"]["samples"] == 500
