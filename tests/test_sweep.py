"""Monte Carlo sweeps: spread validation, vmap against a loop, divergence as data,
chunk/shard/process invariance, summaries (quantiles, SRC, Spearman), CLI and figures."""

import dataclasses
import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from jaxflex.sim.simulate import simulate_sampled
from jaxflex.sweep import SpreadError, build_models, parse_spread, run_sweep, sample_parameters
from jaxflex.sweep.summary import Accumulator, hist_quantiles, spearman

ROOT = Path(__file__).resolve().parents[1]

# A small spread whose stiffness range, with one plant substep per sample, puts the explicit
# RK4 step past its stability bound h sqrt(K / J) ~ 2.8 for the stiffest draws (K > ~4e4):
# those samples blow up, the rest track.
SMALL = {
    "t_final": 0.3, "substeps": 1, "seed": 3, "samples": 12, "band_dt": 0.02,
    "controller": {"compensation": True, "q2d_method": "model", "tau_max": 2.0},
    "uncertain": {
        "plant.I": {"dist": "uniform", "rel": 0.2},
        "plant.K": {"dist": "loguniform", "low": 3.0, "high": 3e5},
        "friction.Fc": {"dist": "uniform", "rel": 0.2},
    },
}


REPORTS: list[tuple[int, int | None]] = []  # what ``small``'s sweep reported


@pytest.fixture(scope="module")
def small():
    spec = parse_spread(SMALL)
    return spec, run_sweep(spec, chunk_size=4,
                           progress=lambda done, total, msg: REPORTS.append((done, total)))


def test_a_sweep_reports_its_chunks_to_any_reporter(small):
    """The one progress protocol (``jaxflex.io.progress``): each chunk of the 12 samples."""
    assert REPORTS == [(1, 3), (2, 3), (3, 3)]


# ----- spread validation (no simulation) -----------------------------------------------------


@pytest.mark.parametrize(
    "change, match",
    [
        ({"uncertain": {"plant.X": {"dist": "uniform", "rel": 0.1}}}, "unknown name 'X'"),
        ({"uncertain": {"foo.I": {"dist": "uniform", "rel": 0.1}}}, "names are <group>.<name>"),
        ({"uncertain": {"plant.I": {"dist": "beta", "a": 1}}}, "'dist' must be one of"),
        ({"uncertain": {"plant.I": {"dist": "uniform", "low": 0.1}}}, "takes high/low or rel"),
        ({"uncertain": {"plant.I": {"dist": "uniform", "low": 0.1, "high": 0.05}}}, "low < high"),
        ({"uncertain": {"plant.I": {"dist": "normal", "std": 0.01}}}, "must stay > 0"),
        ({"uncertain": {"friction.sigma2": {"dist": "uniform", "low": -0.1, "high": 0.1}}}, "must stay >= 0"),
        ({"uncertain": {"plant.I": {"dist": "uniform", "rel": "big"}}}, "'rel' must be a finite number"),
        ({"uncertain": {"effects.nope.a": {"dist": "fixed", "value": 1}}}, "unknown effect 'nope'"),
        ({"uncertain": {"effects.torque_offset.offset": {"dist": "uniform", "rel": 0.1}}}, "no nominal value"),
        ({"uncertain": {"effects.gravity.wrong": {"dist": "fixed", "value": 1.0}}}, "has no parameter"),
        ({"uncertain": {"plant.I[3]": {"dist": "uniform", "rel": 0.1}}}, "out of range"),
        ({"controller": {}, "uncertain": {"limits.tau_max": {"dist": "uniform", "rel": 0.1}}},
         "tau_max is infinite"),
        ({"trajectory": "zigzag"}, "trajectory must be one of"),
        ({"samples": 0}, "samples must be a positive integer"),
        ({"t_final": 1e-5}, "at least one controller period"),
        ({"sensing": "perfect"}, "preset must be one of"),
        ({"sensing": {"q1_noise": -1.0}}, "q1_noise must be >= 0"),
        ({"controller": {"q2d_method": "magic"}}, "q2d_method must be one of"),
        ({"nominal": {"plant": {"I": 0.07}}}, "nominal: .*missing"),
        ({"smaples": 10}, "unknown top-level key"),
    ],
)
def test_bad_spreads_are_refused_with_a_message_naming_the_problem(change, match):
    with pytest.raises(SpreadError, match=match):
        parse_spread({**SMALL, **change})


def test_spread_names_expand_per_group_and_joint_and_keep_nominals():
    spec = parse_spread({"uncertain": {"friction.*": {"dist": "uniform", "rel": 0.2},
                                       "friction.Fc": {"dist": "uniform", "low": 0.1, "high": 0.12}}})
    assert spec.labels == [f"friction.{k}" for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")]
    col = {c.label: c for c in spec.columns}
    assert (col["friction.Fc"].dist.a, col["friction.Fc"].dist.b) == (0.1, 0.12)
    assert col["friction.sigma0"].dist.a == pytest.approx(80.0)
    assert col["friction.sigma0"].nominal == 100.0


def test_load_spread_reports_missing_and_malformed_files(tmp_path):
    from jaxflex.sweep import load_spread

    with pytest.raises(SpreadError, match="not found"):
        load_spread(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(SpreadError, match="not valid JSON"):
        load_spread(tmp_path / "bad.json")
    for f in (ROOT / "studies" / "spreads").glob("sweep_*.json"):
        load_spread(f)  # the shipped examples are valid


def test_samples_follow_their_distributions_and_respect_fs_ge_fc():
    spec = parse_spread({"uncertain": {
        "plant.I": {"dist": "uniform", "low": 0.05, "high": 0.09},
        "plant.K": {"dist": "normal", "mean": 6.77, "std": 0.5, "low": 6.0},
        "friction.sigma0": {"dist": "loguniform", "low": 50.0, "high": 200.0},
        "friction.Fs": {"dist": "uniform", "low": 0.05, "high": 0.2},
    }})
    th = np.asarray(jax.jit(jax.vmap(lambda i: sample_parameters(spec, i)[0]))(jnp.arange(2000)))
    I, K, s0, Fs = th.T
    assert 0.05 <= I.min() and I.max() <= 0.09 and abs(I.mean() - 0.07) < 2e-3
    assert K.min() >= 6.0 and scipy.stats.kstest(
        K, scipy.stats.truncnorm(-0.77 / 0.5, np.inf, loc=6.77, scale=0.5).cdf).pvalue > 1e-3
    assert scipy.stats.kstest(np.log(s0), "uniform", args=(np.log(50), np.log(4))).pvalue > 1e-3
    # same index, same draw (independent of batching); different index, different draw
    a = np.asarray(sample_parameters(spec, jnp.uint32(7))[0])
    np.testing.assert_allclose(a, th[7], rtol=1e-14)
    # draws with Fs < Fc (= 0.11) are redrawn: Fs follows the spread conditioned on Fs >= Fc
    assert spec.fs_below_fc_possible() and Fs.min() >= 0.11
    assert scipy.stats.kstest(Fs, "uniform", args=(0.11, 0.2 - 0.11)).pvalue > 1e-3
    # a theta that still breaks it (beyond the redraws) is raised to Fc and flagged
    bad = th[0].copy()
    bad[3] = 0.05
    plant, *_, raised = build_models(spec, jnp.asarray(bad))
    assert bool(raised) and float(plant.friction.Fs[0]) == float(plant.friction.Fc[0])
    *_, raised = build_models(spec, jnp.asarray(th[np.argmin(Fs)]))
    assert not bool(raised)


def test_spread_with_fs_always_below_fc_is_refused():
    with pytest.raises(SpreadError, match="friction.Fs is always drawn below friction.Fc"):
        parse_spread({"uncertain": {"friction.Fs": {"dist": "uniform", "low": 0.01, "high": 0.1}}})


# ----- summaries (no simulation) ---------------------------------------------------------------


def test_histogram_quantiles_match_numpy_within_a_bin():
    rng = np.random.default_rng(0)
    v = rng.lognormal(-6, 1.0, 20000)
    edges = np.logspace(-10, 3, 521)
    counts = np.histogram(v, edges)[0]
    q = hist_quantiles(counts, edges, (0.05, 0.5, 0.95))
    np.testing.assert_allclose(q, np.quantile(v, [0.05, 0.5, 0.95]), rtol=0.06)


def test_spearman_matches_scipy_with_ties():
    rng = np.random.default_rng(1)
    x = rng.integers(0, 10, 300).astype(float)
    y = x + rng.normal(0, 3, 300)
    assert spearman(x, y) == pytest.approx(scipy.stats.spearmanr(x, y).statistic, abs=1e-12)


def test_src_recovers_known_linear_sensitivities_and_chunks_merge_exactly():
    spec = parse_spread({"uncertain": {"plant.I": {"dist": "uniform", "rel": 0.2},
                                       "plant.J": {"dist": "uniform", "rel": 0.2},
                                       "plant.K": {"dist": "uniform", "rel": 0.2}}})
    rng = np.random.default_rng(2)
    S = 5000
    theta = np.column_stack([c.dist.a + (c.dist.b - c.dist.a) * rng.random(S) for c in spec.columns])
    z = (theta - theta.mean(0)) / theta.std(0)
    y = 1e-3 * (2.0 + 0.8 * z[:, 0] - 0.4 * z[:, 2])  # J has no effect
    T = Accumulator(spec).T

    def out(sl):
        n = sl.stop - sl.start
        return {"theta": theta[sl], "rms_error": y[sl], "max_error": 2 * y[sl], "tau_rms": y[sl],
                "saturation_fraction": np.zeros(n), "diverged": np.zeros(n, bool),
                "fs_raised": np.arange(sl.start, sl.stop) % 7 == 0,
                "band_hist": np.zeros((1, T, 400), np.int64)}

    one = Accumulator(spec)
    one.add(np.arange(S), out(slice(0, S)))
    a, b = Accumulator(spec), Accumulator(spec)
    a.add(np.arange(3000), out(slice(0, 3000)))
    b.add(np.arange(3000, S), out(slice(3000, S)))
    a.merge(b)
    r1, r2 = one.result(), a.result()
    src = {s["parameter"]: s["src"] for s in r1.summary["sensitivity"]}
    assert [s["parameter"] for s in r1.summary["sensitivity"]][:2] == ["plant.I", "plant.K"]
    norm = np.hypot(0.8, 0.4)
    assert src["plant.I"] == pytest.approx(0.8 / norm, abs=0.01)
    assert src["plant.K"] == pytest.approx(-0.4 / norm, abs=0.01)
    assert abs(src["plant.J"]) < 0.01
    for m, v in r1.summary["metrics"].items():  # sums merge up to rounding, quantiles exactly
        w = r2.summary["metrics"][m]
        assert {k: x for k, x in v.items() if k != "quantiles_from"} == pytest.approx(
            {k: x for k, x in w.items() if k != "quantiles_from"}, rel=1e-12, abs=1e-15)
        assert v["q95"] == r2.summary["metrics"][m]["q95"]
    assert r1.summary["worst"] == r2.summary["worst"]
    # samples whose Fs draw was raised to Fc are counted, also across merged accumulators
    assert r1.summary["fs_raised_to_fc"] == r2.summary["fs_raised_to_fc"] == len(range(0, S, 7))


def test_band_grid_stride_is_a_property_of_the_spec():
    spec = parse_spread({"band_dt": 0.0104, "dt": 1e-3})
    assert spec.band_stride == 10 and Accumulator(spec).band_dt == pytest.approx(0.01)
    assert parse_spread({"band_dt": 1e-4}).band_stride == 1


# ----- simulation ---------------------------------------------------------------------------


def test_a_blown_up_sample_is_data_and_the_rest_of_the_batch_is_intact(small):
    spec, res = small
    s = res.samples
    assert res.summary["samples"] == 12
    div = s["diverged"]
    assert 0 < div.sum() < div.size, "the spread must give a mix of stable and diverged samples"
    big = s["theta"][:, spec.labels.index("plant.K")]
    assert big[div].min() > big[~div].max()  # divergence is the stiffest draws
    assert np.all(np.isfinite(s["rms_error"][~div])) and np.all(s["rms_error"][~div] < 0.05)
    w = res.summary["worst"]
    assert all(x["diverged"] for x in w[: div.sum()])  # diverged ranked worst, with parameters
    assert set(w[0]["parameters"]) == set(spec.labels)
    assert res.summary["diverged"] == div.sum()
    # bands use the non-diverged samples only and are ordered quantiles
    q = res.band_q[0]
    assert np.all(np.diff(q, axis=-1) >= -1e-15)
    assert res.band_t.size == q.shape[0] == 15


def test_vmapped_sweep_equals_a_loop_of_single_simulations(small):
    spec, res = small
    sim = eqx.filter_jit(lambda p, c, s: simulate_sampled(p, c, spec.t_final, substeps=spec.substeps, sensing=s))
    for i in (0, 5):
        theta, _ = sample_parameters(spec, jnp.uint32(i))
        np.testing.assert_allclose(np.asarray(theta), res.samples["theta"][i], rtol=1e-14)
        plant, ctrl, sens, _ = build_models(spec, theta)
        m = sim(plant, ctrl, sens).metrics
        assert bool(m.diverged) == res.samples["diverged"][i]
        if not bool(m.diverged):
            np.testing.assert_allclose(float(m.rms_error[0]), res.samples["rms_error"][i], rtol=1e-10)
            np.testing.assert_allclose(float(m.tau_rms[0]), res.samples["tau_rms"][i], rtol=1e-10)


def test_cli_sweep_writes_summary_figures_and_samples(tmp_path, small):
    from jaxflex.app.cli import main

    spec, res = small
    f = tmp_path / "spread.json"
    f.write_text(json.dumps(SMALL))
    out = tmp_path / "out"
    assert main(["sweep", str(f), "--out", str(out), "--chunk-size", "4", "--no-progress"]) == 0
    doc = json.loads((out / "summary.json").read_text())
    assert doc["samples"] == 12 and doc["diverged"] == res.summary["diverged"]
    assert doc["metrics"]["rms_error"]["q50"] == pytest.approx(res.summary["metrics"]["rms_error"]["q50"], rel=1e-12)
    for name in ("error_histograms.png", "error_bands.png", "sensitivity.png", "samples.csv"):
        assert (out / name).stat().st_size > 0
    table = np.loadtxt(out / "samples.csv", delimiter=",", skiprows=1)
    assert table.shape == (12, 1 + len(spec.labels) + 5)


def test_cli_sweep_bad_spread_exits_2_with_message(tmp_path, capsys):
    from jaxflex.app.cli import main

    f = tmp_path / "spread.json"
    f.write_text(json.dumps({"uncertain": {"plant.I": {"dist": "normal", "std": 0.1}}}))
    assert main(["sweep", str(f), "--out", str(tmp_path)]) == 2
    assert "plant.I must stay > 0" in capsys.readouterr().err


# ----- sharding and multiple processes (subprocesses) ------------------------------------------

_SHARD_SCRIPT = textwrap.dedent("""
    import os, sys, json
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from jaxflex.sweep import parse_spread, run_sweep
    spec = parse_spread(json.loads(sys.argv[1]))
    assert len(jax.local_devices()) == 2
    a = run_sweep(spec, chunk_size=6, shard=True, progress=False)
    b = run_sweep(spec, chunk_size=6, shard=False, progress=False)
    sa, sb = a.samples, b.samples
    for k in sa:
        np.testing.assert_allclose(sa[k], sb[k], rtol=1e-12, atol=0)
    assert a.summary["worst"] == b.summary["worst"]
    np.testing.assert_array_equal(a.band_q, b.band_q)
    print("OK", a.timing["devices"], b.timing["devices"])
""")

TINY = {**SMALL, "t_final": 0.1, "samples": 6}


@pytest.mark.slow
def test_sharded_over_two_host_devices_equals_unsharded():
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    r = subprocess.run([sys.executable, "-c", _SHARD_SCRIPT, json.dumps(TINY)], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "OK 2 1" in r.stdout


_PROC_SCRIPT = textwrap.dedent("""
    import sys, json
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    spread, port, pid, out = json.loads(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
    if pid >= 0:
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                                   process_id=pid, initialization_timeout=60)
    from jaxflex.sweep import parse_spread, run_sweep
    res = run_sweep(parse_spread(spread), chunk_size=2, progress=False)
    np.savez(out, rms=res.samples["rms_error"], index=res.samples["index"], band=res.band_q,
             worst=[w["index"] for w in res.summary["worst"]], procs=res.timing["processes"])
    if pid >= 0:
        jax.distributed.shutdown()
""")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_process_run_on_localhost_equals_a_single_process_run(tmp_path):
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    port, spread = str(_free_port()), json.dumps(TINY)
    procs = [subprocess.Popen([sys.executable, "-c", _PROC_SCRIPT, spread, port, str(i),
                               str(tmp_path / f"p{i}.npz")], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in (0, 1)]
    try:
        errs = [p.communicate(timeout=400)[1] for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert all(p.returncode == 0 for p in procs), "\n".join(e[-2000:] for e in errs)
    single = subprocess.run([sys.executable, "-c", _PROC_SCRIPT, spread, port, "-1",
                             str(tmp_path / "single.npz")], env=env, capture_output=True,
                            text=True, timeout=300)
    assert single.returncode == 0, single.stderr[-2000:]
    s = np.load(tmp_path / "single.npz")
    for i in (0, 1):
        m = np.load(tmp_path / f"p{i}.npz")
        assert int(m["procs"]) == 2 and int(s["procs"]) == 1
        np.testing.assert_array_equal(m["index"], s["index"])
        np.testing.assert_allclose(m["rms"], s["rms"], rtol=1e-12)
        np.testing.assert_array_equal(m["band"], s["band"])
        np.testing.assert_array_equal(m["worst"], s["worst"])


# ----- studies at small size ---------------------------------------------------------------------


@pytest.mark.slow
def test_robustness_study_runs_at_small_size(tmp_path):
    from studies import sweep_robustness

    r = sweep_robustness.main(["--small", "--out", str(tmp_path), "--no-progress"])
    assert set(r["runs"]) == {"with compensation", "without compensation"}
    assert r["paired"]["samples_compared"] > 0
    assert (tmp_path / "results.json").exists() and (tmp_path / "error_bands.png").exists()


def _bench_sweep(tmp_path, *args: str, result: str = "results.json") -> dict:
    r = subprocess.run([sys.executable, str(ROOT / "studies" / "bench_sweep.py"), "--small",
                        *args, "--out", str(tmp_path)], capture_output=True, text=True,
                       timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads((tmp_path / result).read_text())


@pytest.mark.slow
def test_benchmark_runs_at_small_size(tmp_path):
    res = _bench_sweep(tmp_path, "--skip-profile")
    assert len(res["scaling"]) == 2 and res["ratio"]["speedup_vs_solve_ivp"] > 1


def test_batched_loop_layout_follows_the_backend():
    """On a CPU the engine rolls the substeps for the jvp-tower laws and unrolls them for
    filtered derivatives, one sample per trip of the time loop; on a GPU it unrolls them
    (``loop_unrolls``; the GPU numbers are in ``studies/bench_sweep.py --gpu``)."""
    from jaxflex.sweep.engine import GPU_SCAN_UNROLL, loop_unrolls

    spec = parse_spread({"nominal": "paper", "t_final": 0.1, "samples": 2})
    ctrl = build_models(spec, sample_parameters(spec, jnp.uint32(0))[0])[1]
    on_gpu = jax.default_backend() != "cpu"
    for method in ("model", "reference", "filtered"):
        c = dataclasses.replace(ctrl, q2d_method=method)
        assert loop_unrolls(c) == ((True, GPU_SCAN_UNROLL) if on_gpu else (method == "filtered", 1))


@pytest.mark.slow
def test_benchmark_gpu_part_says_when_there_is_no_gpu(tmp_path):
    """``--gpu`` times the sweep on a GPU; on a machine without one it writes that it did
    not measure, and why, instead of a number."""
    res = _bench_sweep(tmp_path, "--gpu", result="gpu.json")
    if any(d.platform != "cpu" for d in jax.devices()):
        assert res["measured"] and res["substeps"] is not None
    else:
        assert res["measured"] is False and "no cuda device" in res["reason"]


@pytest.mark.slow
def test_benchmark_target_runs_at_small_size(tmp_path):
    res = _bench_sweep(tmp_path, "--target", result="target.json")
    assert res["accuracy"][str(res["substeps"])] <= res["tolerance_rel"]
    assert set(res["best_steps_per_s"]) == {"one_core", "one_device", "two_devices"}
    assert res["rms_max_rel_diff_between_setups"] < 1e-12  # the devices change no number


def test_an_interrupt_during_a_gc_callback_stops_between_chunks_without_a_traceback():
    """A signal that arrives while a garbage-collector callback runs (JAX registers one) must
    not raise there: Python would print "Exception ignored" with a traceback and drop it. The
    handler then only asks the sweep to stop at the next chunk; elsewhere it raises."""
    import gc
    import signal
    import sys

    from jaxflex.sweep.engine import _deferred_interrupts

    with _deferred_interrupts() as state:
        handler = signal.getsignal(signal.SIGINT)

        def callback(phase, info):
            handler(signal.SIGINT, sys._getframe())

        gc.callbacks.append(callback)
        try:
            callback("start", {})  # as the collector would call it: no exception
        finally:
            gc.callbacks.remove(callback)
        assert state["stop"]
        state["stop"] = False
        with pytest.raises(KeyboardInterrupt):
            handler(signal.SIGINT, sys._getframe())
        assert state["stop"]
