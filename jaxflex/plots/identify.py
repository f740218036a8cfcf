"""Figures of identification: measured against simulated response, static-map fit."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import numpy as np


def plot_fit(result: Any, path: str | Path, max_points: int = 20000) -> list[str]:
    """Measured and simulated outputs of an ``IdentResult`` (segments joined end to end) and
    their difference; segment starts are marked by thin vertical lines."""
    path = Path(path)
    prob = result.problem
    from jaxflex.fit import simulated_outputs

    ys = simulated_outputs(prob, result.solution)
    ys, ym = np.asarray(ys), np.asarray(prob.segs.y_meas)
    S, L, m = ys.shape
    t = np.arange(S * L) * prob.dt
    ys, ym = ys.reshape(S * L, m), ym.reshape(S * L, m)
    step = max(1, (S * L) // max_points)
    labels = [f"{o}[{j}]" for o in prob.outputs for j in range(m // len(prob.outputs))]
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for j in range(m):
        axes[0].plot(t[::step], ym[::step, j], lw=1.0, label=f"measured {labels[j]}")
        axes[0].plot(t[::step], ys[::step, j], "--", lw=1.0, label=f"simulated {labels[j]}")
        axes[1].plot(t[::step], (ys - ym)[::step, j], lw=0.8, label=labels[j])
    if S > 1:
        for ax in axes:
            for s in range(1, S):
                ax.axvline(s * L * prob.dt, color="0.85", lw=0.5, zorder=0)
    axes[0].set_ylabel("position [rad] (m: prismatic)")
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].set_ylabel("simulated - measured [rad]")
    axes[1].set_xlabel("time from first fitted sample [s]")
    axes[1].legend(fontsize=7, loc="upper right")
    axes[0].set_title(f"identification ({prob.kind} model, {S} segment(s)); RMS residual "
                      f"{result.rms:.3g}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path.name]


def plot_static_map(v: np.ndarray, F: np.ndarray, curve: Any, path: str | Path,
                    true_curve: Any = None) -> list[str]:
    """Static-map data (v, F) with the fitted eq. 35 curve ``curve(v)`` (and the true one)."""
    path = Path(path)
    vv = np.linspace(np.min(v), np.max(v), 600)
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(v, F, "o", ms=4, label="constant-velocity runs")
    ax.plot(vv, curve(vv), lw=1.2, label="fit, eq. 35")
    if true_curve is not None:
        ax.plot(vv, true_curve(vv), "k--", lw=0.8, label="true")
    ax.set_xlabel("velocity (rad/s)")
    ax.set_ylabel("friction torque (N m)")
    ax.legend(fontsize=8)
    ax.set_title("Static friction map (eq. 35)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path.name]


def plot_validation(t: np.ndarray, series: dict[str, tuple[np.ndarray, np.ndarray]],
                    path: str | Path, title: str = "") -> list[str]:
    """One panel per quantity: measured and simulated; ``series`` maps a label to the pair."""
    path = Path(path)
    fig, axes = plt.subplots(len(series), 1, figsize=(9, 2.3 * len(series)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, (label, (meas, sim)) in zip(axes, series.items()):
        ax.plot(t, meas, lw=0.9, label="measured")
        ax.plot(t, sim, "--", lw=0.9, label="simulated")
        ax.set_ylabel(label, fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    if title:
        axes[0].set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path.name]
