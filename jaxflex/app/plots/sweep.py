"""Monte Carlo sweep figures: error histograms, error bands over time, sensitivity bars.

Each function takes one or more labelled ``SweepResult``s (e.g. with and without friction
compensation) so that they can be compared on the same axes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from matplotlib.figure import Figure

from jaxflex.app.plots import new_figure

if TYPE_CHECKING:
    from jaxflex.sweep.summary import SweepResult


def _as_runs(results: SweepResult | dict[str, SweepResult]) -> dict[str, SweepResult]:
    return results if isinstance(results, dict) else {"sweep": results}


def plot_error_histograms(results) -> Figure:
    """Histograms of RMS and max link tracking error [rad] (log axis), non-diverged samples.

    From the kept samples when there are (log-spaced bins over the joint range of all runs,
    as many as Rice's rule 2 n^(1/3) gives for n samples, 10 to 60), else from the fixed-grid
    histograms of the summary (40 bins per decade). Returns the figure."""
    runs = _as_runs(results)
    fig, axes = new_figure(1, 2, figsize=(10, 3.6))
    for ax, m, title in zip(axes, ("rms_error", "max_error"), ("RMS link error", "max link error")):
        kept = [r.samples[m][~r.samples["diverged"]] for r in runs.values() if r.samples is not None]
        kept = [v[v > 0] for v in kept]
        fine = None
        if len(kept) == len(runs) and all(v.size for v in kept):
            lo, hi = min(v.min() for v in kept), max(v.max() for v in kept)
            n_min = min(v.size for v in kept)
            bins = int(np.clip(round(2 * n_min ** (1 / 3)), 10, 60))
            fine = np.geomspace(lo, hi * (1 + 1e-9), bins + 1) if hi > lo else None
        for label, r in runs.items():
            if fine is not None:
                v = r.samples[m][~r.samples["diverged"]]
                ax.stairs(np.histogram(v, fine)[0], fine, fill=True, alpha=0.45, label=label)
                continue
            edges, counts = r.hists[m]
            nz = np.nonzero(counts)[0]
            if nz.size == 0:
                continue
            lo, hi = max(nz[0] - 2, 0), min(nz[-1] + 3, counts.size)
            ax.stairs(counts[lo:hi], edges[lo:hi + 1], fill=True, alpha=0.45, label=label)
        ax.set_xscale("log")
        ax.set_xlabel(f"{title} (rad)")
        ax.set_ylabel("samples")
        ax.legend(fontsize=8)
    n = next(iter(runs.values())).summary["samples"]
    fig.suptitle(f"Tracking error over {n} samples", fontsize=10)
    fig.tight_layout()
    return fig


def plot_error_bands(results, joint: int = 0, nominal: dict | None = None) -> Figure:
    """Link error e1 [rad] of ``joint`` over time: median, 25-75 % and 5-95 % bands across
    samples (and the ``nominal`` run's, when given); returns the figure."""
    runs = _as_runs(results)
    fig, ax = new_figure(figsize=(9, 3.8))
    for k, (label, r) in enumerate(runs.items()):
        c = f"C{k}"
        q = r.band_q[joint]
        t = r.band_t
        ax.fill_between(t, q[:, 0], q[:, 4], color=c, alpha=0.15, lw=0)
        ax.fill_between(t, q[:, 1], q[:, 3], color=c, alpha=0.35, lw=0)
        ax.plot(t, q[:, 2], color=c, lw=1.2, label=f"{label}: median, 25-75 %, 5-95 %")
    if nominal is not None:
        ax.plot(nominal["t"], nominal["e1"][:, joint], "k:", lw=0.8, label="nominal plant")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("link error e1 (rad)")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title("Link error bands over the sweep", fontsize=10)
    fig.tight_layout()
    return fig


def plot_sensitivity(results, top: int = 12) -> Figure:
    """Bars of each parameter's Shapley share of the RMS error's variance (valid under
    correlated draws) beside its correlation with the RMS error (and Spearman's rho when the
    samples were kept), largest share first; a parameter too collinear with others to be
    separated is marked with an asterisk. Returns the figure."""
    runs = _as_runs(results)
    fig, axes = new_figure(1, len(runs), figsize=(5 * len(runs), 0.35 * top + 1.5), squeeze=False)
    for ax, (label, r) in zip(axes[0], runs.items()):
        rows = r.summary["sensitivity"][:top][::-1]
        if not rows:
            ax.set_title(f"{label}: no sampled parameters")
            continue
        y = np.arange(len(rows))
        ax.barh(y + 0.27, [s.get("shapley", 0.0) for s in rows], height=0.27,
                label="Shapley share of variance")
        ax.barh(y, [s.get("corr", s["src"]) for s in rows], height=0.27, label="correlation")
        if "spearman" in rows[0]:
            ax.barh(y - 0.27, [s["spearman"] for s in rows], height=0.27, label="Spearman rho")
        ax.set_yticks(y, [s["parameter"] + (" *" if "collinear_with" in s else "")
                          for s in rows], fontsize=8)
        ax.axvline(0, color="k", lw=0.6)
        ax.set_xlabel("effect on RMS link error")
        r2 = rows[0]["r2_linear"]
        note = "; * too collinear to separate" if any("collinear_with" in s for s in rows) else ""
        ax.set_title(f"{label} (linear R^2 = {r2:.2f}{note})", fontsize=9)
        ax.legend(fontsize=8)
    fig.suptitle("Sensitivity of RMS link error to each sampled parameter", fontsize=10)
    fig.tight_layout()
    return fig


def plot_sweep(results: SweepResult | dict[str, SweepResult],
               nominal: dict | None = None) -> dict[str, Figure]:
    """The sweep's three figures, by file stem.

    **Arguments:**

    - `results`: one ``SweepResult`` or labelled ones.
    - `nominal`: the nominal plant's run (``nominal_run``) for the error bands.

    **Returns:**

    ``{"error_histograms", "error_bands", "sensitivity"}``: name -> figure.
    """
    return {"error_histograms": plot_error_histograms(results),
            "error_bands": plot_error_bands(results, nominal=nominal),
            "sensitivity": plot_sensitivity(results)}
