"""Programs made ahead: calls whose only purpose is to compile, or read from the caches, the
programs a later part of a run needs, made in a background thread while the calling thread
works on something else (``identify``: the solver while the static map is fitted;
``discover``: the held-out fits and the replays while the nominal model is fitted).

On the project's two-core machine a fit runs its compiled loop on one core, and reading a
large program from JAX's persistent cache (XLA deserialises and links its object code)
takes the other. A call made ahead computes something
small (one solver step) and throws it away; a failure there is left for the real call to
meet and report.

Work side by side (``side_by_side``): independent calls whose results are all needed (the
candidates' screens and full fits of ``discover``, its held-out start fits from two first
guesses, the floor's draws) run in worker threads, one compiled loop on each core; the
results do not depend on the number of workers.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import jax

#: The background thread's name (tests check that none is left running).
THREAD_NAME = "jaxflex-compile-ahead"
#: The name prefix of ``side_by_side``'s worker threads.
POOL_NAME = "jaxflex-side-by-side"

T = TypeVar("T")
R = TypeVar("R")


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


#: Worker threads of ``side_by_side`` (the project's machines have two cores; one compiled
#: fit loop runs on one).
WORKERS = max(1, min(2, os.cpu_count() or 1))


def side_by_side(work: Callable[[T], R], items: Sequence[T], *,
                 workers: int | None = None) -> list[tuple[R | None, Exception | None]]:
    """``work(item)`` for every item, ``workers`` at a time (default ``WORKERS``) in threads
    under the calling thread's float64 mode, in order: a list of (result, None) or (None, the
    exception it raised). Independent fits side by side: a compiled fit loop runs on one core
    and releases the interpreter while it runs, so two fits of different candidates share the
    two cores (``discover``'s screens and full fits). The results do not depend on the
    number of workers (each call computes what it would alone). Under ``jax.disable_jit``,
    with one worker or one item, or called from a worker (no threads beyond the cores), the
    calls run here one after the other. An interrupt cancels
    the calls not yet started and waits for those running."""
    n = min(WORKERS if workers is None else int(workers), len(items))
    x64 = bool(jax.config.jax_enable_x64)

    def one(item: T) -> tuple[R | None, Exception | None]:
        with jax.enable_x64(x64):
            try:
                return work(item), None
            except Exception as e:  # noqa: BLE001 - handed back to the caller, who decides
                return None, e

    nested = threading.current_thread().name.startswith(POOL_NAME)
    if n <= 1 or nested or jax.config.jax_disable_jit:
        return [one(item) for item in items]
    pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix=POOL_NAME)
    try:
        return list(pool.map(one, items))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def all_side_by_side(work: Callable[[T], R], items: Sequence[T], *,
                     workers: int | None = None) -> list[R]:
    """``side_by_side`` when every call must succeed: the results in order, or the first
    exception (in the items' order) raised once all calls have ended."""
    done = side_by_side(work, items, workers=workers)
    for _, error in done:
        if error is not None:
            raise error
    return [result for result, _ in done]  # type: ignore[misc]
