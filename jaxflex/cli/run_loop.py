"""``jaxflex run-loop``: the fixed-period hardware loop around the simulated rig."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``run-loop`` subcommand."""
    p = subparsers.add_parser(
        "run-loop",
        help="run an exported controller in the real-time loop against the simulated rig",
        description="Fixed-period loop (torque limit, NaN/range guard, deadline watchdog, "
        "zero torque on stop) around a simulated rig whose plant runs in a separate process. "
        "Writes a SPEC section 6 CSV log.",
    )
    p.add_argument("--params", help="rig plant and controller parameters (SPEC section 7); "
                   "default: the paper's")
    p.add_argument("--duration", type=float, default=5.0, help="seconds (default 5)")
    p.add_argument("--rate", type=float, default=1000.0, help="loop rate [Hz] (default 1000)")
    p.add_argument("--log", required=True, help="output CSV log (SPEC section 6)")
    p.add_argument("--controller", help="exported controller file (jaxflex export); default: "
                   "export one now from --params with dt = 1/rate")
    p.add_argument("--trajectory", default="sinusoid", choices=["sinusoid", "polynomial", "fast"],
                   help="reference task when exporting now (default: sinusoid)")
    p.add_argument("--q2d", default=None, choices=["model", "filtered", "reference"],
                   help="q2d derivative method when exporting now (default: the controller's)")
    p.add_argument("--tau-limit", type=float, default=2.0, help="torque limit [N m] (default 2)")
    p.add_argument("--q-limit", type=float, default=10.0,
                   help="guard: stop with zero torque beyond |q| [rad] (default 10)")
    p.add_argument("--max-misses", type=int, default=10,
                   help="watchdog: stop after this many consecutive deadline misses (default 10)")
    p.add_argument("--lockstep", action="store_true",
                   help="do not wait for deadlines (timing-independent run)")
    p.add_argument("--encoder-bits", type=int, default=16,
                   help="simulated encoder resolution, 0 for exact angles (default 16)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the loop; returns 0 when it completed, 1 when a protection stopped it."""
    import json
    import math

    from jaxflex.export import build_controller, generate_source, load_module
    from jaxflex.hardware import LoopConfig, SimulatedRig, run_loop
    from jaxflex.params import load_params, paper_params

    params = load_params(args.params) if args.params else paper_params()
    cfg = LoopConfig(rate=args.rate, duration=args.duration, tau_limit=args.tau_limit,
                     q_limit=args.q_limit, max_consecutive_misses=args.max_misses,
                     realtime=not args.lockstep)
    if args.controller:
        mod = load_module(args.controller)
        if abs(mod.DT - cfg.period) > 1e-12 * cfg.period:
            raise ValueError(f"{args.controller} was exported for dt = {mod.DT} s but the loop "
                             f"runs at {args.rate} Hz (dt = {cfg.period} s); export it again "
                             "with --dt")
        ctrl = mod.Controller.from_json(args.params) if args.params else mod.Controller()
    else:
        c = build_controller(params, args.trajectory, q2d_method=args.q2d, dt=cfg.period)
        ctrl = load_module(generate_source(c)).Controller()
    if ctrl.n != params.n:
        raise ValueError(f"controller is for {ctrl.n} joint(s), the rig has {params.n}")
    res = 2 * math.pi / 2**args.encoder_bits if args.encoder_bits > 0 else 0.0
    q1_0 = ctrl.reference(0.0)
    with SimulatedRig(params, cfg.period, q1_0=q1_0, resolution=(res, res / 50.0)) as rig:
        out = run_loop(rig, ctrl, cfg, log_path=args.log)
    summ = out.timing_summary()
    err = None
    if out.q1d is not None and out.samples:
        err = float(((out.q1 - out.q1d) ** 2).mean() ** 0.5)
    print(json.dumps({"stop_reason": out.stop_reason, "samples": out.samples,
                      "deadline_misses": out.misses, "faults": out.faults[:5],
                      "compute_us": summ["compute"], "lateness_us": summ["lateness"],
                      "rms_tracking_error_rad": err, "log": args.log}, indent=2))
    return 0 if out.stop_reason == "completed" else 1
