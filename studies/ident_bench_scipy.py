"""Benchmark: is gradient identification through the JAX simulator faster than scipy?

Question: on the same least-squares residual (``Problem.residuals``: the
multiple-shooting output error of a flexible-joint log, residuals in units of the log's
encoder noise, all six LuGre parameters free plus the segment start states), from the same
start, through the same stages, with the same tolerances and iteration caps, in the same
process, how long do

- optimistix Levenberg-Marquardt (jitted, Jacobian by forward-mode autodiff through the
  ``lax.scan`` simulator using the multiple-shooting block sparsity, damped normal equations
  by Cholesky, geodesic acceleration ``GEODESIC`` and the statistical stop at a Gauss-Newton
  decrement below ``DECREMENT_TOL`` chi-square; exactly ``jaxflex.identify``'s solver), and
- ``scipy.optimize.least_squares`` (method "trf", dense 2-point finite-difference Jacobian,
  one BLAS thread; the residual itself jitted JAX, so that only the optimiser and the
  Jacobian differ)

take, and to what final cost 0.5 ||r||^2 and parameter errors?

Logs (``--log``):

- ``closed-loop`` (default; the target logs): ``jaxflex.identify.datagen.generate_log((),
  seed=--seed, t_final=T, bits=20, noise_counts=0.5)``: the cascade controller tracking a
  multisine, a 20-bit link encoder (rotor 50x finer) with half a count of white noise, 1 kHz.
  Initial guess: the six LuGre parameters 50% off (``--factors``, default
  1.5,1.5,0.5,1.5,0.5,1.5). The common start is the one ``identify`` itself takes: Fc, Fs,
  vs, sigma2 from the static friction map of the log (``start_from_static_map``; sigma0,
  sigma1 stay at the guess), computed once before any timing and given to both solvers.
  Segments of ``--segment`` samples (default 500, the ``jaxflex identify`` command's).
  Substeps and warm-start schedule (``--substeps``, ``--warm-factor auto``): taken from
  ``identify(..., substeps="auto")`` on this log, run once per log in a child process (so
  that none of its compilations is cached in this one), untimed, its choice recorded:
  ``first`` (default): its first choice (``choose_substeps``: the fewest substeps whose
  replay error is below ``OUTPUT_TOL`` of the noise; where identify takes almost all of its
  solver steps), fixed throughout; ``final``: its final, refined choice (where the integrator
  moves no fitted parameter by more than ``BIAS_TOL`` standard errors), fixed throughout;
  ``path``: identify's own path, coarse to fine (the warm and full stages at the first
  choice, then the full stage again at each refined level it went through, each from the
  previous solution, as ``refine_fit`` does); a number: fixed at that. The warm factor is
  that of identify's winning schedule on the log (or ``--warm-factor``).
- ``open-loop`` (the earlier benchmark): ``synthetic_log`` of a torque excitation, a 16-bit
  link encoder with white noise (``--seed``: the noise key), start every parameter up to 2x
  off (default factors 2,0.6,2,0.5,2,0.5), segments of 300 samples, 2 substeps, warm factor
  1e-3. On its 10 s log both solvers stopped in local minima far above the noise, so no
  speed ratio there was a result.

Stages (both solvers): at most ``WARM_STEPS`` iterations with the continuity weight times
the warm factor, then at most ``MAX_STEPS`` with the full weight (again at each finer level
with ``--substeps path``); JAX: ``max_steps``, scipy: ``max_nfev``, which for "trf" does not
count the finite-difference evaluations. Tolerances: ``--tol`` (default 1e-8) for
optimistix's rtol/atol and scipy's ftol/xtol/gtol; JAX also has identify's statistical stop,
which scipy lacks, so scipy may go on to a cost lower by a negligible amount (``scipy``
``s_to_jax_cost_all``: when each scipy run first evaluated a point at JAX's final cost, and
``speed_ratio_scipy_to_jax_cost``, its median over JAX's: scipy stopped by an oracle).
Timed: the solve only (no covariance, no static start, no log generation, no compilation of
scipy's jitted residual).

Validity: the residuals are in units of the noise, so 2 (cost_jax - cost_scipy) is a
chi-square difference; the final costs count as equal when it is at most ``CHI2_EQUAL`` in
magnitude. Only then are speed ratios reported (``equal_cost``; otherwise the ratio fields
are null and ``comparison`` says why; the times stay recorded).

Reported per log length (default 3 s and 10 s: the targets are 10x warm at equal or lower
cost, and faster than scipy including JAX's compilation from 10 s on): wall times [s] of
each solver (JAX warm, and its first, cold call including compilation: one sample per
length; the compilation estimate is that minus the warm median), CPU times [s] of this
process over the same runs, final costs (0.5 ||r||^2, noise units) and the cost the noise
explains (``noise_cost``), the chi-square difference, iterations (JAX steps; scipy nfev and
njev, i.e. finite-difference Jacobians, per stage) and residual evaluations, relative
parameter errors against the truth (value / true - 1), and the ratios scipy / JAX of the
wall times (min over min, median over median, scipy min over JAX's cold call). Timing habits
(``benchkit``): BLAS limited to one thread (threadpoolctl when installed, else the
environment variables, set before numpy is imported; what was in force is recorded), the
two solvers take turns in paired rounds (``benchkit.paired``; ``--scipy-repeat`` caps
scipy's rounds where one run takes many minutes), min and median of each, the load average
at start and end of each length; jaxflex's ``LEAN_XLA_CPU_FLAGS`` as the ``jaxflex``
command sets them (``--no-lean-xla``: XLA's defaults; ``XLA_FLAGS`` recorded). JAX's
backend starts before any timing (the log is simulated with it); several lengths share one
process, so a later length's cold call may find a little tracing already cached.

Usage: ``python studies/ident_bench_scipy.py [--out DIR] [--small] [--log closed-loop|open-loop]
[--t-final 3,10] [--repeat 3] [--scipy-repeat N] [--substeps first|final|path|N]
[--warm-factor auto|F]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchkit  # noqa: E402

BLAS = benchkit.limit_blas_threads(1)

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

#: Final costs count as equal when |2 (cost_jax - cost_scipy)| (chi-square, the residuals
#: being in noise units) is at most this: well below the 1 that one standard error in one
#: direction costs, so the data cannot tell the two fits apart.
CHI2_EQUAL: float = 0.1
#: Iteration caps of the two stages (those of ``identify``: warm_steps, max_steps).
WARM_STEPS: int = 40
MAX_STEPS: int = 200
#: The closed-loop logs (the targets): encoder bits and white noise in counts.
BITS: int = 20
NOISE_COUNTS: float = 0.5
#: --substeps values taken from ``identify(substeps="auto")`` on the log (``identify_choice``)
IDENTIFY_SUBSTEPS: tuple[str, ...] = ("first", "final", "path")
DEFAULTS: dict[str, dict[str, Any]] = {
    "closed-loop": {"seed": 7, "segment": 500, "factors": "1.5,1.5,0.5,1.5,0.5,1.5"},
    "open-loop": {"seed": 0, "segment": 300, "factors": "2.0,0.6,2.0,0.5,2.0,0.5"},
}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """The command line (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/ident_bench_scipy")
    ap.add_argument("--small", action="store_true",
                    help="1 s log, segments of 250 samples, 2 substeps, warm factor 1e-2 "
                         "(closed loop; no identify run), 2 repeats: a quick check")
    ap.add_argument("--log", choices=tuple(DEFAULTS), default="closed-loop",
                    help="closed-loop: datagen logs (the targets, static-map start); "
                         "open-loop: the earlier synthetic torque log (2x-off start)")
    ap.add_argument("--seed", type=int, default=None,
                    help="closed-loop: the datagen seed (default 7); open-loop: the sensor-"
                         "noise key (default 0)")
    ap.add_argument("--t-final", default="3,10",
                    help="log length(s) [s], comma-separated: each is benchmarked in turn; "
                         "results.json holds the first at the top level and every length "
                         "under 'lengths' (10 s and longer: is JAX faster than scipy including "
                         "its compilation?)")
    ap.add_argument("--segment", type=int, default=None,
                    help="samples per shooting segment (default 500 closed-loop, 300 open-loop)")
    ap.add_argument("--substeps", default="first",
                    help="closed-loop: integrator substeps per sample: 'first' (identify's "
                         "first choice on the log, where it takes most of its steps), 'final' "
                         "(its final, refined choice), each fixed throughout; 'path' "
                         "(identify's levels coarse to fine); or a number (open-loop: 2 "
                         "unless a number)")
    ap.add_argument("--warm-factor", default="auto",
                    help="continuity-weight factor of the warm stage: 'auto' (closed-loop: "
                         "identify's winning schedule on the log; open-loop 1e-3) or a number")
    ap.add_argument("--repeat", type=int, default=None,
                    help="timed repeats of each solver (default 3; --small 2)")
    ap.add_argument("--scipy-repeat", type=int, default=None,
                    help="at most this many of the paired rounds run scipy (default: all; "
                         "for logs where one scipy run takes many minutes)")
    ap.add_argument("--tol", type=float, default=1e-8,
                    help="rtol/atol (JAX) and ftol/xtol/gtol (scipy)")
    ap.add_argument("--factors", default=None,
                    help="the initial guess: factors on the true Fc, Fs, vs, sigma0, sigma1, "
                         "sigma2 (default closed-loop 1.5,1.5,0.5,1.5,0.5,1.5, 50%% off as "
                         "the closed-loop target; open-loop 2,0.6,2,0.5,2,0.5 as the acceptance "
                         "test)")
    ap.add_argument("--no-lean-xla", action="store_true",
                    help="keep XLA's default CPU options (otherwise LEAN_XLA_CPU_FLAGS)")
    ap.add_argument("--identify-choice", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    d = DEFAULTS[args.log]
    args.seed = d["seed"] if args.seed is None else args.seed
    args.segment = (250 if args.small else d["segment"]) if args.segment is None else args.segment
    args.factors = d["factors"] if args.factors is None else args.factors
    args.repeat = (2 if args.small else 3) if args.repeat is None else args.repeat
    if args.small and args.log == "closed-loop":
        args.substeps = "2" if args.substeps in IDENTIFY_SUBSTEPS else args.substeps
        args.warm_factor = "1e-2" if args.warm_factor == "auto" else args.warm_factor
    return args


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; returns the results dict (also written to ``results.json``)."""
    args = parse_args(argv)
    from jaxflex.runtime.xla import use_lean_xla_cpu

    if not args.no_lean_xla:
        use_lean_xla_cpu()  # as the jaxflex command does, before any JAX computation
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.identify_choice is not None:  # the child process of ``identify_choice``
        print(json.dumps(_identify_choice_here(**json.loads(args.identify_choice))))
        return {}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lengths = [1.0] if args.small else [float(x) for x in args.t_final.split(",")]
    runs = [bench_length(t, args) for t in lengths]
    results = dict(runs[0])
    results["lengths"] = {f"{r['log_s']:g}": summary(r) for r in runs}
    print(json.dumps(results["lengths"], indent=2))
    print_table(runs)
    (out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    return results


def summary(r: dict[str, Any]) -> dict[str, Any]:
    """The per-length digest of one ``bench_length`` result (``results.json['lengths']``)."""
    keys = ("log", "unknowns", "residuals", "substeps", "warm_factor", "equal_cost",
            "comparison", "chi2_jax_minus_scipy", "speed_ratio_warm", "speed_ratio_warm_median",
            "speed_ratio_with_compile", "speed_ratio_scipy_to_jax_cost",
            "jax_compile_s_estimate", "cost_ratio_jax_over_scipy", "noise_cost")
    jx, sp = r["jax"], r["scipy"]
    return {k: r[k] for k in keys} | {
        "jax_wall_s": jx["wall_s"], "jax_wall_s_median": jx["wall_s_median"],
        "jax_wall_s_with_compile": jx["wall_s_with_compile"], "jax_cost": jx["cost"],
        "jax_steps": jx["steps"], "jax_converged": jx["converged"],
        "jax_max_abs_rel_error": max(abs(v) for v in jx["rel_error"].values()),
        "scipy_wall_s": sp["wall_s"], "scipy_wall_s_median": sp["wall_s_median"],
        "scipy_cost": sp["cost"], "scipy_nfev": sp["nfev"], "scipy_njev": sp["njev"],
        "scipy_status": sp["status"],
        "scipy_max_abs_rel_error": max(abs(v) for v in sp["rel_error"].values()),
        "load_avg_start": r["machine_start"]["load_avg"],
        "load_avg_end": r["machine_end"]["load_avg"]}


def print_table(runs: list[dict[str, Any]]) -> None:
    """One line per log length: times, costs, chi-square difference, ratios (or why none)."""
    print(f"{'T [s]':>6} {'S':>7} {'JAX warm min/med [s]':>21} {'JAX+compile':>11} "
          f"{'scipy min/med [s]':>19} {'cost JAX':>13} {'cost scipy':>13} {'dchi2':>9} "
          f"{'JAX steps':>12} {'scipy nfev/njev':>17} {'load 1 min':>11}  "
          f"ratio warm (min, med), incl. compile")
    for r in runs:
        jx, sp = r["jax"], r["scipy"]
        ratio = (f"{r['speed_ratio_warm']:.1f}x, {r['speed_ratio_warm_median']:.1f}x, "
                 f"{r['speed_ratio_with_compile']:.2f}x" if r["equal_cost"]
                 else f"none: {r['comparison']}")
        load = f"{r['machine_start']['load_avg'][0]:.1f}-{r['machine_end']['load_avg'][0]:.1f}"
        print(f"{r['log_s']:>6g} {'>'.join(map(str, r['substeps'])):>7} "
              f"{jx['wall_s']:>10.3g}/{jx['wall_s_median']:<10.3g} "
              f"{jx['wall_s_with_compile']:>11.3g} "
              f"{sp['wall_s']:>9.3g}/{sp['wall_s_median']:<9.3g} "
              f"{jx['cost']:>13.7g} {sp['cost']:>13.7g} {r['chi2_jax_minus_scipy']:>9.2g} "
              f"{_plus(jx['steps']):>12} {_plus(sp['nfev']) + '/' + _plus(sp['njev']):>17} "
              f"{load:>11}  {ratio}")
    pools = [p.get("num_threads") for p in BLAS.get("pools", [])]
    print(f"BLAS threads {BLAS['env']['OPENBLAS_NUM_THREADS']} (threadpoolctl "
          f"{BLAS['threadpoolctl']}, pools {pools})")


def _plus(xs: list[int]) -> str:
    """Per-stage counts joined by '+'."""
    return "+".join(map(str, xs))


class Setup:
    """One benchmark problem: the log's ``truth`` (Params), the ``probs``: the problem at
    each substeps level solved in turn (one, or identify's path coarse to fine), the common
    ``start`` (unknowns), the warm stage's factor, a record of how they were chosen
    (``choice``) and the cost the noise explains (``noise_cost``, at the last level). A plain
    class: the test loads this file without registering it as a module, which dataclasses
    need."""

    def __init__(self, truth: Any, probs: list[Any], start: Any, warm_factor: float,
                 choice: dict[str, Any], noise_cost: float) -> None:
        self.truth, self.probs, self.start = truth, probs, start
        self.warm_factor, self.choice, self.noise_cost = warm_factor, choice, noise_cost


def setup_open_loop(t_final: float, args: argparse.Namespace) -> Setup:
    """The earlier benchmark's log: open-loop torque excitation, 16-bit encoder, noise key
    ``args.seed``; start ``args.factors`` x the truth; 2 substeps unless given."""
    import jax

    from jaxflex.identify import (DEFAULT_FREE, excitation_torque, make_problem, noise_cost,
                                  perturb, synthetic_log)
    from jaxflex.io.presets import paper_params
    from jaxflex.core.sensing import Sensing

    truth = paper_params()
    res = 2 * math.pi / 2**16
    sensing = Sensing(q1_resolution=res, q2_resolution=res / 50, q1_noise=2e-5, q2_noise=1e-6)
    log, _ = synthetic_log(truth.to_plant(), excitation_torque(t_final=t_final,
                                                              periods=(1.5, 0.7)),
                           substeps=2, sensing=sensing, key=jax.random.PRNGKey(args.seed))
    init = perturb(truth, DEFAULT_FREE, _factors(args))
    S = int(args.substeps) if args.substeps.isdigit() else 2
    prob, y0 = make_problem(log, init, DEFAULT_FREE, segment_length=args.segment, substeps=S)
    wf = 1e-3 if args.warm_factor == "auto" else float(args.warm_factor)
    return Setup(truth, [prob], y0, wf, {"start": "the initial guess", "substeps": [S]},
                 noise_cost(log, prob))


def setup_closed_loop(t_final: float, args: argparse.Namespace) -> Setup:
    """The log: ``generate_log((), seed, t_final, bits=20, noise_counts=0.5)``; initial
    guess ``args.factors`` x the truth; the common start from the log's static map, as
    ``identify`` takes it; substeps and warm factor given or identify's (``identify_choice``)."""
    from jaxflex.identify.datagen import generate_log
    from jaxflex.fit import get_value, refined
    from jaxflex.identify import DEFAULT_FREE, make_problem, noise_cost, perturb
    from jaxflex.identify.static import start_from_static_map
    from jaxflex.io.params import Params

    g = generate_log((), seed=args.seed, t_final=t_final, bits=BITS, noise_counts=NOISE_COUNTS)
    truth = Params.from_dict(g.truth["plant"])
    init = perturb(truth, DEFAULT_FREE, _factors(args))
    choice: dict[str, Any] = {}
    if args.substeps in IDENTIFY_SUBSTEPS or args.warm_factor == "auto":
        choice["identify"] = identify_choice(t_final, args)
    ident = choice.get("identify", {})
    if args.substeps in IDENTIFY_SUBSTEPS:
        path = [int(x) for x in ident["substeps_path"]]
        levels = {"first": path[:1], "final": path[-1:], "path": path}[args.substeps]
        choice["substeps_from"] = (f"identify(substeps='auto'): its {args.substeps} "
                                   f"{'levels' if args.substeps == 'path' else 'choice'}")
    else:
        levels, choice["substeps_from"] = [int(args.substeps)], "given"
    if args.warm_factor == "auto":
        wf = ident["warm_factor"]
        choice["warm_factor_from"] = "identify's winning schedule on this log"
        if wf is None:
            raise SystemExit("identify's winning schedule has no warm stage: give --warm-factor")
    else:
        wf, choice["warm_factor_from"] = float(args.warm_factor), "given"
    start = start_from_static_map(g.log, init, DEFAULT_FREE)
    if start is None:
        raise SystemExit("the log's static map gives no start (identify would start from the "
                         "guess); give another log")
    prob, y0 = make_problem(g.log, init, DEFAULT_FREE, segment_length=args.segment,
                            substeps=levels[0])
    th = prob.space.theta_of({**{k: get_value(init, k) for k in prob.space.names}, **start})
    choice.update(start="static map of the log (start_from_static_map), as identify's first",
                  static_start={k: [float(x) for x in v] for k, v in start.items()},
                  substeps=levels)
    probs = [prob] + [refined(prob, S // levels[0]) for S in levels[1:]]
    return Setup(truth, probs, (th, y0[1]), float(wf), choice, noise_cost(g.log, probs[-1]))


def identify_choice(t_final: float, args: argparse.Namespace) -> dict[str, Any]:
    """What ``identify(..., substeps="auto")`` chooses on the closed-loop log of ``t_final``
    seconds (``_identify_choice_here``), run in a child process so that none of its
    compilations is cached in this one (the benchmark's JAX compilation stays cold)."""
    arg = json.dumps({"t_final": t_final, "seed": args.seed, "segment": args.segment,
                      "factors": list(_factors(args))})
    cmd = [sys.executable, str(Path(__file__).resolve()), "--identify-choice", arg]
    if args.no_lean_xla:
        cmd.append("--no-lean-xla")
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
    if r.returncode != 0:
        raise SystemExit(f"identify's choice failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    out = json.loads(r.stdout.strip().splitlines()[-1])
    out["child_process_wall_s"] = time.perf_counter() - t
    print(f"[{t_final:g} s] identify(substeps='auto'): substeps {out['substeps_first']} -> "
          f"{out['substeps_final']}, winning warm factor {out['warm_factor']}, converged "
          f"{out['converged']}, cost {out['cost']:.6g}, {out['wall_s_incl_compile']:.1f} s "
          f"(incl. compile, in a fresh process)", flush=True)
    return out


def _identify_choice_here(t_final: float, seed: int, segment: int,
                          factors: list[float]) -> dict[str, Any]:
    """``identify_choice`` in this process: identify's first and final substeps, the warm
    factor and start of its winning schedule, its outcome and wall time (incl. compilation)."""
    from jaxflex.identify.datagen import generate_log
    from jaxflex.identify import DEFAULT_FREE, IdentificationWarning, identify, perturb
    from jaxflex.io.params import Params

    g = generate_log((), seed=seed, t_final=t_final, bits=BITS, noise_counts=NOISE_COUNTS)
    truth = Params.from_dict(g.truth["plant"])
    init = perturb(truth, DEFAULT_FREE, tuple(factors))
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        r = identify(g.log, init, DEFAULT_FREE, segment_length=segment, substeps="auto")
    wall = time.perf_counter() - t
    tried = [a for a in r.attempts if "warm_start" in a and "start" in a]
    best = min(tried, key=lambda a: a["cost"])
    d = r.discretisation
    return {"substeps_first": int(d["first"]["substeps"]), "substeps_final": int(d["substeps"]),
            "substeps_path": [int(c["substeps"]) for c in d["checks"]],
            "bias_se": float(d["bias_se"]), "warm_factor": best["warm_start"],
            "winning_start": best["start"], "converged": bool(r.converged), "reason": r.reason,
            "cost": float(r.cost), "steps": int(r.steps), "wall_s_incl_compile": wall,
            "rel_error": {k: float(r.params.friction[k][0] / truth.friction[k][0] - 1)
                          for k in DEFAULT_FREE},
            "attempts": json.loads(json.dumps(r.attempts, default=float))}


def _factors(args: argparse.Namespace) -> tuple[float, ...]:
    """The initial guess's factors on the true friction parameters (``--factors``)."""
    from jaxflex.identify import DEFAULT_FREE

    factors = tuple(float(x) for x in args.factors.split(","))
    if len(factors) != len(DEFAULT_FREE):
        raise SystemExit(f"--factors needs {len(DEFAULT_FREE)} numbers, got {args.factors!r}")
    return factors


class TracedResidual:
    """scipy's residual function: the jitted JAX residual, recording for every call the
    seconds since ``reset`` and the cost 0.5 ||r||^2 (a dot product of the residual, about
    1% of the cheapest replay), so that the time scipy first reached a given cost is known."""

    def __init__(self, fn: Callable[[Any], Any]) -> None:
        self.fn = fn
        self.reset(time.perf_counter())

    def reset(self, t0: float) -> None:
        """Start a new run at ``t0`` (``time.perf_counter``)."""
        self.t0, self.calls = t0, []

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The residual at ``x``, recorded with its time and cost."""
        r = np.asarray(self.fn(x))
        self.calls.append((time.perf_counter() - self.t0, 0.5 * float(r @ r)))
        return r


def bench_length(t_final: float, args: argparse.Namespace) -> dict[str, Any]:
    """The benchmark on one log of ``t_final`` seconds (module docstring)."""
    import equinox as eqx
    import jax
    import scipy.optimize
    from jax.flatten_util import ravel_pytree

    from jaxflex.fit import least_squares
    from jaxflex.identify import DECREMENT_TOL, GEODESIC

    su = (setup_closed_loop if args.log == "closed-loop" else setup_open_loop)(t_final, args)
    probs, y0, tol, wf = su.probs, su.start, args.tol, su.warm_factor
    prob = probs[-1]  # the problem whose final cost and parameters are compared
    loose = eqx.tree_at(lambda q: q.w_def, probs[0], probs[0].w_def * wf)
    # the stages: the warm one, then the full continuity weight at each substeps level
    stages = [(loose, WARM_STEPS)] + [(p, MAX_STEPS) for p in probs]
    flat0, unravel = ravel_pytree(y0)

    def run_jax() -> list[Any]:  # the engine's solver (optimistix LM, compiled step)
        opts = dict(rtol=tol, atol=tol, geodesic=GEODESIC, decrement_tol=DECREMENT_TOL)
        sols, y = [], y0
        for p, cap in stages:
            sols.append(least_squares(p, y, max_steps=cap, **opts))
            y = sols[-1].y
        jax.block_until_ready(y)
        return sols

    machine_start = benchkit.machine_state()
    t = time.perf_counter()
    run_jax()  # the first, cold call: compiles the solver (once; substeps are traced)
    jax_first = time.perf_counter() - t

    def cost_of(p: Any, f: np.ndarray) -> float:
        """0.5 ||r||^2 of problem ``p`` at the flat unknowns ``f`` (untimed)."""
        return 0.5 * float(np.sum(np.asarray(p.residuals(unravel(jax.numpy.asarray(f)))) ** 2))

    def scipy_fun(p: Any) -> TracedResidual:
        f = jax.jit(lambda x: p.residuals(unravel(x)))
        f(flat0).block_until_ready()  # compile outside the timing
        return TracedResidual(lambda x: f(jax.numpy.asarray(x)))

    funs = [(scipy_fun(p), cap) for p, cap in stages]
    kw = dict(jac="2-point", method="trf", xtol=tol, ftol=tol, gtol=tol)
    traces: list[list[tuple[float, float]]] = []

    def run_scipy() -> list[Any]:
        t0 = time.perf_counter()
        out, x = [], np.asarray(flat0)
        for f, cap in funs:
            f.reset(t0)
            out.append(scipy.optimize.least_squares(f, x, max_nfev=cap, **kw))
            x = out[-1].x
        traces.append(list(funs[-1][0].calls))  # the last stage: the compared cost
        return out

    last: dict[str, Any] = {}
    cpu: dict[str, list[float]] = {}
    print(f"[{t_final:g} s] {flat0.size} unknowns, substeps {[p.substeps for p in probs]}, warm "
          f"factor {wf:g}: JAX first call {jax_first:.2f} s; {args.repeat} paired rounds ...",
          flush=True)
    times = benchkit.paired({"scipy_trf_2point": lambda: last.__setitem__("scipy", run_scipy()),
                             "jax_optimistix_lm": lambda: last.__setitem__("jax", run_jax())},
                            args.repeat, cpu=cpu,
                            only_first={"scipy_trf_2point": args.scipy_repeat or args.repeat})
    machine_end = benchkit.machine_state()
    sols, lss = last["jax"], last["scipy"]
    jax_times, sp_times = times["jax_optimistix_lm"], times["scipy_trf_2point"]
    jax_flat = np.asarray(ravel_pytree(sols[-1].y)[0])
    jax_cost, sp_cost = cost_of(prob, jax_flat), cost_of(prob, lss[-1].x)
    chi2 = 2.0 * (jax_cost - sp_cost)
    equal = bool(abs(chi2) <= CHI2_EQUAL)
    # when scipy first evaluated a point at JAX's final cost (within CHI2_EQUAL / 2 in cost)
    reach = [next((tc for tc, c in tr if c <= jax_cost + 0.5 * CHI2_EQUAL), None)
             for tr in traces]
    reached = [x for x in reach if x is not None]

    def phys(flat: np.ndarray) -> dict[str, float]:
        """The physical friction parameters at the flat unknowns ``flat``."""
        th = unravel(jax.numpy.asarray(flat))[0]
        return {k: float(v[0]) for k, v in prob.space.physical(th).items()}

    def rel(d: dict[str, float]) -> dict[str, float]:
        """Relative errors against the truth (value / true - 1)."""
        return {k: d[k] / su.truth.friction[k][0] - 1 for k in d}

    njev = [int(ls.njev or 0) for ls in lss]
    results: dict[str, Any] = {
        "log": args.log, "seed": args.seed, "log_s": t_final,
        "unknowns": int(flat0.size), "residuals": int(prob.residuals(y0).size),
        "segment_length": args.segment, "segments": int(prob.segs.count),
        "substeps": [int(p.substeps) for p in probs], "warm_factor": wf,
        "choice": su.choice, "tolerance": tol, "start_factors": _factors(args),
        "stages": {"warm_continuity_factor": wf, "warm_steps": WARM_STEPS,
                   "max_steps": MAX_STEPS, "substeps": ["warm"] + [p.substeps for p in probs]},
        "initial_cost": cost_of(prob, np.asarray(flat0)), "noise_cost": su.noise_cost,
        "start_rel_error": rel(phys(np.asarray(flat0))),
        "repeats": {"jax": len(jax_times), "scipy": len(sp_times)},
        "timing": "paired rounds (the solvers alternate), min and median (a shared 2-core "
                  "machine); JAX's first, cold call (compilation included) is one sample",
        "blas_threads": BLAS, "machine_start": machine_start, "machine_end": machine_end,
        "chi2_equal_bound": CHI2_EQUAL,
        "jax": {"wall_s_with_compile": jax_first, "wall_s": min(jax_times),
                "wall_s_median": statistics.median(jax_times), "wall_s_all": jax_times,
                "cpu_s_all": cpu["jax_optimistix_lm"], "cost": jax_cost,
                "stage_costs": [s.cost for s in sols], "steps": [s.steps for s in sols],
                "stage_reasons": [s.reason for s in sols],
                "converged": sols[-1].converged, "reason": sols[-1].reason,
                "s_per_step": statistics.median(jax_times) / max(1, sum(s.steps for s in sols)),
                "geodesic": GEODESIC, "decrement_tol": DECREMENT_TOL,
                "rel_error": rel(phys(jax_flat))},
        "scipy": {"wall_s": min(sp_times), "wall_s_median": statistics.median(sp_times),
                  "wall_s_all": sp_times, "cpu_s_all": cpu["scipy_trf_2point"], "cost": sp_cost,
                  "nfev": [int(ls.nfev) for ls in lss], "njev": njev,
                  "stage_costs": [float(ls.cost) for ls in lss],
                  "status": [int(ls.status) for ls in lss],
                  "stage_messages": [ls.message for ls in lss],
                  "residual_evals_incl_fd": sum(int(ls.nfev) for ls in lss)
                  + int(flat0.size) * sum(njev),
                  "s_per_jacobian_iteration": statistics.median(sp_times) / max(1, sum(njev)),
                  "s_to_jax_cost_all": reach,
                  "rel_error": rel(phys(lss[-1].x))},
        "chi2_jax_minus_scipy": chi2, "equal_cost": equal,
        "jax_cost_lower": bool(chi2 < -CHI2_EQUAL),
        "cost_ratio_jax_over_scipy": jax_cost / sp_cost if sp_cost > 0 else float("nan"),
        "jax_compile_s_estimate": jax_first - statistics.median(jax_times),
    }
    results["comparison"] = (
        f"valid: equal final cost (|chi-square difference| {abs(chi2):.3g} <= {CHI2_EQUAL})"
        if equal else
        f"invalid: final costs differ (chi-square difference 2 (JAX - scipy) = {chi2:.4g}, "
        f"JAX {jax_cost:.6g}, scipy {sp_cost:.6g}); no speed ratio is a result")

    def ok(x: float) -> float | None:
        """A speed ratio, reported only at equal final cost."""
        return x if equal else None

    results["speed_ratio_warm"] = ok(min(sp_times) / min(jax_times))
    results["speed_ratio_warm_median"] = ok(statistics.median(sp_times)
                                            / statistics.median(jax_times))
    results["speed_ratio_with_compile"] = ok(min(sp_times) / jax_first)
    results["speed_ratio_scipy_to_jax_cost"] = (
        ok(statistics.median(reached) / statistics.median(jax_times))
        if reached and len(reached) == len(reach) else None)
    print(json.dumps({k: v for k, v in results.items() if k not in ("blas_threads",)}, indent=2))
    benchkit.ratio_table(times, "scipy_trf_2point")
    print(f"load average start {machine_start['load_avg']}, end {machine_end['load_avg']}; BLAS "
          f"threads {BLAS['env']['OPENBLAS_NUM_THREADS']} (threadpoolctl {BLAS['threadpoolctl']})")
    print(f"[{t_final:g} s] {results['comparison']}")
    if equal:
        print(f"scipy/JAX time ratio: {results['speed_ratio_warm']:.1f}x min, "
              f"{results['speed_ratio_warm_median']:.1f}x median (JAX warm), "
              f"{results['speed_ratio_with_compile']:.2f}x (JAX incl. compile)")
    return results


if __name__ == "__main__":
    main()
