"""Benchmark table: docs/performance.md, regenerated from the benchmarks' JSON.

Question: what do the benchmark scripts in ``studies/`` say about jaxflex's speed, in one
table? Each benchmark writes its numbers to a JSON file; this script reads them and writes
``docs/performance.md``: a fixed header, then one row per figure with what was measured,
the figure (ratios against the baseline the benchmark ran side by side in the same process,
min and median where the JSON has them, compilation or first-call time stated apart), the
baseline, the machine as the JSON records it (cores, load average, BLAS threads, XLA
options) and the command that regenerates it. A benchmark whose JSON is missing and whose
rows the page does not hold says "not measured" and names the command. Nothing is timed here.

Sources (each path an option; defaults relative to the working directory, as the
benchmarks write them):

- ``out/bench_simulate_default/results.json``: ``bench_simulate.py --part single
  --xla-default`` (``simulate_sampled`` with XLA's default options against a plain
  hand-written ``lax.scan`` of the same loop: what a notebook user gets);
- ``out/bench_simulate/results.json``: ``bench_simulate.py --part single`` (jaxflex's lean
  XLA CPU options and the small-loop option, as that script sets them for one loop);
- ``out/bench_export_step/results.json``: ``bench_export_step.py``;
- ``out/bench_compile_cache/``: ``bench_compile_cache.py`` (its ``results_COMMAND.json``,
  one row per command measured);
- ``out/bench_sweep/results.json``: ``bench_sweep.py``;
- ``out/bench_sweep/gpu.json``: ``bench_sweep.py --gpu`` (on a machine with an NVIDIA GPU);
- ``out/ident_bench_scipy/results.json``: ``ident_bench_scipy.py`` (one row per log length);
- ``out/peer_sysid/results.json``: ``peer_sysid.py`` (one row per log: against
  ``mujoco.sysid``).

A benchmark whose JSON is missing here keeps its rows from the page as it stands (a benchmark
run on another machine, such as the GPU's, keeps its figures when the table is regenerated
elsewhere); ``--fresh`` forgets them. Also writes the rows as ``table.json`` to ``--out``.
``--small`` (the studies' smoke test) writes the table to ``--out`` instead of ``docs/``.

    python studies/performance_table.py [--simulate-default PATH] [--simulate PATH]
        [--export-step PATH] [--compile-cache DIR] [--sweep PATH] [--gpu PATH]
        [--ident-scipy PATH] [--peer-sysid PATH] [--doc docs/performance.md]
        [--out out/performance_table] [--fresh] [--small]
"""

from __future__ import annotations

import argparse
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

ROOT = Path(__file__).resolve().parent.parent

HEADER = """\
# Performance

Measured speeds of jaxflex. This file is written by `studies/performance_table.py` from the
JSON files that the benchmark scripts in `studies/` write under `out/`: run the benchmark a row
names, then `python studies/performance_table.py`; do not edit the rows by hand. A row whose
JSON is missing says "not measured" and how to measure it.

Each figure is set against a baseline the benchmark ran side by side (in the same process, in
paired rounds where the script has them, or in fresh processes taking turns, as the baseline
column says): min and median where the JSON has them, "x" ratios as baseline time over jaxflex
time (above 1: jaxflex is faster), compilation or first call stated apart. The machine column
is what each JSON records: cores, load average at start and end, BLAS threads, XLA options.
The machine is shared and its speed varies over a day: compare the figures within a row, not
across rows or machines. Tests never assert wall-clock limits.
"""


class Row(NamedTuple):
    """One line of the table."""

    what: str
    figure: str
    baseline: str
    machine: str
    command: str


class Source(NamedTuple):
    """One benchmark's JSON: the option that names it, its default path, the command that
    writes it, what its row says when it is missing, and the function that turns the JSON into
    rows."""

    option: str
    default: str
    command: str
    what: str
    rows: Callable[[Any, str], list[Row]]


# ----- formatting -----------------------------------------------------------------------------


def _t(s: float | None) -> str:
    """A duration [s] with a readable unit, three significant digits."""
    if s is None:
        return "n/a"
    for unit, scale in (("s", 1.0), ("ms", 1e-3), ("us", 1e-6)):
        if abs(s) >= scale:
            return f"{s / scale:.3g} {unit}"
    return f"{s / 1e-9:.3g} ns"


def _x(r: float | None) -> str:
    """A ratio, as x1.23."""
    return "n/a" if r is None else f"x{r:.3g}"


def _load(start: Any, end: Any = None) -> str:
    """The 1-minute load average at start (and end) of a run."""
    a = f"{start[0]:.2f}" if start else "not recorded"
    return a if end is None else f"{a}-{end[0]:.2f}"


def _blas(info: dict | None) -> str:
    """BLAS threads as ``benchkit.limit_blas_threads`` recorded them."""
    if not info:
        return "BLAS threads not recorded"
    return f"BLAS threads {info.get('env', {}).get('OPENBLAS_NUM_THREADS', '?')}"


def _xla(flags: str | None) -> str:
    """The XLA options a run recorded."""
    if flags is None:
        return "XLA options not recorded"
    return f"`XLA_FLAGS={flags}`" if flags else "XLA's defaults"


# ----- one function per benchmark -------------------------------------------------------------


def simulate_rows(d: dict, command: str) -> list[Row]:
    """``bench_simulate.py --part single`` (or the ``single`` part of ``--part all``): jaxflex
    against the hand-written ``lax.scan`` and against scipy, wall and CPU time."""
    if "single" in d and "single" in d["single"]:  # --part all: one JSON per part
        d = d["single"]
    s = d["single"]
    tab, cpu, comp = s["table"], s.get("table_cpu", {}), s["compile_or_first_call_s"]
    machine = (f"{d['device']}, {d['machine_start']['cpu_count']} cores, load "
               f"{_load(d['machine_start']['load_avg'], d['machine_end']['load_avg'])}, "
               f"{_blas(d.get('blas_threads'))}, {_xla(d.get('xla_flags'))}")
    flags = d.get("xla_flags") or ""
    opts = ("XLA's default options" if not flags else
            "jaxflex's lean XLA CPU options" + (" and the small-loop option" if
                                                "small_while_loop" in flags else ""))
    loop = (f"one {s['t_final_s']:g} s closed loop at 1 kHz ({s['samples']} samples, "
            f"{s['substeps']} substeps)")

    def pair(ours: str, theirs: str, t: dict) -> str:
        a, b = t[ours], t[theirs]
        return (f"{_t(a['min_s'])} (median {_t(a['median_s'])}) against {_t(b['min_s'])} "
                f"({_t(b['median_s'])}): {_x(b['min_s'] / a['min_s'])} min, "
                f"{_x(b['median_s'] / a['median_s'])} median")

    rows = []
    for kind, ours, theirs in (("saved trajectories", "jaxflex_save", "hand_jax_save"),
                               ("no saved trajectories", "jaxflex_lean", "hand_jax_lean")):
        cpu_part = f"; CPU time {pair(ours, theirs, cpu)}" if ours in cpu else ""
        rows.append(Row(
            f"`simulate_sampled`, {loop}, {kind}, {opts}, against a plain hand-written "
            f"`lax.scan` of the same loop",
            f"wall {pair(ours, theirs, tab)}{cpu_part}; compile or first call "
            f"{_t(comp[ours])} against {_t(comp[theirs])}",
            f"`{theirs}`: hand-written JAX `lax.scan` (same plant kernels, unrolled substeps), "
            f"same process, same XLA options", machine, command))
    base = s["baseline"].split(" (")[0]
    scipy = [f"{k} {_t(tab[k]['min_s'])} (median {_t(tab[k]['median_s'])}): "
             f"{_x(tab[k][f'ratio_{base}_over_this_min'])} min, "
             f"{_x(tab[k][f'ratio_{base}_over_this_median'])} median"
             for k in ("jaxflex_save", "jaxflex_lean") if k in tab]
    scipy.append(f"{base} itself {_t(tab[base]['min_s'])} (runs: {tab[base]['repeats']})")
    if "numba" in tab:
        scipy.append(f"numba {_t(tab['numba']['min_s'])}: jaxflex_lean "
                     f"{_x(tab['jaxflex_lean']['ratio_numba_over_this_min'])} min")
    rows.append(Row(f"`simulate_sampled`, {loop}, {opts}, against scipy", "; ".join(scipy),
                    s["baseline"], machine, command))
    return rows


def export_step_rows(d: dict, command: str) -> list[Row]:
    """``bench_export_step.py``: one step of the exported controller in each back end."""
    base, b = d["baseline"], d["backends"]
    fig = [f"{name} {b[name]['min_us']:.3g} us (median {b[name]['median_us']:.3g} us)"
           + ("" if name == base else
              f": {b[name][f'ratio_to_{base}_median']:.3g} times {base}'s step (median)")
           for name in b]
    st = d["setup_s"]
    fig.append(f"apart: trace {_t(st['trace'])}, generate Python {_t(st['generate_python'])}, "
               f"generate C {_t(st['generate_c'])}, compile C {_t(st['compile_c'])}")
    m = d["machine"]
    return [Row(f"one step of the exported controller ({d['controller']}), "
                f"{d['samples_per_run']} samples x {d['paired_repeats']} paired repeats",
                "; ".join(fig),
                f"`{base}`: the C export timed inside C (median step of each repeat)",
                f"{m['processor']}, {m['cpus']} cores, Python {m['python']}, load not "
                f"recorded", command)]


def _compile(label: str, x: dict) -> str:
    """One process of ``bench_compile_cache``: its compilation seconds and wall time."""
    return (f"{label} compile {x['compile_total_s']:.2f} s (trace {x['trace_s']:.2f}, lower "
            f"{x['lower_s']:.2f}, XLA {x['backend_compile_s']:.2f}), wall {x['wall_s']:.1f} s")


def compile_cache_rows(files: dict[str, dict], command: str) -> list[Row]:
    """``bench_compile_cache.py``: one row per command in each of its ``results_COMMAND.json``
    (``files``: file name -> JSON; ``--command all`` holds every command, first and second run
    only)."""
    rows = []
    for name, d in sorted(files.items()):
        tag = name.removeprefix("results_").removesuffix(".json")
        cmd = command if tag == "reproduce" else f"{command} --command {tag}"
        if any("--duration 1 " in r["command"] or "--samples 64 " in r["command"]
               for r in (d["commands"].values() if "commands" in d else [d])):
            cmd += " --small"  # the script's --small: a 1 s experiment, 64 sweep samples
        for r in d["commands"].values() if "commands" in d else [d]:
            first, second = r["first_empty_cache"], r["second_same_cache"]
            fig = [_compile("second run:", second), _compile("first run (empty cache):", first)]
            if "no_cache" in r:
                fig.append(_compile("`--no-cache`:", r["no_cache"]))
            if "other_length_same_cache" in r:
                fig.append(_compile("a log of another length, same cache:",
                                    r["other_length_same_cache"]))
            rows.append(Row(
                f"`{r['command']}`, a second run in a fresh process on the same compilation "
                f"cache", "; ".join(fig), "the first run on an empty cache" + (
                    " and a run with `--no-cache`" if "no_cache" in r else ""),
                f"{d['cpu_count']} cores, load {_load(first['load_avg'], second['load_avg'])} "
                f"(first, second run)", cmd))
    return rows


def sweep_rows(d: dict, command: str) -> list[Row]:
    """``bench_sweep.py``: batched sweep against the solve_ivp (and numba) loop; host devices."""
    machine = (f"{d['cpu_count']} cores, load {_load(d['load_avg_start'], d['load_avg_end'])}, "
               f"{_blas(d.get('blas_threads'))}, {_xla(d.get('xla_flags'))}")
    if d["chunk"] == 32:  # the script's --small: 0.05 s loops in chunks of 32
        command += " --small"
    rows = []
    if "ratio" in d:
        r = d["ratio"]
        fig = (f"{r['batched_steps_per_s_best']:.3g} controller steps/s (median "
               f"{r['batched_steps_per_s_median']:.3g}, {r['batched_repeats']} runs) against "
               f"solve_ivp's {r['solve_ivp_steps_per_s']:.3g}: "
               f"{_x(r['speedup_vs_solve_ivp'])} best, "
               f"{_x(r['batched_steps_per_s_median'] / r['solve_ivp_steps_per_s'])} median")
        if "numba_steps_per_s" in r:
            fig += (f"; numba {r['numba_steps_per_s']:.3g} steps/s: "
                    f"{_x(r['speedup_vs_numba'])}")
        first = [x["first_chunk_s"] for x in d.get("scaling", [])]
        if first:
            fig += f"; a worker's first chunk (with compilation) {_t(first[0])} apart"
        rows.append(Row(f"`run_sweep`, chunks of {d['chunk']} closed loops of "
                        f"{d['horizon_s']:g} s, float64, 10 substeps, "
                        f"{r['batched_devices']} device(s)", fig,
                        "the same samples one after another: solve_ivp (RK45) per 1 ms with "
                        "the exported numpy controller" + (", and numba" if "numba_steps_per_s"
                                                           in r else ""), machine, command))
    if "devices" in d:
        v = d["devices"]
        n = v["runs"]["1"][0]["samples"]
        rows.append(Row(f"`run_sweep` on 2 host devices against 1, {n} closed loops of "
                        f"{d['horizon_s']:g} s",
                        f"{_x(v['ratio_2_over_1_best'])} best, "
                        f"{_x(v['ratio_2_over_1_median'])} median",
                        "the same sweep on 1 host device, alternating processes", machine,
                        command))
    return rows


def gpu_rows(d: dict, command: str) -> list[Row]:
    """``bench_sweep.py --gpu``: the sweep on a GPU, float64 and float32, against the same
    machine's CPU (every core a host device), at the substeps that meet the stated accuracy."""
    if not d.get("measured"):
        return []
    if d["samples"] == 64:  # the script's --small
        command += " --small"
    runs, n, sub = d["runs"], d["samples"], d["substeps"]
    device = d["device"].split(" | ")  # platform | kind | count | JAX version
    machine = (f"{device[1]}, JAX {device[-1]}; host {d['cpu_count']} cores, "
               f"load {_load(d['load_avg_start'], d.get('load_avg_end'))}, "
               f"{_blas(d.get('blas_threads'))}")

    def rate(name: str) -> str:
        r = runs.get(name)
        if not r or "steps_per_s" not in r:
            return "not run"
        return (f"{r['steps_per_s']:.3g} steps/s (median {r['steps_per_s_median']:.3g}, "
                f"first chunk with compilation {_t(r['first_chunk_s'])})")

    if sub is None:
        return [Row(f"`run_sweep` on a GPU, {n} closed loops of {d['t_final']:g} s",
                    f"no accuracy reached: {d.get('note', '')}", "", machine, command)]
    g64 = runs[f"gpu_f64_{n}_sub{sub}"]
    fig = (f"float64 {rate(f'gpu_f64_{n}_sub{sub}')}; float32 "
           f"{rate(f'gpu_f32_{n}_sub{sub}')}, its RMS metric within "
           f"{d.get('float32_rms_rel_diff_vs_float64_max', float('nan')):.1e} of float64's; "
           f"the CPU {rate(f'cpu_f64_{n}_sub{sub}')}")
    if "ratio_gpu_f64_over_cpu_f64_best" in d:  # the CPU's run was not skipped
        fig += (f": GPU float64 {_x(d['ratio_gpu_f64_over_cpu_f64_best'])} best; the two "
                f"agree to {d['gpu_vs_cpu_rms_rel_diff_max']:.1e}")
    rows = [Row(f"`run_sweep` on a GPU, {n} closed loops of {d['t_final']:g} s, {sub} substeps "
                f"(RMS metric within {g64['rms_rel_err_vs_reference']:.1e} of "
                f"{d['reference']['substeps']} substeps, bound {d['tolerance_rel']:g})",
                fig, "the same sweep on the same machine's CPU, every core a host device, "
                "fresh processes in turn", machine, command)]
    big = sorted({int(k.split("_")[2]) for k in runs if k.startswith("gpu_f64_")} - {n})
    if big:
        parts = [f"{m:g} samples: float64 {rate(f'gpu_f64_{m}_sub{sub}')}, float32 "
                 f"{rate(f'gpu_f32_{m}_sub{sub}')}" for m in big]
        cpu_big = f"cpu_f64_{big[0]}_sub{sub}"
        if cpu_big in runs and "steps_per_s" in runs[cpu_big]:
            ratio = runs[f"gpu_f64_{big[0]}_sub{sub}"]["steps_per_s"] / runs[cpu_big]["steps_per_s"]
            parts.append(f"the CPU at {big[0]:g} samples {rate(cpu_big)}: GPU float64 "
                         f"{_x(ratio)} best")
        rows.append(Row(f"`run_sweep` on a GPU, larger batches ({sub} substeps, one chunk each)",
                        "; ".join(parts), "the CPU at the smallest of them, as above",
                        machine, command))
    return rows


def ident_scipy_rows(d: dict, command: str) -> list[Row]:
    """``ident_bench_scipy.py``: identification against scipy's least squares, per log length."""
    if list(d["lengths"]) == ["1"] and d["segment_length"] == 250:
        command += " --small"  # the script's --small: a 1 s log, segments of 250 samples
    rows = []
    for length, r in d["lengths"].items():
        if r["equal_cost"]:
            fig = (f"JAX {_t(r['jax_wall_s'])} (median {_t(r['jax_wall_s_median'])}) against "
                   f"scipy {_t(r['scipy_wall_s'])} ({_t(r['scipy_wall_s_median'])}): "
                   f"{_x(r['speed_ratio_warm'])} min, {_x(r['speed_ratio_warm_median'])} "
                   f"median; with JAX's compilation {_x(r['speed_ratio_with_compile'])} "
                   f"(compilation about {_t(r['jax_compile_s_estimate'])} apart)")
        else:
            fig = (f"no ratio: {r['comparison']} (JAX {_t(r['jax_wall_s'])}, scipy "
                   f"{_t(r['scipy_wall_s'])})")
        rows.append(Row(
            f"identification, {r['log']} log of {length} s ({r['unknowns']} unknowns, "
            f"{'>'.join(map(str, r['substeps']))} substeps)", fig,
            "`scipy.optimize.least_squares` (trf, 2-point finite differences) on the same "
            "residual, same start and stages",
            f"{d['machine_start']['cpu_count']} cores, load "
            f"{_load(r['load_avg_start'], r['load_avg_end'])}, {_blas(d.get('blas_threads'))}, "
            f"{_xla(d['machine_start'].get('XLA_FLAGS'))}", command))
    return rows


def peer_rows(d: dict, command: str) -> list[Row]:
    """``peer_sysid.py``: ``jaxflex.identify`` against ``mujoco.sysid`` on the same logs, one
    row per log: wall times, each tool's largest relative error over the quantities both
    fit, and sysid's time over jaxflex's (warm), said to be at equal or better error or not."""
    rows = []
    loads = d.get("load_avg_per_stage") or []
    for lg in d["logs"].values():
        m = lg["methods"]
        jx = next(v for k, v in m.items() if k.startswith("jaxflex"))
        ratios = {r["sysid"]: r for r in lg.get("ratios", [])}
        parts = []
        for key, label in (("sysid_default", "default scaling"),
                           ("sysid_xscale_jac", "x_scale='jac'")):
            if key not in m:
                continue
            sv, r = m[key], ratios.get(key, {})
            ratio = sv["wall_s"] / jx["warm_s"]  # baseline over jaxflex, as every row
            verdict = ("at equal or better jaxflex error" if r.get("equal_or_better")
                       else "jaxflex's error larger")
            parts.append(f"sysid ({label}) {_t(sv['wall_s'])}, error "
                         f"{100 * r.get('sysid_err', math.nan):.2g}%"
                         f"{'' if sv.get('success') else ', not converged'}: "
                         f"sysid/jaxflex {_x(ratio)} ({verdict})")
        j_err = next(iter(ratios.values()), {}).get("jaxflex_err", math.nan)
        fig = (f"jaxflex warm {_t(jx['warm_s'])} (cold {_t(jx['cold_s'])}, {jx['steps']} "
               f"steps), error {100 * j_err:.2g}%; " + "; ".join(parts))
        rows.append(Row(
            f"identification of a rigid hinge with friction, {lg['source']} (15 s at 1 kHz, "
            "open loop, start 40-50% off), `jaxflex.identify` (rigid + LuGre) against "
            "`mujoco.sysid`", fig,
            f"`mujoco.sysid` {d['versions'].get('mujoco', '?')} (Levenberg-Marquardt on "
            "finite-difference Jacobians of MuJoCo rollouts of the true MJCF), one run each, "
            "same process, same start; errors: the largest relative error over the inertia, "
            "viscous and Coulomb levels",
            f"{d.get('cpu_count', '?')} cores, load "
            f"{_load(loads[0] if loads else None, loads[-1] if loads else None)}, "
            f"{_blas(d.get('blas'))}", command))
    return rows


SOURCES: tuple[Source, ...] = (
    Source("simulate_default", "out/bench_simulate_default/results.json",
           "python studies/bench_simulate.py --part single --xla-default "
           "--out out/bench_simulate_default",
           "`simulate_sampled`, one closed loop, XLA's default options, against a plain "
           "hand-written `lax.scan` and scipy", simulate_rows),
    Source("simulate", "out/bench_simulate/results.json",
           "python studies/bench_simulate.py --part single",
           "`simulate_sampled`, one closed loop, jaxflex's lean XLA CPU options and the "
           "small-loop option, against a plain hand-written `lax.scan` and scipy", simulate_rows),
    Source("export_step", "out/bench_export_step/results.json",
           "python studies/bench_export_step.py",
           "one step of the exported controller, Python and C", export_step_rows),
    Source("compile_cache", "out/bench_compile_cache",
           "python studies/bench_compile_cache.py",
           "a second run of a command on the same compilation cache", compile_cache_rows),
    Source("sweep", "out/bench_sweep/results.json", "python studies/bench_sweep.py",
           "batched sweep against solve_ivp, and 2 host devices against 1", sweep_rows),
    Source("gpu", "out/bench_sweep/gpu.json", "python studies/bench_sweep.py --gpu",
           "batched sweep on a GPU against the same machine's CPU", gpu_rows),
    Source("ident_scipy", "out/ident_bench_scipy/results.json",
           "python studies/ident_bench_scipy.py",
           "identification against scipy's least squares", ident_scipy_rows),
    Source("peer_sysid", "out/peer_sysid/results.json",
           "python studies/peer_sysid.py --out out/peer_sysid",
           "identification against `mujoco.sysid` on the same logs", peer_rows),
)


def _read(path: Path) -> Any:
    """A JSON file's content; for a folder, its ``results_*.json`` by name (empty: none)."""
    if path.is_dir():
        return {p.name: json.loads(p.read_text()) for p in path.glob("results_*.json")}
    return json.loads(path.read_text())


def source_of(command: str) -> str | None:
    """The source whose command a row's "regenerate with" command extends (the longest)."""
    fits = [s for s in SOURCES if command == s.command or command.startswith(s.command + " ")]
    return max(fits, key=lambda s: len(s.command)).option if fits else None


def page_rows(text: str) -> list[Row]:
    """The rows of a page ``render`` wrote (its table's lines, cells unescaped)."""
    rows = []
    for line in text.splitlines():
        if not line.startswith("| ") or line.startswith("| what |"):  # not a row, or the head
            continue
        cells = [c.strip().replace("\\|", "|")
                 for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
        if len(cells) == 5:
            rows.append(Row(*cells[:4], cells[4].strip("`")))
    return rows


def collect(paths: dict[str, Path], previous: list[Row] = ()) -> list[Row]:
    """The rows of every source: read from its JSON (``paths``: option name -> path); where
    the JSON is missing, that source's rows of the ``previous`` page (a benchmark run on
    another machine, a GPU's, keeps its figures), else one "not measured" row."""
    rows: list[Row] = []
    for src in SOURCES:
        path = paths[src.option]
        got = src.rows(_read(path), src.command) if path.exists() else []
        got = got or [r for r in previous if source_of(r.command) == src.option
                      and not r.figure.startswith("not measured")]
        rows += got or [Row(src.what, f"not measured: run `{src.command}`", "", "",
                            src.command)]
    return rows


def render(rows: list[Row]) -> str:
    """The markdown page: the fixed header and the table."""
    cell = lambda s: s.replace("|", "\\|").replace("\n", " ")
    lines = [HEADER, "| what | figure | baseline | machine | regenerate with |",
             "|---|---|---|---|---|"]
    lines += [f"| {cell(r.what)} | {cell(r.figure)} | {cell(r.baseline)} | {cell(r.machine)} "
              f"| `{r.command}` |" for r in rows]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> list[Row]:
    """Read the benchmarks' JSON, write the table; returns its rows."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for src in SOURCES:
        ap.add_argument("--" + src.option.replace("_", "-"), default=src.default,
                        help=f"{src.command.split()[1]}'s "
                             f"{'folder' if src.option == 'compile_cache' else 'JSON'} "
                             f"(default {src.default})")
    ap.add_argument("--doc", default=None, help="the page to write (default docs/performance.md; "
                                                "with --small, OUT/performance.md)")
    ap.add_argument("--out", default="out/performance_table", help="folder of table.json")
    ap.add_argument("--fresh", action="store_true",
                    help="forget the page's rows of benchmarks whose JSON is missing")
    ap.add_argument("--small", action="store_true",
                    help="smoke test: write the page to --out, leave docs/ alone")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    doc = Path(a.doc) if a.doc else (out / "performance.md" if a.small
                                     else ROOT / "docs" / "performance.md")
    previous = page_rows(doc.read_text()) if doc.exists() and not a.fresh else []
    rows = collect({src.option: Path(getattr(a, src.option)) for src in SOURCES}, previous)
    doc.write_text(render(rows))
    (out / "table.json").write_text(json.dumps([r._asdict() for r in rows], indent=2) + "\n")
    measured = sum(not r.figure.startswith("not measured") for r in rows)
    print(f"wrote {doc}: {len(rows)} rows, {measured} measured; rows also in {out / 'table.json'}")
    return rows


if __name__ == "__main__":
    main()
