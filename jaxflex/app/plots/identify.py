"""Figures of identification: measured against simulated response, static-map fit."""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure

from jaxflex.app.plots import new_figure


def fit_traces(result: Any) -> dict[str, Any]:
    """The measured and simulated outputs of an ``IdentResult``, segments joined end to end.

    **Arguments:**

    - `result`: the ``IdentResult`` (its problem replayed at its solution).

    **Returns:**

    ``{"t": (S L,) [s] from the first fitted sample, "measured", "simulated": (S L, m)
    outputs [rad], "labels": m names, "boundaries": the S - 1 segment joins [s], "title"}``.
    """
    from jaxflex.fit import simulated_outputs

    prob = result.problem
    ys = np.asarray(simulated_outputs(prob, result.solution))
    ym = np.asarray(prob.segs.y_meas)
    S, L, m = ys.shape
    return {
        "t": np.arange(S * L) * prob.dt,
        "measured": ym.reshape(S * L, m), "simulated": ys.reshape(S * L, m),
        "labels": [f"{o}[{j}]" for o in prob.outputs for j in range(m // len(prob.outputs))],
        "boundaries": [s * L * prob.dt for s in range(1, S)],
        "title": f"identification ({prob.kind} model, {S} segment(s)); RMS residual "
                 f"{result.rms:.3g}",
    }


def plot_identification(traces: dict[str, Any], max_points: int = 20000) -> Figure:
    """Measured and simulated outputs and their difference; segment joins as thin lines.

    **Arguments:**

    - `traces`: ``fit_traces``' dictionary.
    - `max_points`: at most this many samples are drawn per line (evenly thinned).

    **Returns:**

    The figure.
    """
    t, ym, ys = traces["t"], np.asarray(traces["measured"]), np.asarray(traces["simulated"])
    labels = traces["labels"]
    step = max(1, t.size // max_points)
    fig, axes = new_figure(2, 1, figsize=(9, 5.5), sharex=True)
    for j in range(ym.shape[1]):
        axes[0].plot(t[::step], ym[::step, j], lw=1.0, label=f"measured {labels[j]}")
        axes[0].plot(t[::step], ys[::step, j], "--", lw=1.0, label=f"simulated {labels[j]}")
        axes[1].plot(t[::step], (ys - ym)[::step, j], lw=0.8, label=labels[j])
    for ax in axes:
        for b in traces["boundaries"]:
            ax.axvline(b, color="0.85", lw=0.5, zorder=0)
    axes[0].set_ylabel("position [rad] (m: prismatic)")
    axes[0].legend(fontsize=7, loc="upper right")
    axes[1].set_ylabel("simulated - measured [rad]")
    axes[1].set_xlabel("time from first fitted sample [s]")
    axes[1].legend(fontsize=7, loc="upper right")
    axes[0].set_title(traces["title"], fontsize=9)
    fig.tight_layout()
    return fig


def plot_fit(result: Any, max_points: int = 20000) -> Figure:
    """``plot_identification`` of an ``IdentResult`` (the command line's figure).

    **Arguments:**

    - `result`: the ``IdentResult``.
    - `max_points`: as ``plot_identification``.

    **Returns:**

    The figure.
    """
    return plot_identification(fit_traces(result), max_points)


def plot_static_map(v: np.ndarray, F: np.ndarray, curve: Any,
                    true_curve: Any = None) -> Figure:
    """Static-map data (v, F) with the fitted eq. 35 curve ``curve(v)`` (and the true one);
    returns the figure."""
    vv = np.linspace(np.min(v), np.max(v), 600)
    fig, ax = new_figure(figsize=(6, 4))
    ax.plot(v, F, "o", ms=4, label="constant-velocity runs")
    ax.plot(vv, curve(vv), lw=1.2, label="fit, eq. 35")
    if true_curve is not None:
        ax.plot(vv, true_curve(vv), "k--", lw=0.8, label="true")
    ax.set_xlabel("velocity (rad/s)")
    ax.set_ylabel("friction torque (N m)")
    ax.legend(fontsize=8)
    ax.set_title("Static friction map (eq. 35)", fontsize=10)
    fig.tight_layout()
    return fig


def plot_validation(t: np.ndarray, series: dict[str, tuple[np.ndarray, np.ndarray]],
                    title: str = "") -> Figure:
    """One panel per quantity: measured and simulated; ``series`` maps a label to the pair;
    returns the figure."""
    fig, axes = new_figure(len(series), 1, figsize=(9, 2.3 * len(series)), sharex=True)
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
    return fig
