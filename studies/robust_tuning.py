"""Study: what does robustness cost, and what does it buy? Paper gains, nominally tuned gains
and robustly tuned gains on 1,000 held-out plausible plants.

1. Identification: all six LuGre parameters from a 10 s synthetic log of the paper's link
   (16-bit encoders, 20 % off start); its posterior (``jaxflex.fit.posterior``) is reported.
   It is far too tight to matter (relative standard deviations below 1 %), so the plants
   are drawn from the fallback spread: +-30 % on every friction
   parameter, +-15 % on I, J, K (uniform).
2. Nominal tuning (``jaxflex.tune.tune``) on the nominal plant from the paper's gains; robust
   tuning (``jaxflex.tune.robust.tune_robust``, CVaR_0.9 of the per-plant cost over a fixed
   training batch of 64 plants, certified on the whole box) warm-started at the nominal
   search's point after N steps (--iterations, default 30) and run N more; the nominal gains
   compared are those after 2N nominal steps, so both had the same number of steps. Same task for both: the paper's
   sinusoid, 2 s, rig sensing (16-bit encoders, 12-bit DAC, filtered velocities), 2 N m,
   model-based q2d, 1 kHz, margin 0.05 up to 1.5 x the reference speed.
3. Held-out evaluation (the sweep engine, another seed): RMS link error per plant, its median
   and 95th percentile, lost runs, the fraction of plants on which N2 is positive definite up
   to the task speed, and the cost of robustness (RMS on the nominal plant, robust against
   nominal gains).
4. Timing: one robust step (risk and gradient) over 256 plants x 2 s at 1 kHz, compilation
   apart, min and median of repeats, with BLAS threads and load recorded.

Writes DIR/results.json ({"paper": {"rms_q50", "rms_q95", "certified_fraction", ...},
"nominal": {...}, "robust": {...}, "held_out_plants": N, ...}) and DIR/robust_tuning.png.

    python studies/robust_tuning.py --out DIR [--small]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/robust_tuning")
    ap.add_argument("--held-out", type=int, default=1000, help="held-out plants (default 1000)")
    ap.add_argument("--plants", type=int, default=64, help="training plants (default 64)")
    ap.add_argument("--iterations", type=int, default=30,
                    help="Adam steps of the robust search and of the nominal warm start (default 30)")
    ap.add_argument("--risk", default="cvar:0.9", help="risk measure (default cvar:0.9)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--small", action="store_true",
                    help="smoke run: 0.5 s horizon, 8 training and 32 held-out plants")
    a = ap.parse_args(argv)
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise SystemExit(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from benchkit import limit_blas_threads, machine_state
    from jaxflex.core.certificate import certify_box
    from jaxflex.fit.posterior import Posterior
    from jaxflex.identify import DEFAULT_FREE, excitation_torque, identify, perturb, synthetic_log
    from jaxflex.io.presets import paper_gains, paper_params, sensing_of, trajectory_preset
    from jaxflex.tune.robust import (RiskMeasure, RobustTask, _risk_and_grad, evaluate_batch,
                                sample_batch, tune_robust)
    from jaxflex.core.sensing import Sensing
    from jaxflex.sweep import parse_spread
    from jaxflex.tune import TuneTask, tune

    blas = limit_blas_threads(1)
    t_all = time.perf_counter()
    small = a.small
    t_final = 0.5 if small else 2.0
    held = 32 if small else a.held_out
    plants = 8 if small else a.plants
    iters = 2 if small else a.iterations
    results: dict = {"settings": {"t_final": t_final, "held_out_plants": held,
                                  "training_plants": plants, "iterations": iters,
                                  "risk": a.risk, "seed": a.seed, "small": small}}

    # 1. identification and its posterior
    p = paper_params()
    res16 = 2 * math.pi / 2**16
    sens = Sensing(q1_resolution=res16, q2_resolution=res16 / 50, q1_noise=2e-5, q2_noise=1e-6)
    t0 = time.perf_counter()
    log, _ = synthetic_log(p.to_plant(), excitation_torque(t_final=3.0 if small else 10.0,
                                                           periods=(1.5, 0.7)),
                           substeps=2, sensing=sens, key=jax.random.PRNGKey(a.seed))
    init = perturb(p, DEFAULT_FREE, (1.2, 0.9, 1.2, 0.8, 1.2, 0.8))
    ident = identify(log, init, DEFAULT_FREE, segment_length=300, substeps=2, max_steps=100)
    ident_rec = {"converged": ident.converged, "reason": ident.reason,
                 "seconds": time.perf_counter() - t0, "log_seconds": float(log.t[-1])}
    if ident.converged:
        post = Posterior.from_params(ident.params)
        sd = post.stderr()
        ident_rec["posterior_sd_theta"] = {k: v.tolist() for k, v in sd.items()}
        ident_rec["largest_relative_sd"] = float(max(np.max(v) for v in sd.values()))
    too_tight = (not ident.converged) or ident_rec["largest_relative_sd"] < 0.05
    ident_rec["spread_used"] = ("fallback: +-30% friction, +-15% I, J, K (posterior "
                                + ("too tight to matter)" if ident.converged else
                                   "unavailable: not converged)")) if too_tight else "posterior"
    results["identification"] = ident_rec
    print(f"identification: converged {ident.converged}, largest relative sd "
          f"{ident_rec.get('largest_relative_sd', float('nan')):.2g} -> {ident_rec['spread_used']}")

    spread = {"nominal": "paper", "trajectory": "sinusoid", "t_final": t_final, "sensing": "rig",
              "controller": {"tau_max": 2.0, "q2d_method": "model"}, "seed": a.seed,
              "uncertain": {"friction.*": {"dist": "uniform", "rel": 0.3},
                            "plant.*": {"dist": "uniform", "rel": 0.15}}}
    spec = parse_spread(spread)
    task = RobustTask(spec, RiskMeasure.parse(a.risk), plants=plants)
    gains0 = paper_gains()

    # 2. nominal and robust tuning
    ntask = TuneTask(trajectories=(trajectory_preset("sinusoid"),), t_final=t_final,
                     sensing=sensing_of("rig"), tau_max=2.0, q2d_method="model")
    t0 = time.perf_counter()
    # the nominal search gets as many steps as nominal + robust together, so that a robust
    # advantage is not merely more steps
    nom = tune(p.to_plant(), gains0, ntask, margin=0.05, iterations=2 * iters, starts=1)
    nom_half = tune(p.to_plant(), gains0, ntask, margin=0.05, iterations=iters, starts=1)
    t_nom = time.perf_counter() - t0
    t0 = time.perf_counter()
    # warm start at the nominal search's N-step point: the robust search then asks what
    # robustness adds; a cold robust start would compare how far each search got
    rob = tune_robust(task, nom_half.gains, margin=0.05, iterations=iters, starts=1, seed=a.seed)
    t_rob = time.perf_counter() - t0
    results["tuning"] = {"nominal_seconds": t_nom, "robust_seconds": t_rob,
                         "robust": {k: v for k, v in rob.summary().items() if k != "starts"},
                         "nominal_certified_up_to": nom.certificate.certified_up_to
                         if nom.certificate else None}
    print(f"tuning: nominal {t_nom:.0f} s, robust {t_rob:.0f} s (certified on the box: "
          f"{rob.certified}, feasibility steps {rob.feasibility_steps})")

    # 3. held-out plants
    sets = {"paper": gains0, "nominal": nom.gains, "robust": rob.gains}
    ev = {}
    for name, g in sets.items():
        t0 = time.perf_counter()
        e = evaluate_batch(task, g, samples=held)
        ev[name] = e
        results[name] = {**e.summary(), "seconds": time.perf_counter() - t0,
                         "gains": g.to_dict()}
        print(f"{name:8s} rms q50 {e.rms_q50:.3e}  q95 {e.rms_q95:.3e}  lost "
              f"{e.lost_fraction:.3f}  certified {e.certified_fraction:.3f}")
    # cost of robustness on the nominal plant
    from jaxflex.tune import tracking_cost
    nominal_rms = {}
    for name, g in sets.items():
        _, aux = tracking_cost(p.to_plant(), g, ntask)
        nominal_rms[name] = float(np.max(np.asarray(aux["rms_error"])))
    for name in sets:
        results[name]["rms_nominal_plant"] = nominal_rms[name]
    box_certs = {k: certify_box(rob.box, g, 500.0, num=201, margin=0.05) for k, g in sets.items()}
    for k in sets:
        results[k]["box_certified_up_to"] = box_certs[k].certified_up_to
    results["box"] = rob.box.to_dict()
    results["held_out_plants"] = held
    results["robust_beats_nominal_q95"] = bool(ev["robust"].rms_q95 < ev["nominal"].rms_q95)
    results["cost_of_robustness"] = {
        "nominal_plant_rms_ratio_robust_over_nominal": nominal_rms["robust"] / nominal_rms["nominal"],
        "median_rms_ratio_robust_over_nominal": ev["robust"].rms_q50 / ev["nominal"].rms_q50,
    }

    # 4. one robust step over 256 plants x 2 s
    n_t = 16 if small else 256
    big = RobustTask(parse_spread({**spread, "t_final": 0.5 if small else 2.0}),
                     RiskMeasure.parse(a.risk), plants=n_t)
    settings = (big.spec.t_final, big.spec.substeps, False, big.torque_weight, big.risk,
                big.lost_cost())
    batch = sample_batch(big.spec, jnp.arange(n_t))
    theta = jnp.log(gains0.to_vector())
    t0 = time.perf_counter()
    jax.block_until_ready(_risk_and_grad(theta, gains0.leak, batch, settings))
    first = time.perf_counter() - t0
    reps = []
    for _ in range(2 if small else 3):
        t0 = time.perf_counter()
        jax.block_until_ready(_risk_and_grad(theta, gains0.leak, batch, settings))
        reps.append(time.perf_counter() - t0)
    results["step_timing"] = {
        "plants": n_t, "t_final": big.spec.t_final, "controller_steps_per_plant":
        int(round(big.spec.t_final / big.spec.dt)), "substeps": big.spec.substeps,
        "compile_and_first_s": first, "compile_s_approx": first - min(reps),
        "step_min_s": min(reps), "step_median_s": float(np.median(reps)), "repeats": len(reps),
        "plant_steps_per_s": n_t * big.spec.t_final / big.spec.dt / min(reps),
        "machine": machine_state(), "blas": blas,
    }
    print(f"one robust step, {n_t} plants x {big.spec.t_final} s: min {min(reps):.2f} s "
          f"(compile + first {first:.1f} s)")
    results["wall_s"] = time.perf_counter() - t_all

    # figure
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    allr = np.concatenate([np.asarray(ev[k].rms_error) for k in sets])
    bins = np.geomspace(max(np.nanmin(allr), 1e-6), np.nanmax(allr) * 1.01, 40)
    for k in sets:
        r = np.asarray(ev[k].rms_error)
        ax[0].hist(r[~np.asarray(ev[k].lost)], bins=bins, histtype="step", lw=1.5,
                   label=f"{k}: q50 {ev[k].rms_q50:.2e}, q95 {ev[k].rms_q95:.2e}")
    ax[0].set_xscale("log")
    ax[0].set_xlabel("RMS link error on a held-out plant [rad]")
    ax[0].set_ylabel("plants")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"{held} held-out plants (+-30% friction, +-15% I, J, K)")
    for k in sets:
        c = box_certs[k]
        ax[1].semilogx(np.maximum(c.velocities, 1e-2), c.lambda_min,
                       label=f"{k}: certified on the box to {c.certified_up_to:.3g} rad/s; "
                       f"{100 * ev[k].certified_fraction:.0f}% of plants at task speed")
    ax[1].axhline(0.05, color="k", lw=0.8, ls="--")
    ax[1].axvline(task.certify_speed(), color="gray", lw=0.8, ls=":")
    ax[1].set_xlabel("link speed |q1'| [rad/s]")
    ax[1].set_ylabel("lambda_min(N2) lower bound over the box")
    ax[1].set_yscale("symlog", linthresh=1e-2)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "robust_tuning.png", dpi=120)
    plt.close(fig)
    (out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    print(f"wrote {out}/results.json and robust_tuning.png ({results['wall_s']:.0f} s)")
    return results


if __name__ == "__main__":
    main()
