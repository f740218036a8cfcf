"""Traces kept across processes (``jaxflex.runtime.tracecache``, "a second run of any
command compiles under 2 s"): a kept program gives the same numbers without tracing, the key
changes with everything that shapes the trace, and code the key cannot cover is never kept."""

import dataclasses
import json
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxflex.runtime import tracecache
from jaxflex.fit import least_squares
# the compiled program itself (``jaxflex.fit.residuals`` moves a problem into its bucket of
# segment slots around it)
from jaxflex.fit.replay import _replay as _fast_replay
from jaxflex.identify import DEFAULT_FREE, excitation_torque, make_problem, perturb, synthetic_log
from jaxflex.io.presets import paper_params

# the engine's replay is compiled for compile speed (``fast_compile``: another code generator,
# the same numbers to rounding); kept with XLA's defaults, as plain jit compiles it, a kept
# program must give exactly plain jit's numbers. Both share one kept trace (one name).
_replay = tracecache.persistent_jit(_fast_replay.__wrapped__)


def residuals(prob, y):
    """The residuals read from the engine's kept replay program (``_replay``)."""
    return _replay(prob, y)["residuals"]


residuals.plain = lambda prob, y: _replay.plain(prob, y)["residuals"]

pytest.importorskip("flatbuffers")  # jax.export's serialisation


def _problem(substeps: int = 1):
    """A small identification problem, made with the cache off (its start states' program
    is not among the files the tests count)."""
    folder = tracecache.folder()
    tracecache.enable(None)
    try:
        p = paper_params()
        log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.3), substeps=1)
        init = perturb(p, DEFAULT_FREE, (1.1, 1.1, 0.9, 1.1, 0.9, 1.1))
        return make_problem(log, init, DEFAULT_FREE, segment_length=100, substeps=substeps)
    finally:
        tracecache.enable(folder)


@pytest.fixture
def kept(tmp_path):
    """The cache on, in a fresh folder, with empty in-process tables; off afterwards."""
    jax.config.update("jax_enable_x64", True)
    tracecache.enable(tmp_path / "traces")
    tracecache.forget()
    yield tmp_path / "traces"
    tracecache.enable(None)
    tracecache.forget()


def test_a_kept_program_gives_the_same_numbers_without_tracing(kept, monkeypatch):
    prob, y0 = _problem()
    plain = np.asarray(residuals.plain(prob, y0))
    first = np.asarray(residuals(prob, y0))
    files = sorted(kept.iterdir())
    assert len(files) == 1 and files[0].suffix == ".jaxflex-trace"
    np.testing.assert_array_equal(first, plain)

    # a new process: nothing in memory; the program must come from the file, untraced
    tracecache.forget()

    def no_tracing(*a, **k):
        raise AssertionError("traced again although the program was kept")

    monkeypatch.setattr(tracecache, "_trace_and_store", no_tracing)
    np.testing.assert_array_equal(np.asarray(residuals(prob, y0)), plain)
    # the whole solver (init and step programs, pytree outputs with static parts)
    monkeypatch.undo()
    sol = least_squares(prob, y0, max_steps=3)
    tracecache.forget()
    monkeypatch.setattr(tracecache, "_trace_and_store", no_tracing)
    again = least_squares(prob, y0, max_steps=3)
    assert again.steps == sol.steps and again.cost == sol.cost
    np.testing.assert_array_equal(np.asarray(jax.flatten_util.ravel_pytree(again.y)[0]),
                                  np.asarray(jax.flatten_util.ravel_pytree(sol.y)[0]))


def test_the_key_changes_with_what_shapes_the_trace():
    prob, y0 = _problem()
    k = tracecache.canonical((prob, y0))
    assert tracecache.canonical((prob, y0)) == k  # deterministic
    assert tracecache.canonical((dataclasses.replace(prob, substeps=2), y0)) != k  # static
    wider = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, a]), y0)
    assert tracecache.canonical((prob, wider)) != k  # shapes
    as32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), y0)
    assert tracecache.canonical((prob, as32)) != k  # dtypes
    # two lambdas on one line share a name, not a body
    f, g = (lambda x: x + 1), (lambda x: x * 2)
    f.__module__ = g.__module__ = "jaxflex.fake"
    assert tracecache.canonical(f) != tracecache.canonical(g)


class _UserModule(eqx.Module):
    """A model class written outside jaxflex (its code is not in the key)."""

    a: jax.Array

    def __call__(self, x):
        return self.a * x


def _user_call(m, x):  # noqa: ANN001, ANN202 - a user's function (module tests.*)
    return m(x)


def test_code_outside_jaxflex_is_never_kept(kept):
    with pytest.raises(tracecache.Unkeyable, match="outside jaxflex"):
        tracecache.canonical(_UserModule(jnp.ones(2)))
    with pytest.raises(tracecache.Unkeyable, match="outside jaxflex"):
        tracecache.canonical(lambda x: x)
    # the engine's jitted cost with a user's residual function: compiled as before, not kept
    from jaxflex.fit.solve import _cost

    c = _cost(lambda y, a: y * a, jnp.ones(3), jnp.asarray(2.0))
    assert float(c) == 6.0
    assert not any(kept.iterdir())


def test_inside_another_trace_and_damaged_files(kept):
    prob, y0 = _problem()
    # under jit (tracers): the plain path, which inlines; nothing is kept
    out = jax.jit(lambda y: residuals(prob, y))(y0)
    assert not any(kept.iterdir())
    np.testing.assert_allclose(np.asarray(out), np.asarray(residuals.plain(prob, y0)))
    # a damaged file is ignored and written again
    first = np.asarray(residuals(prob, y0))
    (path,) = kept.iterdir()
    path.write_bytes(b"not a program")
    tracecache.forget()
    np.testing.assert_array_equal(np.asarray(residuals(prob, y0)), first)
    assert path.read_bytes() != b"not a program"


_CHILD = textwrap.dedent("""
    import json, sys
    import jax, jax.monitoring as mon
    jax.config.update("jax_enable_x64", True)
    traced = []
    mon.register_event_duration_secs_listener(
        lambda ev, s, fun_name=None, **k: traced.append(fun_name)
        if ev.endswith("jaxpr_trace_duration") else None)
    from jaxflex.runtime import tracecache
    tracecache.enable(sys.argv[1])
    from jaxflex.fit import residuals
    from jaxflex.identify import DEFAULT_FREE, excitation_torque, make_problem, perturb
    from jaxflex.identify import synthetic_log
    from jaxflex.io.presets import paper_params
    p = paper_params()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=0.3), substeps=1)
    prob, y0 = make_problem(log, perturb(p, DEFAULT_FREE, (1.1,) * 6), DEFAULT_FREE,
                            segment_length=100, substeps=2)
    traced.clear()
    r = residuals(prob, y0)
    print(json.dumps({"r": [float(v) for v in r[:50]], "traced": traced}))
""")


@pytest.mark.slow
def test_a_second_process_does_not_trace(tmp_path):
    """The claim itself, across real processes: the second one reads the program and traces
    nothing of the engine's function, with bitwise the same residuals."""
    runs = []
    for _ in range(2):
        p = subprocess.run([sys.executable, "-c", _CHILD, str(tmp_path)], capture_output=True,
                           text=True, timeout=300, check=True)
        runs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    assert "flat" in runs[0]["traced"]  # the first process traced the engine's function
    assert "flat" not in runs[1]["traced"] and "_replay" not in runs[1]["traced"]
    assert runs[1]["r"] == runs[0]["r"]


def test_the_in_process_key_memo_follows_every_static_change(kept, monkeypatch):
    """A call's key is remembered under its signature (``_signature``): a repeated call does
    not walk its arguments again, and a change ``canonical`` would see changes the
    signature, so it is keyed anew (never served another call's program)."""
    prob, y0 = _problem()
    r0 = np.asarray(residuals(prob, y0))
    walked = []
    real = tracecache.canonical
    def counted(obj, _depth=0):  # noqa: ANN001, ANN202 - canonical, top-level calls counted
        if _depth == 0:
            walked.append(1)
        return real(obj, _depth)

    monkeypatch.setattr(tracecache, "canonical", counted)
    np.testing.assert_array_equal(np.asarray(residuals(prob, y0)), r0)
    assert not walked  # the same call: its key from the memo
    np.testing.assert_array_equal(np.asarray(residuals(dataclasses.replace(prob, substeps=2),
                                                       y0)),
                                  np.asarray(residuals.plain(dataclasses.replace(prob,
                                                                                 substeps=2),
                                                             y0)))
    assert len(walked) == 1  # a static field changed: keyed anew
    sig = tracecache._signature
    leaves, tree = jax.tree_util.tree_flatten((0.0,))
    assert sig(tree, [jnp.zeros(2)]) != sig(tree, [jnp.zeros(2, jnp.float32)])  # dtypes
    assert sig(tree, [jnp.zeros(2)]) != sig(tree, [jnp.zeros(3)])  # shapes
    assert sig(tree, leaves) != sig(tree, [-0.0])  # equal floats with other reprs differ
    assert sig(tree, [1]) != sig(tree, [1.0]) != sig(tree, [True])  # and other types
    # an uncommitted array's committed copy is reused while the array lives
    x = jnp.arange(3.0)
    (a,) = tracecache._committed([x])
    (b,) = tracecache._committed([x])
    assert a.committed and a is b


def test_the_configuration_digest_sees_every_flag_change():
    """``_config_digest`` is remembered under the flags' values (every persistent_jit call
    asks for it): a changed flag gives another digest at once, and the old flag the old
    digest; equal to the unremembered digest either way."""
    before = tracecache._config_digest()
    assert before == tracecache._digest_of_config()
    old = jax.config.jax_debug_nans
    try:
        jax.config.update("jax_debug_nans", not old)
        changed = tracecache._config_digest()
        assert changed != before and changed == tracecache._digest_of_config()
    finally:
        jax.config.update("jax_debug_nans", old)
    assert tracecache._config_digest() == before


def test_fast_compile_programs_share_the_trace_and_reach_xla_with_their_options(
        kept, monkeypatch):
    """``persistent_jit(fast_compile=True)`` (the engine's run-once programs): the same trace
    file as the default variant, the same numbers to rounding, and its options are the ones
    XLA compiles with (an unknown option makes the compilation fail, naming it)."""
    prob, y0 = _problem()
    fast = np.asarray(_fast_replay(prob, y0)["residuals"])
    default = np.asarray(residuals(prob, y0))
    assert len(list(kept.iterdir())) == 1  # one trace serves both variants
    np.testing.assert_allclose(fast, default, rtol=1e-12,
                               atol=1e-12 * float(np.max(np.abs(default))))
    monkeypatch.setattr(tracecache, "FAST_COMPILE_OPTIONS", {"xla_no_such_option": True})
    wrong = tracecache.persistent_jit(_fast_replay.__wrapped__, fast_compile=True)
    with pytest.raises(Exception, match="xla_no_such_option"):
        wrong(prob, y0)


def test_trace_solver_keeps_the_program_least_squares_then_runs(kept, monkeypatch):
    """``fit.trace_solver`` (identify traces its solver before a thread compiles it) keeps the
    very program the same ``least_squares`` call then runs: nothing is traced again."""
    from jaxflex.fit import trace_solver

    prob, y0 = _problem()
    options = dict(rtol=1e-10, atol=1e-10, geodesic=0.3, decrement_tol=1e-2)
    assert trace_solver(prob, y0, **options)

    def no_tracing(*a, **k):
        raise AssertionError("least_squares traced a program trace_solver had not kept")

    monkeypatch.setattr(tracecache, "_trace_and_store", no_tracing)
    sol = least_squares(prob, y0, max_steps=3, **options)
    assert sol.steps >= 1
