"""Study: is the KUKA KR300's joint stiffness identifiable joint by joint, and does the
flexible rotor model predict the motor torque better than a rigid model?

Question: on axes 1-3 of the KUKA KR300 recordings (``jaxflex.data.load_kuka``; motor- and
link-side encoders), fit the rotor subsystem (model kind "rotor", issue 14)

    J q2'' + K (q2 - q1c) + Fm tanh(q2'/w) + bm q2' - c = tau,   q1c = q1 + skew q1' + off

with the *measured* link angle q1 as an input (no model of the multi-body link side; the
``encoder_skew`` effect carries the encoder time skew and offset, the ``motor_friction``
effect the motor-side friction; the torque offset c is left out because K * off is the same
constant) on trajectory A, by equation error on
the torque predicted from the measured motion (``jaxflex.validate.predicted_torque``, the one
inverse dynamics) with the engine's solver (``jaxflex.fit.least_squares``). K is restarted
from 0.3x and 3x the nominal ``c_rad_ff``. Validation on B and C: J, K, friction and c kept;
the per-log sensor nuisances (skew, offset) refitted on each log (they change between
recordings). Baseline: the rigid least-squares model on the motor encoder
``tau = Jt q2'' + Fv q2' + Fc sign(q2') + c`` (Savitzky-Golay zero-phase derivatives), fitted
on A. Also reported: the open-loop segment replay gap of the rotor model (q2 predicted from
tau and measured q1).

Writes ``DIR/results.json`` as ``{"axis1": {"K", "K_stderr", "skew_s", "skew_stderr", "A":
{"torque_pct", "gap"}, "B": {...}, "C": {...}, "rigid_baseline": {"A", "B", "C"}, "K_restarts":
[...]}, ...}`` and a figure per axis.

Usage: ``python studies/kuka_flexible.py --out DIR [--small]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

FREE = ("J", "K", "motor_friction.Fm", "motor_friction.bm",
        "encoder_skew.skew", "encoder_skew.offset")
NUISANCE = ("encoder_skew.skew", "encoder_skew.offset")


class TorqueFit(eqx.Module):
    """Data of an equation-error fit: parameter space, measured motion, torque scale [N m]."""

    space: Any
    motion: dict
    scale: float = eqx.field(static=True)


def torque_fit_residuals(theta: dict, data: TorqueFit) -> jax.Array:
    """(tau_hat - tau) / scale over the samples (the fit's residuals)."""
    from jaxflex.validate import predicted_torque

    plant = data.space.plant(theta)
    return ((predicted_torque(plant, "rotor", data.motion) - data.motion["tau"]) / data.scale
            ).reshape(-1)


def fit(params, log, free, max_steps=50):
    """Equation-error fit of ``free`` on ``log``; returns (params, stderr dict, theta)."""
    from jaxflex.fit import ParamSpace, covariance, least_squares, set_values
    from jaxflex.validate import motion_of

    motion = {k: jnp.asarray(v) for k, v in motion_of(log, "rotor").items()}
    space = ParamSpace.build(params.to_plant(), list(free))
    data = TorqueFit(space=space, motion=motion, scale=float(np.std(log.tau)))
    sol = least_squares(data, space.theta0(), fn=torque_fit_residuals, max_steps=max_steps,
                        scaling="marquardt")
    theta = sol.y
    cov = covariance(data, theta, fn=torque_fit_residuals)  # the engine's, through the space
    phys = {k: np.asarray(v) for k, v in space.physical(theta).items()}
    se = {k: float(np.asarray(v)[0]) for k, v in cov["stderr"].items()}
    return set_values(params, phys), se, sol


def rigid_baseline(log_fit, logs):
    """Rigid LS on the motor encoder fitted on ``log_fit``; torque errors [%] on ``logs``."""
    from jaxflex.fit import savgol
    from jaxflex.validate import rel_error_pct

    def X(lg):
        q = lg.q2[:, 0]
        v, a = savgol(q, lg.dt, 1), savgol(q, lg.dt, 2)
        return np.stack([a, v, np.sign(v), np.ones_like(v)], axis=1)

    coef, *_ = np.linalg.lstsq(X(log_fit), log_fit.tau[:, 0], rcond=None)
    return {k: rel_error_pct(lg.tau[:, 0], X(lg) @ coef) for k, lg in logs.items()}, coef


def main(argv: list[str] | None = None) -> dict:
    """Run the study; returns the results dict (also written to ``results.json``)."""
    jax.config.update("jax_enable_x64", True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jaxflex.data import kuka_record, load_kuka
    from jaxflex.params import Params
    from jaxflex.fit import set_values
    from jaxflex.validate import rel_error_pct, segment_gap, torque_prediction

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/kuka_flexible")
    ap.add_argument("--small", action="store_true", help="axis 1 only, 1000 samples")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rec = kuka_record("A")
    axes = (1,) if args.small else (1, 2, 3)
    results: dict = {}
    for ax in axes:
        logs = {k: load_kuka(k, ax) for k in ("A", "B", "C")}
        if args.small:
            logs = {k: lg.slice(0, 1000) for k, lg in logs.items()}
        i = ax - 1
        J0, K0 = float(rec.J_mr[i] * rec.u[i] ** 2), float(rec.c_rad_ff[i])
        fits = []
        for f in (1.0, 0.3, 3.0):
            init = Params.from_dict({
                "plant": {"I": 1.0, "J": J0, "K": f * K0},
                "friction": {"Fc": 1.0, "Fs": 1.0, "vs": 0.1, "sigma0": 1e5, "sigma1": 0.0,
                             "sigma2": 0.0},
                "effects": {"motor_friction": {"Fm": [100.0], "bm": [100.0], "width": [0.01]},
                            "torque_offset": {"offset": [0.0]},
                            "encoder_skew": {"skew": [0.0], "offset": [0.0]}}})
            fits.append((f, *fit(init, logs["A"], FREE)))
        p, se, sol = min(fits[:1] + fits[1:], key=lambda x: x[3].cost)[1:]
        row: dict = {"K": p.plant["K"][0], "K_stderr": se["K"], "J": p.plant["J"][0],
                     "J_stderr": se["J"], "skew_s": p.effects["encoder_skew"]["skew"][0],
                     "skew_stderr": se["encoder_skew.skew"],
                     "encoder_offset_rad": p.effects["encoder_skew"]["offset"][0],
                     "K_nominal": K0,
                     "K_restarts": [{"start_factor": f, "K": q.plant["K"][0], "K_stderr": s["K"],
                                     "cost": so.cost, "converged": so.converged}
                                    for f, q, s, so in fits]}
        fig, axs = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
        for j, (k, lg) in enumerate(logs.items()):
            pk, nuis = p, None
            if k != "A":  # per-log sensor nuisances
                pk, nuis, _ = fit(p, lg, NUISANCE)
            tau_hat = torque_prediction(pk, lg, kind="rotor")
            row[k] = {"torque_pct": rel_error_pct(lg.tau, tau_hat),
                      "gap": segment_gap(pk, lg, kind="rotor", length=50)}
            if nuis is not None:
                row[k]["skew_s"] = pk.effects["encoder_skew"]["skew"][0]
                row[k]["skew_stderr"] = nuis["encoder_skew.skew"]
            axs[j].plot(lg.t, lg.tau[:, 0], lw=0.7, label="measured")
            axs[j].plot(lg.t, tau_hat[:, 0], lw=0.7, label="rotor model")
            axs[j].set_ylabel(f"{k}: tau [N m]")
        row["rigid_baseline"], _ = rigid_baseline(logs["A"], logs)
        axs[0].legend(fontsize=7)
        axs[-1].set_xlabel("time [s]")
        axs[0].set_title(f"KUKA axis {ax}: link-side motor torque, measured vs rotor model "
                         f"(K = {row['K']:.3g} N m/rad)", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / f"axis{ax}_torque.png", dpi=110)
        plt.close(fig)
        results[f"axis{ax}"] = row
        print(f"axis {ax}: K {row['K']:.4g} +- {row['K_stderr']:.3g} (nominal {K0:.4g}), "
              f"restarts {[round(r['K'], 0) for r in row['K_restarts']]}, skew "
              f"{1e3 * row['skew_s']:.3f} +- {1e3 * row['skew_stderr']:.3f} ms; torque % "
              + ", ".join(f"{k} {row[k]['torque_pct']:.2f} (rigid {row['rigid_baseline'][k]:.2f})"
                          for k in logs) + "; gap " + ", ".join(
                              f"{k} {row[k]['gap']:.3f}" for k in logs))
    del set_values
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    return results


if __name__ == "__main__":
    main()
