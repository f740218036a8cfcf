"""How fast is the exported controller, and does the hardware loop keep 1 kHz and 5 kHz here?

Question: per-step compute time (median, 99th percentile, max) of the standalone controller
written by ``jaxflex export`` for one joint, against the JAX controller called once per sample
(``jax.jit`` of ``CascadeController.step``, the baseline a researcher would otherwise run),
in the same process; and the deadline misses and wake-up lateness of ``jaxflex.app.hardware.
run_loop`` at 1 kHz and 5 kHz, with an in-process loopback rig (loop + controller only) and,
at 1 kHz, with the simulated rig (plant in a separate process).

The VM is not real-time and is shared: numbers are what this machine gave, not a guarantee.

    python studies/bench_export.py [--out out/bench_export] [--small]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np


def _stats(a: np.ndarray) -> dict[str, float]:
    return {"median_us": float(np.median(a) * 1e6), "p99_us": float(np.percentile(a, 99) * 1e6),
            "max_us": float(np.max(a) * 1e6)}


def bench_step(ctrl_factory, steps: int) -> np.ndarray:
    """Per-step wall time [s] of ``ctrl.step`` on a smooth synthetic measurement sequence."""
    ctrl = ctrl_factory()
    for k in range(5):  # warm-up (compilation of the JAX baseline, caches)
        ctrl.step(k * ctrl.dt, 0.0, 0.0)
    ctrl.reset()
    dt = ctrl.dt
    out = np.empty(steps)
    for k in range(steps):
        t = k * dt
        q1 = 0.05 * math.sin(math.pi * t)
        q2 = q1 + 0.01 * math.cos(3.0 * t)
        c0 = time.perf_counter()
        ctrl.step(t, q1, q2)
        out[k] = time.perf_counter() - c0
    return out


class _JaxStep:
    """The JAX controller called once per sample (jitted step), the baseline."""

    def __init__(self, controller):
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        self.c, self.dt = controller, controller.dt
        dyn, static = eqx.partition(controller, eqx.is_array)
        self._dyn = dyn
        self._step = jax.jit(lambda d, s, t, a, b: (lambda o: (o[0], o[1].tau))(
            eqx.combine(d, static).step(s, t, a, b)))
        self._jnp = jnp
        self.reset()

    def reset(self):
        self.st = None

    def step(self, t, q1, q2):
        a, b = np.array([q1]), np.array([q2])
        if self.st is None:
            self.st = self.c.init(t, a, b)
        self.st, tau = self._step(self._dyn, self.st, t, a, b)
        return float(tau[0])


class _Loopback:
    """In-process rig: returns a smooth trajectory, ignores torques (loop + controller only)."""

    n = 1

    def __init__(self, dt):
        self.k, self.dt = 0, dt

    def read(self):
        t = self.k * self.dt
        self.k += 1
        q1 = 0.05 * math.sin(math.pi * t)
        return np.array([q1]), np.array([q1 + 0.001])

    def write(self, tau):
        pass

    def close(self):
        pass


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench_export")
    ap.add_argument("--small", action="store_true", help="short runs (for the slow test)")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.export import build_controller, generate_source, load_module
    from jaxflex.app.hardware import LoopConfig, SimulatedRig, run_loop
    from jaxflex.io.presets import paper_params

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    steps = 2000 if args.small else 20000
    loop_s = 0.5 if args.small else 5.0
    results: dict = {"steps": steps, "compute": {}, "loop": {},
                     "load_average_at_start": list(os.getloadavg()), "cpu_count": os.cpu_count()}
    series = {}
    for traj in ("sinusoid", "polynomial"):
        for method in ("model", "filtered"):
            c = build_controller(paper_params(), traj, q2d_method=method)
            src = generate_source(c)
            mod = load_module(src)
            exp_t = bench_step(mod.Controller, steps)
            jax_t = bench_step(lambda: _JaxStep(c), max(steps // 10, 200))
            key = f"{traj}/{method}"
            series[key] = exp_t
            results["compute"][key] = {
                "export": _stats(exp_t), "jax_jit_step": _stats(jax_t),
                "speedup_median": float(np.median(jax_t) / np.median(exp_t)),
                "source_lines": len(src.splitlines()),
            }
            print(key, json.dumps(results["compute"][key]))
    for rate in (1000.0, 5000.0):
        c = build_controller(paper_params(), "sinusoid", dt=1.0 / rate)
        ctrl = load_module(generate_source(c)).Controller()
        r = run_loop(_Loopback(1.0 / rate), ctrl,
                     LoopConfig(rate=rate, duration=loop_s, max_consecutive_misses=10**9))
        results["loop"][f"loopback_{int(rate)}Hz"] = {
            "samples": r.samples, "misses": r.misses, "miss_fraction": r.misses / r.samples,
            "max_consecutive_misses": r.max_consecutive_misses, **r.timing_summary(),
        }
        series[f"lateness {int(rate)} Hz"] = r.lateness
        print(f"loopback {rate:.0f} Hz", json.dumps(results["loop"][f"loopback_{int(rate)}Hz"]))
    c = build_controller(paper_params(), "sinusoid")
    ctrl = load_module(generate_source(c)).Controller()
    res = 2 * math.pi / 2**16
    with SimulatedRig(paper_params(), c.dt, q1_0=ctrl.reference(0.0),
                      resolution=(res, res / 50)) as rig:
        r = run_loop(rig, ctrl, LoopConfig(rate=1000.0, duration=loop_s,
                                           max_consecutive_misses=10**9))
    e = r.q1 - r.q1d
    results["loop"]["simulated_rig_1000Hz"] = {
        "samples": r.samples, "misses": r.misses, "miss_fraction": r.misses / max(r.samples, 1),
        "max_consecutive_misses": r.max_consecutive_misses,
        "rms_tracking_error_rad": float(np.sqrt(np.mean(e**2))), **r.timing_summary(),
    }
    print("simulated rig 1000 Hz", json.dumps(results["loop"]["simulated_rig_1000Hz"]))
    results["load_average_at_end"] = list(os.getloadavg())
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axs = plt.subplots(1, 2, figsize=(11, 4))
        for k, v in series.items():
            if k.startswith("lateness"):
                axs[1].hist(np.asarray(v) * 1e6, bins=100, histtype="step", label=k, log=True)
            else:
                axs[0].hist(np.asarray(v) * 1e6, bins=np.logspace(0, 3, 120), histtype="step",
                            label=k, log=True)
        axs[0].set_xscale("log")
        axs[0].set_xlabel("exported controller step [us]")
        axs[1].set_xlabel("loop wake-up lateness [us]")
        for a in axs:
            a.legend(fontsize=8)
            a.set_ylabel("count")
        fig.tight_layout()
        fig.savefig(out / "bench_export.png", dpi=120)
    except ImportError:  # pragma: no cover
        pass
    return results


if __name__ == "__main__":
    main()
