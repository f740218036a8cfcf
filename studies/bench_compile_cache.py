"""Question: does a second run of a command on the same machine compile again?

The ``jaxflex`` command turns on JAX's persistent compilation cache (``$JAXFLEX_CACHE_DIR``,
``jaxflex.app.cli.enable_compilation_cache``; every compilation is kept), and the traced
programs of the fitting engine, simulator and tuner beside it (``jaxflex.runtime.tracecache``: no
tracing or lowering of those in a second run). This study runs one command (``--command``:
``reproduce`` (a short paper experiment), ``identify`` (a 3 s closed-loop log of
``jaxflex.identify.datagen``, seed 7, 20-bit encoder, six LuGre parameters from 50% off) or
``discover`` (a 20 s log of the same generator with a hidden joint damping, every candidate);
the other commands on the paper's parameters: ``certify``, ``analyse`` (with ``--floquet``),
``tune``, ``export --check``, ``validate`` (the identify log against the generator's
parameters), ``sweep`` (256 plants of ``studies/spreads/sweep_paper_20pct.json``); ``all``:
each command once, first and second run only) in fresh processes: with an empty cache folder, again with the same folder (the second run of
a user) and once more; for identify and discover, with the same folder, on a log of another
length (2.6 s, 18 s: a user's next log, with other shapes); twice with ``--no-trace-cache`` in
another empty folder (what the kept traces save: there only XLA's executables are reused);
and with ``--no-cache``. In each process a
``jax.monitoring`` listener sums the seconds spent tracing, lowering and compiling (XLA
backend) and reading the cache, and counts cache hits; wall time is also recorded. Target:
the second run spends under 2 s compiling.

    python studies/bench_compile_cache.py [--command reproduce|identify|discover|...|all]
        [--small] [--out out/bench_compile_cache]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# runs in the child: listeners first, then the command
_CHILD = r"""
import atexit, collections, json, sys
import jax.monitoring as mon
tot = collections.defaultdict(float)
cnt = collections.Counter()
def dur(event, secs, **kw):
    tot[event] += secs
    cnt[event] += 1
def ev(event, **kw):
    cnt[event] += 1
mon.register_event_duration_secs_listener(dur)
mon.register_event_listener(ev)
atexit.register(lambda: print("COMPILE_STATS " + json.dumps({"seconds": tot, "counts": cnt}),
                              file=sys.stderr))
from jaxflex.app.cli import main
rc = main(json.loads(sys.argv[1]))
sys.exit(rc)
"""

_EVENTS = {
    "trace_s": "/jax/core/compile/jaxpr_trace_duration",
    "lower_s": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "backend_compile_s": "/jax/core/compile/backend_compile_duration",
    "cache_read_s": "/jax/compilation_cache/cache_retrieval_time_sec",
}


def run_once(argv: list[str], cache: str | None, ok: tuple[int, ...] = (0,)) -> dict:
    """One command in a fresh process; returns wall time, compile seconds and cache hits.
    ``ok``: the exit codes that count as a run (``analyse`` exits 1 when a mode grows, as the
    paper's observer does at rest)."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    if cache is not None:
        env["JAXFLEX_CACHE_DIR"] = cache
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(argv)], env=env,
                       capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode not in ok:
        raise RuntimeError(r.stderr[-3000:])
    line = [x for x in r.stderr.splitlines() if x.startswith("COMPILE_STATS ")][-1]
    st = json.loads(line[len("COMPILE_STATS "):])
    out = {k: st["seconds"].get(v, 0.0) for k, v in _EVENTS.items()}
    out["compile_total_s"] = out["trace_s"] + out["lower_s"] + out["backend_compile_s"]
    out["compilations"] = st["counts"].get(_EVENTS["backend_compile_s"], 0)
    out["cache_hits"] = st["counts"].get("/jax/compilation_cache/cache_hits", 0)
    out["wall_s"] = wall
    out["load_avg"] = list(os.getloadavg())
    return out


def main(argv: list[str] | None = None) -> dict:
    """Run the three processes and write results_COMMAND.json; returns the results."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/bench_compile_cache")
    ap.add_argument("--small", action="store_true", help="a 1 s experiment (reproduce)")
    ap.add_argument("--command", choices=("reproduce", "identify", "discover", *OTHERS, "all"),
                    default="reproduce")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    if a.command == "all":
        return every_command(out, a.small)
    if a.command in OTHERS:
        return every_command(out, a.small, names=(a.command,))
    cmd = _command(a.command, out, a.small)
    with tempfile.TemporaryDirectory() as cache:
        first = run_once(cmd, cache)
        second = run_once(cmd, cache)
        second_again = run_once(cmd, cache)  # a repeat of the second run (spread)
        # a log of another length, a user's next log: identify 2.6 s against 3 s (5
        # multiple-shooting segments of 500 samples against 6; the solver runs in buckets of
        # segment slots, 8 for both), discover 18 s against 20 s
        other = None if a.command == "reproduce" else run_once(
            _command(a.command, out, a.small, t_final=OTHER_LENGTH[a.command]), cache)
    with tempfile.TemporaryDirectory() as cache:
        # XLA's cache alone, every function traced again in each run: what the kept traces
        # (jaxflex.runtime.tracecache) save. Its own folder: a traced function lowers to another
        # program than its kept export, so the first run fills XLA's cache for it.
        first_traced = run_once(["--no-trace-cache"] + cmd, cache)
        second_traced = run_once(["--no-trace-cache"] + cmd, cache)
    nocache = run_once(["--no-cache"] + cmd, None)
    res = {"command": "jaxflex " + " ".join(cmd), "cpu_count": os.cpu_count(),
           "target": "second run under 2 s compiling (trace + lower + XLA, cache reads included)",
           "first_empty_cache": first, "second_same_cache": second,
           "second_same_cache_repeat": second_again,
           **({"other_length_same_cache": other} if other else {}),
           "first_empty_cache_no_trace_cache": first_traced,
           "second_same_cache_no_trace_cache": second_traced, "no_cache": nocache,
           "note": "seconds summed from jax.monitoring events in each process (identify "
                   "compiles partly in a background thread, jaxflex.identify.compile_ahead: "
                   "overlapping compilations add up, so the sum can exceed the wall time); every "
                   "compilation is cached (jax_persistent_cache_min_compile_time_secs 0); "
                   "the traced programs of the fitting engine, simulator and tuner are kept "
                   "too (jaxflex.runtime.tracecache, in the cache's traces/ folder; "
                   "*_no_trace_cache: two runs with --no-trace-cache in another folder); other "
                   "functions are traced in every process"}
    for k, r in (("first (empty cache)", first), ("second (same cache)", second),
                 ("second, repeated", second_again),
                 *((("other length, same cache", other),) if other else ()),
                 ("first, --no-trace-cache", first_traced),
                 ("second, --no-trace-cache", second_traced), ("--no-cache", nocache)):
        print(f"{k:>20}: wall {r['wall_s']:.1f} s, compile {r['compile_total_s']:.2f} s (trace "
              f"{r['trace_s']:.2f}, lower {r['lower_s']:.2f}, XLA {r['backend_compile_s']:.2f}; "
              f"{r['compilations']} XLA compilations), cache read {r['cache_read_s']:.2f} s, "
              f"{r['cache_hits']} hits; load {r['load_avg'][0]:.2f}")
    (out / f"results_{a.command}.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


#: The commands measured by ``every_command`` besides reproduce, identify and discover.
OTHERS = ("certify", "analyse", "tune", "export", "validate", "sweep")


def every_command(out: Path, small: bool, names: tuple[str, ...] | None = None) -> dict:
    """Each command (``names``, default all) in two fresh processes on one empty cache
    folder: the first run and the second; writes results_all.json (or results_NAME.json for
    one) and prints one line per command."""
    names = names or ("reproduce", "identify", "discover", *OTHERS)
    res = {"cpu_count": os.cpu_count(),
           "target": "second run under 2 s compiling (trace + lower + XLA, cache reads included)",
           "commands": {}}
    for name in names:
        cmd = _command(name, out, small)
        ok = (0, 1) if name == "analyse" else (0,)
        with tempfile.TemporaryDirectory() as cache:
            first = run_once(cmd, cache, ok)
            second = run_once(cmd, cache, ok)
        res["commands"][name] = {"command": "jaxflex " + " ".join(cmd), "first_empty_cache": first,
                                 "second_same_cache": second}
        print(f"{name:>10}: first wall {first['wall_s']:.1f} s, compile "
              f"{first['compile_total_s']:.2f} s; second wall {second['wall_s']:.1f} s, compile "
              f"{second['compile_total_s']:.2f} s (trace {second['trace_s']:.2f}, lower "
              f"{second['lower_s']:.2f}, XLA {second['backend_compile_s']:.2f}; cache read "
              f"{second['cache_read_s']:.2f} s, {second['compilations']} programs); load "
              f"{second['load_avg'][0]:.2f}", flush=True)
    tag = "all" if len(names) > 1 else names[0]
    (out / f"results_{tag}.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


#: The log length [s] of each command's "other length" run (after 3 s / 20 s ones).
OTHER_LENGTH = {"identify": 2.6, "discover": 18.0}


def _command(name: str, out: Path, small: bool, t_final: float | None = None) -> list[str]:
    """The jaxflex command line of ``name``, its input files written under ``out``
    (``t_final``: the log's length [s]; default 3 s for identify, 20 s for discover)."""
    if name == "reproduce":
        return ["reproduce", "--tasks", "sinusoid", "--no-q2d-comparison", "--duration",
                "1" if small else "10", "--force", "--out", str(out / "reproduce")]
    import jax

    jax.config.update("jax_enable_x64", True)
    from jaxflex.identify.datagen import generate_log
    from jaxflex.identify import DEFAULT_FREE, perturb
    from jaxflex.io.logs import save_log
    from jaxflex.io.params import Params, save_params
    from jaxflex.io.presets import paper_params

    paper = out / "paper.json"
    if name in ("certify", "tune", "export"):
        save_params(paper_params(), paper)
    if name == "certify":
        return ["certify", "--params", str(paper), "--json"]
    if name == "analyse":
        return ["analyse", "--json", "--floquet"]
    if name == "tune":
        return ["tune", "--params", str(paper), "--out", str(out / "tuned.json"), "--force"]
    if name == "export":
        return ["export", "--params", str(paper), "--out", str(out / "controller.py"),
                "--check", "--force"]
    if name == "sweep":
        spread = Path(__file__).resolve().parent / "spreads" / "sweep_paper_20pct.json"
        return ["sweep", str(spread), "--out", str(out / "sweep"), "--samples",
                "64" if small else "256", "--force"]
    if name == "validate":
        g = generate_log((), seed=7, t_final=3.0, bits=20, noise_counts=0.5)
        save_log(g.log, out / "log_validate.csv")
        save_params(Params.from_dict(g.truth["plant"]), out / "truth.json")
        return ["validate", str(out / "log_validate.csv"), "--params", str(out / "truth.json"),
                "--out", str(out / "validate"), "--force"]

    if name == "identify":
        t_final = 3.0 if t_final is None else t_final
        g = generate_log((), seed=7, t_final=t_final, bits=20, noise_counts=0.5)
        name = f"log{t_final:g}.csv"
        save_log(g.log, out / name)
        truth = Params.from_dict(g.truth["plant"])
        save_params(perturb(truth, DEFAULT_FREE, (1.5, 1.5, 0.5, 1.5, 0.5, 1.5)),
                    out / "init.json")
        return ["identify", str(out / name), "--params", str(out / "init.json"),
                "--out", str(out / "identified.json"), "--force"]
    t_final = 20.0 if t_final is None else t_final
    g = generate_log(("joint_damping",), seed=3, t_final=t_final)
    name = f"log{t_final:g}.csv"
    save_log(g.log, out / name)
    return ["discover", str(out / name), "--out", str(out / "discover"), "--force"]


if __name__ == "__main__":
    main()
