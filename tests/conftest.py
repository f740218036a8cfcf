"""Tests run in float64 (identification and certificates need it).

Every test module ends by dropping JAX's compiled executables (``jax.clear_caches``): each one
holds its own memory mappings (measured: 3 per ``jax.jit`` executable, about 18 per
``equinox.filter_jit`` one), and the whole suite in one process compiles enough of them to pass
Linux's default limit of 65530 mappings per process (``vm.max_map_count``), after which LLVM's
code allocation fails and the process dies in XLA compilation or a cache read (seen twice at
90% of the suite, in test_tune, with no Python error). Clearing after each module keeps the
count at what one module needs; executables are recompiled (or read from the persistent
cache) where a later module needs them again.
"""

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
    yield
    jax.clear_caches()
    gc.collect()
