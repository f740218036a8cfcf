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


def envelope(t: np.ndarray, y: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """A line of ``y`` over ``t`` drawn with at most ``max_points`` points: the samples cut
    into ``max_points // 2`` runs of consecutive samples, each drawn by its lowest and highest
    sample in time order, so that the line covers the same pixels as the whole series
    wherever a run spans at most a pixel (even thinning drops the extremes between its
    points). A series of at most ``max_points`` samples is returned as it is.

    **Arguments:**

    - `t`: (N,) the samples' times [s].
    - `y`: (N,) the values.
    - `max_points`: the most points drawn (at least 2).

    **Returns:**

    ``(t, y)`` of the points drawn.
    """
    t, y = np.asarray(t), np.asarray(y)
    if t.size <= max_points:
        return t, y
    runs = max(1, max_points // 2)
    k = -(-t.size // runs)  # samples per run; the last run padded with the last sample
    blocks = np.concatenate([y, np.repeat(y[-1:], runs * k - t.size)]).reshape(runs, k)
    start = np.arange(runs) * k
    pick = np.sort(np.stack([start + blocks.argmin(axis=1), start + blocks.argmax(axis=1)],
                            axis=1), axis=1).ravel()
    pick = np.unique(np.minimum(pick, t.size - 1))
    return t[pick], y[pick]


def plot_identification(traces: dict[str, Any], max_points: int = 2000) -> Figure:
    """Measured and simulated outputs and their difference; segment joins as thin lines.

    **Arguments:**

    - `traces`: ``fit_traces``' dictionary.
    - `max_points`: at most this many points are drawn per line (``envelope``: each run of
      samples by its extremes; 2000 is two per pixel of the figure's width).

    **Returns:**

    The figure.
    """
    t, ym, ys = traces["t"], np.asarray(traces["measured"]), np.asarray(traces["simulated"])
    labels = traces["labels"]
    fig, axes = new_figure(2, 1, figsize=(9, 5.5), sharex=True)
    for j in range(ym.shape[1]):
        axes[0].plot(*envelope(t, ym[:, j], max_points), lw=1.0, label=f"measured {labels[j]}")
        axes[0].plot(*envelope(t, ys[:, j], max_points), "--", lw=1.0,
                     label=f"simulated {labels[j]}")
        axes[1].plot(*envelope(t, ys[:, j] - ym[:, j], max_points), lw=0.8, label=labels[j])
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


def plot_fit(result: Any, max_points: int = 2000) -> Figure:
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
