"""XLA options set before JAX starts: CPU options that make jaxflex's loops of many small
kernels cheaper. They change how XLA schedules and emits code, never what it computes; the
``jaxflex`` command turns them on per command (``jaxflex.app.cli.SMALL_LOOP_COMMANDS``)."""

from __future__ import annotations

import os

import jax


#: XLA CPU options for jaxflex's loops of many small kernels (a sampled-data loop runs 10-70
#: kernels per sample): XLA's concurrent scheduler keeps a second thread busy for nothing in a
#: sequential loop (speeds in ``docs/performance.md``). Numbers are unchanged (both are
#: scheduling and buffer options).
LEAN_XLA_CPU_FLAGS: tuple[str, ...] = (
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
    "--xla_cpu_copy_insertion_use_region_analysis=true",
)

#: XLA CPU option for programs whose time loops carry small arrays: XLA's CPU compiler emits a
#: ``while`` loop that touches fewer bytes than this threshold (its
#: ``small_while_loop_byte_threshold``, a backend option; its default hoists none of jaxflex's
#: loops: one closed loop is hoisted from a threshold of 1e4 bytes, in part at 3e3) as one
#: compiled function instead of one runtime thunk per kernel, so an iteration no longer pays a
#: dispatch per kernel and per branch. It speeds up single closed loops, ``discover`` and
#: ``tune`` (the same numbers to rounding), but it is not a general gain: ``identify`` on a long
#: log (a traced substep loop) and batched sweep chunks run slower with it
#: (``docs/performance.md``). So it is opt-in (``use_lean_xla_cpu(small_loops=True)``),
#: and the command line turns it on for ``discover`` and ``tune``
#: (``jaxflex.app.cli.SMALL_LOOP_COMMANDS``).
#: The same operations run, in another code generator: results agree to rounding (discover's
#: dAIC to 1e-14 relative; a closed loop's trajectory, checked by a test). XLA ignores a
#: backend option it does not know (checked).
SMALL_LOOP_XLA_CPU_FLAGS: tuple[str, ...] = (
    "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=1000000000",
)


def use_lean_xla_cpu(small_loops: bool = False) -> bool:
    """Add ``LEAN_XLA_CPU_FLAGS`` (and, with ``small_loops``, ``SMALL_LOOP_XLA_CPU_FLAGS``: for
    single closed loops, ``discover``'s fits and the tuner; not for long identification logs
    nor batched sweeps) to ``XLA_FLAGS`` (a flag the user already set is kept as set). Call it
    before any JAX computation, as ``jaxflex.sweep.engine.use_all_cores``; the ``jaxflex``
    command does (``--no-lean-xla`` turns it off). Returns False when JAX's backends have
    already started (the flags would no longer take effect; nothing is changed), else True."""
    if _backends_started():
        return False
    flags = os.environ.get("XLA_FLAGS", "")
    wanted = LEAN_XLA_CPU_FLAGS + (SMALL_LOOP_XLA_CPU_FLAGS if small_loops else ())
    add = [f for f in wanted if f.split("=")[0] not in flags]
    if add:
        os.environ["XLA_FLAGS"] = " ".join([flags] + add).strip()
    return True


def _backends_started() -> bool:
    """Whether JAX's backends have started (XLA has read ``XLA_FLAGS``), asked through JAX's
    public configuration: an option that must be set before JAX starts
    (``jax_num_cpu_devices``) refuses a change once it has, and is put back otherwise."""
    name = "jax_num_cpu_devices"
    current = int(getattr(jax.config, name))
    try:
        jax.config.update(name, 2 if current == 1 else 1)
    except RuntimeError:
        return True
    jax.config.update(name, current)
    return False
