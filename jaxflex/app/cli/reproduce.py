"""``jaxflex reproduce --out DIR``: the paper's experiments (Fig. 9-15) on its parameters."""

from __future__ import annotations

import argparse

from jaxflex.io.presets import (REPRODUCE_LEAK, SENSING_DESCRIPTIONS, SENSING_PRESETS, TRAJECTORIES,
                             VELOCITY_ESTIMATORS)


EXAMPLE = "jaxflex reproduce --out out/paper --duration 10"

def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``reproduce`` subcommand."""
    p = sub.add_parser(
        "reproduce",
        help="re-run the paper's tracking experiments (with/without friction compensation)",
        description="Re-run the paper's experiments (sinusoid, polynomial, fast motion; q2d "
        "derivative options) in simulation and write PNG figures and DIR/results.json. Each "
        "figure's title names the velocity estimator and the observer it shows; the paper's "
        "own controller (its observer without leak, dirty-derivative velocities) is run "
        "and plotted too (NAME_paper_own_observer.png).",
    )
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--params", help="parameter file (docs/spec.md section 7); default: the paper's")
    p.add_argument("--sensing", default="paper", choices=SENSING_PRESETS,
                   help="measurement realism (default: paper); " + "; ".join(
                       f"{k}: {v}" for k, v in SENSING_DESCRIPTIONS.items()))
    p.add_argument("--estimator", default="kalman", choices=VELOCITY_ESTIMATORS,
                   help="where the controller's velocities come from (default: kalman, the "
                   "model-based Kalman filter; filtered: the dirty derivative); ignored with "
                   "--sensing ideal (exact velocities)")
    p.add_argument("--q2d", default="model", choices=["model", "filtered", "reference"],
                   help="how the controller gets q2d' and q2d'' (default: model)")
    p.add_argument("--leak", type=float, default=None,
                   help="observer leakage [rad/s] (CascadeGains.leak; 0: the paper's observer, "
                   "which oscillates at rest); default: the parameter file's, or "
                   f"{REPRODUCE_LEAK} for the paper's parameters (studies/observer_leak.py)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds per run (default 10)")
    p.add_argument("--tasks", nargs="+", default=None, choices=TRAJECTORIES,
                   help="run only these experiments (default: all)")
    p.add_argument("--no-q2d-comparison", action="store_true",
                   help="skip the comparison of the three q2d options")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the experiments and print a table of the results."""
    from jaxflex.loop.experiments import run_paper_experiments
    from jaxflex.io.params import load_params
    from jaxflex.io.progress import Printer
    from jaxflex.app.cli.outputs import check_outputs, writing
    from jaxflex.io.errors import InputError
    from jaxflex.app.reports import write_paper_experiments

    if args.leak is not None and not args.leak >= 0:
        raise InputError(f"--leak must be >= 0 rad/s, got {args.leak}")
    if not args.duration > 0:
        raise InputError(f"--duration must be > 0 s, got {args.duration}")
    tasks = args.tasks or TRAJECTORIES
    check_outputs(args.force, folders=[args.out],
                  marker=["results.json", "params.json", "sinusoid_torque_friction.png",
                          "q2d_comparison.png", *(f"{t}_tracking.png" for t in tasks),
                          *(f"{t}_paper_own_observer.png" for t in tasks)])
    params = load_params(args.params) if args.params else None
    results = run_paper_experiments(
        params=params, sensing=args.sensing, estimator=args.estimator, q2d_method=args.q2d,
        t_final=args.duration, leak=args.leak,
        compare_q2d=not args.no_q2d_comparison, tasks=args.tasks, progress=Printer(),
    )
    with writing():  # the whole result or nothing, Ctrl-C included
        res = write_paper_experiments(results, args.out)
    print(f"\n{'experiment':<12} {'compensation':<13} {'RMS err (rad)':>14} {'max err (rad)':>14} {'torque RMS (N m)':>17}")
    for name, e in res["experiments"].items():
        for key in ("without_compensation", "with_compensation"):
            print(f"{name:<12} {key.split('_')[0]:<13} {e['rms_error'][key]:>14.3e} "
                  f"{e['max_error'][key]:>14.3e} {e['tau_rms'][key]:>17.3f}")
    leak = res["config"]["observer_leak"]
    print(f"observer leakage {leak} rad/s" + (" (the paper's observer)" if not any(leak) else "")
          + f"; figures show {res['config']['label']}")

    def rest_lines(rest, label):
        for key in ("without_compensation", "with_compensation"):
            if key not in rest:
                continue
            r = rest[key]
            print(f"at rest {key.split('_')[0]:<8}{label} RMS error {r['rms_error_tail']:.2e} rad, "
                  f"spectral peak {r['peak_amplitude']:.2e} rad at {r['peak_hz']:.2f} Hz; "
                  f"linearised loop: spectral radius {r['spectral_radius']:.4f} "
                  f"({'stable' if r['stable'] else 'a growing mode'})")

    if res.get("rest"):
        rest_lines(res["rest"], "")
    po = res.get("paper_observer")
    if po:
        print("the paper's observer (leak 0), with compensation:")
        for name, e in po["experiments"].items():
            w = e["with_compensation"]
            print(f"  {name:<12} RMS err {w['rms_error']:.3e} rad, max {w['max_error']:.3e} rad, "
                  f"{100 * w['saturation_fraction']:.0f}% of samples at the torque limit")
        rest_lines(po["rest"], " (paper's observer)")
    own = res.get("paper_own_observer")
    if own:
        print(f"the paper's own controller ({own['label']}), with compensation:")
        for name, e in own["experiments"].items():
            w = e["with_compensation"]
            print(f"  {name:<12} RMS err {w['rms_error']:.3e} rad, max {w['max_error']:.3e} rad, "
                  f"{100 * w['saturation_fraction']:.0f}% of samples at the torque limit")
    print(f"\nwrote {args.out}/results.json, figures and {args.out}/params.json, the "
          f"configuration run ({res['wall_time_s']:.0f} s); export it with: jaxflex export "
          f"--params {args.out}/params.json --out controller.c")
    return 0
