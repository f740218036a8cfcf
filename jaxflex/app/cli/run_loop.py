"""``jaxflex run-loop``: the fixed-period hardware loop around the simulated rig."""

from __future__ import annotations

import argparse
import types
from pathlib import Path
from typing import Any

from jaxflex.io.params import ControllerConfig
from jaxflex.io.presets import TRAJECTORIES

EXAMPLE = ("jaxflex export --params tuned.json --out controller.py\n"
           "  jaxflex run-loop --controller controller.py --duration 5 --log run.csv\n"
           "  jaxflex run-loop --controller controller.c --duration 5 --log run.csv "
           "(compiled with cc)\n"
           "  (writes run.csv and run.summary.json, also after Ctrl-C or a fault)")
# what run-loop reads from an exported controller module (jaxflex export)
EXPORTED_NAMES: tuple[str, ...] = ("Controller", "DT", "Q2D_METHOD", "SPEC_MAP", "DEFAULT_PARAMS")

# option of each controller-section entry, for the messages of a contradiction
CONTROLLER_FLAGS: dict[str, str] = {
    "trajectory": "--trajectory", "q2d_method": "--q2d", "dt": "--rate (dt = 1/rate)",
    "tau_max": "--tau-limit",
}


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``run-loop`` subcommand."""
    p = subparsers.add_parser(
        "run-loop",
        help="run an exported controller in the real-time loop against the simulated rig",
        description="Fixed-period loop (torque limit, NaN/range guard, deadline watchdog, "
        "zero torque on stop) around a simulated rig whose plant runs in a separate process. "
        "Writes a docs/spec.md section 6 CSV log. The controller is either an exported file "
        "(--controller, which carries its own gains) or exported now from --params; the two "
        "are not combined, so a parameter file never replaces exported gains. The rig's "
        "plant is --rig-params, by default the controller's own plant. The loop's rate, "
        "torque limit, trajectory and q2d method follow the controller's configuration (the "
        "'controller' section of --params, or the constants of --controller): an option that "
        "contradicts it is refused; an option it does not record fills it in. Every way out "
        "(completion, Ctrl-C, SIGTERM, a guard trip, the watchdog, a controller that raises, a "
        "dead rig) ends at zero torque and writes the log and LOG.summary.json (the summary "
        "also printed); the exit status is 0 only when the run completed.",
    )
    p.add_argument("--params", help="the controller's parameter file (docs/spec.md section 7: model, "
                   "gains, 'controller' section) to export a controller from now; default: "
                   "the paper's. Not with --controller")
    p.add_argument("--controller", help="exported controller file (jaxflex export): a .py "
                   "file, or a .c file (compiled with the system's cc); its gains and model are "
                   "used as exported")
    p.add_argument("--rig-params", help="the simulated rig's plant (docs/spec.md section 7, effects "
                   "included); default: the controller's own plant")
    p.add_argument("--duration", type=float, default=5.0, help="seconds (default 5)")
    p.add_argument("--rate", type=float, default=None,
                   help="loop rate [Hz] (default: 1/dt of the controller, else 1000)")
    p.add_argument("--log", required=True, help="output CSV log (docs/spec.md section 6)")
    p.add_argument("--trajectory", default=None, choices=TRAJECTORIES,
                   help="reference task when exporting now (default: the file's, else sinusoid)")
    p.add_argument("--reference", default=None, choices=TRAJECTORIES,
                   help="the rig's reference task, given to the controller at each step (q1d "
                   "and its first four derivatives) instead of the trajectory it was exported "
                   "with (default: the controller's own)")
    p.add_argument("--q2d", default=None, choices=["model", "filtered", "reference"],
                   help="q2d derivative method when exporting now (default: the file's, else "
                   "model)")
    p.add_argument("--tau-limit", type=float, default=None,
                   help="torque limit [N m] (default: the controller's tau_max, else 2)")
    p.add_argument("--q-limit", type=float, default=10.0,
                   help="guard: stop with zero torque beyond |q| [rad] (default 10)")
    p.add_argument("--max-misses", type=int, default=10,
                   help="watchdog: stop after this many consecutive deadline misses (default 10)")
    p.add_argument("--lockstep", action="store_true",
                   help="do not wait for deadlines (timing-independent run)")
    p.add_argument("--encoder-bits", type=int, default=16,
                   help="simulated rig's encoder resolution, 0 for exact angles (default 16)")
    p.set_defaults(func=run)


def summary_path(log: str) -> Path:
    """Where the run's summary goes: the log's path with the suffix ``.summary.json``."""
    return Path(log).with_suffix(".summary.json")


def load_exported(path: str) -> Any:
    """Import an exported controller file (a ``.py`` module, or a ``.c`` file compiled with
    the system's C compiler and loaded through ctypes).

    **Arguments:**

    - ``path``: the file written by ``jaxflex export``.

    **Returns:**

    The module (or ``jaxflex.export.native.CModule``) with ``EXPORTED_NAMES``.

    **Raises:**

    ``ValueError`` naming the file and what is wrong: it does not compile, fails on import,
    or lacks what ``jaxflex export`` writes; ``FileNotFoundError`` for a missing file.
    """
    from jaxflex.export import load_module

    if Path(path).suffix == ".c":
        from jaxflex.export.native import load_c

        if not Path(path).exists():
            raise FileNotFoundError(f"controller file not found: {path}")
        try:
            mod = load_c(path)
        except (RuntimeError, OSError, ValueError, KeyError) as e:
            raise ValueError(f"controller file {path}: {e}") from None
        return mod
    try:
        mod = load_module(path)
    except SyntaxError as e:
        raise ValueError(f"controller file {path}: syntax error at line {e.lineno}: {e.msg}; "
                         "write it again with 'jaxflex export'") from None
    except FileNotFoundError:
        raise
    except Exception as e:
        raise ValueError(f"controller file {path}: importing it raised {type(e).__name__}: "
                         f"{e}") from None
    missing = [k for k in EXPORTED_NAMES if not hasattr(mod, k)]
    if missing:
        raise ValueError(f"controller file {path}: no {', '.join(missing)}; run-loop needs a "
                         "file written by 'jaxflex export'")
    try:
        dt = float(mod.DT)
    except (TypeError, ValueError):
        dt = float("nan")
    if not dt > 0 or dt == float("inf"):
        raise ValueError(f"controller file {path}: DT must be a number > 0 [s], got {mod.DT!r}")
    return mod


def exported_plant(mod: types.ModuleType) -> dict[str, Any]:
    """The controller model baked into an exported module, as a docs/spec.md section 7 mapping of
    its plant and friction entries (SI units)."""
    d: dict[str, Any] = {}
    for key, name in mod.SPEC_MAP.items():
        section, entry = key.split(".")
        if section in ("plant", "friction"):
            d.setdefault(section, {})[entry] = list(mod.DEFAULT_PARAMS[name][1])
    return d


def exported_config(mod: types.ModuleType) -> ControllerConfig:
    """The controller configuration of an exported module: q2d method, dt [s] and (when
    finite and the same on every joint) the torque limit tau_max [N m]."""
    import math

    taus = set(mod.DEFAULT_PARAMS.get("tau_max", ((), []))[1])
    tau = taus.pop() if len(taus) == 1 else None
    return ControllerConfig(q2d_method=mod.Q2D_METHOD, dt=float(mod.DT),
                            tau_max=float(tau) if tau is not None and math.isfinite(tau) else None)


def rig_reference(name: str, n: int, period: float, duration: float) -> Any:
    """The reference task ``name`` at every sample of a run, as the rig gives it to an
    exported controller.

    **Arguments:**

    - ``name``: a trajectory of ``jaxflex.io.presets.TRAJECTORIES`` (one joint, broadcast to n).
    - ``n``: joints; ``period`` [s]: the loop's period; ``duration`` [s]: the run's length.

    **Returns:**

    An array (samples, 5, n): q1d [rad] and its first four derivatives [rad/s^k].
    """
    import jax
    import numpy as np

    from jaxflex.export import REFERENCE_ROWS, broadcast_trajectory
    from jaxflex.io.presets import trajectory_preset

    with jax.enable_x64(True):
        traj = trajectory_preset(name)
        traj = broadcast_trajectory(traj, n) if n > 1 else traj
        ts = np.arange(int(round(duration / period)) + 1) * period
        return np.asarray(jax.jit(lambda t: traj.sample(t, order=REFERENCE_ROWS - 1))(ts))


def run(args: argparse.Namespace) -> int:
    """Run the loop; returns 0 when it completed, 1 when a protection stopped it."""
    import dataclasses
    import json
    import math
    import sys

    from jaxflex.app.cli.outputs import check_outputs
    from jaxflex.export import generate_source, load_module, rig_controller
    from jaxflex.app.hardware import LoopConfig, SimulatedRig, run_loop
    from jaxflex.io.params import Params, load_params
    from jaxflex.io.presets import controller_config, paper_params

    check_outputs(args.force, files=[args.log, summary_path(args.log)], flag="--log")

    given = {"trajectory": args.trajectory, "q2d_method": args.q2d,
             "dt": None if args.rate is None else 1.0 / args.rate, "tau_max": args.tau_limit}
    if args.controller:
        if args.params:
            raise ValueError("--params and --controller: the exported controller carries its "
                             "own gains and model; give the rig's plant with --rig-params, or "
                             "export again from the parameter file")
        for flag, v in (("--trajectory", args.trajectory), ("--q2d", args.q2d)):
            if v is not None:
                raise ValueError(f"{flag} applies when exporting now; {args.controller} was "
                                 "exported with its own (export it again to change it)")
        mod = load_exported(args.controller)
        own = Params.from_dict(exported_plant(mod))
        cfg = controller_config(dataclasses.replace(own, controller=exported_config(mod)),
                                given, CONTROLLER_FLAGS, source=args.controller)
        ctrl = mod.Controller()
    else:
        own = load_params(args.params) if args.params else paper_params()
        cfg = controller_config(own, given, CONTROLLER_FLAGS,
                                source=args.params or "the paper's parameters")
        # the certified controller: the file's velocity source (Kalman filter included)
        c = rig_controller(own, cfg.trajectory_name, q2d_method=cfg.q2d_method, dt=cfg.dt,
                           tau_max=cfg.tau_max, compensation=cfg.compensation)
        ctrl = load_module(generate_source(c)).Controller()
    rig_params = load_params(args.rig_params) if args.rig_params else own
    loop = LoopConfig(rate=1.0 / cfg.dt, duration=args.duration, tau_limit=cfg.tau_max,
                      q_limit=args.q_limit, max_consecutive_misses=args.max_misses,
                      realtime=not args.lockstep)
    if ctrl.n != rig_params.n:
        raise ValueError(f"controller is for {ctrl.n} joint(s), the rig has {rig_params.n}")
    res = 2 * math.pi / 2**args.encoder_bits if args.encoder_bits > 0 else 0.0
    reference = None
    if args.reference is not None:
        reference = rig_reference(args.reference, ctrl.n, loop.period, args.duration)
    q1_0 = ctrl.reference(0.0) if reference is None else reference[0, 0]
    with SimulatedRig(rig_params, loop.period, q1_0=q1_0, resolution=(res, res / 50.0)) as rig:
        print(f"[run-loop] rig ready; running {args.duration:g} s at {loop.rate:g} Hz "
              "(Ctrl-C stops at zero torque and writes the log)", file=sys.stderr, flush=True)
        out = run_loop(rig, ctrl, loop, log_path=args.log, reference=reference)
    summ = out.timing_summary()
    err = None
    if out.q1d is not None and out.samples:
        err = float(((out.q1 - out.q1d) ** 2).mean() ** 0.5)
    doc = {"stop_reason": out.stop_reason, "completed": out.stop_reason == "completed",
           "samples": out.samples, "deadline_misses": out.misses, "faults": out.faults[:5],
           "compute_us": summ["compute"], "lateness_us": summ["lateness"],
           "rms_tracking_error_rad": err,
           "log": out.log_path or f"not written ({out.samples} sample(s); a log needs 2)",
           "rig_params": args.rig_params or "the controller's plant",
           "rate_hz": loop.rate, "tau_limit": loop.tau_limit}
    summary_path(args.log).write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))
    if out.stop_reason != "completed":
        print(f"jaxflex run-loop: stopped early ({out.stop_reason}); zero torque written; "
              f"wrote {doc['log']} and {summary_path(args.log)}", file=sys.stderr)
    if out.stop_reason.startswith("signal"):
        return 130
    return 0 if out.stop_reason == "completed" else 1
