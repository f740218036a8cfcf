"""``jaxflex export``: write the cascade controller as a standalone numpy Python file."""

from __future__ import annotations

import argparse

from jaxflex.presets import TRAJECTORIES

# option of each controller-section entry, for the messages of a contradiction
CONTROLLER_FLAGS: dict[str, str] = {
    "trajectory": "--trajectory", "q2d_method": "--q2d", "dt": "--dt", "tau_max": "--tau-max",
    "compensation": "--no-compensation",
}


EXAMPLE = "jaxflex export --params tuned.json --out controller.py --check"

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand."""
    p = subparsers.add_parser(
        "export",
        help="export the controller to a standalone numpy file (no JAX needed to run it)",
        description="Trace the JAX cascade controller (observer, velocity filters, q2d "
        "derivatives, saturation) and write a Python file with class Controller "
        "(reset(), step(t, q1, q2) -> tau) that imports only numpy and the standard library. "
        "The controller configuration (trajectory, q2d method, dt, torque limit, "
        "compensation) is read from the parameter file's 'controller' section, which "
        "'jaxflex tune' writes: the gains are certified for it. An option that contradicts "
        "the section is refused (tune again for another configuration); an option the "
        "section does not record fills it in; the rest take the defaults below.",
    )
    p.add_argument("--params", help="parameter file (docs/spec.md section 7); default: the paper's")
    p.add_argument("--out", required=True, help="output Python file, e.g. controller.py")
    p.add_argument("--trajectory", default=None, choices=TRAJECTORIES,
                   help="reference task baked into the controller (default: the file's, "
                   "else sinusoid)")
    p.add_argument("--q2d", default=None, choices=["model", "filtered", "reference"],
                   help="how q2d' and q2d'' are obtained (default: the file's, else model)")
    p.add_argument("--dt", type=float, default=None,
                   help="sample period [s] (default: the file's, else 1e-3)")
    p.add_argument("--tau-max", type=float, default=None,
                   help="torque saturation [N m] (default: the file's, else 2, the rig's DAC "
                   "range)")
    p.add_argument("--no-compensation", action="store_true",
                   help="export the controller without friction compensation (F_hat = 0); "
                   "refused if the file records compensation on")
    p.add_argument("--check", action="store_true",
                   help="close the loop in JAX, run the exported file on the same measured "
                   "angles and print the largest torque difference")
    p.add_argument("--check-duration", type=float, default=10.0,
                   help="seconds of closed loop for --check (default 10)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Export (and optionally check); returns the exit status (1 if the check fails)."""
    from jaxflex.export import (
        build_controller,
        check_parity,
        export_controller,
        load_module,
        parity_ok,
    )
    from jaxflex.cli.outputs import check_outputs, writing
    from jaxflex.params import load_params
    from jaxflex.presets import controller_config, paper_params

    check_outputs(args.force, files=[args.out])
    params = load_params(args.params) if args.params else paper_params()
    cfg = controller_config(params, {
        "trajectory": args.trajectory, "q2d_method": args.q2d, "dt": args.dt,
        "tau_max": args.tau_max, "compensation": False if args.no_compensation else None,
    }, CONTROLLER_FLAGS, source=args.params or "the paper's parameters")
    c = build_controller(
        params, cfg.trajectory_name,
        q2d_method=cfg.q2d_method, dt=cfg.dt, tau_max=cfg.tau_max,
        compensation=cfg.compensation,
    )
    desc = (f"Cascade controller ({args.params or 'paper parameters'}, trajectory "
            f"{cfg.trajectory_name!r})")
    with writing():  # the whole file or nothing, Ctrl-C included
        src = export_controller(c, args.out, description=desc)
    print(f"wrote {args.out} ({len(src.splitlines())} lines, {c.model.n} joint(s), "
          f"q2d_method={c.q2d_method!r}, dt={c.dt} s, tau_max={cfg.tau_max} N m, "
          f"compensation={cfg.compensation})")
    if args.check:
        r = check_parity(c, load_module(args.out), t_final=args.check_duration)
        print(r)
        print(f"largest difference: {r.max_abs_diff:.3e} N m")
        if r.max_abs_diff <= 1e-12:
            print("check passed (<= 1e-12 N m)")
        elif parity_ok(r):
            print("check passed: above 1e-12 N m against the jitted JAX loop, but the export "
                  "equals JAX evaluated op by op to 1e-12 at the worst samples, and XLA's "
                  "compilation itself moves the torque as much there")
        else:
            print("check FAILED: exported torques differ from JAX by more than 1e-12 N m")
            return 1
    return 0
