"""What does the N2 stability certificate cost in tracking performance?

Question: on the paper's sinusoid (sampled-data loop, 16-bit encoders, filtered velocities,
12-bit DAC, 2 N m torque limit), how much RMS link error do we give up when the tuned gains
must keep N2 (paper eq. 29) positive definite with a margin over the task's speeds, against
the best gains found by the same search without the certificate; and how does the certified
link-speed range we demand trade against the tracking error?

Also checked: the paper's 0.72 deg link encoder with the paper's gains (L1 = 200): chatter and
torque saturation, against the 16-bit rig.

Writes ``results.json`` and ``tradeoff.png``, ``lambda_min.png``, ``tracking.png`` to ``--out``
(default ``out/certificate_cost``). ``--small`` runs a tiny version (for the slow test).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np


def certified_start(plant, gains, v_req: float, margin: float):
    """Initial gains certified up to ``v_req`` [rad/s]: the given gains with the observer gain
    Ke halved until sigma0 Psi#(v) / Ke (eq. 29) is large enough (None if 40 halvings fail)."""
    from jaxflex.core.certificate import certify

    g = gains
    for _ in range(40):
        if certify(plant, g, v_req, margin=margin, num=101).certified:
            return g
        g = eqx.tree_at(lambda x: x.Ke, g, g.Ke / 2)
    return None


def main(argv: list[str] | None = None) -> dict:
    """Run the study; returns the results dict."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/certificate_cost")
    ap.add_argument("--small", action="store_true", help="tiny run (seconds, for tests)")
    ap.add_argument("--t-final", type=float, default=None)
    ap.add_argument("--iterations", type=int, default=None)
    ap.add_argument("--starts", type=int, default=None)
    ap.add_argument("--margin", type=float, default=0.05)
    ap.add_argument("--torque-weight", type=float, default=1e-6,
                    help="weight of mean squared torque in the cost [rad^2/(N m)^2]; 1e-6 "
                    "prices 1 N m RMS like 1 mrad RMS error (0 lets the search chatter at the "
                    "torque limit)")
    args = ap.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    from jaxflex.core.certificate import certify
    from jaxflex.app.plots import save_figure
    from jaxflex.app.plots.tune import plot_lambda_min, plot_tracking_comparison, plot_tradeoff
    from jaxflex.io.presets import paper_gains, paper_plant, paper_sensing, paper_sinusoid
    from jaxflex.tune import TuneTask, evaluate, simulate_task, tune

    t_final = args.t_final or (0.5 if args.small else 2.0)
    iterations = args.iterations if args.iterations is not None else (2 if args.small else 15)
    starts = args.starts or (1 if args.small else 2)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    plant, paper = paper_plant(), paper_gains()
    task = TuneTask(trajectories=(paper_sinusoid(),), t_final=t_final,
                    torque_weight=args.torque_weight)
    v_ref = task.reference_speed()
    vmax_report = 500.0
    t0 = time.perf_counter()

    def ev(g, tk=task):
        e = evaluate(plant, g, tk, vmax=vmax_report)
        return {"cost": e["rms_error"] ** 2 + args.torque_weight * e["tau_rms"] ** 2,
                "rms_error": e["rms_error"], "tau_rms": e["tau_rms"],
                "saturation_fraction": max(p["saturation_fraction"] for p in e["per_trajectory"]),
                "max_link_speed": max(p["max_link_speed"] for p in e["per_trajectory"]),
                "certified_up_to": e["certificate"]["certified_up_to"],
                "lambda_min_at_task_speed": e["lambda_min_at_task_speed"],
                "certificate": e["certificate"], "gains": e["gains"]}

    def run_tune(margin, v_req, start):
        tk = TuneTask(trajectories=task.trajectories, t_final=t_final,
                      torque_weight=args.torque_weight, velocity_factor=max(1.0, v_req / v_ref))
        print(f"[certificate_cost] tune margin={margin} v_req={v_req:.3g} rad/s", flush=True)
        return tune(plant, start, tk, margin=margin, iterations=iterations, starts=starts,
                    seed=0)

    results: dict = {"config": {"t_final": t_final, "iterations": iterations, "starts": starts,
                                "torque_weight": args.torque_weight,
                                "margin": args.margin, "reference_speed": v_ref,
                                "sensing": "16-bit encoders, filtered velocities, 12-bit DAC",
                                "tau_max": task.tau_max, "q2d_method": task.q2d_method}}
    results["paper"] = ev(paper)
    v_task = task.certify_speed()
    cert_res = run_tune(args.margin, v_task, paper)
    unc_res = run_tune(None, v_task, paper)
    results["certified"] = ev(cert_res.gains)
    results["uncertified"] = ev(unc_res.gains)
    results["certified"]["search_wall_time_s"] = cert_res.wall_time_s
    results["uncertified"]["search_wall_time_s"] = unc_res.wall_time_s
    results["certificate_cost_ratio"] = (results["certified"]["rms_error"]
                                         / results["uncertified"]["rms_error"])

    # trade-off: demand certification up to v_req, tune, record the error
    levels = [v_task, 100.0] if args.small else [v_task, 10.0, 30.0, 100.0, 300.0, 1000.0]
    trade = []
    for v_req in levels:
        start = certified_start(plant, paper, v_req, args.margin)
        if start is None:
            trade.append({"required_speed": v_req, "rms_error": None, "note": "no certified start"})
            continue
        r = run_tune(args.margin, v_req, start)
        ok = certify(plant, r.gains, v_req, margin=args.margin, num=101).certified
        e = ev(r.gains)
        trade.append({"required_speed": v_req, "cost": e["cost"], "rms_error": e["rms_error"],
                      "tau_rms": e["tau_rms"], "certified_up_to": e["certified_up_to"],
                      "start_Ke": float(start.Ke[0]), "gains": e["gains"],
                      "passes_certify_at_required_speed": ok})
    results["tradeoff"] = trade
    # Every certified candidate is also an uncertified one: the best gains found without the
    # certificate are the best of all runs; the best certified at the task speed likewise.
    found = [("uncertified", results["uncertified"]["cost"], v_task)] + [
        (f"certified_to_{p['required_speed']:.3g}", p["cost"], p["required_speed"])
        for p in trade if p["rms_error"] is not None]
    best_any = min(found, key=lambda f: f[1])
    best_cert = min([f for f in found[1:] if f[2] >= v_task] or [("none", np.inf, 0.0)],
                    key=lambda f: f[1])
    results["best_found"] = {"any": {"run": best_any[0], "cost": best_any[1]},
                             "certified_at_task_speed": {"run": best_cert[0], "cost": best_cert[1]},
                             "cost_ratio_certified_over_any": best_cert[1] / best_any[1]}

    # the paper's 0.72 deg link encoder (section 6.3) with the paper's and the tuned gains
    ptask = TuneTask(trajectories=task.trajectories, t_final=t_final, sensing=paper_sensing(),
                     torque_weight=args.torque_weight)
    results["paper_encoder"] = {
        "paper_gains": {k: v for k, v in ev(paper, ptask).items() if k != "certificate"},
        "certified_tuned_gains": {k: v for k, v in ev(cert_res.gains, ptask).items()
                                  if k != "certificate"},
    }

    figs = [
        save_figure(plot_tradeoff([p for p in trade if p["rms_error"] is not None],
                                  unconstrained=results["uncertified"], paper=results["paper"]),
                    out / "tradeoff.png"),
        save_figure(plot_lambda_min({k: results[k]["certificate"]
                                     for k in ("paper", "certified", "uncertified")},
                                    v_task=v_task, margin=args.margin), out / "lambda_min.png"),
        save_figure(plot_tracking_comparison({k: simulate_task(plant, g, task) for k, g in
                                              (("paper", paper), ("certified", cert_res.gains),
                                               ("uncertified", unc_res.gains))}),
                    out / "tracking.png"),
    ]
    for k in ("paper", "certified", "uncertified"):
        c = results[k].pop("certificate")
        results[k]["min_lambda_min_to_500"] = c["min_lambda_min"]
    results["figures"] = figs
    results["wall_time_s"] = time.perf_counter() - t0
    (out / "results.json").write_text(json.dumps(results, indent=2, default=float) + "\n")
    print(json.dumps({k: results[k] for k in ("paper", "certified", "uncertified")}, indent=1,
                     default=float))
    print("tradeoff:", [(p["required_speed"], p["rms_error"]) for p in trade])
    print("best found:", results["best_found"])
    print("paper encoder:", json.dumps(results["paper_encoder"], default=float))
    return results


if __name__ == "__main__":
    main()
