"""Benchmark: how fast and how lean is the batched Monte Carlo sweep on this machine?

Question: closed-loop controller steps per second of ``jaxflex.sweep.run_sweep`` for 1e3, 1e4
and 1e5 samples, its peak memory for each (it must stay flat in the number of samples), and
the ratio against a baseline loop of ``scipy.integrate.solve_ivp`` over a subset, run in the
same process. Also a profile of what limits the batched loop (plant substeps, q2d method,
float32 against float64) and the float32 path's accuracy.

Every sweep size runs in a fresh subprocess and reads its own peak resident set size from
``resource.getrusage(RUSAGE_SELF).ru_maxrss``. Throughput excludes tracing and XLA
compilation (a one-chunk warm-up run first; its time is reported as ``first_chunk_s``).

BASELINE (labelled as such, used only here): the same sampled-data loop, one sample at a
time: the controller is the jitted single-sample ``CascadeController.step`` called every
1 ms with numpy in/out, and the plant (paper eq. 3-5 with LuGre, one link, re-implemented in
numpy below) is integrated over each 1 ms zero-order-hold interval by ``solve_ivp`` (RK45,
rtol 1e-8, atol 1e-10), restarted at every sample.

    python studies/bench_sweep.py [--small] [--out out/bench_sweep]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

SPREAD = {
    "nominal": "paper", "trajectory": "sinusoid",
    "controller": {"compensation": True, "q2d_method": "model", "tau_max": 2.0},
    "sensing": "ideal", "seed": 0,
    "uncertain": {"plant.*": {"dist": "uniform", "rel": 0.2},
                  "friction.*": {"dist": "uniform", "rel": 0.2}},
}


def worker(samples: int, t_final: float, chunk: int, substeps: int, method: str, float32: bool,
           keep: bool) -> dict:
    """One sweep in this (fresh) process; returns throughput and peak memory."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.sweep import parse_spread, run_sweep

    spec = parse_spread({**SPREAD, "t_final": t_final, "substeps": substeps,
                         "controller": {**SPREAD["controller"], "q2d_method": method}})
    # warm-up: one chunk compiles the chunk function (cached per spec in this process)
    warm = run_sweep(spec, samples=min(chunk, samples), chunk_size=chunk, keep_samples=False,
                     progress=False, float32=float32)
    res = run_sweep(spec, samples=samples, chunk_size=chunk, keep_samples=keep, progress=False,
                    float32=float32)
    tm = res.timing
    out = {
        "samples": samples, "t_final": t_final, "chunk": chunk, "substeps": substeps,
        "q2d_method": method, "float32": float32, "keep_samples": keep,
        "first_chunk_s": warm.timing["wall_s"], "wall_s": tm["wall_s"],
        "steps_per_s": tm["controller_steps"] / tm["wall_s"],
        # the machine is shared: CPU time of this process says what it would do on its own
        # (an upper bound; a busy co-tenant slows caches too)
        "steps_per_cpu_s": tm["controller_steps"] / tm["cpu_s"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "diverged": res.summary["diverged"],
        "rms_q50": res.summary["metrics"]["rms_error"]["q50"],
    }
    if keep:
        import numpy as np

        out["_rms"] = np.asarray(res.samples["rms_error"]).tolist()
    return out


def run_worker(**kw) -> dict:
    """``worker`` in a fresh Python process (so ru_maxrss is this sweep's own peak)."""
    cmd = [sys.executable, __file__, "--worker", json.dumps(kw)]
    r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-3000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


# ----- baseline: numpy plant + solve_ivp per ZOH interval + jitted JAX controller step ---------


def baseline(samples: int, t_final: float) -> dict:
    """BASELINE loop over ``samples`` samples of the same spread (same parameters, same
    controller); returns steps/s and each sample's RMS link error [rad]."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from scipy.integrate import solve_ivp

    jax.config.update("jax_enable_x64", True)
    from jaxflex.sweep import build_models, parse_spread, sample_parameters

    spec = parse_spread({**SPREAD, "t_final": t_final})
    dt, N = spec.dt, round(t_final / spec.dt)
    rms, t0 = [], time.perf_counter()
    for i in range(samples):
        theta, _ = sample_parameters(spec, jnp.uint32(i))
        plant, ctrl, _, _ = build_models(spec, theta)
        I, J, K = (float(plant.links.I[0]), float(plant.J[0]), float(plant.K[0]))
        f = plant.friction
        Fc, Fs, vs, s0, s1, s2 = (float(getattr(f, k)[0]) for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2"))

        def rhs(t, x, tau):  # BASELINE re-implementation of eq. 3-6, one link
            q1, v1, q2, v2, z = x
            g = Fc + (Fs - Fc) * np.exp(-((v1 / vs) ** 2))
            zd = v1 - s0 * abs(v1) / g * z
            F = s0 * z + s1 * zd + s2 * v1
            return [v1, (K * (q2 - q1) - F) / I, v2, (tau - K * (q2 - q1)) / J, zd]

        step = jax.jit(lambda c, t, q1, q2, dq1, dq2: ctrl.step(c, t, q1, q2, dq1, dq2))
        q1d0 = float(ctrl.trajectory.position(jnp.asarray(0.0))[0])
        x = np.array([q1d0, 0.0, q1d0, 0.0, 0.0])
        c = ctrl.init(0.0, jnp.array([x[0]]), jnp.array([x[2]]), jnp.array([x[1]]), jnp.array([x[3]]))
        step(c, 0.0, *(jnp.array([v]) for v in (x[0], x[2], x[1], x[3])))  # compile outside the clock
        if i == 0:
            t0 = time.perf_counter()
        se = 0.0
        for k in range(N):
            t = k * dt
            c, out = step(c, t, *(jnp.array([v]) for v in (x[0], x[2], x[1], x[3])))
            tau = float(out.tau[0])
            se += float(out.e1[0]) ** 2
            sol = solve_ivp(rhs, (t, t + dt), x, args=(tau,), method="RK45", rtol=1e-8, atol=1e-10)
            x = sol.y[:, -1]
        rms.append(np.sqrt(se / N))
    wall = time.perf_counter() - t0
    return {"samples": samples, "t_final": t_final, "wall_s": wall, "steps_per_s": samples * N / wall,
            "rms": rms}


def components(n: int, t_final: float, substeps: int = 10) -> dict:
    """Where the time goes in one batched loop of ``n`` samples: the whole closed loop, the
    plant alone (``plant_step`` under a fixed torque) and the controller alone (``step`` on a
    fixed state), each a vmapped ``lax.scan`` over the same number of 1 ms samples."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from jaxflex.simulate import simulate_sampled
    from jaxflex.step import plant_step
    from jaxflex.sweep import build_models, parse_spread, sample_parameters

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
        return simulate_sampled(p, c, t_final, substeps=substeps, sensing=s, save=False).metrics.sum_e2

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/bench_sweep")
    ap.add_argument("--small", action="store_true", help="tiny sizes (for the slow test)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--skip-profile", action="store_true")
    ap.add_argument("--components", action="store_true", help="only the time-split profile")
    ap.add_argument("--profile-only", action="store_true", help="skip scaling and baseline")
    a = ap.parse_args()
    if a.worker:
        print(json.dumps(worker(**json.loads(a.worker))))
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
                 "load_avg_start": os.getloadavg(), "gpu": "none available in this task"}

    if a.profile_only:
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

    nb = 2 if a.small else 5
    if not a.profile_only:
        print(f"[bench] baseline: solve_ivp loop over {nb} samples (same process) ...")
        b = baseline(nb, H)
        res["baseline"] = dict(b)
        # the same samples through the batched path, in this process: ratio and agreement
        spec = parse_spread({**SPREAD, "t_final": H})
        ours = run_sweep(spec, samples=chunk, chunk_size=chunk, progress=False)  # compile
        ours = run_sweep(spec, samples=chunk, chunk_size=chunk, progress=False)
        sps = ours.timing["controller_steps"] / ours.timing["wall_s"]
        rel = np.abs(np.asarray(ours.samples["rms_error"][:nb]) - np.asarray(b["rms"])) / np.asarray(b["rms"])
        res["ratio"] = {"batched_steps_per_s": sps, "baseline_steps_per_s": b["steps_per_s"],
                        "speedup": sps / b["steps_per_s"], "rms_rel_diff_vs_baseline_max": float(rel.max())}
        print(f"  baseline {b['steps_per_s']:.3g} steps/s, batched {sps:.3g} steps/s in the same process: "
              f"x{sps / b['steps_per_s']:.0f}; RMS error agrees to {rel.max():.1e} (relative)")

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
