"""studies/performance_table.py: rows from a benchmark's JSON, "not measured" for a missing one."""

import json

from studies import benchkit, performance_table


def _simulate_json(path):
    """A tiny results.json in bench_simulate's layout (``--part single --xla-default``), its
    tables built by the same ``benchkit.ratio_table`` the benchmark uses."""
    base = "scipy_solve_ivp+numpy_ctrl"
    times = {base: [0.8], "jaxflex_save": [0.05, 0.06, 0.07], "jaxflex_lean": [0.04, 0.05, 0.06],
             "hand_jax_save": [0.1, 0.12, 0.14], "hand_jax_lean": [0.08, 0.1, 0.12]}
    cpu = {k: [2 * t for t in v] for k, v in times.items()}
    extra = ("hand_jax_lean", "hand_jax_save")
    machine = {"load_avg": [0.5, 0.4, 0.3], "cpu_count": 2, "XLA_FLAGS": ""}
    d = {"device": "cpu:0", "blas_threads": {"env": {"OPENBLAS_NUM_THREADS": "1"}},
         "xla_flags": "", "machine": machine, "machine_start": machine,
         "machine_end": {**machine, "load_avg": [0.7, 0.4, 0.3]},
         "single": {"t_final_s": 10.0, "samples": 10000, "substeps": 10,
                    "baseline": f"{base} (solve_ivp RK45 per sample)",
                    "compile_or_first_call_s": {"jaxflex_save": 1.5, "jaxflex_lean": 1.25,
                                                "hand_jax_save": 2.5, "hand_jax_lean": 2.25},
                    "times_s": times, "table": benchkit.ratio_table(times, base, extra),
                    "cpu_times_s": cpu, "table_cpu": benchkit.ratio_table(cpu, base, extra)}}
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps(d))


def _missing(tmp_path, but=None):
    """Every source's option pointed at a missing file (``but`` that one), so that no JSON
    in the working directory's ``out/`` reaches a test."""
    return [f"--{s.option.replace('_', '-')}={tmp_path / 'missing' / s.option}"
            for s in performance_table.SOURCES if s.option != but]


def test_rows_from_json_and_not_measured(tmp_path):
    sim = tmp_path / "sim" / "results.json"
    _simulate_json(sim)
    doc, out = tmp_path / "performance.md", tmp_path / "out"
    missing = _missing(tmp_path, but="simulate_default")
    rows = performance_table.main([f"--simulate-default={sim}", *missing, f"--doc={doc}",
                                   f"--out={out}"])
    text = doc.read_text()
    assert text.startswith(performance_table.HEADER)
    assert "never assert" in text

    save = next(r for r in rows if "saved trajectories, XLA's default" in r.what)
    # jaxflex 50 ms (median 60) against the hand-written scan's 100 ms (120): x2 both
    assert save.figure.startswith("wall 50 ms (median 60 ms) against 100 ms (120 ms): x2 min, "
                                  "x2 median; CPU time 100 ms")
    assert "compile or first call 1.5 s against 2.5 s" in save.figure
    assert "hand_jax_save" in save.baseline and "load 0.50-0.70" in save.machine
    scipy = next(r for r in rows if r.what.endswith("against scipy"))
    assert "jaxflex_lean 40 ms (median 50 ms): x20 min, x16 median" in scipy.figure
    assert f"| {save.what} | {save.figure} |" in text

    not_measured = [r for r in rows if r.figure.startswith("not measured")]
    assert len(not_measured) == 7
    export = next(r for r in not_measured if "bench_export_step" in r.command)
    assert export.figure == "not measured: run `python studies/bench_export_step.py`"
    assert export.figure in text
    assert json.loads((out / "table.json").read_text())[0]["figure"] == save.figure


def test_a_benchmark_without_its_json_keeps_its_rows_from_the_page(tmp_path):
    """A GPU's rows, measured on another machine, survive a regeneration here; --fresh and a
    page without them give "not measured"."""
    doc, out = tmp_path / "performance.md", tmp_path / "out"
    missing = _missing(tmp_path)
    kept = performance_table.Row("`run_sweep` on a GPU | float64", "4e7 steps/s", "the CPU",
                                 "H200", "python studies/bench_sweep.py --gpu --small")
    sweep = performance_table.Row("sweep", "6e5 steps/s", "solve_ivp", "2 cores",
                                  "python studies/bench_sweep.py --small")
    doc.write_text(performance_table.render([kept, sweep]))
    assert performance_table.page_rows(doc.read_text()) == [kept, sweep]
    rows = performance_table.main([*missing, f"--doc={doc}", f"--out={out}"])
    assert kept in rows and sweep in rows
    # each row back under its own benchmark (the longest command it extends)
    assert rows.index(sweep) < rows.index(kept)
    rows = performance_table.main([*missing, f"--doc={doc}", f"--out={out}", "--fresh"])
    assert all(r.figure.startswith("not measured") for r in rows)


def test_gpu_rows_state_the_accuracy_and_a_run_the_budget_skipped():
    """``bench_sweep --gpu``'s JSON: the substeps chosen and their accuracy, GPU against the
    same machine's CPU; a run its time budget skipped reads "not run" (no ratio)."""
    def run(s, **k):
        return {"steps_per_s": s, "steps_per_s_median": s, "first_chunk_s": 5.0, **k}

    d = {"measured": True, "samples": 1000, "t_final": 10.0, "tolerance_rel": 1e-5,
         "device": "gpu | NVIDIA H200 | 1 | 0.11.2", "cpu_count": 16,
         "load_avg_start": [0.1], "load_avg_end": [1.0], "substeps": 3,
         "reference": {"substeps": 100}, "float32_rms_rel_diff_vs_float64_max": 4e-5,
         "runs": {"gpu_f64_1000_sub3": run(4e7, rms_rel_err_vs_reference=2e-6),
                  "gpu_f32_1000_sub3": run(6e7),
                  "cpu_f64_1000_sub3": {"skipped": "time budget of 300 s spent"},
                  "gpu_f64_10000_sub3": run(4e8), "gpu_f32_10000_sub3": run(5e8),
                  "cpu_f64_10000_sub3": run(4e7)}}
    first, big = performance_table.gpu_rows(d, "python studies/bench_sweep.py --gpu")
    assert "3 substeps (RMS metric within 2.0e-06 of 100 substeps" in first.what
    assert "the CPU not run" in first.figure and "x" not in first.figure.split("CPU")[-1]
    assert big.figure.endswith("GPU float64 x10 best")
    assert "NVIDIA H200, JAX 0.11.2" in first.machine
    assert performance_table.gpu_rows({"measured": False}, "cmd") == []


def test_peer_rows_give_the_baseline_s_time_over_jaxflex_s_and_say_which_error_is_larger():
    """``peer_rows``: per log, sysid's wall time over jaxflex's warm one (above 1: jaxflex
    faster, as every row of the table), each tool's error, a sysid run that did not converge
    said so, and whether jaxflex's error is at least as small."""
    method = {"wall_s": 10.0, "success": True}
    log = {"source": "MuJoCo 4.0.0 rigid hinge, seed 0",
           "methods": {"sysid_default": method,
                       "sysid_xscale_jac": {**method, "wall_s": 20.0, "success": False},
                       "jaxflex_same_start": {"warm_s": 40.0, "cold_s": 55.0, "steps": 99}},
           "ratios": [{"sysid": "sysid_default", "jaxflex_err": 0.004, "sysid_err": 1e-5,
                       "equal_or_better": False},
                      {"sysid": "sysid_xscale_jac", "jaxflex_err": 0.004, "sysid_err": 0.02,
                       "equal_or_better": True}]}
    d = {"logs": {"mujoco_log": log}, "versions": {"mujoco": "4.0.0"}, "cpu_count": 2,
         "load_avg_per_stage": [[0.5, 0, 0], [1.5, 0, 0]], "blas": None}
    (row,) = performance_table.peer_rows(d, "python studies/peer_sysid.py --out x")
    assert row.figure.startswith("jaxflex warm 40 s (cold 55 s, 99 steps), error 0.4%")
    assert ("sysid (default scaling) 10 s, error 0.001%: sysid/jaxflex x0.25 (jaxflex's error "
            "larger)") in row.figure
    assert ("sysid (x_scale='jac') 20 s, error 2%, not converged: sysid/jaxflex x0.5 (at equal "
            "or better jaxflex error)") in row.figure
    assert "mujoco.sysid` 4.0.0" in row.baseline and "load 0.50-1.50" in row.machine
