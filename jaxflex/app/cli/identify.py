"""``jaxflex identify LOG --out RESULT.json``: fit parameters to a log.

Writes the identified parameters in the docs/spec.md section 7 format with standard errors under
``"stderr"``, a figure of measured against simulated response next to it, and prints a short
table with the two-part verdict: the solver's (converged or not) and the model's (adequate, or
model-limited with what the residual shows). ``LOG`` is a file or a shipped data set
(``jaxflex:emps/DATA_EMPS``, ``jaxflex:kuka/A/2``); without ``--params`` every parameter
starts from the log's inverse dynamics. The model kind follows the log's encoders and its
declared link side (``--link-side``, a start file's ``link_side``, a shipped data set's own):
a coupled link side with two encoders is the rotor kind, fitted by equation error on the
torque from the measured motion (``jaxflex.identify.torque``) with a figure of measured
against predicted torque; the command prints the kind and why and writes them to
``identification.start`` (``kind``, ``kind_reason``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from jaxflex.app.cli.spans import span_or_auto

EXAMPLE = ("jaxflex identify jaxflex:emps/DATA_EMPS --out emps.json\n"
           "  jaxflex identify jaxflex:emps/DATA_EMPS --out emps_cl.json --closed-loop\n"
           "  jaxflex identify DATA_EMPS.mat --map 't=t,tau=gtau*vir,q1=qm,q2=qm' --out emps.json\n"
           "  jaxflex identify log.csv --params init.json --out identified.json "
           "--free Fc,Fs,vs,sigma0,sigma1,sigma2\n"
           "  (exit 0: converged, adequate or model-limited; 3: the solver did not converge)")


def _count_or_auto(least: int, what: str) -> Callable[[str], int | str]:
    """An argparse type: an integer >= ``least`` (``what`` names it in the error) or
    "auto"."""
    def parse(text: str) -> int | str:
        if text == "auto":
            return text
        try:
            k = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} or 'auto', got {text!r}") from None
        if k < least:
            raise argparse.ArgumentTypeError(f"expected {what} or 'auto', got {k}")
        return k

    return parse


#: ``--substeps``: a positive integer or "auto".
_substeps = _count_or_auto(1, "a positive integer")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``identify`` subcommand."""
    p = sub.add_parser(
        "identify", help="identify friction (and plant) parameters from a log",
        description="Fit LuGre (and optionally I, J, K or effect) parameters to a logged run "
        "by gradient through the simulator (Levenberg-Marquardt, multiple shooting).",
    )
    p.add_argument("log", help="log file (.csv with header, .npz or .mat), or a shipped data "
                               "set: jaxflex:emps/DATA_EMPS, jaxflex:emps/DATA_EMPS_PULSES, "
                               "jaxflex:kuka/A (axes 1-3; B, C), jaxflex:kuka/A/2 (one axis)")
    p.add_argument("--params", default=None,
                   help="start parameter file (JSON, docs/spec.md section 7); default: every "
                        "parameter from the log's inverse dynamics (linear least squares, "
                        "as the EMPS benchmark's IDIM-LS), a torque offset included where "
                        "the log shows one")
    p.add_argument("--out", required=True, help="where to write the identified parameters (JSON)")
    p.add_argument("--free", default=None,
                   help="comma-separated free parameters: Fc,Fs,vs,sigma0,sigma1,sigma2,I,J,K "
                   "or <effect>.<param> (an effect the start lacks is added, e.g. "
                   "torque_offset.offset). Default: the six LuGre parameters, with --params; "
                   "without, also the inertia (I; J, K for the flexible model) and the "
                   "offset the data show; for the rotor kind J, K, motor_friction.Fm, "
                   "motor_friction.bm, torque_offset.offset, encoder_scale.scale (the "
                   "encoder skew and offset from the first step unless named)")
    p.add_argument("--fix", default=None, metavar="NAME=VALUE,...",
                   help="pin parameters at values before the fit (e.g. 'sigma1=0,J=1e-3'), "
                        "names as --free; a pinned name is not fitted")
    p.add_argument("--map", dest="mapping", default=None,
                   help="column mapping for .mat/.npz/.csv variables, e.g. "
                   "'t=t,tau=gtau*vir,q1=qm,q2=qm'")
    p.add_argument("--model", choices=("auto", "flexible", "rigid", "rotor", "link"),
                   default="auto",
                   help="auto (default): rigid when the log has one encoder (q2 absent or "
                        "equal to q1); with two, rotor where the link side is declared "
                        "coupled (--link-side; the shipped KUKA axes), else flexible. "
                        "flexible joint (eq. 3), rigid Jx x'' = u - F (eq. 37), or rotor: the "
                        "rotor subsystem J q2'' + K (q2 - q1c) + Fm tanh(q2'/w) + bm q2' - c = "
                        "tau driven by the measured link motion q1c = (1 + scale) (q1 + skew "
                        "q1' + off) (no link model: the spring's deflection carries gravity, a "
                        "counterbalance and the other axes), fitted by equation error on the "
                        "torque in two steps (the encoder skew and offset in the deflection, "
                        "then J, K, motor friction Fm, bm with w = 1e-4 rad/s, the torque "
                        "offset c and the encoder scale; jaxflex.identify.torque), "
                        "or link: the link subsystem M q1'' + F = K (q2 - q1) driven by the "
                        "measured rotor motion (no motor model: friction on the link side). "
                        "An explicit kind always wins. The rotor kind is not replayed: "
                        "--segment, --substeps and --closed-loop do not apply to it")
    p.add_argument("--link-side", choices=("single", "coupled"), default=None,
                   help="what a single-joint model can describe of the link side: single (the "
                        "link is the one joint the model describes) or coupled (it belongs to "
                        "a multi-axis arm: the other axes, gravity, a counterbalance act on "
                        "it; with two encoders --model auto then picks rotor). Default: the "
                        "start file's top-level link_side, else the shipped data set's "
                        "(KUKA: coupled; EMPS: single), else single")
    p.add_argument("--segment", type=span_or_auto, default="auto",
                   help="multiple-shooting segment length in samples (250) or seconds (0.2s); "
                        "0: the whole log; or 'auto' "
                        "(default): two mechanical time constants of the start model "
                        "(inertia / sigma2), at most the log's mean interval between "
                        "velocity reversals, on a grid of 125 x 2^k samples within 0.1-2 s")
    p.add_argument("--substeps", type=_substeps, default="auto",
                   help="integrator substeps per sample, or 'auto' (default): the fewest whose "
                        "replay error is at most half the log's noise, refined until the "
                        "integrator moves no fitted parameter by more than half a standard "
                        "error (docs/spec.md section 5)")
    p.add_argument("--reading", choices=("exact", "gaussian"), default="exact",
                   help="'exact' (default): a fit the noise explains, on a log whose encoders "
                        "round coarser than their noise, is continued under the readings' "
                        "exact likelihood (rounded Gaussian noise: no pull to the centre of a "
                        "count where the angle dwells); 'gaussian': least squares throughout "
                        "(docs/spec.md section 5)")
    p.add_argument("--max-steps", type=int, default=200, help="solver iteration cap")
    p.add_argument("--start", type=int, default=0, help="first sample used")
    p.add_argument("--stop", type=int, default=None, help="one past the last sample used")
    p.add_argument("--figure", default=None,
                   help="figure path (default: RESULT.json with .png suffix)")
    p.add_argument("--closed-loop", action="store_true",
                   help="then refine by closed-loop output error through the loop controller "
                        "that ran (the start file's 'loop_controller' section, or the shipped "
                        "data set's: EMPS's P/P cascade), on the log's reference q1d "
                        "(jaxflex.validate.closed_loop_fit); the closed-loop errors before "
                        "and after are written under identification.closed_loop")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--accept-unconverged", dest="accept_result", action="store_true",
                   help="exit 0 even when the solver does not converge (the result file is "
                        "still marked unconverged)")
    p.set_defaults(func=run)


def _pins(text: str | None) -> dict[str, float]:
    """``--fix``'s NAME=VALUE pairs; raises ``ValueError`` naming a malformed item."""
    out = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        name, eq, value = item.partition("=")
        try:
            if not eq:
                raise ValueError
            out[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"--fix: expected NAME=VALUE, got {item.strip()!r}") from None
    return out


def run(args: argparse.Namespace) -> int:
    """Run the identification; returns the exit code (0 converged, 3 the solver did not
    converge)."""
    import importlib
    import sys
    import threading
    import warnings
    from pathlib import Path

    import numpy as np

    from jaxflex.data import is_named, load_named
    from jaxflex.identify import IdentificationWarning, choose_segment_length, identify
    from jaxflex.identify.problem import SEGMENT_TIME_CONSTANTS, default_free, start_hints
    from jaxflex.identify.start import StartError, check_model, link_sides, start_from_data
    from jaxflex.io.logs import REQUIRED_COLUMNS, load_log, parse_mapping
    from jaxflex.io.params import load_params, save_params
    from jaxflex.io.progress import Printer

    from jaxflex.app.cli.outputs import check_outputs

    check_outputs(args.force, files=[args.out, args.figure or Path(args.out).with_suffix(".png")])
    pins = _pins(args.fix)
    loop, axis, side, side_from = None, None, None, None
    if is_named(args.log):
        if args.mapping:
            raise ValueError("--map is for files; a shipped data set has its own columns")
        named = load_named(args.log)
        log, loop, axis = named.log, named.loop_controller, named.axis
        side, side_from = named.link_side, f"the shipped data set {args.log}"
    else:
        required = REQUIRED_COLUMNS if args.model not in ("rigid", "auto") else ("t", "tau", "q1")
        log = load_log(args.log, parse_mapping(args.mapping), required=required)
    log = log.slice(args.start, args.stop)
    say = (lambda s: None) if args.quiet else print
    start_file = None
    if args.params is not None:
        start_file = load_params(args.params, accept_unconverged=True)  # a start guess
        if "link_side" in start_file.extra:
            side, side_from = start_file.extra["link_side"], args.params
    if args.link_side is not None:
        side, side_from = args.link_side, "--link-side"
    side = link_sides(side, log.n, where=f"link_side ({side_from})")
    model, why = check_model(log, args.model, side)
    if args.model != "auto":
        why = "--model " + args.model
    elif side is not None and "coupled" in side:
        why += f"; link side declared by {side_from}"
    if model == "rotor":
        return _rotor(args, log, model, why, start_file, pins, axis, side, say)
    data = None
    if args.params is not None:
        init = start_file
        start_note = f"start {args.params}"
        try:  # the common mistakes (degrees, rate, sign), named before the long fit
            data = start_from_data(log, model)
            for hint in start_hints(data, init):
                print(f"jaxflex identify: hint: {hint}", file=sys.stderr)
        except StartError as e:
            print(f"jaxflex identify: hint: {e}", file=sys.stderr)
    else:
        data = start_from_data(log, model)
        init = data.params
        start_note = "start from the log's inverse dynamics:\n  " + data.summary().replace(
            "\n", "\n  ")
    loop = init.extra.get("loop_controller", loop)
    if args.closed_loop and loop is None:
        raise ValueError("--closed-loop: no loop controller declared (add a 'loop_controller' "
                         "section to --params, docs/spec.md section 7)")
    if args.closed_loop and log.q1d is None:
        raise ValueError("--closed-loop: the log has no reference column q1d")
    if args.free:
        free = [s.strip() for s in args.free.split(",") if s.strip()]
    else:  # identify's default: the LuGre six, the inertia from a data start, an offset
        shows = data is not None and "torque_offset" in data.params.effects
        free = default_free(model, init, from_data=args.params is None, data_offset=shows)
        if shows and args.params is not None:
            off = data.params.effects["torque_offset"]["offset"]
            say(f"[identify] the log's inverse dynamics show a torque offset "
                f"({', '.join(f'{o:.4g}' for o in off)} N m): fitted as torque_offset.offset "
                "(--free to choose otherwise)")
    free = [k for k in free if k not in pins]
    if args.segment == "auto":
        seg, rec = choose_segment_length(log, init, model)
        how = (f" (auto: {SEGMENT_TIME_CONSTANTS:g} x the smallest time constant of "
               f"{', '.join(f'{t:.3g}' for t in rec['time_constants_s'])} s)")
    else:
        k = args.segment.samples(log.dt)
        seg, how = (None if k <= 0 else min(k, log.N)), ""
    say(f"[identify] {log.N} samples at {1e3 * log.dt:g} ms, {log.n} joint(s), model "
        f"{model} ({why}), free {free}, segments of {seg or log.N} samples{how}")
    say(f"[identify] {start_note}")
    say("[identify] compiling and solving (progress every 5 steps; Ctrl-C stops) ...")
    # the figure's module (matplotlib, 0.33 s) loads beside the fit, in the seconds a first
    # run waits for its compiled solver
    threading.Thread(target=importlib.import_module, args=("jaxflex.app.plots.identify",),
                     name="jaxflex-import-figures", daemon=True).start()
    from jaxflex.app.cli.outputs import interrupts_stop, writing

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)  # printed below, once
        try:
            # a Ctrl-C stops the command even where it lands in a callback that swallows it
            with interrupts_stop():
                res = identify(log, init if args.params is not None else None, free,
                               model=model, pin=pins,
                               segment_length="auto" if args.segment == "auto" else seg,
                               substeps=args.substeps, max_steps=args.max_steps,
                               reading=args.reading, progress=None if args.quiet else Printer(
                                   every=5, prefix="  [identify] "))
                if args.closed_loop:
                    _closed_loop(res, log, loop, model, args.max_steps, say)
        except (np.linalg.LinAlgError, FloatingPointError) as e:
            # the fit ran into non-finite values (a diverged replay): a result that did not
            # converge, not a bad input; nothing is written
            print(f"jaxflex identify: the fit failed numerically ({type(e).__name__}: {e}); "
                  "nothing written. Check the hints above, the start file and --model",
                  file=sys.stderr)
            return 3
    _declare(res.params, model, why, axis, side)
    out = Path(args.out)
    fig = Path(args.figure) if args.figure else out.with_suffix(".png")
    from jaxflex.app.plots import save_figure
    from jaxflex.app.plots.identify import plot_fit

    with writing():  # the file and its figure, or nothing, Ctrl-C included
        save_params(res.params, out)
        save_figure(plot_fit(res), fig)
    print(res.table())
    for w in res.warnings:
        print(f"warning: {w}")
    say(f"[identify] wrote {out} and {fig} ({res.wall_s:.1f} s solve)")
    verdict = res.model.get("summary", "")
    if not res.converged:
        print(f"jaxflex identify: the solver did not converge: {res.reason}. {out} is marked "
              "unconverged; downstream commands refuse it unless given --accept-unconverged",
              file=sys.stderr)
        return 0 if args.accept_result else 3
    say(f"[identify] verdict: solver converged; {verdict}")
    return 0


def _closed_loop(res: Any, log: Any, loop: dict[str, Any], model: str, max_steps: int,
                 say: Callable[[str], None]) -> None:
    """Refine ``res`` by closed-loop output error (``closed_loop_fit``) through the declared
    ``loop``; the refined parameters replace ``res.params`` only where they lower both
    closed-loop errors' combined cost, and the numbers go under
    ``identification.closed_loop``."""
    import dataclasses

    from jaxflex.validate import closed_loop_errors, closed_loop_fit

    p = dataclasses.replace(res.params, extra={**res.params.extra, "loop_controller": loop})
    kind = "rigid" if model == "rigid" else "flexible"
    names = [k for k in res.params.extra["identification"]["free"]
             if res.params.extra["identification"]["parameters"].get(k, {}).get("identified")]
    before = closed_loop_errors(p, log, kind=kind)
    say(f"[identify] closed-loop refinement of {names} (before: position "
        f"{before['position_pct']:.4g}%, torque {before['torque_pct']:.4g}%) ...")
    fit = closed_loop_fit(p, log, names, kind=kind, max_steps=max_steps)
    after = closed_loop_errors(fit.params, log, kind=kind)
    better = (after["position_pct"] / before["position_pct"]) ** 2 + (
        after["torque_pct"] / before["torque_pct"]) ** 2 < 2.0
    numbers = lambda e: {k: v for k, v in e.items() if k != "series"}  # noqa: E731
    record = {"free": names, "before": numbers(before), "after": numbers(after),
              "kept": bool(better),
              "converged": fit.converged, "reason": fit.reason, "steps": fit.steps,
              "stderr": {k: list(map(float, v)) for k, v in fit.stderr.items()},
              "stderr_kind": fit.stderr_kind}
    if better:
        extra = dict(fit.params.extra)
        extra["identification"] = {**res.params.extra["identification"], "closed_loop": record}
        res.params = dataclasses.replace(fit.params, extra=extra)
    else:
        res.params.extra["identification"]["closed_loop"] = record
    say(f"[identify] closed loop: position {after['position_pct']:.4g}%, torque "
        f"{after['torque_pct']:.4g}% ({'kept' if better else 'not kept: no better'})")


def _declare(params: Any, model: str, why: str, axis: list[str] | None,
             side: list[str] | None) -> None:
    """Write into a result's ``extra`` the model kind chosen and why
    (``identification.start``'s ``kind`` and ``kind_reason``), and what the log's owner
    declared of the axes (``axis``: what gravity can do, so that discover does not try an
    effect that cannot act; ``link_side``)."""
    ident = params.extra.setdefault("identification", {})
    ident["start"] = {**ident.get("start", {}), "kind": model, "kind_reason": why}
    for key, value in (("axis", axis), ("link_side", side)):
        if value is not None and key not in params.extra:
            params.extra[key] = value[0] if len(value) == 1 else value


def _rotor(args: argparse.Namespace, log: Any, model: str, why: str, start_file: Any,
           pins: dict[str, float], axis: list[str] | None, side: list[str] | None,
           say: Callable[[str], None]) -> int:
    """``identify`` of the rotor kind: equation error on the torque from the measured motion
    (``jaxflex.identify.torque.identify_rotor``); writes the file and a figure of the measured
    against the predicted torque. Returns the exit code (0 converged, 3 not)."""
    import sys
    from pathlib import Path

    from jaxflex.identify.problem import with_named_effects
    from jaxflex.identify.start import start_from_data
    from jaxflex.identify.torque import ROTOR_FREE, identify_rotor
    from jaxflex.io.params import save_params

    if args.closed_loop:
        raise ValueError("--closed-loop: the rotor model takes the link motion from the log and "
                         "has no closed loop to simulate; choose --model flexible or rigid")
    free = ([s.strip() for s in args.free.split(",") if s.strip()] if args.free
            else list(ROTOR_FREE))
    data = start_from_data(log, "rotor")
    if start_file is None:
        init = data.params
        say("[identify] start from the log's inverse dynamics (rotor line):\n  "
            + data.summary().replace("\n", "\n  "))
    else:
        init = with_named_effects(start_file, free, data.params)
        say(f"[identify] start {args.params}")
    say(f"[identify] {log.N} samples at {1e3 * log.dt:g} ms, {log.n} joint(s), model {model} "
        f"({why}), free {[k for k in free if k not in pins]}; equation error on the torque "
        "from the measured motion")
    from jaxflex.app.cli.outputs import interrupts_stop, writing

    with interrupts_stop():  # a Ctrl-C stops the command wherever it lands
        res = identify_rotor(log, init, free, pin=pins, max_steps=args.max_steps)
    _declare(res.params, model, why, axis, side)
    out = Path(args.out)
    fig = Path(args.figure) if args.figure else out.with_suffix(".png")
    from jaxflex.app.plots import save_figure
    from jaxflex.app.plots.validate import plot_validation_log
    from jaxflex.validate import torque_prediction

    series = {"t": log.t, "tau": log.tau, "q": log.q1, "closed_loop": None,
              "tau_hat": torque_prediction(res.params, log, kind="rotor")}
    with writing():  # the file and its figure, or nothing, Ctrl-C included
        save_params(res.params, out)
        save_figure(plot_validation_log(series, units=("rad", "N m"), title=(
            f"rotor model on the identification log: torque error {res.torque_pct:.3g}%")),
            fig)
    print(res.table())
    say(f"[identify] wrote {out} and {fig} ({res.wall_s:.1f} s)")
    if not res.converged:
        print(f"jaxflex identify: the solver did not converge: {res.reason}. {out} is marked "
              "unconverged; downstream commands refuse it unless given --accept-unconverged",
              file=sys.stderr)
        return 0 if args.accept_result else 3
    say("[identify] verdict: solver converged; validate on other logs of the axis with "
        f"jaxflex validate LOG... --params {out} (the encoder offset and scale re-estimated "
        "on each)")
    return 0
