"""Figures of the discrepancy workflow: residual signature against the telling quantity,
measured against simulated (held-out) before and after, candidate scores, and the final
model's residual analysis (autocorrelation and input cross-correlation with their bands)."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from jaxflex.app.plots import new_figure

#: Tick labels of the log axes as plain numbers (1e-05, 0.1, 10): matplotlib's default writes
#: them in mathtext, whose parser costs 0.2-0.3 s to build on a run's first figure.
PLAIN_LOG_TICKS = FuncFormatter(lambda v, _: f"{v:g}")
NO_TICKS = FuncFormatter(lambda v, _: "")
#: Fixed margins of the figures (fractions of the figure): ``tight_layout`` measures every
#: text to place them, 0.4 s of a discover run's 1 s of figures.
MARGINS = dict(left=0.09, right=0.98, bottom=0.12, top=0.9, wspace=0.25, hspace=0.15)


def plot_signature(summary: dict[str, Any], samples: int, quantity: str) -> Figure:
    """Binned inverse-dynamics residuals (link and rotor side) against ``quantity``, with the
    noise floor band; plus their spectra.

    **Arguments:**

    - `summary`: a ``Localisation.summary`` (signatures, spectrum, noise floor).
    - `samples`: the number of samples the localisation binned (sets the bin mean's floor).
    - `quantity`: the signature to draw ("link velocity", "position", ...).

    **Returns:**

    The figure.
    """
    sig = summary["signatures"]
    fig, ax = new_figure(1, 2, figsize=(10, 4))
    keys = [k for k in (quantity, f"{quantity} (rotor side)") if k in sig] or ["link velocity"]
    for k in keys:
        b = sig[k]
        ax[0].errorbar(b["x"], b["mean"], yerr=b["se"], marker="o", ms=3, label=k)
    fl = summary["noise_floor_link"] / np.sqrt(max(samples / 15, 1))
    ax[0].axhspan(-fl, fl, color="0.85", label="noise floor (bin mean)")
    ax[0].set_xlabel(quantity)
    ax[0].set_ylabel("torque residual [N m]")
    ax[0].legend(fontsize=7)
    sp = summary["spectrum"]
    ax[1].loglog(sp["f"][1:], sp["link"][1:], label="link side")
    ax[1].loglog(sp["f"][1:], sp["rotor"][1:], label="rotor side")
    ax[1].set_xlabel("frequency [Hz]")
    ax[1].set_ylabel("PSD [N^2 m^2 / Hz]")
    ax[1].legend(fontsize=7)
    for axis in (ax[1].xaxis, ax[1].yaxis):
        axis.set_major_formatter(PLAIN_LOG_TICKS)
        axis.set_minor_formatter(NO_TICKS)
    fig.suptitle(f"Residual signature against {quantity}", fontsize=10)
    fig.subplots_adjust(**MARGINS)
    return fig


def plot_replay(replay: dict[str, np.ndarray], count: int = 4) -> Figure:
    """Measured against simulated q1 on a few held-out segments, before and after.

    **Arguments:**

    - `replay`: ``DiscoverResult.held_out_replay()``: ``t0`` (S,) segment starts [s], ``dt``
      [s], and (S, L) arrays of q1 [rad] ``measured``, ``before`` (the refit nominal model)
      and ``after`` (the final model).
    - `count`: how many segments to draw.

    **Returns:**

    The figure.
    """
    q1, b1, a1 = replay["measured"], replay["before"], replay["after"]
    t0, dt = np.asarray(replay["t0"]), float(replay["dt"])
    L = q1.shape[1]
    fig, ax = new_figure(2, 1, figsize=(10, 6), sharex=True)
    for i in range(min(count, q1.shape[0])):
        t = t0[i] + np.arange(L) * dt
        ax[0].plot(t, q1[i], "k", lw=1.2, label="measured" if i == 0 else None)
        ax[0].plot(t, b1[i], "C3--", lw=1, label="nominal (refit)" if i == 0 else None)
        ax[0].plot(t, a1[i], "C0", lw=1, label="augmented" if i == 0 else None)
        ax[1].plot(t, b1[i] - q1[i], "C3--", lw=1)
        ax[1].plot(t, a1[i] - q1[i], "C0", lw=1)
    ax[0].set_ylabel("q1 [rad]")
    ax[0].legend(fontsize=8)
    ax[1].set_ylabel("simulated - measured q1 [rad]")
    ax[1].set_xlabel("t [s] (held-out segments, each replayed from its measured start)")
    fig.suptitle("Held-out replay: nominal against augmented model", fontsize=10)
    fig.subplots_adjust(**MARGINS)
    return fig


def plot_scores(scores: dict[str, dict[str, Any]], base_gap: float) -> Figure:
    """Held-out gap of every candidate fitted in round 1 (``candidate_scores``) against the
    refit nominal model's ``base_gap`` (those the screen left out have no held-out gap and
    are not drawn); returns the figure."""
    scores = {k: s for k, s in scores.items() if s.get("gap_test") is not None}
    names = sorted(scores, key=lambda k: scores[k]["gap_test"])
    fig, ax = new_figure(figsize=(8, 4))
    gaps = [scores[k]["gap_test"] for k in names]
    colors = ["C2" if scores[k]["significant"] else "C7" for k in names]
    ax.barh(names, gaps, color=colors)
    ax.axvline(base_gap, color="C3", ls="--", label="nominal refit")
    ax.set_xlabel("held-out gap (green: significant)")
    ax.legend(fontsize=8)
    ax.set_title("Candidate effects: held-out gap after adding each", fontsize=10)
    fig.subplots_adjust(**(MARGINS | dict(left=0.22)))
    return fig


def plot_residual_analysis(analysis: dict[str, Any], title: str) -> Figure:
    """MATLAB ``resid``'s figure of a residual analysis (``jaxflex.discover.residual_analysis``
    or ``jaxflex.validate.replay_residual_analysis``): per output channel (columns), the
    residual's autocorrelation (top) and its cross-correlation with the input (bottom),
    each with its confidence band (shaded: a residual that explains nothing more stays
    inside); returns the figure."""
    chans = analysis["channels"]
    names = list(chans)
    fig, ax = new_figure(2, len(names), figsize=(5 * len(names), 5.5), squeeze=False)
    conf = 100 * analysis.get("confidence", 0.99)
    for j, name in enumerate(names):
        c = chans[name]
        rho = np.asarray(c["autocorrelation"])
        k = np.arange(rho.size)
        ax[0, j].axhspan(-c["band"], c["band"], color="0.85", label=f"{conf:g}% band")
        ax[0, j].vlines(k, 0, rho, color="C0")
        ax[0, j].plot(k, rho, "C0o", ms=3)
        ax[0, j].set_title(f"{name}: autocorrelation (Ljung-Box p {c['p_white']:.2g})",
                           fontsize=9)
        ax[0, j].set_xlabel("lag [samples]")
        ax[0, j].legend(fontsize=7)
        if c.get("cross_correlation") is not None:
            xc = np.asarray(c["cross_correlation"])
            kx = np.arange(xc.size) - (xc.size - 1) // 2
            ax[1, j].axhspan(-c["cross_band"], c["cross_band"], color="0.85")
            ax[1, j].vlines(kx, 0, xc, color="C1")
            ax[1, j].plot(kx, xc, "C1o", ms=3)
        ax[1, j].set_title(f"{name}: cross-correlation with {analysis.get('input', 'input')}",
                           fontsize=9)
        ax[1, j].set_xlabel("lag [samples] (positive: input leads)")
    fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(**(MARGINS | dict(hspace=0.45, top=0.88)))
    return fig


def report_figures(report: dict[str, Any], localisation: dict[str, Any], samples: int,
                   replay: dict[str, np.ndarray]) -> dict[str, Figure]:
    """The figures of one discovery run, by file stem.

    **Arguments:**

    - `report`: ``DiscoverResult.to_json()``.
    - `localisation`: the refit nominal model's ``Localisation.summary``.
    - `samples`: the samples it binned.
    - `replay`: ``DiscoverResult.held_out_replay()``.

    **Returns:**

    ``{"signature", "replay"}`` and, where the run has them, ``"scores"`` and
    ``"residuals"``: name -> figure.
    """
    q = report.get("telling_quantity") or "link velocity"
    if q in ("frequency", "time"):
        q = "link velocity"
    figs = {"signature": plot_signature(localisation, samples, q), "replay": plot_replay(replay)}
    if report.get("candidate_scores"):
        figs["scores"] = plot_scores(report["candidate_scores"], report["gap_before"])
    if (report.get("residual_analysis") or {}).get("channels"):
        figs["residuals"] = plot_residual_analysis(
            report["residual_analysis"], "Residual analysis of the final model (held-out segments)")
    return figs


def plot_report(result: Any) -> dict[str, Figure]:
    """Every figure of one ``DiscoverResult`` (``report_figures``), by file stem.

    **Arguments:**

    - `result`: the ``DiscoverResult``.

    **Returns:**

    Name -> figure, as ``report_figures``.
    """
    return report_figures(result.to_json(), result.localisation.summary,
                          len(result.localisation.series["t"]), result.held_out_replay())
