"""Shared habits of the benchmark studies: one BLAS thread unless stated, the
machine's load and thread settings recorded with every timing, paired repeated runs (the
methods take turns within each repeat, so a change in the shared machine's load hits all of
them alike), min and median reported, ratios against a named baseline printed side by side.

A folder, not a ``studies/*.py`` file, so that the test that runs every study skips it. The
scripts import it as ``benchkit`` (``python studies/X.py`` puts ``studies/`` on the path).
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

_BLAS_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
              "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def limit_blas_threads(n: int = 1) -> dict[str, Any]:
    """Limit BLAS/OpenMP to ``n`` threads and say how.

    Sets the usual environment variables when they are unset (effective only if numpy was not
    imported yet, which the returned ``numpy_imported_before`` records) and, when
    ``threadpoolctl`` is installed, also limits the pools already loaded. Returns what was
    in force: the variables, whether threadpoolctl was used and the pools it saw.
    """
    before = "numpy" in sys.modules
    for v in _BLAS_VARS:
        os.environ.setdefault(v, str(n))
    info: dict[str, Any] = {"requested_threads": n, "numpy_imported_before": before,
                            "env": {v: os.environ.get(v) for v in _BLAS_VARS}}
    try:
        import numpy  # noqa: F401  (load the BLAS so that threadpoolctl sees it)
        import threadpoolctl
    except ImportError:
        info["threadpoolctl"] = None
        return info
    global _LIMITER
    _LIMITER = threadpoolctl.threadpool_limits(limits=n)
    info["threadpoolctl"] = threadpoolctl.__version__
    info["pools"] = [{k: p.get(k) for k in ("user_api", "internal_api", "num_threads", "version")}
                     for p in threadpoolctl.threadpool_info()]
    return info


_LIMITER: Any = None


def machine_state() -> dict[str, Any]:
    """Load average (1, 5, 15 min), core count, XLA_FLAGS and, if JAX is imported, its
    devices: what a timing taken now ran beside."""
    out: dict[str, Any] = {"load_avg": list(os.getloadavg()), "cpu_count": os.cpu_count(),
                           "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    if "jax" in sys.modules:
        import jax

        out["jax_devices"] = [str(d) for d in jax.local_devices()]
    return out


def paired(fns: dict[str, Callable[[], Any]], repeats: int,
           only_first: dict[str, int] | None = None,
           cpu: dict[str, list[float]] | None = None) -> dict[str, list[float]]:
    """Wall times [s] of each zero-argument function over ``repeats`` rounds; in every round
    each function runs once, in an order rotated from round to round. ``only_first`` caps the
    rounds of slow functions (name -> rounds). Each function must block until its result is
    ready (``jax.block_until_ready``). ``cpu``, if given, receives the CPU time [s] of this
    process over the same runs (every thread; on a shared machine it says what a run costs
    while its wall time also counts the time other processes held the cores)."""
    names = list(fns)
    times: dict[str, list[float]] = {k: [] for k in names}
    if cpu is not None:
        cpu.update({k: [] for k in names})
    caps = only_first or {}
    for r in range(repeats):
        order = names[r % len(names):] + names[: r % len(names)]
        for k in order:
            if r >= caps.get(k, repeats):
                continue
            c0, t0 = time.process_time(), time.perf_counter()
            fns[k]()
            times[k].append(time.perf_counter() - t0)
            if cpu is not None:
                cpu[k].append(time.process_time() - c0)
    return times


def ratio_table(times: dict[str, list[float]], baseline: str,
                extra_baselines: tuple[str, ...] = ()) -> dict[str, dict[str, Any]]:
    """Per method: min and median [s], repeats, and the ratio baseline / method of the minima
    and of the medians (> 1: faster than the baseline); also against ``extra_baselines``.
    Prints the table and returns it."""
    rows: dict[str, dict[str, Any]] = {}
    b = times[baseline]
    for k, t in times.items():
        row = {"min_s": min(t), "median_s": statistics.median(t), "repeats": len(t),
               f"ratio_{baseline}_over_this_min": min(b) / min(t),
               f"ratio_{baseline}_over_this_median": statistics.median(b) / statistics.median(t)}
        for e in extra_baselines:
            if e in times:
                row[f"ratio_{e}_over_this_min"] = min(times[e]) / min(t)
        rows[k] = row
    w = max(len(k) for k in rows)
    head = "".join(f"  {e + '/this':>14}" for e in extra_baselines)
    print(f"  {'method':<{w}}  {'min [s]':>10}  {'median [s]':>10}  n  "
          f"{baseline + '/this (min, median)':>30}{head}")
    for k, r in rows.items():
        ext = "".join(f"  {r.get(f'ratio_{e}_over_this_min', float('nan')):>14.3g}"
                      for e in extra_baselines)
        print(f"  {k:<{w}}  {r['min_s']:>10.4g}  {r['median_s']:>10.4g}  {r['repeats']}  "
              f"{r[f'ratio_{baseline}_over_this_min']:>15.3g}, "
              f"{r[f'ratio_{baseline}_over_this_median']:<13.3g}{ext}")
    return rows
