"""Tracking figures of the paper's experiments (Fig. 9-15 style)."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure

from jaxflex.app.plots import new_figure

from jaxflex.sim.simulate import SimResult


def plot_tracking(runs: dict[str, SimResult], title: str) -> Figure:
    """Desired and actual link position for each run, and the tracking errors (Fig. 9/10/12-15).

    ``runs`` maps a label (e.g. 'with_compensation') to a saved ``SimResult``. Returns the
    figure.
    """
    fig, axes = new_figure(len(runs) + 1, 1, figsize=(8, 2.4 * (len(runs) + 1)), sharex=True)
    for ax, (label, r) in zip(axes, runs.items()):
        t = np.asarray(r.t)
        ax.plot(t, np.asarray(r.q1d)[:, 0], "k--", lw=1.0, label="desired")
        ax.plot(t, np.asarray(r.q1)[:, 0], lw=1.0, label="actual")
        ax.set_ylabel("position (rad)")
        ax.set_title(label.replace("_", " "), fontsize=9)
        ax.legend(loc="upper right", fontsize=8)
    for label, r in runs.items():
        axes[-1].plot(np.asarray(r.t), np.asarray(r.e1)[:, 0], lw=1.0, label=label.replace("_", " "))
    axes[-1].set_ylabel("error (rad)")
    axes[-1].set_xlabel("time (s)")
    axes[-1].legend(loc="upper right", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_torque_friction(r: SimResult, config: str = "") -> Figure:
    """Control torque (top) and estimated against true friction torque (bottom) (Fig. 11);
    separate panels, since the control torque's chatter would hide the friction traces.
    ``config``: a second title line (the velocity estimator and observer shown)."""
    fig, (ax0, ax) = new_figure(2, 1, figsize=(8, 5), sharex=True)
    t = np.asarray(r.t)
    ax0.plot(t, np.asarray(r.tau)[:, 0], lw=0.6, color="0.3", label="control torque tau")
    ax0.set_ylabel("control torque [N m]")
    ax0.legend(loc="upper right", fontsize=8)
    ax.plot(t, np.asarray(r.F)[:, 0], lw=1.6, alpha=0.6, label="true friction F (simulated)")
    ax.plot(t, np.asarray(r.F_hat)[:, 0], lw=1.0, ls="--", label="estimated friction F_hat")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("friction torque [N m]")
    ax.legend(loc="upper right", fontsize=8)
    fig.suptitle("Control torque and friction, compensated sinusoid (paper Fig. 11)"
                 + (f"\n{config}" if config else ""), fontsize=10)
    fig.tight_layout()
    return fig


def plot_q2d_comparison(table: dict[str, Any], config: str = "") -> Figure:
    """Bar chart of RMS tracking error per q2d option and sensing (log scale; hatched bars
    diverged or saturated most of the time)."""
    sensings = list(table)
    fig, axes = new_figure(1, len(sensings), figsize=(4.2 * len(sensings), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    for ax, s in zip(axes, sensings):
        labels = list(table[s])
        x = np.arange(len(labels))
        for j, comp in enumerate(("without_compensation", "with_compensation")):
            vals = [table[s][lab][comp]["rms_error"] for lab in labels]
            bad = [table[s][lab][comp]["diverged"] or table[s][lab][comp]["saturation_fraction"] > 0.2
                   for lab in labels]
            bars = ax.bar(x + (j - 0.5) * 0.38, vals, 0.38, label=comp.replace("_", " "))
            for b, flag in zip(bars, bad):
                if flag:
                    b.set_hatch("//")
        ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_title(f"sensing: {s}", fontsize=9)
    axes[0].set_ylabel("RMS link error [rad]")
    from matplotlib.patches import Patch

    handles, _ = axes[0].get_legend_handles_labels()
    handles.append(Patch(facecolor="white", edgecolor="0.3", hatch="//",
                         label="diverged or saturated > 20% of the time"))
    axes[0].legend(handles=handles, fontsize=7)
    fig.suptitle("q2d derivative options: RMS link error by sensing"
                 + (f"\n{config}" if config else ""), fontsize=10)
    fig.tight_layout()
    return fig
