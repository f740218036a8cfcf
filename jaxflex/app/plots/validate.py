"""Figures of validation: measured against predicted torque and closed-loop response."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure

from jaxflex.app.plots import new_figure


def plot_validation_log(series: dict[str, Any], title: str,
                        units: tuple[str, str] = ("rad", "N m")) -> Figure:
    """Torque measured against predicted from measured motion, and (if present) the closed
    loop's position and torque against the measurement, with residuals. ``units``:
    (position unit, torque unit) for the axis labels. Returns the figure."""
    pu, tu = units
    cl = series.get("closed_loop")
    rows = 2 if cl is None else 4
    fig, ax = new_figure(rows, 1, figsize=(9, 2.2 * rows), sharex=True)
    t = series["t"]
    tau, tau_hat = series["tau"][:, 0], series["tau_hat"][:, 0]
    ax[0].plot(t, tau, lw=0.7, label="measured")
    ax[0].plot(t, tau_hat, lw=0.7, label="inverse dynamics (measured motion)")
    ax[0].set_ylabel(f"torque [{tu}]")
    ax[0].legend(fontsize=7, loc="upper right")
    ax[1].plot(t, tau_hat - tau, lw=0.7, color="C3")
    ax[1].set_ylabel(f"predicted - measured [{tu}]")
    if cl is not None:
        q = series["q"][:, 0]
        ax[2].plot(t, q, lw=0.8, label="measured")
        ax[2].plot(t, cl["q"], "--", lw=0.8, label="closed-loop simulation")
        ax[2].set_ylabel(f"position [{pu}]")
        ax[2].legend(fontsize=7, loc="upper right")
        ax[3].plot(t, cl["tau"] - tau, lw=0.7, color="C3")
        ax[3].set_ylabel(f"sim - meas torque [{tu}]")
    ax[-1].set_xlabel("time [s]")
    ax[0].set_title(title, fontsize=9)
    fig.tight_layout()
    return fig


def plot_table(rows: list[dict[str, Any]]) -> Figure:
    """Bar chart of the torque prediction error [%] per log and parameter set, each bar with
    its noise floor (the error the log's noise alone gives, ``torque_noise_pct``) marked."""
    fig, ax = new_figure(figsize=(7, 3))
    labels = [f"{r['log']}\n{r['params']}" for r in rows]
    x = np.arange(len(rows))
    ax.bar(x, [r["torque_pct"] for r in rows], color="C0", label="torque prediction error")
    if rows and all("torque_noise_pct" in r for r in rows):
        ax.hlines([r["torque_noise_pct"] for r in rows], x - 0.4, x + 0.4, colors="k",
                  linestyles="--", label="noise floor (noise alone)")
        ax.legend(fontsize=7, loc="upper right")
    ax.set_xticks(x, labels, fontsize=6)
    ax.set_ylabel("torque prediction error [%]")
    ax.set_title("validation: 100 ||tau - tau_hat|| / ||tau|| per log", fontsize=9)
    fig.tight_layout()
    return fig
