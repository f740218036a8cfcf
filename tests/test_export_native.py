"""The C export (jaxflex.export.cgen, .native): C99 with libm only, the same traced program as
the Python export, compiled with the system's cc and called through ctypes against the JAX
controller; run-loop runs it."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from jaxflex.export import (
    check_parity,
    generate_source,
    load_module,
    parity_ok,
    rig_controller,
    trace,
)
from jaxflex.export.native import compile_c, export_c, find_cc, load_c
from jaxflex.io.presets import REPRODUCE_LEAK, paper_params, paper_sensing, with_estimator

needs_cc = pytest.mark.skipif(find_cc() is None, reason="no C compiler (cc) on this machine")


def _reproduce_params() -> dict:
    p = paper_params().to_dict()
    p["gains"]["leak"] = [REPRODUCE_LEAK]
    return p


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """reproduce's default configuration (paper sensing, Kalman filter, leak), traced once
    and written as C and Python."""
    sc = rig_controller(_reproduce_params(), sensing=with_estimator(paper_sensing(), "kalman"))
    tr = trace(sc)
    folder = tmp_path_factory.mktemp("c_export")
    src, hdr = export_c(sc, folder / "controller.c", traced=tr)
    return sc, folder, src, hdr, load_module(generate_source(sc, traced=tr))


def test_header_declares_the_entry_points(exported):
    _, folder, src, hdr, _ = exported
    assert (folder / "controller.h").read_text() == hdr
    for decl in ("int jaxflex_state_size(void);", "void jaxflex_reset(void *state);",
                 "void jaxflex_step(void *state, double t, const double *q1, const double *q2, "
                 "double *tau);", "void jaxflex_step_ref(void *state, double t, const double *q1,"):
        assert decl in hdr
    assert "#define JAXFLEX_REF_ROWS 5" in hdr and "#define JAXFLEX_N_JOINTS 1" in hdr
    # C99 and libm only
    assert set(re.findall(r"#include\s+[<\"]([^>\"]+)", src)) == {"math.h", "controller.h"}
    assert "jaxflex_info" in src


@needs_cc
def test_compiles_cleanly_as_c99(exported, tmp_path):
    """Strict C99 with every warning an error."""
    import subprocess

    _, folder, _, _, _ = exported
    res = subprocess.run([find_cc(), "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror",
                          "-c", str(folder / "controller.c"), "-o", str(tmp_path / "c.o")],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("experiment", ["sinusoid", "polynomial", "fast"])
def test_c_parity_with_jax_and_python(exported, experiment, tmp_path):
    """The C controller in reproduce's full 10 s closed loop of each of the paper's
    experiments under the paper's sensing, with the Kalman filter and the leak: equal to the
    JAX controller compiled without XLA's fusion (each carrying its own state) to 1e-12 N m,
    to the jitted one within what XLA's two compilations differ by (plus 1e-12), and bit
    for bit to the Python export of the same traced program."""
    sc, folder, _, _, py = exported
    if experiment != "sinusoid":
        sc = rig_controller(_reproduce_params(), experiment,
                            sensing=with_estimator(paper_sensing(), "kalman"))
        tr = trace(sc)
        folder = tmp_path
        export_c(sc, folder / "controller.c", traced=tr)
        py = load_module(generate_source(sc, traced=tr))
    cmod = load_c(folder / "controller.c")
    assert cmod.VELOCITY == "kalman" and cmod.N_JOINTS == 1 and cmod.DT == 1e-3
    assert cmod.STATE_NAMES == py.STATE_NAMES
    assert cmod.DEFAULT_PARAMS == py.DEFAULT_PARAMS and cmod.SPEC_MAP == py.SPEC_MAP
    r = check_parity(sc, cmod, t_final=10.0)
    assert r.unfused_diff <= 1e-12, str(r)
    assert r.max_abs_diff <= float(np.max(np.abs(r.tau_unfused - r.tau_jax))) + 1e-12, str(r)
    assert r.eager_diff <= 1e-14 and parity_ok(r), str(r)
    ctrl = py.Controller()
    tau_py = [ctrl.step(k * 1e-3, r.q1_meas[k, 0], r.q2_meas[k, 0]) for k in range(10_000)]
    np.testing.assert_array_equal(r.tau_export[:, 0], np.array(tau_py))


@needs_cc
def test_c_reference_input_and_reset(exported):
    """jaxflex_step_ref with the recorded reference's derivatives gives jaxflex_step's torques
    (to rounding); reset starts again from the next angles; the state is the declared size."""
    sc, folder, _, _, _ = exported
    cmod = load_c(folder / "controller.c")
    a, b = cmod.Controller(), cmod.Controller()
    assert cmod._lib.jaxflex_state_size() == 8 * (1 + len(cmod.STATE_NAMES))
    first, diffs = None, []
    for k in range(300):
        t = k * 1e-3
        q1 = 0.05 * math.sin(math.pi * t)
        q2 = q1 + 1e-3 * math.cos(5.0 * t)
        ta = a.step(t, q1, q2)
        tb = b.step(t, q1, q2, ref=b.reference_derivatives(t))
        first = ta if first is None else first
        diffs.append(abs(ta - tb))
    assert max(diffs) <= 1e-12
    assert a.reference(0.25) == pytest.approx(float(sc.controller.trajectory.position(0.25)[0]),
                                              abs=1e-15)
    a.reset()
    assert a.state is None
    assert a.step(0.0, 0.0, 0.0) == first
    with pytest.raises(ValueError, match="ref"):
        a.step(0.0, 0.0, 0.0, ref=[1.0])


@pytest.mark.slow
def test_cli_export_c_check(tmp_path, capsys):
    """`export --out controller.c` writes controller.c and controller.h; --check compiles it
    and runs it in the closed loop, --check-reference also with the reference given at each
    step (or it says there is no compiler)."""
    from jaxflex.app.cli import main

    out = tmp_path / "controller.c"
    rc = main(["export", "--out", str(out), "--check", "--check-reference",
               "--check-duration", "0.3"])
    text = capsys.readouterr().out
    assert out.exists() and (tmp_path / "controller.h").exists()
    assert "wrote" in text and "controller.h" in text
    if find_cc() is None:
        assert rc == 1 and "no C compiler" in text
    else:
        assert rc == 0, text
        assert text.count("check passed") == 2 and "reference given at each sample" in text


@needs_cc
def test_compile_error_is_reported(tmp_path):
    bad = tmp_path / "bad.c"
    bad.write_text("int f(void) { return }\n")
    with pytest.raises(RuntimeError, match="compiling"):
        compile_c(bad)


@pytest.mark.slow
@needs_cc
def test_run_loop_runs_the_c_controller(exported, tmp_path, capsys):
    """run-loop --controller controller.c: the C controller in the fixed-period loop against
    the simulated rig, lock-step, to completion with a log; with --reference the rig gives it
    another task's reference at each step."""
    from jaxflex.app.cli import main

    _, folder, _, _, _ = exported
    log = tmp_path / "run.csv"
    rc = main(["run-loop", "--controller", str(folder / "controller.c"), "--duration", "0.3",
               "--lockstep", "--log", str(log)])
    text = capsys.readouterr().out
    assert rc == 0, text
    summary = json.loads((tmp_path / "run.summary.json").read_text())
    assert summary["completed"] and summary["samples"] == 300
    assert log.read_text().splitlines()[0] == "t,tau,q1,q2,q1d"
    # the rig's reference instead of the recorded one (--reference)
    from jaxflex.app.cli.run_loop import rig_reference
    from jaxflex.io.logs import load_log

    log2 = tmp_path / "run_poly.csv"
    rc = main(["run-loop", "--controller", str(folder / "controller.c"), "--duration", "0.3",
               "--lockstep", "--reference", "polynomial", "--log", str(log2)])
    assert rc == 0, capsys.readouterr().out
    q1d = np.asarray(load_log(log2).q1d).reshape(-1)
    np.testing.assert_allclose(q1d, rig_reference("polynomial", 1, 1e-3, 0.3)[:300, 0, 0],
                               atol=1e-12)


@pytest.mark.slow
@needs_cc
def test_c_parity_two_joints(tmp_path):
    p = _reproduce_params()
    p["plant"] = {"I": [0.07, 0.05], "J": [0.005, 0.004], "K": [6.77, 8.0]}
    p["friction"] = {k: [v[0], v[0]] for k, v in p["friction"].items()}
    p["gains"] = {k: [v[0], v[0]] for k, v in p["gains"].items()}
    sc = rig_controller(p, sensing=with_estimator(paper_sensing(), "kalman"))
    export_c(sc, tmp_path / "controller.c")
    cmod = load_c(tmp_path / "controller.c")
    assert cmod.N_JOINTS == 2
    r = check_parity(sc, cmod, t_final=1.0)
    assert r.tau_jax.shape == (1000, 2)
    assert parity_ok(r), str(r)


@pytest.mark.slow
@needs_cc
def test_bench_export_step_study_small(tmp_path):
    import importlib.util
    import pathlib

    path = pathlib.Path(__file__).parents[1] / "studies" / "bench_export_step.py"
    spec = importlib.util.spec_from_file_location("bench_export_step", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    res = mod.main(["--small", "--out", str(tmp_path), "--repeats", "2"])
    assert json.loads((tmp_path / "results.json").read_text())["baseline"] == "c"
    b = res["backends"]
    assert set(b) == {"numpy", "python", "c", "c_ctypes"}
    assert all(v["max_abs_diff_to_jax_Nm"] <= 1e-12 for v in b.values())
    assert b["c"]["median_us"] > 0 and res["setup_s"]["compile_c"] > 0
