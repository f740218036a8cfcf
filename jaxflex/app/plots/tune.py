"""Figures of gain tuning against the N2 certificate (``jaxflex tune``, studies/certificate_cost)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from matplotlib.figure import Figure

from jaxflex.app.plots import new_figure

from jaxflex.sim.simulate import SimResult


def plot_lambda_min(curves: dict[str, dict[str, Any]],
                    v_task: float | None = None, margin: float | None = None) -> Figure:
    """lambda_min(N2) [-] against link speed [rad/s] for each labelled certificate dict
    (``CertificateResult.to_dict()``), with the task speed and the margin marked."""
    fig, ax = new_figure(figsize=(7, 4))
    for label, c in curves.items():
        v, lam = np.asarray(c["velocities"]), np.asarray(c["lambda_min"])
        ax.plot(v, lam, lw=1.3, label=f"{label} (certified to {c['certified_up_to']:.3g} rad/s)")
    ax.axhline(0.0, color="k", lw=0.8)
    if margin:
        ax.axhline(margin, color="k", ls=":", lw=0.8, label=f"margin {margin:g}")
    if v_task:
        # the task's speeds, shaded; the axis ends a little beyond them (the curve goes on to
        # the certificate's vmax, where lambda_min would squeeze the task range to a sliver)
        ax.axvspan(0.0, v_task, color="tab:green", alpha=0.08, lw=0,
                   label=f"task speeds 0..{v_task:.3g} rad/s")
        vmax = max(float(np.max(np.asarray(c["velocities"]))) for c in curves.values())
        ax.set_xlim(0.0, min(vmax, 2.0 * v_task))
    ax.set_xlabel("link speed |q1'| [rad/s]")
    ax.set_ylabel("lambda_min(N2) [-]")
    ax.set_title("N2 certificate (paper eq. 29-31)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def plot_tracking_comparison(runs: dict[str, Sequence[SimResult]]) -> Figure:
    """Link tracking error e1 [rad] and torque [N m] against time for each labelled gain set
    (first joint, every trajectory of the task one after another)."""
    fig, (ax1, ax2) = new_figure(2, 1, figsize=(8, 5), sharex=True)
    for label, rs in runs.items():
        t0 = 0.0
        for i, r in enumerate(rs):
            t = np.asarray(r.t) + t0
            kw = {"label": label} if i == 0 else {}
            line = ax1.plot(t, np.asarray(r.e1)[:, 0], lw=0.9, **kw)[0]
            ax2.plot(t, np.asarray(r.tau)[:, 0], lw=0.7, color=line.get_color())
            t0 = float(t[-1]) + float(t[1] - t[0])
    ax1.set_ylabel("e1 (rad)")
    ax2.set_ylabel("tau (N m)")
    ax2.set_xlabel("time (s), task trajectories in sequence")
    ax1.legend(fontsize=8)
    fig.suptitle("Initial against tuned gains on the task", fontsize=10)
    fig.tight_layout()
    return fig


def plot_history(starts: Sequence[dict[str, Any]]) -> Figure:
    """RMS tracking error [rad] per iteration of each start of the multi-start search."""
    fig, ax = new_figure(figsize=(7, 4))
    for i, s in enumerate(starts):
        ax.semilogy(np.asarray(s["rms_error"]), marker=".", lw=1.0, label=f"start {i}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("RMS link error (rad)")
    ax.set_title("certified search (every iterate certified)", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def plot_tradeoff(points: Sequence[dict[str, Any]],
                  unconstrained: dict[str, Any] | None = None,
                  paper: dict[str, Any] | None = None) -> Figure:
    """RMS tracking error [rad] of the best gains against the certified speed they were
    required to reach [rad/s] (the cost of the certificate)."""
    fig, ax = new_figure(figsize=(7, 4))
    v = [p["required_speed"] for p in points]
    e = [p["rms_error"] for p in points]
    ax.semilogx(v, e, "o-", label="certified search")
    if unconstrained is not None:
        ax.axhline(unconstrained["rms_error"], color="r", ls="--",
                   label=f"search without certificate (certified to {unconstrained['certified_up_to']:.3g} rad/s)")
    if paper is not None:
        ax.axhline(paper["rms_error"], color="k", ls=":", label="paper gains")
    ax.set_xlabel("certified link-speed range required (rad/s)")
    ax.set_ylabel("RMS link error (rad)")
    ax.legend(fontsize=8)
    ax.set_title("Tracking error against torque (certified gains)", fontsize=10)
    fig.tight_layout()
    return fig
