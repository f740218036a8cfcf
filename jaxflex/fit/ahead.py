"""Programs made ahead: calls whose only purpose is to compile, or read from the caches, the
programs a later part of a run needs, made in a background thread while the calling thread
works on something else (``identify``: the solver while the static map is fitted;
``discover``: the held-out fits and the replays while the nominal model is fitted).

On the project's two-core machine a fit runs its compiled loop on one core, and reading a
large program from JAX's persistent cache (XLA deserialises and links its object code:
0.7-1.0 s for a solver of a 20 s log) takes the other. A call made ahead computes something
small (one solver step) and throws it away; a failure there is left for the real call to
meet and report.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

import jax

#: The background thread's name (tests check that none is left running).
THREAD_NAME = "jaxflex-compile-ahead"


class Ahead:
    """Runs ``work`` (callables without arguments, in order) in a daemon thread under the
    calling thread's float64 mode (thread-local under ``requires_float64``); ``wait(i)``
    blocks until the i-th has run (or failed), ``join`` until all have. Under
    ``jax.disable_jit`` (or with no work) nothing is started."""

    def __init__(self, work: Sequence[Callable[[], Any]]) -> None:
        self._done = [threading.Event() for _ in work]
        self._thread: threading.Thread | None = None
        if jax.config.jax_disable_jit or not work:
            for event in self._done:
                event.set()
            return
        x64 = bool(jax.config.jax_enable_x64)
        self._thread = threading.Thread(target=self._work, args=(list(work), x64),
                                        name=THREAD_NAME, daemon=True)
        self._thread.start()

    def _work(self, work: list[Callable[[], Any]], x64: bool) -> None:
        with jax.enable_x64(x64):
            for thunk, done in zip(work, self._done):
                try:
                    thunk()
                except Exception:  # noqa: BLE001 - the real call meets it again and reports it
                    pass
                finally:
                    done.set()

    def wait(self, i: int) -> None:
        """Block until the ``i``-th callable has run (or failed)."""
        self._done[i].wait()

    def join(self) -> None:
        """Block until every callable has run."""
        if self._thread is not None:
            self._thread.join()
