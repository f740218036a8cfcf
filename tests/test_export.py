"""Export of the cascade controller to standalone numpy (jaxflex.export): parity with JAX,
no JAX in the generated file, parameter overrides, translator primitives, clear errors."""

from __future__ import annotations

import ast
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.export import (
    UnsupportedPrimitive,
    build_controller,
    check_parity,
    export_controller,
    generate_source,
    load_module,
    parity_ok,
)
from jaxflex.export.pygen import function_source
from jaxflex.io.presets import paper_params


@pytest.fixture(scope="module")
def default_export():
    c = build_controller()  # paper parameters, paper sinusoid, CascadeController's q2d default
    src = generate_source(c)
    return c, src, load_module(src)


def _imports(src: str) -> set[str]:
    mods = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Import):
            mods |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            mods.add((node.module or "").split(".")[0])
    return mods


def test_generated_file_imports_only_numpy_and_stdlib(default_export, tmp_path):
    _, src, _ = default_export
    assert _imports(src) <= {"math", "json", "fractions", "numpy"}
    assert "jax" not in src.split('"""', 2)[2].replace("jaxflex", "")
    # it runs in a fresh interpreter where importing jax fails
    path = tmp_path / "controller.py"
    path.write_text(src)
    code = (
        "import sys; sys.modules['jax'] = None; sys.modules['jaxflex'] = None\n"
        "import importlib.util as u\n"
        f"s = u.spec_from_file_location('c', {str(path)!r}); m = u.module_from_spec(s)\n"
        "s.loader.exec_module(m); c = m.Controller(); c.reset()\n"
        "print(c.step(0.0, 0.0, 0.0), c.step(0.001, 1e-4, 2e-4))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert len(out.stdout.split()) == 2


@pytest.mark.slow
def test_parity_default_long_run(default_export):
    """10 s of closed loop (10^4 samples, quantised encoders, controller-side velocity
    estimation): exported torques equal the JAX sampled-data controller's to 1e-12."""
    c, _, mod = default_export
    r = check_parity(c, mod, t_final=10.0)
    assert r.tau_jax.shape == (10_000, 1)
    assert np.ptp(r.tau_jax) > 1.0  # the run actually exercises the law
    assert r.max_abs_diff <= 1e-12, str(r)


@pytest.mark.slow
def test_parity_filtered_polynomial():
    """The other exported q2d method and the piecewise-polynomial reference (clip in the
    jaxpr). Where XLA itself does not reproduce its own torques to 1e-12 (a recompiled scan
    of the same controller), the export must stay within 4x of that."""
    c = build_controller(trajectory="polynomial", q2d_method="filtered")
    r = check_parity(c, t_final=4.0)
    assert parity_ok(r), str(r)
    assert r.max_abs_diff < 1e-9, str(r)


@pytest.mark.slow
def test_parity_two_joints():
    p = paper_params().to_dict()
    p["plant"] = {"I": [0.07, 0.05], "J": [0.005, 0.004], "K": [6.77, 8.0]}
    p["friction"] = {k: [v[0], v[0]] for k, v in p["friction"].items()}
    p["gains"] = {k: [v[0], v[0]] for k, v in p["gains"].items()}
    c = build_controller(p)
    mod = load_module(generate_source(c))
    assert mod.N_JOINTS == 2
    r = check_parity(c, mod, t_final=2.0)
    assert r.tau_jax.shape == (2000, 2)
    assert parity_ok(r), str(r)
    tau = mod.Controller().step(0.0, [0.0, 0.0], np.zeros(2))
    assert isinstance(tau, np.ndarray) and tau.shape == (2,)


def test_parameter_override_equals_fresh_export(tmp_path):
    """Controller(params=...) and Controller.from_json rebuild the constants: same torques
    as a controller exported with those values."""
    base = build_controller(tau_max=1e3)  # no saturation on the synthetic angles
    mod = load_module(generate_source(base))
    pd = paper_params().to_dict()
    pd["gains"]["L1"] = [150.0]
    pd["friction"]["Fc"] = [0.09]
    other = load_module(generate_source(build_controller(pd, tau_max=1e3))).Controller()
    path = tmp_path / "p.json"
    path.write_text(json.dumps(pd))
    for ctrl in (mod.Controller(params={"gains.L1": [150.0], "model.friction.Fc": 0.09}),
                 mod.Controller.from_json(path)):
        other.reset()
        diffs, changed = [], []
        plain = mod.Controller()
        for k in range(300):
            t = k * 1e-3
            q1 = 0.05 * np.sin(np.pi * t) + 1e-3
            q2 = q1 + 1e-3 * np.cos(5.0 * t)
            a, b = ctrl.step(k * 1e-3, q1, q2), other.step(k * 1e-3, q1, q2)
            diffs.append(abs(a - b))
            changed.append(abs(a - plain.step(k * 1e-3, q1, q2)))
        assert max(diffs) <= 1e-13
        assert max(changed) > 1e-3  # the override did something
    with pytest.raises(ValueError, match="unknown controller parameter"):
        mod.Controller(params={"gains.L3": 1.0})
    with pytest.raises(ValueError, match="expected 1 value"):
        mod.Controller(params={"gains.L1": [1.0, 2.0]})


def test_export_follows_the_jax_controller():
    """One source of truth: a different JAX controller gives different generated code."""
    a = generate_source(build_controller(compensation=True))
    b = generate_source(build_controller(compensation=False))
    assert a != b
    assert "Q2D_METHOD = 'model'" in a


def test_step_input_errors(default_export):
    _, _, mod = default_export
    ctrl = mod.Controller()
    with pytest.raises(ValueError, match="q1"):
        ctrl.step(0.0, [0.0, 1.0], 0.0)
    assert isinstance(ctrl.step(0.0, np.float64(0.0), np.array([0.0])), float)


def test_ieee_fallback_matches_jax():
    """Division by zero / overflow in a branch that jnp.where discards: the generated code
    falls back to numpy float64 and gives JAX's inf/nan-free selected result."""
    def f(x):
        return jnp.where(x > 0, 1.0 / jnp.where(x > 0, x, 1.0), jnp.exp(800.0 * x) * 0.0 + 1.0 / x)

    ns: dict = {}
    exec(function_source(f, jnp.array([0.5, 0.0, -2.0])), ns)
    out = ns["f"](0.5, 0.0, -2.0)
    ref = np.asarray(f(jnp.array([0.5, 0.0, -2.0])))
    np.testing.assert_array_equal(np.array(out), ref)


def test_translator_primitives_match_jax():
    def f(x, y, A):
        z = jnp.concatenate([x, jnp.pad(y, (1, 2))])
        w = jnp.cumsum(z)[::-1] * jnp.sign(z) + jnp.clip(z, -0.3, 0.4) ** 3
        m = A.T @ x[:3] + jnp.max(A, axis=1) - jnp.min(A, axis=0)
        s = jnp.linalg.solve(A + 3 * jnp.eye(3), x[:3])
        u = jnp.where(w > 0, jnp.arctan2(w, 1.5), jnp.tanh(w + 0.1) ** -2)
        v = jnp.sum(jnp.expm1(x) * jnp.log1p(jnp.abs(x))) + jnp.sqrt(jnp.abs(y)).prod()
        return u, m, s, v, jnp.outer(x, y).reshape(-1), jnp.stack([y, -y]).T

    rng = np.random.default_rng(0)
    args = rng.normal(size=4), rng.normal(size=2), rng.normal(size=(3, 3))
    ns: dict = {}
    exec(function_source(f, *args), ns)
    out = np.array(ns["f"](*[v for a in args for v in np.ravel(a)]))
    ref = np.concatenate([np.ravel(o) for o in f(*args)])
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=1e-14)


def test_translator_indexing_and_pivoted_solve_match_jax():
    """Indexing at constant indices (gather, ``.at[].set`` and ``.at[].add`` scatters, a
    locked chain's free-joint selection) and a linear solve whose pivots move rows (a
    coupled arm's mass matrix) translate, and equal JAX's results."""
    idx = np.array([2, 0, 1])

    def f(x, A):
        M = A[idx][:, idx] + jnp.diag(x[:3])
        q = jnp.zeros(6).at[jnp.array([0, 2, 4])].set(x[:3]).at[1].add(x[3])
        return jnp.linalg.solve(M, x[1:]), q, x[idx], jnp.stack(jnp.unstack(A, axis=1))

    rng = np.random.default_rng(1)
    # the largest entry of each column below the diagonal, so partial pivoting swaps rows
    A = np.array([[0.1, 2.0, 0.3], [3.0, 0.2, 0.5], [0.4, 5.0, 0.1]])
    args = rng.normal(size=4), A
    ns: dict = {}
    exec(function_source(f, *args), ns)
    out = np.array(ns["f"](*[v for a in args for v in np.ravel(a)]))
    ref = np.concatenate([np.ravel(o) for o in f(*args)])
    np.testing.assert_allclose(out, ref, rtol=1e-13, atol=1e-14)


def test_unsupported_primitive_is_named():
    def f(x):
        return jax.lax.while_loop(lambda c: c[0] < 10.0, lambda c: c * 2.0, x)

    with pytest.raises(UnsupportedPrimitive, match="'while'"):
        function_source(f, jnp.ones(2))


def test_cli_export_check(tmp_path, capsys):
    from jaxflex.app.cli import main

    out = tmp_path / "controller.py"
    params = tmp_path / "p.json"
    params.write_text(json.dumps(paper_params().to_dict()))
    rc = main(["export", "--params", str(params), "--out", str(out), "--q2d", "filtered",
               "--check", "--check-duration", "0.5"])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "largest difference" in text
    assert out.exists() and "class Controller" in out.read_text()
    mod = load_module(out)
    assert mod.Q2D_METHOD == "filtered"


def test_export_controller_writes_file(tmp_path):
    path = tmp_path / "c.py"
    src = export_controller(build_controller(q2d_method="filtered"), path)
    assert path.read_text() == src


def test_translator_unrolls_static_scan():
    def f(x, w):
        def body(c, wi):
            c = jnp.tanh(c * wi) + 0.1 * c
            return c, jnp.sum(c)

        c, ys = jax.lax.scan(body, x, w)
        return c, ys

    x, w = np.array([0.3, -0.2]), np.linspace(0.5, 1.5, 4)
    ns: dict = {}
    exec(function_source(f, x, w), ns)
    out = np.array(ns["f"](*x, *w))
    ref = np.concatenate([np.ravel(o) for o in f(x, w)])
    np.testing.assert_allclose(out, ref, rtol=1e-14, atol=1e-15)


# ----- the certified configuration: velocity source, Kalman filter, leak, reference --------

from jaxflex.export import ExportError, REFERENCE_ROWS, SampledController, rig_controller  # noqa: E402
from jaxflex.io.presets import REPRODUCE_LEAK, paper_sensing, with_estimator  # noqa: E402


def _reproduce_params() -> dict:
    """The paper's parameters with reproduce's default observer leak."""
    p = paper_params().to_dict()
    p["gains"]["leak"] = [REPRODUCE_LEAK]
    return p


@pytest.fixture(scope="module")
def kalman_export():
    """reproduce's default configuration: paper sensing, Kalman estimator, observer leak."""
    sc = rig_controller(_reproduce_params(), sensing=with_estimator(paper_sensing(), "kalman"))
    return sc, load_module(generate_source(sc))


def test_kalman_and_leak_exported_as_certified(kalman_export):
    """The Kalman filter (gains, state) and the leak are in the export, not dropped."""
    sc, mod = kalman_export
    assert mod.VELOCITY == "kalman"
    assert {"estimator.A", "estimator.B", "estimator.L", "gains.leak"} <= set(mod.DEFAULT_PARAMS)
    assert mod.DEFAULT_PARAMS["gains.leak"][1] == [REPRODUCE_LEAK]
    assert [k for k in mod.STATE_NAMES if k.startswith("estimator.")] == [
        "estimator.q1", "estimator.dq1", "estimator.q2", "estimator.dq2", "estimator.d"]
    assert "Kalman" in mod.CONFIG and "leak 0.2" in mod.CONFIG
    ctrl = mod.Controller()
    ctrl.step(0.0, 0.0, 0.0)
    assert set(ctrl.state) == set(mod.STATE_NAMES)
    # the filter's matrices belong to the exported model: a model override is refused by name
    with pytest.raises(ValueError, match=r"model\.friction\.Fc.*Kalman"):
        mod.Controller(params={"model.friction.Fc": 0.1})
    mod.Controller(params={"gains.L1": 150.0})


@pytest.mark.parametrize("experiment", [
    "sinusoid",
    # the C test runs these too, equal bit for bit to the Python export of the same program
    pytest.param("polynomial", marks=pytest.mark.slow),
    pytest.param("fast", marks=pytest.mark.slow),
])
@pytest.mark.slow
def test_parity_kalman_leak_under_paper_sensing(kalman_export, experiment):
    """reproduce's full 10 s closed loop of each of the paper's experiments under the paper's
    sensing (0.72 deg encoder, 12-bit DAC) with the Kalman filter and the leak. Replayed on
    the loop's sensed angles, each carrying its own state, the exported torques equal the
    JAX controller's as written (compiled without XLA's fusion, rounding primitive by
    primitive as ``jax.disable_jit`` does) to 1e-12 N m. Against the jitted loop they
    differ by no more than XLA's fused and un-fused compilations of the same controller
    differ from each other (plus 1e-12), and the DAC turns them into the loop's torques."""
    if experiment == "sinusoid":
        sc, mod = kalman_export
    else:
        sc = rig_controller(_reproduce_params(), experiment,
                            sensing=with_estimator(paper_sensing(), "kalman"))
        mod = load_module(generate_source(sc))
    r = check_parity(sc, mod, t_final=10.0)
    assert r.tau_jax.shape == (10_000, 1) and np.ptp(r.tau_jax) > 1.0
    assert r.unfused_diff <= 1e-12, str(r)
    xla_self = float(np.max(np.abs(r.tau_unfused - r.tau_jax)))
    assert r.max_abs_diff <= xla_self + 1e-12, str(r)
    assert r.applied_diff == 0.0, str(r)
    assert r.eager_diff <= 1e-14, str(r)
    assert parity_ok(r), str(r)


def test_parity_check_catches_a_dropped_estimator(kalman_export):
    """The check can fail: the same law with dirty-derivative velocities (the estimator
    dropped) is far from the certified controller in its own closed loop."""
    sc, _ = kalman_export
    dirty = rig_controller(_reproduce_params(), sensing=paper_sensing())
    r = check_parity(sc, load_module(generate_source(dirty)), t_final=0.5)
    assert r.max_abs_diff > 1e-3
    assert not parity_ok(r)


@pytest.mark.slow
def test_reference_given_by_the_rig(kalman_export):
    """step(t, q1, q2, ref=R) follows the rig's reference, not the recorded one: a controller
    exported for the sinusoid, given the polynomial task's derivatives at each sample,
    equals the JAX controller built for the polynomial task in its closed loop (to 1e-12
    against it compiled un-fused over the run, and within XLA's own drift -- JAX against
    itself compiled batched -- against the jitted one)."""
    sc, mod = kalman_export
    poly = rig_controller(_reproduce_params(), "polynomial",
                          sensing=with_estimator(paper_sensing(), "kalman"))
    r = check_parity(poly, mod, t_final=2.0, reference=True)
    assert parity_ok(r) and r.eager_diff <= 1e-14, str(r)
    assert r.unfused_diff <= 1e-12 and r.max_abs_diff <= 4e-12, str(r)
    ctrl = mod.Controller()  # without ref: the recorded sinusoid, another torque
    tau = [ctrl.step(k * 1e-3, r.q1_meas[k, 0], r.q2_meas[k, 0]) for k in range(500)]
    assert np.max(np.abs(np.array(tau) - r.tau_jax[:500, 0])) > 1e-2
    ctrl = mod.Controller()
    R = ctrl.reference_derivatives(0.3)
    assert R.shape == (REFERENCE_ROWS, 1)
    np.testing.assert_allclose(R[:, 0], np.asarray(
        sc.controller.trajectory.derivatives(0.3, order=REFERENCE_ROWS - 1))[:, 0], rtol=1e-13)
    with pytest.raises(ValueError, match="ref"):
        ctrl.step(0.0, 0.0, 0.0, ref=[0.0, 0.0])


@pytest.mark.parametrize("sensing", ["ideal", {"velocity": "exact", "q1_resolution": 1e-4}])
def test_exact_velocity_refused_by_name(sensing, tmp_path, capsys):
    """A controller section whose sensing gives the controller exact velocities (a rig
    measures none) is refused naming controller.sensing.velocity, by the library and the
    command line."""
    p = paper_params().to_dict()
    p["controller"] = {"sensing": sensing}
    with pytest.raises(ExportError, match=r"controller\.sensing\.velocity"):
        rig_controller(p)
    path = tmp_path / "p.json"
    path.write_text(json.dumps(p))
    from jaxflex.app.cli import main

    assert main(["export", "--params", str(path), "--out", str(tmp_path / "c.py")]) == 2
    assert "controller.sensing.velocity" in capsys.readouterr().err
    assert not (tmp_path / "c.py").exists()


def test_unknown_output_suffix_refused_by_name(tmp_path, capsys):
    from jaxflex.app.cli import main

    assert main(["export", "--out", str(tmp_path / "controller.cpp")]) == 2
    err = capsys.readouterr().err
    assert "'.cpp'" in err and ".py" in err and ".c" in err
    assert not list(tmp_path.iterdir())


def test_sampled_controller_of_a_bare_controller_is_the_old_export():
    """A bare CascadeController exports as before: dirty derivative, no DAC, no estimator."""
    from jaxflex.export import sampled_controller

    sc = sampled_controller(build_controller())
    assert isinstance(sc, SampledController) and sc.estimator is None
    assert sc.sensing.velocity == "filtered" and sc.sensing.dac_bits == 0
