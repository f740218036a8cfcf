"""Question: how fast is the closed-loop simulation, single and batched, on this CPU?

1. One 10 s closed loop at 1 kHz (paper plant, paper gains, compensation on, model-based q2d
   derivatives): wall time after compilation of ``simulate_sampled`` against a baseline of
   ``scipy.integrate.solve_ivp`` (RK45, rtol 1e-8) on the same model in the same process. The
   baseline integrates a numpy version of the plant between samples (written here, for the
   baseline only) and calls the jitted JAX controller step once per sample, exactly as a
   scipy script around a given controller would.
2. Batched: closed-loop controller steps per second for B parallel simulations (vmap over
   LuGre and inertia perturbations, ``save=False``), float64 and float32, for several plant
   substep counts, with the accuracy of each fast path against the float64 / 10-substep run.

Writes results.json to --out (default out/bench_simulate). Ratios are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _single(out: dict, t_final: float) -> None:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    from scipy.integrate import solve_ivp

    from jaxflex.controller import CascadeController
    from jaxflex.presets import paper_gains, paper_plant, paper_sinusoid
    from jaxflex.simulate import simulate_sampled

    plant = paper_plant()
    ctrl = CascadeController(model=plant, gains=paper_gains(), trajectory=paper_sinusoid())
    sim = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, t_final))
    t0 = time.perf_counter()
    r = jax.block_until_ready(sim(plant, ctrl))
    t_compile = time.perf_counter() - t0
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        jax.block_until_ready(sim(plant, ctrl))
        times.append(time.perf_counter() - t0)
    t_jax = min(times)

    # --- baseline: solve_ivp between samples, numpy plant, jitted JAX controller step ---
    fr = plant.friction
    I, J, K = 0.07, 0.005, 6.77
    Fc, Fs, vs, s0, s1, s2 = (float(getattr(fr, k)[0]) for k in ("Fc", "Fs", "vs", "sigma0", "sigma1", "sigma2"))

    def f(t, y, tau):
        q1, dq1, q2, dq2, z = y
        g = Fc + (Fs - Fc) * np.exp(-((dq1 / vs) ** 2))
        dz = dq1 - s0 * abs(dq1) / g * z
        F = s0 * z + s1 * dz + s2 * dq1
        Ts = K * (q2 - q1)
        return [dq1, (Ts - F) / I, dq2, (tau - Ts) / J, dz]

    step = jax.jit(lambda c, t, q1, q2, dq1, dq2: ctrl.step(c, t, q1, q2, dq1, dq2))
    dt = ctrl.dt
    N = int(round(t_final / dt))
    y = np.zeros(5)
    c = ctrl.init(0.0, jnp.zeros(1), jnp.zeros(1), jnp.zeros(1), jnp.zeros(1))
    step(c, 0.0, jnp.zeros(1), jnp.zeros(1), jnp.zeros(1), jnp.zeros(1))  # compile
    q1_base = np.zeros(N)
    t0 = time.perf_counter()
    t_ctrl = 0.0
    for k in range(N):
        tk = k * dt
        ta = time.perf_counter()
        c, o = step(c, tk, jnp.array([y[0]]), jnp.array([y[2]]), jnp.array([y[1]]), jnp.array([y[3]]))
        tau = float(o.tau[0])
        t_ctrl += time.perf_counter() - ta
        q1_base[k] = y[0]
        sol = solve_ivp(f, (tk, tk + dt), y, args=(tau,), rtol=1e-8, atol=1e-11, method="RK45")
        y = sol.y[:, -1]
    t_scipy = time.perf_counter() - t0
    diff = float(np.max(np.abs(q1_base - np.asarray(r.q1[:, 0]))))
    out["single"] = {
        "t_final_s": t_final, "steps": N, "jax_compile_s": t_compile, "jax_run_s": t_jax,
        "scipy_solve_ivp_s": t_scipy, "scipy_of_which_controller_calls_s": t_ctrl,
        "ratio_scipy_over_jax": t_scipy / t_jax,
        "ratio_scipy_integration_only_over_jax": (t_scipy - t_ctrl) / t_jax,
        "max_q1_difference_rad": diff,
    }
    print(f"single 10 s loop: jax {t_jax:.3f} s (compile {t_compile:.1f} s), scipy solve_ivp "
          f"{t_scipy:.1f} s (controller calls {t_ctrl:.1f} s) -> ratio {t_scipy / t_jax:.0f}x "
          f"({(t_scipy - t_ctrl) / t_jax:.0f}x on integration alone); max |q1 diff| {diff:.1e} rad")


def _batched(out: dict, B: int, t_final: float, configs: list[tuple[str, int, str]],
             out_dir: Path) -> None:
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from jaxflex.controller import CascadeController
    from jaxflex.friction import LuGre
    from jaxflex.plant import DiagonalInertia, FlexibleJointPlant
    from jaxflex.presets import paper_gains, paper_plant, paper_sinusoid
    from jaxflex.simulate import simulate_sampled

    rng = np.random.default_rng(0)
    scale = rng.uniform(0.8, 1.2, size=(B, 4))
    results = {}
    for dtype_name, substeps, method in configs:
        dtype = jnp.float64 if dtype_name == "float64" else jnp.float32
        sc = jnp.asarray(scale, dtype)
        nominal = paper_plant()
        gains = jax.tree_util.tree_map(lambda a: a.astype(dtype), paper_gains())
        traj = jax.tree_util.tree_map(lambda a: a.astype(dtype), paper_sinusoid())
        nominal = jax.tree_util.tree_map(lambda a: a.astype(dtype), nominal)

        def one(s):
            fr = nominal.friction
            lug = LuGre(Fc=fr.Fc * s[0], Fs=fr.Fs * s[0], vs=fr.vs, sigma0=fr.sigma0 * s[1],
                        sigma1=fr.sigma1, sigma2=fr.sigma2 * s[2])
            true = FlexibleJointPlant(links=DiagonalInertia(I=nominal.links.I * s[3]),
                                      J=nominal.J, K=nominal.K, friction=lug)
            c = CascadeController(model=nominal, gains=gains, trajectory=traj,
                                  q2d_method=method)
            return simulate_sampled(true, c, t_final, substeps=substeps, save=False).metrics.rms_error[0]

        f = eqx.filter_jit(jax.vmap(one))
        t0 = time.perf_counter()
        jax.block_until_ready(f(sc))
        tc = time.perf_counter() - t0
        t0 = time.perf_counter()
        rms = np.asarray(jax.block_until_ready(f(sc)), float)
        tr = time.perf_counter() - t0
        steps = B * int(round(t_final / 1e-3))
        key = f"{dtype_name}_sub{substeps}_{method}"
        np.save(out_dir / f"rms_{key}.npy", rms)
        results[key] = {"batch": B, "steps_per_s": steps / tr, "run_s": tr, "compile_s": tc,
                        "any_nonfinite": bool(np.any(~np.isfinite(rms)))}
        print(f"batched B={B} {key}: {steps / tr / 1e6:.2f} M controller steps/s "
              f"(run {tr:.2f} s, compile {tc:.1f} s)")
    out["batched"] = results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/bench_simulate")
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--small", action="store_true", help="short horizons (smoke test)")
    ap.add_argument("--part", choices=["all", "single", "batched32", "batched64"], default="all")
    args = ap.parse_args()
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    if args.part == "all":
        # float32 and float64 need separate processes (jax_enable_x64 is global)
        merged: dict = {}
        for part in ("single", "batched64", "batched32"):
            cmd = [sys.executable, __file__, "--out", str(out_dir / part), "--batch", str(args.batch),
                   "--part", part] + (["--small"] if args.small else [])
            subprocess.run(cmd, check=True)
            merged[part] = json.loads((out_dir / part / "results.json").read_text())
        ref = np.load(out_dir / "batched64" / "rms_float64_sub10_model.npy")
        # the 'filtered' rows are a different controller, not a faster path of the same one
        for key in ("float32_sub10_model", "float32_sub2_model", "float64_sub2_model"):
            part = "batched32" if key.startswith("float32") else "batched64"
            rms = np.load(out_dir / part / f"rms_{key}.npy")
            d = float(np.max(np.abs(rms - ref) / ref))
            merged[part]["batched"][key]["max_rel_rms_error_vs_float64_sub10"] = d
            print(f"accuracy of {key}: RMS-error metric within {d:.1e} (relative) of float64/10 substeps")
        (out_dir / "results.json").write_text(json.dumps(merged, indent=2) + "\n")
        return
    import jax

    if args.part != "batched32":
        jax.config.update("jax_enable_x64", True)
    out: dict = {"device": str(jax.devices()[0]), "cpu_count": __import__("os").cpu_count()}
    T = 1.0 if args.small else 10.0
    if args.part == "single":
        _single(out, T)
    elif args.part == "batched64":
        _batched(out, args.batch, 0.2 if args.small else 1.0,
                 [("float64", 10, "model"), ("float64", 2, "model"), ("float64", 2, "filtered")],
                 out_dir)
    else:
        _batched(out, args.batch, 0.2 if args.small else 1.0,
                 [("float32", 10, "model"), ("float32", 2, "model"), ("float32", 2, "filtered")],
                 out_dir)
    (out_dir / "results.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
