"""Benchmark: how fast and how lean is the batched Monte Carlo sweep on this machine?

Question: closed-loop controller steps per second of ``jaxflex.sweep.run_sweep`` for 1e3, 1e4
and 1e5 samples, its peak memory for each (it must stay flat in the number of samples), the
ratio against baselines run in the same process, the gain from a second CPU core (host
devices), and a profile of what limits the batched loop (plant substeps, q2d method, float32
against float64) with the float32 path's accuracy.

Every sweep size runs in a fresh subprocess and reads its own peak resident set size from
``resource.getrusage(RUSAGE_SELF).ru_maxrss``. Throughput excludes tracing and XLA
compilation (a one-chunk warm-up run first; its time is reported as ``first_chunk_s``).

BASELINES (labelled as such, used only here; nothing compiled or generated inside a clock):

- ``solve_ivp``: the same sampled-data loop, one sample after another, with the controller
  exported by ``jaxflex.export`` (numpy/math only, generated once) called every 1 ms and the
  plant (paper eq. 3-6 with LuGre, one link, numpy) integrated over each 1 ms zero-order-hold
  interval by ``solve_ivp`` (RK45, rtol 1e-8, atol 1e-10), restarted at every sample;
- ``numba``: the same samples through ``bench_simulate``'s numba loop (the library's
  splitting scheme, 10 substeps, the exported controller compiled by numba), one core.

The spread's controller estimates velocities from the angles (``sensing.velocity
"filtered"``), as the exported controller does, so every path does the same work.
Devices: the same sweep in subprocesses with 1 and 2 host devices
(``XLA_FLAGS=--xla_force_host_platform_device_count``), in alternating pairs.

Target (``--target``): 1000 samples x 10 s, float64, at a stated accuracy: the
fewest plant substeps whose per-sample RMS-error metric is within 1e-5 (relative) of a fine
reference (the first 100 samples at 100 substeps), then controller steps/s on one core (one
host device pinned to one core), one device (free to use every core) and two host devices, in
alternating rounds (best and median).

GPU (``--gpu``): the target's spread on an NVIDIA GPU in float64 and float32 beside
the same machine's CPU (every core as a host device), accuracy first (``gpu``'s docstring),
then 1e4 and 1e5 samples; on a machine without a GPU it writes ``gpu.json`` saying so. On a
GPU every trip of a loop waits for the host to read its condition, so the loop rather than
the arithmetic sets the pace: the substeps are unrolled there
(``jaxflex.sweep.engine.loop_unrolls``), and ``GPU_SCAN_UNROLL`` (set before the first
sweep) puts more samples in each trip of the time loop at a longer compilation. The figures
are in docs/performance.md (``performance_table.py``).

    python studies/bench_sweep.py [--small] [--gpu] [--out out/bench_sweep]
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchkit  # noqa: E402

BLAS = benchkit.limit_blas_threads(1)
#: --xla-default: the workers keep XLA's default CPU options (otherwise they get jaxflex's
#: LEAN_XLA_CPU_FLAGS, as the jaxflex command sets them)
XLA_DEFAULT = False

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

SPREAD = {
    "nominal": "paper", "trajectory": "sinusoid",
    "controller": {"compensation": True, "q2d_method": "model", "tau_max": 2.0},
    "sensing": {"velocity": "filtered"}, "seed": 0,
    "uncertain": {"plant.*": {"dist": "uniform", "rel": 0.2},
                  "friction.*": {"dist": "uniform", "rel": 0.2}},
}


def worker(samples: int, t_final: float, chunk: int, substeps: int, method: str, float32: bool,
           keep: bool, repeats: int = 1, unrolls: list | None = None) -> dict:
    """One sweep in this (fresh) process, timed ``repeats`` times after a warm-up chunk;
    returns throughput (best run; the median too) and peak memory. ``unrolls``
    ``[unroll_substeps, unroll]`` forces the batched loop's layout (the engine's
    ``loop_unrolls`` otherwise), for the comparison of layouts."""
    import jax

    from jaxflex.runtime.xla import use_lean_xla_cpu

    if not XLA_DEFAULT:
        use_lean_xla_cpu()  # as the jaxflex command does, before any JAX computation
    jax.config.update("jax_enable_x64", True)
    from jaxflex.sweep import engine, parse_spread, run_sweep

    if unrolls is not None:
        engine.loop_unrolls = lambda controller: tuple(unrolls)
    spec = parse_spread({**SPREAD, "t_final": t_final, "substeps": substeps,
                         "controller": {**SPREAD["controller"], "q2d_method": method}})
    # warm-up: one chunk compiles the chunk function (cached per spec in this process)
    warm = run_sweep(spec, samples=min(chunk, samples), chunk_size=chunk, keep_samples=False,
                     progress=False, float32=float32)
    walls = []
    for _ in range(repeats):
        res = run_sweep(spec, samples=samples, chunk_size=chunk, keep_samples=keep,
                        progress=False, float32=float32)
        walls.append(res.timing["wall_s"])
    tm = res.timing
    out = {
        "samples": samples, "t_final": t_final, "chunk": chunk, "substeps": substeps,
        "q2d_method": method, "float32": float32, "keep_samples": keep,
        "first_chunk_s": warm.timing["wall_s"], "wall_s": min(walls), "walls_s": walls,
        "steps_per_s": tm["controller_steps"] / min(walls),
        "steps_per_s_median": tm["controller_steps"] / statistics.median(walls),
        "backend": jax.default_backend(), "device_kind": jax.devices()[0].device_kind,
        "loop_unrolls": list(engine.loop_unrolls(
            engine.build_models(spec, engine.sample_parameters(spec, 0)[0])[1])),
        # the machine is shared: CPU time of this process says what it would do on its own
        # (an upper bound; a busy co-tenant slows caches too)
        "steps_per_cpu_s": tm["controller_steps"] / tm["cpu_s"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "diverged": res.summary["diverged"], "devices": tm["devices"],
        "load_avg": list(os.getloadavg()),
        "rms_q50": res.summary["metrics"]["rms_error"]["q50"],
    }
    if keep:
        import numpy as np

        out["_rms"] = np.asarray(res.samples["rms_error"]).tolist()
    return out


def run_worker(devices: int = 1, cores: int | None = None, platform: str = "cpu",
               timeout: float | None = None, **kw) -> dict:
    """``worker`` in a fresh Python process (so ru_maxrss is this sweep's own peak) with
    ``devices`` host devices (the sweep shards each chunk over them), pinned to the first
    ``cores`` CPU cores if given (XLA's own threads included), on JAX platform ``platform``
    (``"cpu"``, or ``"cuda"`` for an NVIDIA GPU), stopped after ``timeout`` seconds."""
    cmd = [sys.executable, __file__, "--worker", json.dumps(kw)] + (
        ["--xla-default"] if XLA_DEFAULT else [])
    flags = os.environ.get("XLA_FLAGS", "").split()
    env = {**os.environ, "JAX_PLATFORMS": platform,
           "XLA_FLAGS": " ".join(flags + [f"--xla_force_host_platform_device_count={devices}"])}
    pin = None
    if cores is not None:
        allowed = sorted(os.sched_getaffinity(0))[:cores]
        pin = lambda: os.sched_setaffinity(0, allowed)  # noqa: E731
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, preexec_fn=pin,
                       timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-3000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


# ----- baselines (used only here), compiled or generated outside the clock ---------------------


def _sample_plants(spec, samples: int):
    """Plant constants P = (I, J, K, Fc, Fs, vs, sigma0, sigma1, sigma2, dt) of the first
    ``samples`` samples of ``spec`` (one joint) and the sweep's controller (the nominal one:
    the spread perturbs only the true plant), built before any clock starts."""
    import jax.numpy as jnp
    import numpy as np

    from jaxflex.sweep import build_models, sample_parameters

    rows = []
    for i in range(samples):
        theta, _ = sample_parameters(spec, jnp.uint32(i))
        plant, ctrl, _, _ = build_models(spec, theta)
        f = plant.friction
        rows.append([float(plant.links.I[0]), float(plant.J[0]), float(plant.K[0])]
                    + [float(getattr(f, k)[0]) for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2")]
                    + [spec.dt])
    return np.array(rows), ctrl


def baseline(samples: int, t_final: float) -> dict:
    """BASELINE: ``samples`` samples of the same spread one after another: the controller
    exported by ``jaxflex.export`` (numpy/math, generated once, outside the clock) called every
    1 ms, the plant (eq. 3-6, one link, numpy) integrated over each zero-order-hold interval
    by ``solve_ivp`` (RK45, rtol 1e-8, atol 1e-10). Returns steps/s and each sample's RMS link
    error [rad]."""
    import numpy as np
    from scipy.integrate import solve_ivp

    from jaxflex.export import generate_source, load_module
    from jaxflex.sweep import parse_spread

    spec = parse_spread({**SPREAD, "t_final": t_final})
    Ps, ctrl = _sample_plants(spec, samples)
    t0 = time.perf_counter()
    mod = load_module(generate_source(ctrl))
    t_export = time.perf_counter() - t0
    dt, N = spec.dt, round(t_final / spec.dt)
    ref = np.array([mod.Controller().reference(k * dt) for k in range(N)])
    rms = []
    t0 = time.perf_counter()
    for P in Ps:
        I, J, K, Fc, Fs, vs, s0, s1, s2, _ = P

        def rhs(t, x, tau):  # BASELINE re-implementation of eq. 3-6, one link
            q1, v1, q2, v2, z = x
            g = Fc + (Fs - Fc) * np.exp(-((v1 / vs) ** 2))
            zd = v1 - s0 * abs(v1) / g * z
            F = s0 * z + s1 * zd + s2 * v1
            return [v1, (K * (q2 - q1) - F) / I, v2, (tau - K * (q2 - q1)) / J, zd]

        c = mod.Controller()
        x = np.array([ref[0], 0.0, ref[0], 0.0, 0.0])
        se = 0.0
        for k in range(N):
            t = k * dt
            tau = c.step(t, x[0], x[2])
            se += (x[0] - ref[k]) ** 2
            x = solve_ivp(rhs, (t, t + dt), x, args=(tau,), method="RK45", rtol=1e-8,
                          atol=1e-10).y[:, -1]
        rms.append(float(np.sqrt(se / N)))
    wall = time.perf_counter() - t0
    return {"samples": samples, "t_final": t_final, "wall_s": wall, "export_s": t_export,
            "steps_per_s": samples * N / wall, "rms": rms}


def numba_baseline(samples: int, t_final: float, substeps: int = 10) -> dict | None:
    """The same samples through the numba loop of ``bench_simulate`` (the library's splitting
    scheme with ``substeps`` substeps, the exported controller compiled by numba), one after
    another on one core; compilation on a first run outside the clock. None without numba."""
    try:
        import numba
    except ImportError:
        return None
    import numpy as np

    from bench_simulate import _generated_step, _kernels
    from jaxflex.export import generate_source, load_module
    from jaxflex.sweep import parse_spread

    spec = parse_spread({**SPREAD, "t_final": t_final})
    Ps, ctrl = _sample_plants(spec, samples)
    src = generate_source(ctrl)
    mod = load_module(src)
    step, S0 = _generated_step(src, mod)
    step = numba.njit(step)
    loop = _kernels("numba")["_k_loop"]
    dt, N = spec.dt, round(t_final / spec.dt)
    ref = np.array([mod.Controller().reference(k * dt) for k in range(N)])
    q1 = np.empty(N)
    t0 = time.perf_counter()
    loop(Ps[0], N, substeps, step, mod.Controller()._init(0.0, ref[0], ref[0]), ref[0], ref[0], q1)
    t_compile = time.perf_counter() - t0
    rms = []
    t0 = time.perf_counter()
    for P in Ps:
        S0 = mod.Controller()._init(0.0, ref[0], ref[0])
        loop(P, N, substeps, step, S0, ref[0], ref[0], q1)
        rms.append(float(np.sqrt(np.mean((q1 - ref) ** 2))))
    wall = time.perf_counter() - t0
    return {"samples": samples, "t_final": t_final, "wall_s": wall, "compile_s": t_compile,
            "steps_per_s": samples * N / wall, "rms": rms, "numba": numba.__version__}


def components(n: int, t_final: float, substeps: int = 10) -> dict:
    """Where the time goes in one batched loop of ``n`` samples: the whole closed loop, the
    plant alone (``plant_step`` under a fixed torque) and the controller alone (``step`` on a
    fixed state), each a vmapped ``lax.scan`` over the same number of 1 ms samples."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from jaxflex.sim.simulate import simulate_sampled
    from jaxflex.sim.step import plant_step
    from jaxflex.sweep import build_models, parse_spread, sample_parameters
    from jaxflex.sweep.engine import loop_unrolls

    spec = parse_spread({**SPREAD, "t_final": t_final, "substeps": substeps})
    N = round(t_final / spec.dt)
    models = jax.vmap(lambda i: build_models(spec, sample_parameters(spec, i)[0])[:3])(jnp.arange(n))
    plant, ctrl, sens = models

    def timed(f, *args):
        f = eqx.filter_jit(f)
        jax.block_until_ready(f(*args))
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        return n * N / (time.perf_counter() - t0)

    @eqx.filter_vmap
    def full(p, c, s):
        sub_unroll, unroll = loop_unrolls(c)
        return simulate_sampled(p, c, t_final, substeps=substeps, sensing=s, save=False,
                                unroll_substeps=sub_unroll, unroll=unroll).metrics.sum_e2

    @eqx.filter_vmap
    def plant_only(p, c):
        x0 = p.init_state(q1=0.0)
        return jax.lax.scan(lambda x, _: (plant_step(p, x, jnp.full((1,), 0.1), spec.dt, substeps), None),
                            x0, None, length=N)[0].q1

    @eqx.filter_vmap
    def ctrl_only(p, c):
        q = jnp.zeros(1)
        st = c.init(0.0, q, q)
        def body(st, t):
            st, out = c.step(st, t, q + 1e-3 * t, q, q, q)
            return st, None
        return jax.lax.scan(body, st, jnp.arange(N) * spec.dt)[0].z_hat

    return {"batch": n, "steps": N, "substeps": substeps,
            "closed_loop_steps_per_s": timed(full, plant, ctrl, sens),
            "plant_only_steps_per_s": timed(plant_only, plant, ctrl),
            "controller_only_steps_per_s": timed(ctrl_only, plant, ctrl)}


def alternating(setups: dict, rounds: int, **kw) -> tuple[dict, dict, dict, float]:
    """``run_worker`` for each setup (name -> its ``run_worker`` keywords, e.g. devices and
    cores) in ``rounds`` rounds, the order reversed every other round, with the common
    keywords ``kw`` (``keep=True``). Returns the runs per setup (per-sample RMS dropped),
    the best and median steps/s per setup, and the largest relative difference of the
    per-sample RMS errors between any run and the first setup's first run."""
    import numpy as np

    runs: dict = {k: [] for k in setups}
    for r in range(rounds):
        for name in (list(setups) if r % 2 == 0 else list(setups)[::-1]):
            runs[name].append(run_worker(**setups[name], **kw))
    r0 = np.asarray(runs[next(iter(setups))][0]["_rms"])
    same = max(float(np.max(np.abs(np.asarray(w["_rms"]) - r0) / r0))
               for v in runs.values() for w in v)
    for v in runs.values():
        for w in v:
            w.pop("_rms")
    best = {k: max(w["steps_per_s"] for w in v) for k, v in runs.items()}
    med = {k: statistics.median(w["steps_per_s"] for w in v) for k, v in runs.items()}
    return runs, best, med, same


def target(out: Path, small: bool = False, tol: float = 1e-5) -> dict:
    """The sweep throughput target: ``samples`` x ``T`` s of the spread in float64 with the
    fewest plant substeps (of 1, 2, 3, 5, 10) whose per-sample RMS link error is within
    ``tol`` (relative) of the same samples at 100 substeps (checked on the first
    ``n_ref`` samples), timed on one core, one device and two devices in alternating rounds,
    each run in a fresh process, compilation (the first chunk) apart. Writes
    ``out/target.json``."""
    import numpy as np

    samples, T, n_ref, rounds = (64, 0.5, 16, 1) if small else (1000, 10.0, 100, 2)
    out.mkdir(parents=True, exist_ok=True)
    res: dict = {"samples": samples, "t_final": T, "reference": {"samples": n_ref, "substeps": 100},
                 "tolerance_rel": tol, "cpu_count": os.cpu_count(),
                 "load_avg_start": os.getloadavg(), "blas_threads": BLAS,
                 "xla_flags": "default" if XLA_DEFAULT else "lean (jaxflex.sweep.engine)"}
    kw = dict(t_final=T, method="model", float32=False, keep=True)
    ref = np.asarray(run_worker(samples=n_ref, chunk=n_ref, substeps=100, **kw)["_rms"])
    res["accuracy"] = {}
    chosen = None
    for sub in (1, 2, 3, 5, 10):
        rms = np.asarray(run_worker(samples=n_ref, chunk=n_ref, substeps=sub, **kw)["_rms"])
        err = float(np.max(np.abs(rms - ref) / ref))
        res["accuracy"][str(sub)] = err
        print(f"  substeps {sub:>2}: RMS metric within {err:.1e} (relative) of 100 substeps")
        if err <= tol:
            chosen = sub
            break
    if chosen is None:
        raise RuntimeError(f"bench_sweep --target: no substep count reaches {tol:g}")
    res["substeps"] = chosen
    # "one core": one host device pinned to one core (XLA's intra-op threads included);
    # "one device": one host device free to use every core; "two devices": one per core
    setups = {"one_core": dict(devices=1, cores=1), "one_device": dict(devices=1),
              "two_devices": dict(devices=2)}
    runs, best, med, same = alternating(setups, rounds, samples=samples, chunk=samples,
                                        substeps=chosen, **kw)
    res["rms_max_rel_diff_between_setups"] = same
    res.update(runs=runs, best_steps_per_s=best, median_steps_per_s=med,
               ratio_two_devices_over_one_core_best=best["two_devices"] / best["one_core"],
               ratio_two_devices_over_one_core_median=med["two_devices"] / med["one_core"],
               ratio_two_devices_over_one_device_best=best["two_devices"] / best["one_device"],
               load_avg_end=os.getloadavg())
    print(f"  {samples} x {T} s, float64, {chosen} substeps, steps/s best (median): "
          + ", ".join(f"{k} {best[k]:.3g} ({med[k]:.3g})" for k in setups)
          + f"; two devices / one core x{res['ratio_two_devices_over_one_core_best']:.2f} best, "
          f"x{res['ratio_two_devices_over_one_core_median']:.2f} median; setups agree to "
          f"{res['rms_max_rel_diff_between_setups']:.1e}; load "
          f"{[w['load_avg'][0] for v in runs.values() for w in v]}")
    (out / "target.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


def gpu(out: Path, small: bool = False, tol: float = 1e-5, platform: str = "cuda",
        budget_s: float = 300.0) -> dict:
    """Sweep throughput on a GPU, float64 and float32, beside this machine's CPU.

    Every run is a fresh process on JAX platform ``platform``, timed three times after a
    warm-up chunk that compiles (its time is ``first_chunk_s``). Accuracy first: a fine
    reference (the first ``n_ref`` samples at 100 substeps, float64, on this machine's CPU with
    every core as a host device), then the target's spread (``samples`` x ``T`` s) on the
    GPU in float64 at 1, 2, 3, 5, 10 substeps until the per-sample RMS-error metric is within
    ``tol`` (relative) of the reference; float32 at the same substeps (its error stated); the
    same sweep on this machine's CPU (every core) for a same-machine ratio and a check that
    both devices compute the same numbers; then larger batches on the GPU (one chunk each).
    Runs are skipped (and say so) once ``budget_s`` seconds have passed. Writes
    ``out/gpu.json`` after every run, so a run cut short keeps what it measured."""
    import numpy as np

    out.mkdir(parents=True, exist_ok=True)
    samples, T, n_ref = (64, 0.5, 16) if small else (1000, 10.0, 100)
    big = (256,) if small else (10_000, 100_000)
    ncpu = len(os.sched_getaffinity(0))
    t_start = time.perf_counter()
    res: dict = {"platform": platform, "samples": samples, "t_final": T, "tolerance_rel": tol,
                 "reference": {"samples": n_ref, "substeps": 100, "float32": False,
                               "device": f"cpu ({ncpu} host devices)"},
                 "cpu_count": ncpu, "load_avg_start": os.getloadavg(), "blas_threads": BLAS,
                 "runs": {}}
    path = out / "gpu.json"

    def save():
        res["elapsed_s"] = time.perf_counter() - t_start
        path.write_text(json.dumps(res, indent=2) + "\n")

    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"}
    probe = subprocess.run(
        [sys.executable, "-c", "import jax; d = jax.devices(); print(d[0].platform, '|', "
         "d[0].device_kind, '|', len(d), '|', jax.__version__)"],
        capture_output=True, text=True, env=env if platform != "cpu" else os.environ)
    seen = probe.stdout.strip().split(" | ")
    wanted = ("gpu", "cuda") if platform == "cuda" else (platform,)
    if probe.returncode != 0 or seen[0] not in wanted:
        res["measured"] = False
        res["reason"] = (f"JAX sees no {platform} device here (its devices: {probe.stdout.strip()}"
                         f"{probe.stderr.strip()[-200:]})")
        save()
        print(f"[bench] gpu: not measured: {res['reason']}")
        return res
    res["device"] = probe.stdout.strip()
    res["measured"] = True
    print(f"[bench] gpu: {res['device']}; reference on the CPU ({ncpu} host devices) ...")
    kw = dict(t_final=T, method="model", keep=True)
    ref_run = run_worker(devices=ncpu, samples=n_ref, chunk=n_ref, substeps=100, float32=False,
                         timeout=300, **kw)
    ref = np.asarray(ref_run.pop("_rms"))
    res["runs"]["reference"] = ref_run
    save()

    def err(rms):
        return float(np.max(np.abs(np.asarray(rms[:n_ref]) - ref) / ref))

    def timed(name, **k):
        if time.perf_counter() - t_start > budget_s:
            res["runs"][name] = {"skipped": f"time budget of {budget_s:.0f} s spent"}
            save()
            return None
        r = run_worker(timeout=300, **k)
        rms = r.pop("_rms", None)
        if rms is not None:
            r["rms_rel_err_vs_reference"] = err(rms)
        res["runs"][name] = r
        save()
        print(f"  {name}: {r['steps_per_s']:.3g} steps/s best ({r['steps_per_s_median']:.3g} median "
              f"of {len(r['walls_s'])}), compile+first chunk {r['first_chunk_s']:.1f} s"
              + (f", RMS within {r['rms_rel_err_vs_reference']:.1e} of the reference" if rms is not None else ""))
        return r, rms

    chosen = None
    for sub in (1, 2, 3, 5, 10):
        got = timed(f"gpu_f64_{samples}_sub{sub}", platform=platform, samples=samples,
                    chunk=samples, substeps=sub, float32=False, repeats=3, **kw)
        if got is None:
            break
        if got[0]["rms_rel_err_vs_reference"] <= tol:
            chosen, rms64 = sub, np.asarray(got[1])
            break
    res["substeps"] = chosen
    if chosen is None:
        res["note"] = f"no substep count of 1-10 reached {tol:g} (or the budget ran out)"
        save()
        return res
    f32 = timed(f"gpu_f32_{samples}_sub{chosen}", platform=platform, samples=samples,
                chunk=samples, substeps=chosen, float32=True, repeats=3, **kw)
    cpu = timed(f"cpu_f64_{samples}_sub{chosen}", platform="cpu", devices=ncpu, samples=samples,
                chunk=samples, substeps=chosen, float32=False, repeats=3, **kw)
    g64 = res["runs"][f"gpu_f64_{samples}_sub{chosen}"]
    if f32 is not None:
        res["float32_rms_rel_diff_vs_float64_max"] = float(
            np.max(np.abs(np.asarray(f32[1]) - rms64) / rms64))
    if cpu is not None:
        res["gpu_vs_cpu_rms_rel_diff_max"] = float(np.max(np.abs(np.asarray(cpu[1]) - rms64) / rms64))
        res["ratio_gpu_f64_over_cpu_f64_best"] = g64["steps_per_s"] / cpu[0]["steps_per_s"]
    kw["keep"] = False
    for n in big:
        for single in (False, True):
            timed(f"gpu_{'f32' if single else 'f64'}_{n}_sub{chosen}", platform=platform,
                  samples=n, chunk=n, substeps=chosen, float32=single, repeats=3, **kw)
    timed(f"cpu_f64_{big[0]}_sub{chosen}", platform="cpu", devices=ncpu, samples=big[0],
          chunk=big[0], substeps=chosen, float32=False, repeats=3, **kw)
    res["load_avg_end"] = os.getloadavg()
    save()
    print(f"[bench] wrote {path}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_sweep")
    ap.add_argument("--small", action="store_true", help="tiny sizes (for the slow test)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--skip-profile", action="store_true")
    ap.add_argument("--skip-devices", action="store_true", help="skip 1 vs 2 host devices")
    ap.add_argument("--skip-scaling", action="store_true", help="skip the 1e3..1e5 sizes")
    ap.add_argument("--components", action="store_true", help="only the time-split profile")
    ap.add_argument("--profile-only", action="store_true", help="skip scaling and baseline")
    ap.add_argument("--target", action="store_true",
                    help="only the throughput target: 1000 x 10 s at a stated accuracy, one core vs two devices")
    ap.add_argument("--gpu", action="store_true",
                    help="only the GPU throughput (float64, float32) beside this machine's CPU")
    ap.add_argument("--gpu-platform", default="cuda", help=argparse.SUPPRESS)
    ap.add_argument("--xla-default", action="store_true",
                    help="workers keep XLA's default CPU options (else jaxflex's lean flags)")
    a = ap.parse_args()
    global XLA_DEFAULT
    XLA_DEFAULT = a.xla_default
    if a.worker:
        print(json.dumps(worker(**json.loads(a.worker))))
        return
    if a.target:
        target(Path(a.out), small=a.small)
        return
    if a.gpu:
        gpu(Path(a.out), small=a.small, platform=a.gpu_platform)
        return
    if a.components:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        rows = [components(1000, 0.1, sub) for sub in (10, 2)]
        for r in rows:
            print(json.dumps(r))
        (Path(a.out) / "components.json").write_text(json.dumps(rows, indent=2) + "\n")
        return
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    H = 0.05 if a.small else 0.1  # [s]; short horizon so that 1e5 samples finish in minutes
    sizes = (64, 256) if a.small else (1_000, 10_000, 100_000)
    chunk = 32 if a.small else 1000
    res: dict = {"horizon_s": H, "chunk": chunk, "cpu_count": os.cpu_count(),
                 "load_avg_start": os.getloadavg(), "blas_threads": BLAS}

    if a.profile_only or a.skip_scaling:
        sizes = ()
    res["scaling"] = []
    print(f"[bench] scaling: {sizes} samples, horizon {H} s, chunk {chunk}, float64, 10 substeps")
    for n in sizes:
        r = run_worker(samples=n, t_final=H, chunk=chunk, substeps=10, method="model",
                       float32=False, keep=False)
        res["scaling"].append(r)
        print(f"  {n:>7} samples: {r['steps_per_s']:.3g} steps/s wall, {r['steps_per_cpu_s']:.3g} per CPU-s "
              f"(compile {r['first_chunk_s']:.1f} s), "
              f"peak RSS {r['peak_rss_mb']:.0f} MB")

    import jax
    import numpy as np

    jax.config.update("jax_enable_x64", True)
    from jaxflex.sweep import parse_spread, run_sweep

    # what this process's JAX sees, not an assumption about the machine
    gpus = [str(d) for d in jax.devices() if d.platform in ("gpu", "cuda", "rocm")]
    res["gpu"] = (f"visible ({', '.join(gpus)}) but not timed: this study times CPU devices only"
                  if gpus else f"not measured: JAX sees no GPU (backend "
                               f"{jax.default_backend()}, {len(jax.devices())} device(s))")

    nb = 2 if a.small else 5
    nn = 8 if a.small else 100
    if not a.profile_only:
        print(f"[bench] baselines: solve_ivp loop over {nb} samples, numba loop over {nn} "
              f"(same process, load {os.getloadavg()}) ...")
        b = baseline(nb, H)
        nbb = numba_baseline(nn, H)
        res["baseline"] = dict(b)
        res["numba_baseline"] = nbb
        # the same samples through the batched path, in this process (its own devices: stated)
        spec = parse_spread({**SPREAD, "t_final": H})
        run_sweep(spec, samples=chunk, chunk_size=chunk, progress=False)  # compile
        walls, rms_ours = [], None
        for _ in range(3):
            ours = run_sweep(spec, samples=chunk, chunk_size=chunk, progress=False)
            walls.append(ours.timing["wall_s"])
            rms_ours = np.asarray(ours.samples["rms_error"])
        steps = ours.timing["controller_steps"]
        sps, sps_med = steps / min(walls), steps / statistics.median(walls)
        rel = np.abs(rms_ours[:nb] - np.asarray(b["rms"])) / np.asarray(b["rms"])
        ratio = {"batched_steps_per_s_best": sps, "batched_steps_per_s_median": sps_med,
                 "batched_devices": ours.timing["devices"], "batched_repeats": len(walls),
                 "solve_ivp_steps_per_s": b["steps_per_s"],
                 "speedup_vs_solve_ivp": sps / b["steps_per_s"],
                 "rms_rel_diff_vs_solve_ivp_max": float(rel.max()),
                 "load_avg": list(os.getloadavg())}
        line = (f"  batched ({ours.timing['devices']} device(s)) {sps:.3g} steps/s best, "
                f"{sps_med:.3g} median of {len(walls)}; solve_ivp+numpy controller "
                f"{b['steps_per_s']:.3g} steps/s (export {b['export_s']:.2f} s apart): "
                f"x{sps / b['steps_per_s']:.0f}; RMS error agrees to {rel.max():.1e} (relative)")
        if nbb is not None:
            reln = np.abs(rms_ours[:nn] - np.asarray(nbb["rms"])) / np.asarray(nbb["rms"])
            ratio.update(numba_steps_per_s=nbb["steps_per_s"],
                         speedup_vs_numba=sps / nbb["steps_per_s"],
                         rms_rel_diff_vs_numba_max=float(reln.max()))
            line += (f"; numba {nbb['steps_per_s']:.3g} steps/s (compile {nbb['compile_s']:.1f} s "
                     f"apart): x{sps / nbb['steps_per_s']:.2f}, RMS agrees to {reln.max():.1e}")
        else:
            line += "; numba not installed (column skipped)"
        res["ratio"] = ratio
        print(line)

    if not a.skip_devices:
        nd_samples = 128 if a.small else 4000
        nd_chunk = 64 if a.small else 2000
        rounds = 1 if a.small else 3
        print(f"[bench] host devices: {nd_samples} samples, chunk {nd_chunk}, 1 vs 2 devices, "
              f"{rounds} alternating pair(s)")
        runs, best, med, same = alternating(
            {1: dict(devices=1), 2: dict(devices=2)}, rounds, samples=nd_samples, t_final=H,
            chunk=nd_chunk, substeps=10, method="model", float32=False, keep=True)
        res["devices"] = {"runs": {str(k): v for k, v in runs.items()},
                          "best_steps_per_s": best, "median_steps_per_s": med,
                          "ratio_2_over_1_best": best[2] / best[1],
                          "ratio_2_over_1_median": med[2] / med[1],
                          "rms_max_rel_diff_1_vs_2_devices": same}
        print(f"  1 device {best[1]:.3g} steps/s best ({med[1]:.3g} median), 2 devices "
              f"{best[2]:.3g} ({med[2]:.3g}): x{best[2] / best[1]:.2f} best, "
              f"x{med[2] / med[1]:.2f} median; per-sample RMS max rel. diff {same:.1e}; load "
              f"{[w['load_avg'][0] for v in runs.values() for w in v]}")

    if not a.skip_profile:
        n = 64 if a.small else 1000
        print(f"[bench] profile: {n} samples, horizon {H} s")
        res["profile"] = []
        ref = None
        for sub, meth, f32 in [(10, "model", False), (10, "model", True), (10, "filtered", False),
                               (5, "model", False), (2, "model", False), (1, "model", False),
                               (2, "model", True)]:
            r = run_worker(samples=n, t_final=H, chunk=n // 2, substeps=sub,
                           method=meth, float32=f32, keep=True)
            rms = np.asarray(r.pop("_rms"))
            if ref is None:
                ref = rms
            r["rms_rel_diff_vs_first_max"] = float(np.max(np.abs(rms - ref) / ref)) if meth == "model" else None
            res["profile"].append(r)
            print(f"  substeps {sub:>2} {meth:>8} {'f32' if f32 else 'f64'}: {r['steps_per_s']:.3g} steps/s, "
                  f"{r['steps_per_cpu_s']:.3g} per CPU-s, "
                  f"compile {r['first_chunk_s']:.1f} s, RMS rel. diff vs first row {r['rms_rel_diff_vs_first_max']}")
    res["load_avg_end"] = os.getloadavg()
    name = "profile.json" if a.profile_only else "results.json"
    (out / name).write_text(json.dumps(res, indent=2) + "\n")
    print(f"[bench] wrote {out / name}")


if __name__ == "__main__":
    main()
