"""Tests run in float64 (identification and certificates need it).

Every test module ends by dropping JAX's compiled executables (``jax.clear_caches``): each one
holds its own memory mappings (measured: 3 per ``jax.jit`` executable, about 18 per
``equinox.filter_jit`` one), and the whole suite in one process compiles enough of them to pass
Linux's default limit of 65530 mappings per process (``vm.max_map_count``), after which LLVM's
code allocation fails and the process dies in XLA compilation or a cache read (seen twice at
90% of the suite, in test_tune, with no Python error). Clearing after each module keeps the
count at what one module needs; executables a later module needs again are read back from
JAX's persistent compilation cache.

That cache is on from the start, in a folder of this process's own (each test worker has one;
empty at the start, removed at the end), and ``JAXFLEX_CACHE_DIR`` points the command line's
own cache there too (in-process and in subprocesses): a run never reads what an earlier run or
the user's ``~/.cache`` kept.

Tests compile for compile speed (``XLA_FLAGS`` below, inherited by the command lines they
start): XLA CPU's older emitters (as ``jaxflex.runtime.tracecache.FAST_COMPILE_OPTIONS``) and
LLVM at its first optimisation level. Most of a test's time is the compilation of programs it
runs for a few steps. Level 0 is not used: there, two evaluations of one residual at one point
differ by more than the fit's tolerance, and a fit to exact data never meets its stop test.
"""

import atexit
import contextlib
import gc
import os
import shutil
import tempfile

#: before JAX starts its backend, which reads XLA_FLAGS once
_COMPILE_FOR_SPEED = "--xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=1"
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_COMPILE_FOR_SPEED}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# after float64 is on: no jaxflex module is imported under JAX's float32 default
from jaxflex.app.cli import enable_compilation_cache  # noqa: E402

_CACHE = tempfile.mkdtemp(prefix="jaxflex-tests-cache-")
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)
os.environ["JAXFLEX_CACHE_DIR"] = _CACHE
enable_compilation_cache(traces=False)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
    yield
    jax.clear_caches()
    gc.collect()


@contextlib.contextmanager
def _lowerings(by_name: bool = False):
    """The names of the programs JAX lowers inside the block (a list, filled as it runs).
    ``by_name``: the kept-programs cache (``jaxflex.runtime.tracecache``, which a command run
    in this process may have turned on) is off inside the block, so that programs lower by
    their own names (kept ones lower as "call"); its state is restored after."""
    from jaxflex.runtime import tracecache

    lowered: list[str] = []

    def listen(event: str, secs: float, **kw) -> None:
        if event.endswith("jaxpr_to_mlir_module_duration"):
            lowered.append(kw.get("fun_name", "?"))

    kept = tracecache.folder()
    if by_name:
        tracecache.enable(None)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield lowered
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
        tracecache.enable(kept)


@pytest.fixture
def lowerings():
    """``with lowerings() as lowered:`` collects the names of the programs lowered inside
    the block (tests that a call reuses compiled programs); ``lowerings(by_name=True)``
    with the kept-programs cache off inside it."""
    return _lowerings
