"""``jaxflex tune --params P.json --out GAINS.json``: tune the cascade gains on a simulated task
under the N2 stability certificate (paper section 4; docs/spec.md section 4)."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxflex.io.presets import SENSING_DESCRIPTIONS, SENSING_PRESETS, TRAJECTORIES
from jaxflex.io.progress import Bar


EXAMPLE = ("jaxflex tune --params identified.json --out tuned.json --trajectory sinusoid "
           "--margin 0.05   (report in tuned_report/)")

def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``tune`` subcommand."""
    p = sub.add_parser(
        "tune",
        help="tune the controller gains on a simulated task, certified by N2",
        description="Gradient-based multi-start tuning of Ke, KD1, KD2, kv, L1, L2 (log-space "
        "Adam through the sampled-data simulation) minimising the RMS link error, with "
        "lambda_min(N2) >= margin enforced for all link speeds of the task. Writes the tuned "
        "parameter file (docs/spec.md section 7) and a report folder comparing initial and tuned gains. "
        "The controller configuration (trajectory, sensing, torque limit, q2d method, dt) is "
        "taken from the options, then from the 'controller' section of --params, then the "
        "defaults; it is recorded in the 'controller' section of --out, which 'jaxflex export' "
        "and 'jaxflex run-loop' then follow.",
    )
    p.add_argument("--params",
                   help="parameter file (plant, friction; its gains, or the paper's, start the "
                   "search); with --spread: the initial gains only (default: the spread's)")
    p.add_argument("--spread",
                   help="robust tuning: a spread file (jaxflex sweep's format; 'identified' draws "
                   "from an identification's posterior) whose plants the gains must serve; the "
                   "trajectory, horizon, sensing, torque limit, q2d method and dt are the "
                   "spread's; the gains are certified on the spread's whole parameter box")
    p.add_argument("--risk", default="cvar:0.9",
                   help="with --spread: risk measure of the per-plant cost: mean, quantile:A or "
                   "cvar:A (default cvar:0.9)")
    p.add_argument("--plants", type=int, default=64,
                   help="with --spread: training plants per step (default 64)")
    p.add_argument("--resample", action="store_true",
                   help="with --spread: a fresh batch of plants each step (default: one fixed "
                   "batch, a deterministic objective)")
    p.add_argument("--confidence", type=float, default=0.95,
                   help="with --spread: coverage of the certified box for unbounded "
                   "distributions and an identification's posterior (default 0.95)")
    p.add_argument("--out", required=True, help="output parameter file with the tuned gains")
    p.add_argument("--report", help="report folder (default: <out stem>_report next to --out)")
    p.add_argument("--trajectory", action="append", choices=TRAJECTORIES,
                   help="task trajectory, repeat for several (default: sinusoid)")
    p.add_argument("--t-final", type=float, default=None,
                   help="seconds per trajectory (default 2; with --spread: the spread's)")
    p.add_argument("--margin", type=float, default=0.05,
                   help="required lambda_min(N2) over the task speeds (default 0.05)")
    p.add_argument("--velocity-factor", type=float, default=1.5,
                   help="certify up to this factor x the fastest reference speed (default 1.5)")
    p.add_argument("--iterations", type=int, default=30, help="Adam steps per start (default 30)")
    p.add_argument("--starts", type=int, default=3, help="multi-start count (default 3)")
    p.add_argument("--lr", type=float, default=0.1, help="step size in log-gain units (default 0.1)")
    p.add_argument("--sensing", default=None, choices=SENSING_PRESETS,
                   help="sensing preset (default rig); " + "; ".join(
                       f"{k}: {v}" for k, v in SENSING_DESCRIPTIONS.items()))
    p.add_argument("--tau-max", type=float, default=None, help="torque limit [N m] (default 2)")
    p.add_argument("--dt", type=float, default=None, help="sample period [s] (default 1e-3)")
    p.add_argument("--q2d", default=None, choices=["model", "filtered"],
                   help="how the controller gets q2d', q2d'' (default model)")
    p.add_argument("--torque-weight", type=float, default=1e-6,
                   help="weight of mean squared torque in the cost [rad^2/(N m)^2] (default "
                   "1e-6: 1 N m RMS costs like 1 mrad RMS error)")
    p.add_argument("--min-rest-damping", type=float, default=None,
                   help="require every mode of the loop linearised at rest to have at least "
                   "this damping ratio (no persistent oscillation at rest; the paper's gains "
                   "have a growing rest mode); default: not required")
    p.add_argument("--seed", type=int, default=0, help="seed of the random starts (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Tune, write the gains (with their controller section) and the report, print a
    comparison."""
    import dataclasses

    from jaxflex.io.params import ControllerConfig, load_params, save_params
    from jaxflex.io.presets import controller_config, paper_gains, sensing_of, trajectory_preset
    from jaxflex.app.reports import write_tune_report
    from jaxflex.tune import TuneTask, compare, tune

    from jaxflex.app.cli.outputs import check_outputs, writing

    out = Path(args.out)
    report_dir = Path(args.report) if args.report else out.with_name(out.stem + "_report")
    check_outputs(args.force, files=[out])
    check_outputs(args.force, folders=[report_dir], flag="--report",
                  marker=["report.json", "lambda_min.png", "tracking.png", "history.png"])
    if args.margin < 0:
        raise ValueError(f"--margin must be >= 0, got {args.margin}")
    if args.iterations < 0 or args.starts < 1:
        raise ValueError("--iterations must be >= 0 and --starts >= 1")
    if args.spread:
        return run_robust(args, out, report_dir)
    if not args.params:
        raise ValueError("jaxflex tune: give --params (nominal tuning) or --spread (robust)")
    params = load_params(args.params)
    plant = params.to_plant()
    initial = params.to_gains() if params.gains is not None else paper_gains()
    if plant.n != 1:
        raise ValueError("jaxflex tune: the built-in trajectories are for one joint; use "
                         "jaxflex.tune.tune from Python for n joints")
    trajectory = None
    if args.trajectory:
        trajectory = args.trajectory[0] if len(args.trajectory) == 1 else tuple(args.trajectory)
    options = {"q2d_method": args.q2d, "dt": args.dt, "tau_max": args.tau_max,
               "sensing": args.sensing, "trajectory": trajectory, "compensation": True}
    recorded = params.controller or ControllerConfig()
    cfg = controller_config(dataclasses.replace(params, controller=dataclasses.replace(
        recorded, **{k: v for k, v in options.items() if v is not None})))
    names = (cfg.trajectory,) if isinstance(cfg.trajectory, str) else cfg.trajectory
    task = TuneTask(trajectories=tuple(trajectory_preset(n) for n in names),
                    t_final=2.0 if args.t_final is None else args.t_final,
                    sensing=sensing_of(cfg.sensing), tau_max=cfg.tau_max, dt=cfg.dt,
                    q2d_method=cfg.q2d_method, torque_weight=args.torque_weight,
                    velocity_factor=args.velocity_factor, min_rest_damping=args.min_rest_damping)
    bar = None if args.quiet else Bar("tune", unit="sim")
    try:
        res = tune(plant, initial, task, margin=args.margin, iterations=args.iterations,
                   starts=args.starts, learning_rate=args.lr, seed=args.seed, progress=bar)
    finally:
        if bar is not None:
            bar.close()
    comparison = compare(plant, res, task)
    with writing():  # the whole result or nothing, Ctrl-C included
        save_params(dataclasses.replace(params, gains=res.gains.to_dict(), controller=cfg), out)
        rep = write_tune_report(res, task, comparison, report_dir)
    print(f"{'':<8} {'RMS err (rad)':>14} {'torque RMS (N m)':>17} {'lambda_min@task':>16} "
          f"{'certified to (rad/s)':>21}")
    for k in ("initial", "tuned"):
        e = rep[k]
        print(f"{k:<8} {e['rms_error']:>14.3e} {e['tau_rms']:>17.3f} "
              f"{e['lambda_min_at_task_speed']:>16.4g} {e['certificate']['certified_up_to']:>21.4g}")
    print(f"wrote {out} and {report_dir}/report.json ({res.wall_time_s:.0f} s, "
          f"{res.evaluations} simulations)")
    return 0


def run_robust(args: argparse.Namespace, out: Path, report_dir: Path) -> int:
    """``--spread``: tune over the spread's plants (``jaxflex.tune.robust.tune_robust``), evaluate
    initial and tuned gains on held-out plants, write the gains with their controller section
    and certificate record; refuse (exit 3, nothing written) when no candidate is certified."""
    import dataclasses
    import json
    import math

    from jaxflex.io.params import ControllerConfig, load_params, save_params
    from jaxflex.tune.robust import RiskMeasure, RobustTask, evaluate_batch, tune_robust
    from jaxflex.sweep import load_spread

    from jaxflex.app.cli.outputs import writing

    ignored = [f"--{k.replace('_', '-')}" for k in ("trajectory", "sensing", "tau_max", "dt", "q2d")
               if getattr(args, k) is not None]
    if ignored:
        raise ValueError(f"jaxflex tune --spread: {ignored} come from the spread file (its "
                         "'trajectory', 'sensing', 'controller' and 'dt' entries); set them there")
    spec = load_spread(args.spread)
    spec = spec.with_(t_final=args.t_final) if args.t_final is not None else spec
    task = RobustTask(spec, RiskMeasure.parse(args.risk), plants=args.plants,
                      resample=args.resample, torque_weight=args.torque_weight,
                      velocity_factor=args.velocity_factor, confidence=args.confidence)
    initial = load_params(args.params).to_gains() if args.params else None
    bar = None if args.quiet else Bar("tune (robust)", unit="step")
    try:
        res = tune_robust(task, initial, margin=args.margin, iterations=args.iterations,
                          starts=args.starts, learning_rate=args.lr, seed=args.seed,
                          progress=bar)
    finally:
        if bar is not None:
            bar.close()
    summary = res.summary()
    if not res.certified:
        print(f"refused: no candidate is certified on the spread's box with margin {args.margin} "
              f"(box bounds: {res.box_how}); nothing written. Narrow the spread or lower the "
              "margin.")
        return 3
    ev = {k: evaluate_batch(task, g, samples=max(200, args.plants))
          for k, g in (("initial", res.initial_gains), ("tuned", res.gains))}
    cfg = ControllerConfig(q2d_method=spec.q2d_method, dt=spec.dt,
                           tau_max=spec.tau_max if math.isfinite(spec.tau_max) else None,
                           compensation=spec.compensation, sensing=dict(spec.sensing),
                           trajectory=spec.trajectory)
    params = dataclasses.replace(spec.nominal, gains=res.gains.to_dict(), controller=cfg)
    params.extra = {**params.extra, "certificate": {k: v for k, v in summary.items()
                                                    if k != "starts"}}
    report = {"search": summary,
              "held_out": {k: e.summary() for k, e in ev.items()}}
    with writing():  # the whole result or nothing, Ctrl-C included
        report_dir.mkdir(parents=True, exist_ok=True)
        (report_dir / "report.json").write_text(json.dumps(report, indent=1, default=float))
        save_params(params, out)
    print(f"{'':<8} {'RMS q50 (rad)':>14} {'RMS q95 (rad)':>14} {'lost':>6} {'N2>0 at task':>13}")
    for k, e in ev.items():
        print(f"{k:<8} {e.rms_q50:>14.3e} {e.rms_q95:>14.3e} {e.lost_fraction:>6.3f} "
              f"{e.certified_fraction:>13.3f}")
    print(f"certified on the box up to {res.certificate.certified_up_to:.4g} rad/s (margin "
          f"{args.margin}); wrote {out} and {report_dir}/report.json ({res.wall_time_s:.0f} s)")
    return 0
