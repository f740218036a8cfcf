"""``jaxflex export``: write the certified controller as a standalone Python (numpy) or C99
file, the format from the output's suffix."""

from __future__ import annotations

import argparse

from jaxflex.io.presets import TRAJECTORIES

# option of each controller-section entry, for the messages of a contradiction
CONTROLLER_FLAGS: dict[str, str] = {
    "trajectory": "--trajectory", "q2d_method": "--q2d", "dt": "--dt", "tau_max": "--tau-max",
    "compensation": "--no-compensation",
}


EXAMPLE = ("jaxflex export --params tuned.json --out controller.py --check\n"
           "  jaxflex export --params tuned.json --out controller.c --check   "
           "(writes controller.c and controller.h)")
# output formats by suffix
FORMATS: dict[str, str] = {".py": "Python (numpy and the standard library)",
                           ".c": "C99 source and header (libm only)"}


def output_format(out: str) -> str:
    """The format of an output path, from its suffix (``FORMATS``): ".py" or ".c".

    **Arguments:**

    - ``out``: the output file given to ``--out``.

    **Returns:**

    The suffix.

    **Raises:**

    ``ValueError`` naming the suffix and the known ones.
    """
    import pathlib

    suffix = pathlib.Path(out).suffix
    if suffix not in FORMATS:
        raise ValueError(f"--out {out}: unknown output format {suffix or '(no suffix)'!r}; "
                         "the format is taken from the suffix: "
                         + "; ".join(f"{k} {v}" for k, v in FORMATS.items()))
    return suffix

def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand."""
    p = subparsers.add_parser(
        "export",
        help="export the controller to a standalone Python or C file (no JAX needed to run it)",
        description="Trace the JAX controller as the certified configuration runs it (velocity "
        "source: dirty derivative or Kalman filter with its state; observer with its leak; q2d "
        "derivatives; saturation) and write it in the format of --out's suffix: .py, a "
        "Python file with class Controller (reset(), step(t, q1, q2, ref=None) -> tau) that "
        "imports only numpy and the standard library; .c, a C99 source and its header "
        "(jaxflex_state_size, jaxflex_reset, jaxflex_step, jaxflex_step_ref) that need only "
        "libm. Both take the rig's reference at each step (ref: q1d and its first four "
        "derivatives) or follow the recorded trajectory. The controller configuration "
        "(trajectory, sensing, q2d method, dt, torque limit, compensation) is read from the "
        "parameter file's 'controller' section, which 'jaxflex tune' writes: the gains are "
        "certified for it. An option that contradicts the section is refused (tune again for "
        "another configuration); an option the section does not record fills it in; the rest "
        "take the defaults below. A configuration the export cannot run is refused naming "
        "the entry.",
    )
    p.add_argument("--params", help="parameter file (docs/spec.md section 7); default: the paper's")
    p.add_argument("--out", required=True, help="output file; its suffix sets the format: "
                   "controller.py (Python) or controller.c (C99, with controller.h beside it)")
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
                   help="close the loop in JAX under the configuration's own sensing, run the "
                   "exported file (a C file compiled with the system's cc) on the same sensed "
                   "angles and print the largest torque difference")
    p.add_argument("--check-reference", action="store_true",
                   help="with --check: also run the check with the reference given to the "
                   "exported controller at each step (its ref input, as a rig gives it)")
    p.add_argument("--check-duration", type=float, default=10.0,
                   help="seconds of closed loop for --check (default 10)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Export (and optionally check); returns the exit status (1 if the check fails).

    **Arguments:**

    - ``args``: the parsed options of ``register``.

    **Returns:**

    0, or 1 when ``--check`` fails.

    **Raises:**

    ``ValueError`` for an unknown output suffix; ``ExportError`` naming the controller
    entry the export cannot run; ``ParamsError`` for an option that contradicts the file.
    """
    from pathlib import Path

    from jaxflex.app.cli.outputs import check_outputs, writing
    from jaxflex.export import (
        check_parity,
        describe,
        export_controller,
        load_module,
        parity_ok,
        parity_tolerance,
        rig_controller,
        trace,
    )
    from jaxflex.io.params import load_params
    from jaxflex.io.presets import controller_config, paper_params

    header = str(Path(args.out).with_suffix(".h")) if Path(args.out).suffix == ".c" else None
    check_outputs(args.force, files=[args.out, header])
    params = load_params(args.params) if args.params else paper_params()
    cfg = controller_config(params, {
        "trajectory": args.trajectory, "q2d_method": args.q2d, "dt": args.dt,
        "tau_max": args.tau_max, "compensation": False if args.no_compensation else None,
    }, CONTROLLER_FLAGS, source=args.params or "the paper's parameters")
    fmt = output_format(args.out)  # before any tracing or writing
    sc = rig_controller(
        params, cfg.trajectory_name,
        q2d_method=cfg.q2d_method, dt=cfg.dt, tau_max=cfg.tau_max,
        compensation=cfg.compensation,
    )
    c = sc.controller
    desc = (f"Cascade controller ({args.params or 'paper parameters'}, trajectory "
            f"{cfg.trajectory_name!r})")
    traced = trace(sc)
    with writing():  # the whole file (and header) or nothing, Ctrl-C included
        if fmt == ".c":
            from jaxflex.export.native import export_c

            src, _ = export_c(sc, args.out, description=desc, traced=traced)
            wrote = f"{args.out} and {header}"
        else:
            src = export_controller(sc, args.out, description=desc, traced=traced)
            wrote = args.out
    print(f"wrote {wrote} ({len(src.splitlines())} lines, {c.model.n} joint(s), "
          f"q2d_method={c.q2d_method!r}, dt={c.dt} s, tau_max={cfg.tau_max} N m, "
          f"compensation={cfg.compensation}; {describe(sc)})")
    if args.check:
        if fmt == ".c":
            from jaxflex.export.native import find_cc, load_c

            if find_cc() is None:
                print("check skipped: no C compiler (set CC or install cc)")
                return 1
            module = load_c(args.out)
        else:
            module = load_module(args.out)
        modes = (False, True) if args.check_reference else (False,)
        for reference in modes:
            r = check_parity(sc, module, t_final=args.check_duration, reference=reference)
            print(r)
            tol = parity_tolerance(r)
            print(f"largest difference: {r.unfused_diff:.3e} N m against the JAX controller "
                  f"compiled un-fused, {r.max_abs_diff:.3e} N m against the jitted loop")
            if parity_ok(r) and r.max_abs_diff <= tol:
                print(f"check passed (<= {tol:.3g} N m)")
            elif parity_ok(r):
                print(f"check passed: the export equals the JAX controller compiled un-fused "
                      f"to {tol:.3g} N m over the run; against the jitted loop it is above "
                      f"{tol:.3g} N m, as XLA's compilation itself moves the torque (JAX "
                      "against itself)")
            else:
                print(f"check FAILED: exported torques differ from JAX by more than {tol:.3g} "
                      "N m")
                return 1
    return 0
