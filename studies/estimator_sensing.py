"""Question: which q2d-derivative method and which velocity estimator make the paper's friction
compensation help under the ideal, rig and paper sensing presets (coarse encoders)?

Method: the paper's sinusoid experiment (Fig. 9-11; ``jaxflex.io.presets.paper_sinusoid``) on the
paper's plant and gains (Tables 1-3, corrected Table 2; ``paper_params``), closed by
``jaxflex.loop.experiments.run_closed_loop`` as ``jaxflex reproduce`` does (1 kHz, 2 N m torque
limit), for each sensing preset x q2d method (model, filtered, reference; docs/spec.md
section 3) x velocity estimator ("exact" where the sensing is ideal, "filtered": the
controller's dirty derivative, "kalman": the steady-state Kalman filter of
``jaxflex.core.estimator``; and, where the encoders are coarse, "kalman_angles": the same filter
also handing its angles to the controller, ``KalmanTuning(angles=True)``), with and without
compensation. Per run: RMS link tracking error
[rad], torque RMS [N m], RMS friction-estimate error F_hat - F [N m] (with compensation),
RMS error of the link velocity the controller used [rad/s], divergence (the loop's lost-run
flag, ``jaxflex.sim.simulate.Metrics``), fraction of samples at the 2 N m torque limit; and the
spectral radius of the loop linearised at rest (``jaxflex.loop.analyse.analyse_loop``, quantisers
as the identity, the estimator's state in the loop state; > 1: a growing mode, which the
quantisation noise then drives into chatter or a limit cycle).
Compensation "helps" when the run with it is not lost and its RMS error is below the run
without it; it helps "cleanly" when, in addition, the run with it spends at most
SATURATION_LIMIT of its samples at the torque limit (more is chatter between the limits,
which a low RMS error does not excuse on a rig). The verdict per preset names the cleanly
helping pair with the lowest RMS error, or else the helping one.

Writes DIR/results.json (every number) and DIR/estimator_sensing.png, and prints the table.
``--small`` runs 3 s instead of 10 s.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import jax

Q2D_METHODS = ("model", "filtered", "reference")
PRESETS = ("ideal", "rig", "paper")
SATURATION_LIMIT = 0.05
"""Largest fraction of samples at the torque limit of a run that counts as clean."""


def estimators_for(preset: str) -> tuple[str, ...]:
    """The velocity sources compared under a sensing preset: exact velocities only where the
    sensing is ideal (a rig has no velocity sensor); the filter's angles only where the
    encoders quantise (with exact angles they are the encoders' own)."""
    if preset == "ideal":
        return ("exact", "filtered", "kalman")
    return ("filtered", "kalman", "kalman_angles")


def sensing_for(preset: str, estimator: str) -> Any:
    """The sensing preset with the velocity source ``estimator`` (``estimators_for``)."""
    from jaxflex.core.estimator import KalmanTuning
    from jaxflex.io.presets import sensing_preset

    base = sensing_preset(preset)
    if estimator == "kalman_angles":
        return dataclasses.replace(base, velocity="kalman", kalman=KalmanTuning(angles=True))
    return dataclasses.replace(base, velocity=estimator)


def run(t_final: float, progress: Any = print) -> dict[str, Any]:
    """Every run of the grid (module docstring); JSON-ready rows and the per-preset verdict."""
    import numpy as np

    from jaxflex.loop.analyse import analyse_loop
    from jaxflex.loop.experiments import run_closed_loop
    from jaxflex.io.presets import paper_params, paper_sinusoid

    params = paper_params()
    plant, gains = params.to_plant(), params.to_gains()
    traj = paper_sinusoid()
    rows = []
    for preset in PRESETS:
        for method in Q2D_METHODS:
            for est in estimators_for(preset):
                sensing = sensing_for(preset, est)
                row: dict[str, Any] = {"sensing": preset, "q2d_method": method, "estimator": est}
                for comp in (False, True):
                    t0 = time.perf_counter()
                    r = run_closed_loop(plant, gains, traj, compensation=comp, q2d_method=method,
                                        sensing=sensing, t_final=t_final)
                    key = "with" if comp else "without"
                    e1, tau = np.asarray(r.e1[:, 0]), np.asarray(r.tau[:, 0])
                    F, F_hat = np.asarray(r.F[:, 0]), np.asarray(r.F_hat[:, 0])
                    v_err = np.asarray(r.dq1_hat[:, 0] - r.dq1[:, 0])
                    row[key] = {
                        "rms_error_rad": float(np.sqrt(np.mean(e1**2))),
                        "max_error_rad": float(np.max(np.abs(e1))),
                        "tau_rms_Nm": float(np.sqrt(np.mean(tau**2))),
                        "friction_estimate_rms_error_Nm": float(np.sqrt(np.mean((F_hat - F) ** 2))),
                        "velocity_rms_error_rad_s": float(np.sqrt(np.mean(v_err**2))),
                        "saturation_fraction": float(np.asarray(r.metrics.saturation_fraction).max()),
                        "diverged": bool(r.metrics.diverged),
                        "rest_spectral_radius": analyse_loop(
                            plant, gains, q2d_method=method, compensation=comp,
                            sensing=sensing).rest.spectral_radius,
                        "wall_s": time.perf_counter() - t0,
                    }
                w, wo = row["with"], row["without"]
                row["compensation_ratio"] = w["rms_error_rad"] / wo["rms_error_rad"]
                row["compensation_helps"] = bool(not w["diverged"]
                                                 and w["rms_error_rad"] < wo["rms_error_rad"])
                rows.append(row)
                if progress:
                    progress(_line(row))
    return {"rows": rows, "verdict": verdict(rows)}


def verdict(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per sensing preset: the (q2d method, estimator) pairs with which compensation helps,
    those with which it helps cleanly (module docstring), and the best of the clean ones (or,
    if none, of the helping ones) by RMS link error with compensation."""
    out = {}
    for preset in PRESETS:
        ok = [r for r in rows if r["sensing"] == preset and r["compensation_helps"]]
        clean = [r for r in ok if r["with"]["saturation_fraction"] <= SATURATION_LIMIT]
        pool = clean or ok
        best = min(pool, key=lambda r: r["with"]["rms_error_rad"]) if pool else None
        out[preset] = {
            "compensation_helps_with": [f"{r['q2d_method']}/{r['estimator']}" for r in ok],
            "compensation_helps_cleanly_with": [f"{r['q2d_method']}/{r['estimator']}"
                                                for r in clean],
            "best": None if best is None else {
                "q2d_method": best["q2d_method"], "estimator": best["estimator"],
                "clean": bool(clean),
                "rms_error_with_rad": best["with"]["rms_error_rad"],
                "rms_error_without_rad": best["without"]["rms_error_rad"],
                "tau_rms_with_Nm": best["with"]["tau_rms_Nm"],
                "saturation_fraction_with": best["with"]["saturation_fraction"]},
        }
    return out


HEADER = (f"{'sensing':<7} {'q2d':<9} {'velocity':<13} | {'RMS e1 off':>10} {'RMS e1 on':>10} "
          f"{'on/off':>6} | {'tau off':>7} {'tau on':>7} | {'F_hat err':>9} | {'v err on':>8} | "
          f"{'sat on':>6} | {'rest radius off/on':>17} | {'lost off/on':>11}")


def _line(r: dict[str, Any]) -> str:
    w, wo = r["with"], r["without"]
    return (f"{r['sensing']:<7} {r['q2d_method']:<9} {r['estimator']:<13} | "
            f"{wo['rms_error_rad']:10.2e} {w['rms_error_rad']:10.2e} {r['compensation_ratio']:6.2f} | "
            f"{wo['tau_rms_Nm']:7.3f} {w['tau_rms_Nm']:7.3f} | "
            f"{w['friction_estimate_rms_error_Nm']:9.3f} | {w['velocity_rms_error_rad_s']:8.3f} | "
            f"{w['saturation_fraction']:6.2f} | "
            f"{wo['rest_spectral_radius']:8.4f}/{w['rest_spectral_radius']:8.4f} | "
            f"{str(wo['diverged'])[0]}/{str(w['diverged'])[0]:>9}")


def figure(rows: list[dict[str, Any]], path: Path) -> None:
    """RMS link error without and with compensation per (q2d method, estimator), one panel
    per sensing preset; lost runs hatched."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axs = plt.subplots(1, len(PRESETS), figsize=(14, 4.2), sharey=True)
    for ax, preset in zip(axs, PRESETS):
        sub = [r for r in rows if r["sensing"] == preset]
        x = np.arange(len(sub))
        for off, key, colour in ((-0.2, "without", "tab:gray"), (0.2, "with", "tab:blue")):
            vals = [r[key]["rms_error_rad"] for r in sub]
            bars = ax.bar(x + off, vals, 0.4, color=colour,
                          label=f"{key} compensation")
            for b, r in zip(bars, sub):
                if r[key]["diverged"]:
                    b.set_hatch("xx")
                    b.set_alpha(0.5)
        ax.set_xticks(x, [f"{r['q2d_method']}\n{r['estimator']}" for r in sub], fontsize=7)
        ax.set_yscale("log")
        ax.set_title(f"sensing: {preset}")
        ax.grid(axis="y", which="both", lw=0.3)
    axs[0].set_ylabel("RMS link error (rad); hatched: lost")
    axs[0].legend(fontsize=8)
    fig.suptitle("paper's sinusoid: q2d method x velocity estimator, with and without "
                 "friction compensation")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out/estimator_sensing")
    ap.add_argument("--small", action="store_true", help="3 s runs instead of 10 s")
    args = ap.parse_args()
    jax.config.update("jax_enable_x64", True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_final = 3.0 if args.small else 10.0
    t0 = time.perf_counter()
    print(HEADER)
    res = run(t_final)
    doc = {
        "question": __doc__.split("\n\n")[0],
        "config": {"trajectory": "sinusoid", "t_final_s": t_final, "dt_s": 1e-3,
                   "tau_max_Nm": 2.0, "params": "paper (Tables 1-3, corrected Table 2)",
                   "kalman_tuning": "defaults of jaxflex.core.estimator.KalmanTuning",
                "saturation_limit": SATURATION_LIMIT},
        **res,
        "wall_time_s": time.perf_counter() - t0,
    }
    (out / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
    figure(res["rows"], out / "estimator_sensing.png")
    for preset, v in res["verdict"].items():
        best = v["best"]
        print(f"{preset}: compensation helps with {v['compensation_helps_with'] or 'none'}, "
              f"cleanly with {v['compensation_helps_cleanly_with'] or 'none'}"
              + ("" if best is None else
                 f"; best {best['q2d_method']}/{best['estimator']}"
                 f"{'' if best['clean'] else ' (chattering)'} "
                 f"({best['rms_error_without_rad']:.2e} -> {best['rms_error_with_rad']:.2e} rad, "
                 f"torque RMS {best['tau_rms_with_Nm']:.2f} N m, "
                 f"{100 * best['saturation_fraction_with']:.0f}% of samples at the limit)"))


if __name__ == "__main__":
    main()
