"""Study: does ``jaxflex identify`` with its defaults recover the six LuGre parameters from a
closed-loop log made by a simulator it did not write, and how long does it take?

Question: a flexible joint (the paper's Table 1 plant with its Table 2 LuGre friction on the
link, eq. 3-6) runs under a PD law on the rotor encoder at 1 kHz (zero-order hold), reading
18-bit encoders on both sides; the log is made here by scipy's adaptive Dormand-Prince
(``solve_ivp``, DOP853, rtol 1e-10) on the equations as the paper writes them, with no
jaxflex code. From a start file with the plant known and the six LuGre parameters 40-70% off,
``jaxflex identify LOG --params START --out R`` is run exactly as a user types it (a fresh
process, its default free set, segments and substeps; the compilation cache given empty or
warm as stated). Does it converge, how far is each LuGre parameter from the truth (relative
error and in its own standard errors), and how long does the whole command take, for a 20 s
and a 60 s log?

Writes ``DIR/results.json`` (the truth, the start, per log: wall time, exit code, verdict,
per-parameter values, relative errors and standard errors, machine load and BLAS threads) and
``DIR/ident_independent.png`` (relative error per parameter and log).

Three logs: 20 s and 60 s with the true angles quantised, and 20 s with a count of white noise
added before the quantisation. ``--variants`` adds two logs of the same simulator with another
rate, plant, friction and loop (``SETUPS``): the paper's plant at 250 Hz (20 s), and a
lighter, stiffer-bristled joint with a narrower Stribeck hump at 2 kHz under other PD gains and
17-bit encoders (10 s); each has its own start file, its LuGre parameters off by the same
factors. Usage: ``python studies/ident_independent.py --out DIR [--small] [--variants]
[--cold]``; ``--small`` runs the 20 s logs only, ``--cold`` gives each command an empty
compilation cache.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchkit  # noqa: E402

BLAS = benchkit.limit_blas_threads(1)

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402

#: Table 1 (I, J [kg m^2], K [N m/rad]) and Table 2 with the correction of docs/spec.md (LuGre).
PLANT: dict[str, float] = {"I": 0.07, "J": 0.005, "K": 6.77}
TRUTH: dict[str, float] = {"Fc": 0.11, "Fs": 0.15, "vs": 0.05, "sigma0": 100.0,
                           "sigma1": 0.1, "sigma2": 0.2}
#: The start: each LuGre parameter this factor off its truth (40-70% off, Fs >= Fc kept).
START_FACTORS: dict[str, float] = {"Fc": 0.5, "Fs": 1.6, "vs": 1.7, "sigma0": 0.4,
                                   "sigma1": 1.5, "sigma2": 0.55}
#: Sample period [s], PD gains on the rotor [N m/rad, N m s/rad], encoder counts per turn.
DT: float = 1e-3
KP: float = 20.0
KD: float = 0.6
COUNTS: int = 2**18
#: The reference q1d(t) [rad]: three sines, amplitudes [rad] and frequencies [Hz].
REFERENCE: tuple[tuple[float, float], ...] = ((0.8, 0.3), (0.3, 1.1), (0.1, 2.7))


@dataclasses.dataclass(frozen=True)
class Setup:
    """One simulated rig: the plant (I, J [kg m^2], K [N m/rad]), the true LuGre parameters,
    the sample period ``dt`` [s], the PD gains on the rotor ``kp`` [N m/rad] and ``kd``
    [N m s/rad], and the encoders' counts per turn."""

    name: str
    plant: dict[str, float]
    truth: dict[str, float]
    dt: float
    kp: float
    kd: float
    counts: int


PAPER = Setup("paper", PLANT, TRUTH, DT, KP, KD, COUNTS)
#: The study's rigs (``--variants`` adds all but the paper's).
SETUPS: dict[str, Setup] = {s.name: s for s in (
    PAPER,
    dataclasses.replace(PAPER, name="paper_250hz", dt=4e-3),
    Setup("stiff_2khz", {"I": 0.15, "J": 0.01, "K": 20.0},
          {"Fc": 0.3, "Fs": 0.4, "vs": 0.02, "sigma0": 500.0, "sigma1": 0.5, "sigma2": 0.05},
          5e-4, 30.0, 1.0, 2**17),
)}


def reference(t: np.ndarray | float) -> tuple[Any, Any]:
    """The reference angle [rad] and rate [rad/s] at time ``t`` [s]."""
    q = sum(a * np.sin(2 * np.pi * f * t) for a, f in REFERENCE)
    dq = sum(a * 2 * np.pi * f * np.cos(2 * np.pi * f * t) for a, f in REFERENCE)
    return q, dq


def rhs(_t: float, x: np.ndarray, tau: float, setup: Setup = PAPER) -> np.ndarray:
    """The flexible joint with LuGre friction on the link (eq. 3-6): x = q1, q1', q2, q2', z."""
    q1, v1, q2, v2, z = x
    f, p = setup.truth, setup.plant
    g = f["Fc"] + (f["Fs"] - f["Fc"]) * np.exp(-(v1 / f["vs"]) ** 2)
    dz = v1 - f["sigma0"] * abs(v1) / g * z
    friction = f["sigma0"] * z + f["sigma1"] * dz + f["sigma2"] * v1
    spring = p["K"] * (q2 - q1)
    return np.array([v1, (spring - friction) / p["I"], v2, (tau - spring) / p["J"], dz])


def quantise(q: float, counts: int = COUNTS) -> float:
    """An encoder reading [rad] of ``counts`` counts per turn."""
    step = 2 * np.pi / counts
    return float(np.floor(q / step + 0.5) * step)


def simulate(duration: float, noise_counts: float = 0.0, seed: int = 0,
             setup: Setup = PAPER) -> dict[str, np.ndarray]:
    """The closed loop of ``setup`` for ``duration`` seconds: PD on the rotor encoder, the
    velocity by a backward difference of its readings, torque held over each sample.
    ``noise_counts``: white Gaussian noise of this many encoder counts (std) added to each
    angle before it is quantised (``seed`` its generator); 0: the readings are the true angles
    quantised."""
    rng = np.random.default_rng(seed)
    dt = setup.dt
    noise = noise_counts * 2 * np.pi / setup.counts
    n = int(round(duration / dt))
    x = np.zeros(5)
    t = np.arange(n) * dt
    log = {"t": t, "tau": np.zeros(n), "q1": np.zeros(n), "q2": np.zeros(n)}
    prev = 0.0
    for k in range(n):
        n1, n2 = rng.normal(0.0, noise, 2) if noise else (0.0, 0.0)
        q1m, q2m = quantise(x[0] + n1, setup.counts), quantise(x[2] + n2, setup.counts)
        dq2m = (q2m - prev) / dt if k else 0.0
        prev = q2m
        qd, dqd = reference(t[k])
        tau = setup.kp * (qd - q2m) + setup.kd * (dqd - dq2m)
        log["tau"][k], log["q1"][k], log["q2"][k] = tau, q1m, q2m
        sol = solve_ivp(rhs, (0.0, dt), x, method="DOP853", rtol=1e-10, atol=1e-12,
                        args=(tau, setup))
        x = sol.y[:, -1]
    return log


def start_values(setup: Setup = PAPER) -> dict[str, Any]:
    """The start parameters: ``setup``'s plant known, its LuGre parameters off by
    ``START_FACTORS``."""
    return {"plant": dict(setup.plant),
            "friction": {k: v * START_FACTORS[k] for k, v in setup.truth.items()}}


def log_and_start(duration: float, noise_counts: float = 0.0, setup: Setup = PAPER,
                  ) -> tuple[Any, Any]:
    """The closed loop's log (``simulate``) as a ``jaxflex.io.logs.Log`` and the start file's
    parameters (``start_values``) as ``jaxflex.io.params.Params``, for in-process use."""
    from jaxflex.io.logs import Log
    from jaxflex.io.params import Params

    arrays = simulate(duration, noise_counts, setup=setup)
    log = Log.from_arrays(**{k: arrays[k] for k in ("t", "tau", "q1", "q2")})
    return log, Params.from_dict(start_values(setup))


def write_log(log: dict[str, np.ndarray], path: Path) -> None:
    """The log as a CSV file with the columns of docs/spec.md section 6."""
    cols = ["t", "tau", "q1", "q2"]
    np.savetxt(path, np.column_stack([log[c] for c in cols]), delimiter=",",
               header=",".join(cols), comments="", fmt="%.17g")


def start_file(path: Path, setup: Setup = PAPER) -> dict[str, Any]:
    """The start parameter file (``start_values``)."""
    start = start_values(setup)
    path.write_text(json.dumps(start, indent=1))
    return start


def run_identify(log: Path, start: Path, out: Path, cache: str | None) -> dict[str, Any]:
    """``jaxflex identify LOG --params START --out OUT`` in a fresh process, timed."""
    env = dict(os.environ)
    if cache is not None:
        env["JAXFLEX_CACHE_DIR"] = cache
    cmd = [sys.executable, "-m", "jaxflex", "identify", str(log), "--params", str(start),
           "--out", str(out), "--quiet", "--force"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    return {"command": " ".join(cmd[2:]), "wall_s": wall, "exit": proc.returncode,
            "stderr_tail": proc.stderr[-2000:]}


def judge(result_path: Path, truth: dict[str, float] = TRUTH) -> dict[str, Any]:
    """Per LuGre parameter: the identified value, its relative error and its standard errors
    against ``truth``."""
    res = json.loads(result_path.read_text())
    ident = res["identification"]
    fitted = res["friction"]
    stderr = res.get("stderr", {})
    out: dict[str, Any] = {"verdict": {k: ident.get(k) for k in
                                       ("solver", "model", "converged", "substeps",
                                        "steps") if k in ident}}
    for k, true in truth.items():
        value = float(np.ravel(fitted[k])[0])
        se = stderr.get(k)
        se = None if se is None else float(np.ravel(se)[0])
        out[k] = {"value": value, "rel_error_pct": 100 * (value - true) / true,
                  "stderr": se, "in_stderr": None if not se else (value - true) / se}
    out["max_abs_rel_error_pct"] = max(abs(out[k]["rel_error_pct"]) for k in truth)
    out["max_abs_in_stderr"] = max((abs(out[k]["in_stderr"]) for k in truth
                                    if out[k]["in_stderr"] is not None), default=float("nan"))
    return out


def figure(results: dict[str, Any], path: Path) -> None:
    """Relative error per LuGre parameter, one bar group per log."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    logs = [k for k in results["logs"] if "judged" in results["logs"][k]]
    fig, ax = plt.subplots(figsize=(7, 3.5))
    width = 0.8 / max(len(logs), 1)
    for i, name in enumerate(logs):
        errs = [results["logs"][name]["judged"][k]["rel_error_pct"] for k in TRUTH]
        ax.bar(np.arange(len(TRUTH)) + i * width, errs, width, label=name)
    ax.axhline(2, color="k", lw=0.5, ls="--")
    ax.axhline(-2, color="k", lw=0.5, ls="--")
    ax.set_xticks(np.arange(len(TRUTH)) + 0.4 - width / 2, list(TRUTH))
    ax.set_ylabel("relative error [%]")
    ax.set_title("jaxflex identify on an independent simulator's closed-loop log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Run the study; returns and writes the results (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder")
    ap.add_argument("--small", action="store_true", help="the 20 s logs only")
    ap.add_argument("--variants", action="store_true",
                    help="also the other rigs of SETUPS (another rate, plant and loop)")
    ap.add_argument("--cold", action="store_true", help="an empty compilation cache per run")
    args = ap.parse_args(argv)
    if not args.out.is_dir():
        raise SystemExit(f"ident_independent: output folder {args.out} does not exist")
    #: (name, rig, duration [s], encoder noise [counts]): the readings quantised, and
    #: quantised after a count of white noise (dithered: the quantisation error no longer
    #: follows the motion, the noise is larger)
    runs = [("20s", PAPER, 20.0, 0.0), ("20s_noisy", PAPER, 20.0, 1.0)] + (
        [] if args.small else [("60s", PAPER, 60.0, 0.0)]) + (
        [("250hz_20s", SETUPS["paper_250hz"], 20.0, 0.0),
         ("stiff_2khz_10s", SETUPS["stiff_2khz"], 10.0, 0.0)] if args.variants else [])
    rigs = {setup.name: setup for _, setup, _, _ in runs}
    # each rig's start file: the paper's as start.json, the others by their names
    start_paths = {name: args.out / ("start.json" if setup is PAPER else f"start_{name}.json")
                   for name, setup in rigs.items()}
    starts = {name: start_file(start_paths[name], setup) for name, setup in rigs.items()}
    results: dict[str, Any] = {
        "truth": {"plant": PLANT, "friction": TRUTH},
        "start": starts[PAPER.name],
        "simulator": {"method": "scipy solve_ivp DOP853", "rtol": 1e-10, "atol": 1e-12,
                      "controller": "PD on the rotor encoder, backward-difference velocity",
                      "reference": REFERENCE},
        "setups": {name: dataclasses.asdict(setup) for name, setup in rigs.items()},
        "blas": BLAS, "cold_cache": args.cold, "logs": {},
    }
    for name, setup, duration, noise_counts in runs:
        log_path = args.out / f"log_{name}.csv"
        if not log_path.exists():
            t0 = time.perf_counter()
            write_log(simulate(duration, noise_counts, setup=setup), log_path)
            print(f"{name}: simulated in {time.perf_counter() - t0:.1f} s", flush=True)
        entry: dict[str, Any] = {"setup": setup.name, "machine_before": benchkit.machine_state()}
        with tempfile.TemporaryDirectory() as cache:
            entry["run"] = run_identify(log_path, start_paths[setup.name],
                                        args.out / f"identified_{name}.json",
                                        cache if args.cold else None)
        entry["machine_after"] = benchkit.machine_state()
        if (args.out / f"identified_{name}.json").exists():
            entry["judged"] = judge(args.out / f"identified_{name}.json", setup.truth)
        entry["noise_counts"] = noise_counts
        results["logs"][name] = entry
        j = entry.get("judged", {})
        print(f"{name}: {entry['run']['wall_s']:.1f} s wall, exit {entry['run']['exit']}, "
              f"max |rel error| {j.get('max_abs_rel_error_pct', float('nan')):.2f}%, "
              f"max |error| {j.get('max_abs_in_stderr', float('nan')):.2f} stderr", flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    figure(results, args.out / "ident_independent.png")
    return results


if __name__ == "__main__":
    main()
