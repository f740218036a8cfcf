"""Figures of the discrepancy workflow: residual signature against the telling quantity,
measured against simulated (held-out) before and after, candidate scores, and the final
model's residual analysis (autocorrelation and input cross-correlation with their bands)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402

#: Tick labels of the log axes as plain numbers (1e-05, 0.1, 10): matplotlib's default writes
#: them in mathtext, whose parser costs 0.2-0.3 s to build on a run's first figure.
PLAIN_LOG_TICKS = FuncFormatter(lambda v, _: f"{v:g}")
NO_TICKS = FuncFormatter(lambda v, _: "")
#: Fixed margins of the figures (fractions of the figure): ``tight_layout`` measures every
#: text to place them, 0.4 s of a discover run's 1 s of figures.
MARGINS = dict(left=0.09, right=0.98, bottom=0.12, top=0.9, wspace=0.25, hspace=0.15)


def plot_signature(loc: Any, quantity: str, path: Path) -> None:
    """Binned inverse-dynamics residuals (link and rotor side) of a ``Localisation`` against
    ``quantity``, with the noise floor band; plus their spectra."""
    sig = loc.summary["signatures"]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    keys = [k for k in (quantity, f"{quantity} (rotor side)") if k in sig] or ["link velocity"]
    for k in keys:
        b = sig[k]
        ax[0].errorbar(b["x"], b["mean"], yerr=b["se"], marker="o", ms=3, label=k)
    fl = loc.summary["noise_floor_link"] / np.sqrt(max(len(loc.series["t"]) / 15, 1))
    ax[0].axhspan(-fl, fl, color="0.85", label="noise floor (bin mean)")
    ax[0].set_xlabel(quantity)
    ax[0].set_ylabel("torque residual [N m]")
    ax[0].legend(fontsize=7)
    sp = loc.summary["spectrum"]
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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_replay(result: Any, path: Path, count: int = 4) -> None:
    """Measured against simulated q1 on a few held-out segments, before and after (a
    ``DiscoverResult``)."""
    from jaxflex.discover import held_out_traces

    ws = result.workspace
    dt = ws.test.dt
    b1 = held_out_traces(ws, result.before)[..., 0]
    a1 = held_out_traces(ws, result.after)[..., 0]
    q1 = np.asarray(ws.test.segs.y_meas)[..., 0]
    t0 = np.asarray(ws.test.segs.t0)
    L = q1.shape[1]
    fig, ax = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_scores(scores: dict[str, dict[str, Any]], base_gap: float, path: Path) -> None:
    """Held-out gap of every candidate fitted in round 1 against the refit nominal model
    (those the screen left out have no held-out gap and are not drawn)."""
    scores = {k: s for k, s in scores.items() if s.get("gap_test") is not None}
    names = sorted(scores, key=lambda k: scores[k]["gap_test"])
    fig, ax = plt.subplots(figsize=(8, 4))
    gaps = [scores[k]["gap_test"] for k in names]
    colors = ["C2" if scores[k]["significant"] else "C7" for k in names]
    ax.barh(names, gaps, color=colors)
    ax.axvline(base_gap, color="C3", ls="--", label="nominal refit")
    ax.set_xlabel("held-out gap (green: significant)")
    ax.legend(fontsize=8)
    ax.set_title("Candidate effects: held-out gap after adding each", fontsize=10)
    fig.subplots_adjust(**(MARGINS | dict(left=0.22)))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_residual_analysis(analysis: dict[str, Any], path: Path, title: str) -> None:
    """MATLAB ``resid``'s figure of a residual analysis (``jaxflex.discover.residual_analysis``
    or ``jaxflex.validate.replay_residual_analysis``): per output channel (columns), the
    residual's autocorrelation (top) and its cross-correlation with the input (bottom),
    each with its confidence band (shaded: a residual that explains nothing more stays
    inside)."""
    chans = analysis["channels"]
    names = list(chans)
    fig, ax = plt.subplots(2, len(names), figsize=(5 * len(names), 5.5), squeeze=False)
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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_report(result: Any, out: Path) -> list[str]:
    """All figures of one ``DiscoverResult`` into ``out``; returns their file names."""
    out = Path(out)
    q = result.to_json().get("telling_quantity") or "link velocity"
    if q in ("frequency", "time"):
        q = "link velocity"
    plot_signature(result.localisation, q, out / "signature.png")
    plot_replay(result, out / "replay.png")
    names = ["signature.png", "replay.png"]
    if result.candidate_scores:
        plot_scores(result.candidate_scores, result.gap_before, out / "scores.png")
        names.append("scores.png")
    if result.residuals.get("channels"):
        plot_residual_analysis(result.residuals, out / "residuals.png",
                               "Residual analysis of the final model (held-out segments)")
        names.append("residuals.png")
    return names
