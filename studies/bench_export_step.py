"""How long does one step of the exported controller take in each back end?

Question: the compute time of one sample of the certified controller (``jaxflex export``,
``reproduce``'s default configuration: the paper's parameters with the observer leak, the
steady-state Kalman filter of the paper's sensing, q2d along the model), on the sensed
angles of a closed-loop run, in the three back ends of the one traced program: the Python
export on numpy float64 scalars (its IEEE variant), the same on plain Python floats and
``math`` (its fast path), and the C export (timed inside C, and called through ctypes as a
Python caller pays it). Each repeat runs every back end over the same samples, one after
the other in a rotating order (paired runs); per back end the median step of each repeat,
then the min and median over repeats, and the ratios to C within each repeat. The time to
trace and generate, and to compile the C, is stated apart.

The machine is shared: numbers are what it gave, not a guarantee.

    python studies/bench_export_step.py [--out out/bench_export_step] [--small]
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np

_DRIVER = r"""
#define _POSIX_C_SOURCE 199309L  /* clock_gettime under -std=c99 */
#include <time.h>
#include "controller.h"

/* Every step of a recorded run, each timed with CLOCK_MONOTONIC: dur[k] [s]. */
void bench_run(int N, const double *t, const double *q1, const double *q2, double *tau,
               double *dur, void *state)
{
    struct timespec a, b;
    int k;
    jaxflex_reset(state);
    for (k = 0; k < N; k++) {
        clock_gettime(CLOCK_MONOTONIC, &a);
        jaxflex_step(state, t[k], q1 + k * JAXFLEX_N_JOINTS, q2 + k * JAXFLEX_N_JOINTS,
                     tau + k * JAXFLEX_N_JOINTS);
        clock_gettime(CLOCK_MONOTONIC, &b);
        dur[k] = (double)(b.tv_sec - a.tv_sec) + 1e-9 * (double)(b.tv_nsec - a.tv_nsec);
    }
}

/* The cost of the two clock reads alone, per step [s] (subtracted from dur). */
double bench_clock_overhead(int N)
{
    struct timespec a, b;
    double total = 0.0;
    int k;
    for (k = 0; k < N; k++) {
        clock_gettime(CLOCK_MONOTONIC, &a);
        clock_gettime(CLOCK_MONOTONIC, &b);
        total += (double)(b.tv_sec - a.tv_sec) + 1e-9 * (double)(b.tv_nsec - a.tv_nsec);
    }
    return total / N;
}
"""


def _recorded_run(sc, mod, t_final: float):
    """Sensed angles and JAX torques of the controller's closed loop under its sensing."""
    from jaxflex.export import check_parity

    return check_parity(sc, mod, t_final=t_final, n_worst=1)


def _python_steps(mod, ieee: bool):
    """The exported module's step function (fast path, or the numpy float64 variant) and
    its initial state, as (step(S, t, q1, q2) -> (S, tau), S0 builder)."""
    ctrl = mod.Controller()
    flat = [x for k in mod.DEFAULT_PARAMS for x in ctrl.params[k]]
    if not ieee:
        return ctrl._step, ctrl._init, float
    closure = mod._derive_step(*flat)
    step = mod._make_step_ieee(*[np.float64(c) for c in closure])
    return step, ctrl._init, np.float64


def time_python(mod, ts, q1, q2, ieee: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per-step times [s] and torques of the Python export over the recorded samples."""
    step, init, conv = _python_steps(mod, ieee)
    N = ts.shape[0]
    dur = np.empty(N)
    tau = np.empty(N)
    S = tuple(conv(x) for x in init(float(ts[0]), float(q1[0]), float(q2[0])))
    args = [(conv(ts[k]), conv(q1[k]), conv(q2[k])) for k in range(N)]
    pc = time.perf_counter
    for k in range(N):
        a = pc()
        S, tk = step(S, *args[k])
        dur[k] = pc() - a
        tau[k] = tk
    return dur, tau


def time_ctypes(cmod, ts, q1, q2) -> tuple[np.ndarray, np.ndarray]:
    """Per-step times [s] of the C export called from Python through ctypes, one call a step."""
    ctrl = cmod.Controller()
    N = ts.shape[0]
    dur = np.empty(N)
    tau = np.empty(N)
    pc = time.perf_counter
    for k in range(N):
        t, a1, a2 = float(ts[k]), float(q1[k]), float(q2[k])
        a = pc()
        tau[k] = ctrl.step(t, a1, a2)
        dur[k] = pc() - a
    return dur, tau


class NativeBench:
    """The C export linked with a timing driver (``bench_run``), loaded through ctypes."""

    def __init__(self, folder: Path, cc: str):
        from jaxflex.export.cgen import C_FLAGS

        (folder / "bench_driver.c").write_text(_DRIVER)
        lib = folder / "libbench.so"
        t0 = time.perf_counter()
        subprocess.run([cc, *C_FLAGS, "-shared", "-fPIC", "-o", str(lib),
                        str(folder / "controller.c"), str(folder / "bench_driver.c"), "-lm"],
                       check=True, capture_output=True, text=True)
        self.compile_s = time.perf_counter() - t0
        self.lib = ctypes.CDLL(str(lib))
        self.lib.bench_clock_overhead.restype = ctypes.c_double
        self.lib.jaxflex_state_size.restype = ctypes.c_int
        self.state = ctypes.create_string_buffer(self.lib.jaxflex_state_size())

    def run(self, ts, q1, q2) -> tuple[np.ndarray, np.ndarray]:
        """Per-step times [s] (clock overhead subtracted) and torques."""
        N = ts.shape[0]
        dp = lambda a: a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
        ts, q1, q2 = (np.ascontiguousarray(a, dtype=float) for a in (ts, q1, q2))
        tau, dur = np.empty(N), np.empty(N)
        self.lib.bench_run(ctypes.c_int(N), dp(ts), dp(q1), dp(q2), dp(tau), dp(dur),
                           self.state)
        overhead = self.lib.bench_clock_overhead(ctypes.c_int(N))
        return dur - overhead, tau


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; writes results.json (and steps.png) to --out; returns the results."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench_export_step")
    ap.add_argument("--small", action="store_true", help="short runs (for the slow test)")
    ap.add_argument("--repeats", type=int, default=None, help="paired repeats (default 7)")
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.export import describe, generate_source, load_module, rig_controller, trace
    from jaxflex.export.cgen import C_FLAGS
    from jaxflex.export.native import export_c, find_cc, load_c
    from jaxflex.io.presets import REPRODUCE_LEAK, paper_params, paper_sensing, with_estimator

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    repeats = args.repeats or (3 if args.small else 7)
    t_final = 0.5 if args.small else 2.0

    p = paper_params().to_dict()
    p["gains"]["leak"] = [REPRODUCE_LEAK]
    sc = rig_controller(p, sensing=with_estimator(paper_sensing(), "kalman"))
    t0 = time.perf_counter()
    tr = trace(sc)
    t_trace = time.perf_counter() - t0
    t0 = time.perf_counter()
    src = generate_source(sc, traced=tr)
    t_python = time.perf_counter() - t0
    mod = load_module(src)
    t0 = time.perf_counter()
    export_c(sc, out / "controller.c", traced=tr)
    t_cgen = time.perf_counter() - t0
    cc = find_cc()
    native = NativeBench(out, cc) if cc else None
    cmod = load_c(out / "controller.c") if cc else None

    run = _recorded_run(sc, mod, t_final)
    ts = np.asarray(np.arange(run.tau_jax.shape[0]) * sc.controller.dt)
    q1, q2 = run.q1_meas[:, 0], run.q2_meas[:, 0]

    backends = {
        "numpy": lambda: time_python(mod, ts, q1, q2, ieee=True),
        "python": lambda: time_python(mod, ts, q1, q2, ieee=False),
    }
    if native is not None:
        backends["c"] = lambda: native.run(ts, q1, q2)
        backends["c_ctypes"] = lambda: time_ctypes(cmod, ts, q1, q2)
    names = list(backends)
    medians = {k: [] for k in names}
    agree = {}
    for rep in range(repeats + 1):  # the first round warms every back end and is dropped
        order = names[rep % len(names):] + names[:rep % len(names)]
        for name in order:
            dur, tau = backends[name]()
            if rep:
                medians[name].append(float(np.median(dur)))
            agree[name] = float(np.max(np.abs(tau - run.tau_jax[:, 0])))
    base = "c" if "c" in names else "python"
    stats = {}
    for name in names:
        m = np.array(medians[name])
        ratio = m / np.array(medians[base])
        stats[name] = {"min_us": float(m.min() * 1e6), "median_us": float(np.median(m) * 1e6),
                       f"ratio_to_{base}_min": float(ratio.min()),
                       f"ratio_to_{base}_median": float(np.median(ratio)),
                       "max_abs_diff_to_jax_Nm": agree[name]}
    res = {
        "question": __doc__.splitlines()[0],
        "controller": describe(sc), "q2d_method": sc.controller.q2d_method,
        "samples_per_run": int(ts.shape[0]), "paired_repeats": repeats,
        "statistic": "per back end: median step time of each repeat; min and median of those "
                     "over repeats; ratios to the baseline within each repeat",
        "baseline": base, "backends": stats,
        "setup_s": {"trace": t_trace, "generate_python": t_python, "generate_c": t_cgen,
                    "compile_c": native.compile_s if native else None},
        "c_compiler": cc, "c_flags": list(C_FLAGS),
        "machine": {"processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "python": platform.python_version()},
    }
    (out / "results.json").write_text(json.dumps(res, indent=2) + "\n")
    print(f"{res['controller']}; {res['samples_per_run']} samples x {repeats} paired repeats")
    print(f"{'back end':<10} {'min us':>9} {'median us':>10} {'x ' + base + ' (median)':>14}")
    for name in names:
        s = stats[name]
        print(f"{name:<10} {s['min_us']:>9.3f} {s['median_us']:>10.3f} "
              f"{s[f'ratio_to_{base}_median']:>14.1f}")
    st = res["setup_s"]
    print(f"apart: trace {st['trace']:.2f} s, generate Python {st['generate_python']:.2f} s, "
          f"generate C {st['generate_c']:.2f} s, compile C "
          + (f"{st['compile_c']:.2f} s" if st["compile_c"] is not None else "(no cc)"))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(5, 3))
        ax.bar(names, [stats[k]["median_us"] for k in names])
        ax.set_yscale("log")
        ax.set_ylabel("median step [us]")
        ax.set_title("one step of the exported controller")
        fig.tight_layout()
        fig.savefig(out / "steps.png", dpi=120)
        plt.close(fig)
    except ImportError:
        pass
    return res


if __name__ == "__main__":
    main()
