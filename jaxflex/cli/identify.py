"""``jaxflex identify LOG --params INIT.json --out RESULT.json``: fit parameters to a log.

Writes the identified parameters in the docs/spec.md section 7 format with standard errors under
``"stderr"``, a figure of measured against simulated response next to it, and prints a short
table. ``--free`` picks the free parameters, ``--map`` maps a ``.mat`` file's variables to the
log columns (e.g. ``t=t,tau=gtau*vir,q1=qm,q2=qm``).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

EXAMPLE = ("jaxflex identify log.csv --params init.json --out identified.json "
           "--free Fc,Fs,vs,sigma0,sigma1,sigma2")


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


#: ``--substeps``: a positive integer or "auto"; ``--segment``: samples >= 0 (0: the whole
#: log) or "auto".
_substeps = _count_or_auto(1, "a positive integer")
_segment = _count_or_auto(0, "a number of samples >= 0")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``identify`` subcommand."""
    p = sub.add_parser(
        "identify", help="identify friction (and plant) parameters from a log",
        description="Fit LuGre (and optionally I, J, K or effect) parameters to a logged run "
        "by gradient through the simulator (Levenberg-Marquardt, multiple shooting).",
    )
    p.add_argument("log", help="log file (.csv with header, .npz or .mat)")
    p.add_argument("--params", required=True, help="initial parameter file (JSON, docs/spec.md section 7)")
    p.add_argument("--out", required=True, help="where to write the identified parameters (JSON)")
    p.add_argument("--free", default="Fc,Fs,vs,sigma0,sigma1,sigma2",
                   help="comma-separated free parameters: Fc,Fs,vs,sigma0,sigma1,sigma2,I,J,K "
                   "or <effect>.<param> (default: the six LuGre parameters)")
    p.add_argument("--map", dest="mapping", default=None,
                   help="column mapping for .mat/.npz/.csv variables, e.g. "
                   "'t=t,tau=gtau*vir,q1=qm,q2=qm'")
    p.add_argument("--model", choices=("flexible", "rigid", "rotor", "link"), default="flexible",
                   help="flexible joint (eq. 3), rigid Jx x'' = u - F (eq. 37), or rotor: the "
                        "rotor subsystem J q2'' + K (q2 - q1) + motor effects = tau driven by "
                        "the measured link motion (subsystem identification, no link model), "
                        "or link: the link subsystem M q1'' + F = K (q2 - q1) driven by the "
                        "measured rotor motion (no motor model: friction on the link side)")
    p.add_argument("--segment", type=_segment, default="auto",
                   help="samples per multiple-shooting segment (0: whole log), or 'auto' "
                        "(default): two mechanical time constants of the start model "
                        "(inertia / sigma2) on a grid of 125 x 2^k samples within 0.1-2 s")
    p.add_argument("--substeps", type=_substeps, default="auto",
                   help="integrator substeps per sample, or 'auto' (default): the fewest whose "
                        "replay error is at most half the log's noise, refined until the "
                        "integrator moves no fitted parameter by more than half a standard "
                        "error (docs/spec.md section 5)")
    p.add_argument("--max-steps", type=int, default=200, help="solver iteration cap")
    p.add_argument("--start", type=int, default=0, help="first sample used")
    p.add_argument("--stop", type=int, default=None, help="one past the last sample used")
    p.add_argument("--figure", default=None,
                   help="figure path (default: RESULT.json with .png suffix)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--accept-unconverged", dest="accept_result", action="store_true",
                   help="exit 0 even when the fit does not converge (the result file is still "
                        "marked unconverged)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the identification; returns the exit code."""
    import importlib
    import sys
    import threading
    import warnings
    from pathlib import Path

    from jaxflex.identify import IdentificationWarning, choose_segment_length, identify
    from jaxflex.identify.core import SEGMENT_TIME_CONSTANTS
    from jaxflex.logs import REQUIRED_COLUMNS, load_log, parse_mapping
    from jaxflex.params import load_params, save_params

    from jaxflex.cli.outputs import check_outputs

    check_outputs(args.force, files=[args.out, args.figure or Path(args.out).with_suffix(".png")])
    required = REQUIRED_COLUMNS if args.model != "rigid" else ("t", "tau", "q1")
    log = load_log(args.log, parse_mapping(args.mapping), required=required)
    log = log.slice(args.start, args.stop)
    init = load_params(args.params, accept_unconverged=True)  # a start guess
    free = [s.strip() for s in args.free.split(",") if s.strip()]
    if args.segment == "auto":
        seg, rec = choose_segment_length(log, init, args.model)
        how = (f" (auto: {SEGMENT_TIME_CONSTANTS:g} x the smallest time constant of "
               f"{', '.join(f'{t:.3g}' for t in rec['time_constants_s'])} s)")
    else:
        seg, how = (None if args.segment <= 0 else min(args.segment, log.N)), ""
    say = (lambda s: None) if args.quiet else print
    say(f"[identify] {log.N} samples at {1e3 * log.dt:g} ms, {log.n} joint(s), model "
        f"{args.model}, free {free}, segments of {seg or log.N} samples{how}")
    say("[identify] compiling and solving (progress every 5 steps) ...")
    # the figure's module (matplotlib, 0.33 s) loads beside the fit, in the seconds a first
    # run waits for its compiled solver; Python's import lock hands it to the import below
    # (cold identify on the 3 s log, 8 pairs: 0.2-0.35 s sooner on average, warm unchanged)
    threading.Thread(target=importlib.import_module, args=("jaxflex.plots.identify",),
                     name="jaxflex-import-figures", daemon=True).start()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IdentificationWarning)
        res = identify(log, init, free, model=args.model,
                       segment_length="auto" if args.segment == "auto" else seg,
                       substeps=args.substeps, max_steps=args.max_steps,
                       progress=False if args.quiet else 5)
    out = Path(args.out)
    save_params(res.params, out)
    fig = Path(args.figure) if args.figure else out.with_suffix(".png")
    from jaxflex.plots.identify import plot_fit

    plot_fit(res, fig)
    print(res.table())
    for w in res.warnings:
        print(f"warning: {w}")
    say(f"[identify] wrote {out} and {fig} ({res.wall_s:.1f} s solve)")
    if not res.converged:
        print(f"jaxflex identify: not converged: {res.reason}. {out} is marked unconverged; "
              "downstream commands refuse it unless given --accept-unconverged",
              file=sys.stderr)
        return 0 if args.accept_result else 3
    return 0
