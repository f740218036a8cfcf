"""``sweep_spread``: a Monte Carlo robustness sweep over a spread of plants (``Sweep``)."""

from __future__ import annotations

import dataclasses
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from jaxflex.app.api.result import Result
from jaxflex.sweep import SweepSpec, load_spread, parse_spread, run_sweep
from jaxflex.io.progress import Progress

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: The figures of a sweep, by name (``Sweep.plot``).
SWEEP_FIGURES: tuple[str, ...] = ("sensitivity", "error_histograms", "error_bands")


@dataclasses.dataclass(frozen=True)
class Sweep(Result):
    """The outcome of ``sweep_spread`` (``jaxflex.sweep.SweepResult``'s numbers).

    summary: metric quantiles, failure counts, sensitivities (JSON-ready); band_t [s] (T,),
    band_q [rad] (n, T, quantiles): the link error's quantiles over time; hists: metric ->
    (edges, counts); samples: per-sample parameters and metrics when kept, else None.
    """

    summary: dict[str, Any]
    band_t: np.ndarray
    band_q: np.ndarray
    hists: dict[str, tuple[np.ndarray, np.ndarray]]
    samples: dict[str, np.ndarray] | None

    def plot(self, which: str = "sensitivity") -> Figure:
        """One figure of the sweep (``jaxflex.app.plots.sweep``).

        **Arguments:**

        - `which`: "sensitivity" (each parameter's share of the RMS error's variance),
          "error_histograms" or "error_bands".

        **Returns:**

        The figure.

        **Raises:**

        ``ValueError`` for another name.
        """
        from jaxflex.app.plots import sweep as figures

        if which not in SWEEP_FIGURES:
            raise ValueError(f"Sweep.plot: no figure {which!r}; choose from {SWEEP_FIGURES}")
        return getattr(figures, f"plot_{which}")(self)


def sweep_spread(spread: SweepSpec | dict[str, Any] | str | os.PathLike, *,
                 samples: int | None = None, progress: Progress | bool = False,
                 **options: Any) -> Sweep:
    """Run the closed loop on plants drawn from ``spread`` and summarise the errors
    (``jaxflex.sweep.run_sweep``).

    **Arguments:**

    - `spread`: a ``SweepSpec``, a spread mapping or a spread file (docs/spec.md; examples
      in ``studies/spreads/``).
    - `samples`: how many plants; None: the spread's own count.
    - `progress`: a reporter of the chunks done (``jaxflex.io.progress.Progress``), True: a
      progress bar, False: silent.
    - `options`: keywords of ``run_sweep`` (``chunk_size``, ``shard``, ``keep_samples``,
      ``float32``, ...).

    **Returns:**

    A ``Sweep``.

    **Raises:**

    ``jaxflex.sweep.SpreadError`` for a spread that does not validate; ``ValueError`` for bad
    settings; ``KeyboardInterrupt`` when interrupted before any chunk was done.
    """
    if isinstance(spread, dict):
        spread = parse_spread(spread)
    elif not isinstance(spread, SweepSpec):
        spread = load_spread(spread)
    r = run_sweep(spread, samples=samples, progress=progress, **options)
    if r is None:
        raise KeyboardInterrupt("sweep_spread: interrupted before the first chunk")
    return Sweep(summary=r.summary, band_t=np.asarray(r.band_t), band_q=np.asarray(r.band_q),
                 hists=dict(r.hists), samples=r.samples)
