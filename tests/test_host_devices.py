"""All cores by default: ``use_all_cores`` exposes the CPU cores as host devices
before JAX starts, the ``jaxflex`` command calls it, and a sweep sharded over two host
devices gives the numbers of a run on one device (separate processes, as a user would run)."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from jaxflex.sweep.engine import use_all_cores

_SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    from jaxflex.sweep.engine import use_all_cores
    n = use_all_cores(int(sys.argv[2]))
    jax.config.update("jax_enable_x64", True)
    from jaxflex.sweep import parse_spread, run_sweep
    assert len(jax.local_devices()) == n, (n, jax.local_devices())
    res = run_sweep(parse_spread(json.loads(sys.argv[1])), chunk_size=6, progress=False)
    print(json.dumps({"devices": res.timing["devices"], "rms": res.samples["rms_error"].tolist(),
                      "max": res.samples["max_error"].tolist(),
                      "band": res.band_q.tolist()}))
""")

TINY = {"t_final": 0.1, "substeps": 2, "seed": 3, "samples": 6, "band_dt": 0.02,
        "controller": {"compensation": True, "q2d_method": "model", "tau_max": 2.0},
        "uncertain": {"plant.I": {"dist": "uniform", "rel": 0.2},
                      "friction.Fc": {"dist": "uniform", "rel": 0.2}}}


def _run(n: int) -> dict:
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    r = subprocess.run([sys.executable, "-c", _SCRIPT, json.dumps(TINY), str(n)], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_two_host_devices_give_the_numbers_of_one():
    one, two = _run(1), _run(2)
    assert (one["devices"], two["devices"]) == (1, 2)
    # separate processes compile separately (the sharded program is partitioned): agreement
    # to rounding, not bit for bit
    for k in ("rms", "max"):
        np.testing.assert_allclose(two[k], one[k], rtol=1e-12, atol=0)
    np.testing.assert_allclose(two["band"], one["band"], rtol=1e-9, atol=1e-15)


def test_use_all_cores_keeps_a_count_set_in_xla_flags(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--foo --xla_force_host_platform_device_count=3")
    assert use_all_cores() == 3
    assert use_all_cores(1) == 3


def test_use_all_cores_refuses_a_count_below_one():
    with pytest.raises(ValueError, match="n must be >= 1"):
        use_all_cores(0)


def test_cli_exposes_every_core_before_jax_starts():
    code = ("import sys, jax; from jaxflex.app.cli import main; "
            "rc = main(['--host-devices', '2', 'sweep', 'missing.json']); "
            "print(len(jax.devices('cpu')), rc)")
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("XLA_FLAGS", None)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=120)
    assert r.stdout.split() == ["2", "2"], r.stdout + r.stderr[-2000:]


_LEAN = textwrap.dedent("""
    import os
    import jax.numpy as jnp
    import sys
    from jaxflex.runtime.xla import use_lean_xla_cpu
    small = sys.argv[1] == "1"
    before = use_lean_xla_cpu(small_loops=small)
    flags = os.environ.get("XLA_FLAGS", "")
    jnp.ones(1).block_until_ready()  # backends start: the flags must have been accepted
    after = use_lean_xla_cpu(small_loops=small)
    print(before, after, flags)
""")


@pytest.mark.parametrize("user,small", [
    ("", True), ("", False), ("--xla_cpu_enable_concurrency_optimized_scheduler=true", True),
    ("--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5000", True)])
def test_lean_xla_flags_are_added_before_jax_starts_and_keep_the_users(user, small):
    """``use_lean_xla_cpu`` adds its options before the backends start (XLA accepts them),
    the small-loop option only when asked, keeps an option the user set, and changes nothing
    once JAX has started."""
    from jaxflex.runtime.xla import LEAN_XLA_CPU_FLAGS, SMALL_LOOP_XLA_CPU_FLAGS

    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": user}
    r = subprocess.run([sys.executable, "-c", _LEAN, "1" if small else "0"], env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    before, after, *flags = r.stdout.split()
    assert (before, after) == ("True", "False")
    for f in LEAN_XLA_CPU_FLAGS + SMALL_LOOP_XLA_CPU_FLAGS:
        name = f.split("=")[0]
        kept = [g for g in flags if g.startswith(name)]
        ours = [f] if small or f in LEAN_XLA_CPU_FLAGS else []
        assert kept == ([user] if user.startswith(name) else ours), flags


_SMALL_LOOP_RUN = textwrap.dedent("""
    import sys
    import numpy as np
    from jaxflex.runtime.xla import use_lean_xla_cpu
    use_lean_xla_cpu(small_loops=sys.argv[1] == "1")
    import jax
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    from jaxflex.core.controller import CascadeController
    from jaxflex.io.presets import paper_gains, paper_plant, paper_sinusoid
    from jaxflex.core.sensing import Sensing
    from jaxflex.sim.simulate import simulate_sampled
    plant = paper_plant()
    ctrl = CascadeController(model=plant, gains=paper_gains(), trajectory=paper_sinusoid())
    run = eqx.filter_jit(lambda p, c: simulate_sampled(p, c, 1.0,
                                                       sensing=Sensing(velocity="filtered")))
    np.save(sys.argv[2], np.asarray(run(plant, ctrl).q1))
""")


@pytest.mark.slow
def test_small_loop_option_runs_the_same_closed_loop(tmp_path):
    """The small-loop option (``SMALL_LOOP_XLA_CPU_FLAGS``: a loop as one compiled function)
    changes XLA's code, not the numbers: the same 1 s closed loop with and without it agrees
    to rounding."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": ""}
    q = []
    for small in ("1", "0"):
        path = tmp_path / f"q1_{small}.npy"
        r = subprocess.run([sys.executable, "-c", _SMALL_LOOP_RUN, small, str(path)], env=env,
                           capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        q.append(np.load(path))
    assert q[0].shape == q[1].shape and q[0].size > 900
    assert np.max(np.abs(q[0] - q[1])) <= 1e-12 * np.max(np.abs(q[1]))


def test_small_loop_commands_are_commands():
    """``jaxflex.app.cli.SMALL_LOOP_COMMANDS`` names commands the parser knows (a renamed command
    would silently lose its XLA option), and the batched sweep is not among them."""
    from jaxflex.app.cli import SMALL_LOOP_COMMANDS, build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(SMALL_LOOP_COMMANDS) <= set(sub.choices), SMALL_LOOP_COMMANDS
    assert "sweep" not in SMALL_LOOP_COMMANDS
